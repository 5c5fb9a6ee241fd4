"""Shared test configuration: float64 numerics and a fresh-key fixture."""

import itertools

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
