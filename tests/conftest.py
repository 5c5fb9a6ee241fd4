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



#: The longest tests of `make test` (subprocesses, or many compilations), most expensive first.
#: `--dist loadgroup` hands the xdist groups out first, then the ungrouped tests one at a
#: time in collection order; a long test collected last (the alphabet put the thread-pool
#: reproducer and the examples late) keeps one worker busy while the other has finished.
#: Started first, they overlap with the groups and the short tests fill in around them; the
#: ones that compile the NMPC expert's loop alternate with others, so that one of them has
#: put it in the shared compilation cache when the next starts.
LONG_FIRST = (
    "test_examples.py::test_example_runs_quick[ren]",
    "test_thread_pool.py::test_issue_reproducer_does_not_hang",
    "test_examples.py::test_example_runs_quick[horizons]",
    "test_experiments_cli.py::test_entry_point_with_jobs_gives_the_serial_records",
    "test_examples.py::test_example_runs_quick[no_state]",
    "test_examples.py::test_example_runs_quick[indefinite_q]",
    "test_experiments_cli.py::test_cli_writes_summary_tables_and_figures",
    "test_examples.py::",
    "test_direct.py::test_sharded_sweep_equals_unsharded",
    "test_direct.py::test_defaults_follow_the_order",
    "test_direct.py::test_issue_failure_case_q_minus_1e4",
    "test_direct.py::test_the_run_is_pure_jax_and_differentiable",
)


def pytest_collection_modifyitems(config, items):
    """Move the tests in `LONG_FIRST` to the front, in that order (a stable sort: the
    order within each entry, and of every other test, is pytest's)."""
    def rank(item):
        return next((i for i, prefix in enumerate(LONG_FIRST) if prefix in item.nodeid),
                    len(LONG_FIRST))

    items.sort(key=rank)
