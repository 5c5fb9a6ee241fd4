"""MkDocs hook: publish a local copy of MathJax so the site renders maths offline.

The MathJax 3.2.2 browser build comes from the pip-installed ``sphinx-mathjax-offline``
wheel (a pinned dev/docs dependency in pyproject.toml), whose ``static/mathjax`` directory
is the ``es5/`` tree of the ``mathjax`` npm package, byte for byte. Only the data files are
used, not the Sphinx extension. They are added to the site under ``javascripts/mathjax/``,
and ``mkdocs.yml`` loads ``javascripts/mathjax/tex-mml-chtml.js`` from there. MathJax finds
its fonts and lazily loaded extensions relative to that script, so no page needs the network.

Of the top-level combined builds only the entry point is copied; the subdirectories (fonts,
TeX extensions, accessibility, menu) are copied whole, as MathJax may load any of them on demand.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

DISTRIBUTION = "sphinx-mathjax-offline"
PACKAGE_DIR = "sphinx-mathjax-offline/static/mathjax"
ENTRY_POINT = "tex-mml-chtml.js"  # MathJax 3's TeX input + CommonHTML output build
SITE_DIR = "javascripts/mathjax"


def _mathjax_root() -> Path:
    try:
        dist = distribution(DISTRIBUTION)
    except PackageNotFoundError:
        raise PluginError(
            f"{DISTRIBUTION} is not installed; the docs bundle MathJax from it. "
            "Install the docs extras: pip install -e '.[docs]' (or `make install`)."
        ) from None
    root = Path(str(dist.locate_file(PACKAGE_DIR)))
    if not (root / ENTRY_POINT).is_file():
        raise PluginError(f"{root / ENTRY_POINT} missing from the {DISTRIBUTION} installation")
    return root


def on_files(files: Files, config) -> Files:
    root = _mathjax_root()
    sources = [root / ENTRY_POINT]
    sources += sorted(p for p in root.glob("*/**/*") if p.is_file())
    for path in sources:
        src_uri = f"{SITE_DIR}/{path.relative_to(root).as_posix()}"
        files.append(File.generated(config, src_uri, abs_src_path=str(path)))
    return files
