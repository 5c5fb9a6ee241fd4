"""The documentation site builds strictly and the API reference covers the public names."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import dissil_jax as dj

REPO = Path(__file__).resolve().parents[1]


def _public_names() -> set[str]:
    return {name for name, obj in vars(dj).items()
            if not name.startswith("_") and not isinstance(obj, type(sys))}


def _documented_names() -> set[str]:
    text = "\n".join(p.read_text() for p in (REPO / "docs").glob("api*.md"))
    text += "\n".join(p.read_text() for p in (REPO / "docs").glob("api/*.md"))
    return set(re.findall(r"^::: dissil_jax\.(\w+)\s*$", text, flags=re.M))


def test_api_reference_covers_public_names():
    missing = _public_names() - _documented_names()
    assert not missing, (
        f"public names without an entry in docs/api.md: {sorted(missing)}; add a "
        "`::: dissil_jax.NAME` line in the matching section."
    )


@pytest.mark.xdist_group("site")  # with tests/test_site.py: one build per run
def test_docs_build_strict(built_site):
    assert (built_site / "api" / "index.html").exists()


@pytest.mark.parametrize("page", ["README.md", "docs/index.md"])
def test_front_page_code_runs_as_written(page):
    """The first code a newcomer copies runs in a fresh interpreter (float32, no setup)."""
    text = (REPO / page).read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, f"{page} has no python block"
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    result = subprocess.run([sys.executable, "-c", blocks[0]], cwd=REPO, capture_output=True,
                            text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "True" in result.stdout or "holds=True" in result.stdout, result.stdout
