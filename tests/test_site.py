"""The built docs site loads every script from itself, so its maths renders offline.

MathJax is served from the site (copied from the pip-installed sphinx-mathjax-offline
wheel by docs/javascripts/mathjax_assets.py), not from a CDN.
"""

from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

pytest.importorskip("mkdocs")
pytestmark = pytest.mark.xdist_group("site")  # with test_docs.py: the site is built once

REPO = Path(__file__).resolve().parents[1]
# The math renderer each page with maths loads, relative to the site root.
MATH_RENDERER = "javascripts/mathjax/tex-mml-chtml.js"
MATH_FONT = "javascripts/mathjax/output/chtml/fonts/woff-v2/MathJax_Main-Regular.woff"


class _ScriptSources(HTMLParser):
    def __init__(self):
        super().__init__()
        self.sources: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag == "script":
            src = dict(attrs).get("src")
            if src is not None:
                self.sources.append(src)


def _script_sources(page: Path) -> list[str]:
    parser = _ScriptSources()
    parser.feed(page.read_text(encoding="utf-8"))
    return parser.sources


def _resolve(site: Path, page: Path, src: str) -> Path:
    """The file a local script URL points at; root-absolute URLs (404.html) start at the site."""
    path = unquote(urlsplit(src).path)
    base = site if path.startswith("/") else page.parent
    return (base / path.lstrip("/")).resolve()


@pytest.fixture
def site(built_site) -> Path:
    return built_site


def _pages(site: Path) -> list[Path]:
    pages = sorted(site.rglob("*.html"))
    assert pages, f"no HTML pages in {site}"
    return pages


def test_every_script_is_local_and_exists(site):
    problems = []
    for page in _pages(site):
        rel_page = page.relative_to(site)
        for src in _script_sources(page):
            parts = urlsplit(src)
            if parts.scheme or parts.netloc or src.startswith("//"):
                problems.append(f"{rel_page}: remote script {src!r}")
                continue
            target = _resolve(site, page, src)
            if not target.is_relative_to(site.resolve()) or not target.is_file():
                problems.append(f"{rel_page}: script {src!r} not found in the built site")
    assert not problems, "\n".join(problems)


def test_math_renderer_is_in_the_site(site):
    renderer = site / MATH_RENDERER
    assert renderer.is_file(), f"{MATH_RENDERER} missing from the built site"
    assert "MathJax" in renderer.read_text(encoding="utf-8", errors="replace")[:200_000]
    assert (site / MATH_FONT).is_file(), f"{MATH_FONT} missing: MathJax would lack its fonts"

    math_pages = [p for p in _pages(site) if 'class="arithmatex"' in p.read_text(encoding="utf-8")]
    assert math_pages, "no page with maths found; did pymdownx.arithmatex stop running?"
    for page in math_pages:
        loaded = {_resolve(site, page, src) for src in _script_sources(page)}
        assert renderer.resolve() in loaded, (
            f"{page.relative_to(site)} has maths but does not load {MATH_RENDERER}"
        )
