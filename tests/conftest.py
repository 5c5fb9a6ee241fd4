"""Shared test configuration: float64 numerics, a fresh-key fixture, the built docs site."""

import importlib.util
import itertools
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.random as jr
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture
def getkey():
    """Return a function producing a new PRNG key on each call (deterministic per test)."""
    counter = itertools.count()
    base = jr.PRNGKey(0)
    return lambda: jr.fold_in(base, next(counter))


@pytest.fixture(scope="session")
def built_site(tmp_path_factory) -> Path:
    """The documentation site, built strictly once per test run (it takes ~30 s)."""
    if (importlib.util.find_spec("mkdocs") is None
            or importlib.util.find_spec("mkdocstrings_handlers") is None):
        pytest.skip("mkdocs/mkdocstrings not installed (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("site")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stderr[-4000:]}"
    return out

