"""A supply rate by reference, for the projection inside a trainer's compiled run.

A [`QSR`][dissil_jax.QSR] is a static value, so a compiled run that closes over one is
compiled again for every rate, and every compiled run keeps its code mapped for the life
of the process (a few hundred rates exhausted Linux's default memory-map limit). The
projection's Clarabel path needs the rate only on the host, in its callback: a run can
pass a traced token instead, which the callback resolves here.
"""

from __future__ import annotations

import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._rate_scale import rate_factor, scaled_rate
from .._supply import QSR
from . import first_order as _first_order

_LOCK = threading.Lock()
_TOKENS: dict[QSR, int] = {}
_RATES: list[QSR] = []  # the rate of token t is _RATES[t - 1] (token 0: none)


class RateHandle(eqx.Module):
    """A supply rate for `project` inside a compiled run, by reference: a traced `token`
    that the host callback resolves (`resolve`), so that runs under rates of one shape
    share one compilation. Clarabel's path only; the caller checks the rate and divides it
    by `rate_factor` first (`trainer_rate`)."""

    token: jax.Array
    n_in: int = eqx.field(static=True)
    n_out: int = eqx.field(static=True)


def rate_handle(qsr: QSR) -> RateHandle:
    """The `RateHandle` of `qsr` (one token per distinct rate, kept for the process's life:
    a few hundred bytes each)."""
    with _LOCK:
        if qsr not in _TOKENS:
            _RATES.append(qsr)
            _TOKENS[qsr] = len(_RATES)
        token = _TOKENS[qsr]
    return RateHandle(jnp.asarray(token, jnp.int32), qsr.n_in, qsr.n_out)


def resolve(token) -> QSR:
    """The rate of a token (an array broadcast like the callback's batch)."""
    with _LOCK:
        return _RATES[int(np.ravel(np.asarray(token))[0]) - 1]


def trainer_rate(qsr: QSR | None, method: str, n_state: int, dtype):
    """`(rate, k)` for `fit_pgd`'s compiled run: on Clarabel's path the rate divided by
    `k = rate_factor(qsr)` as a `RateHandle`, with `k` as an array of `dtype` (P is
    multiplied back by it); where the first-order projection may run (its ADMM is built
    around the rate's values), `(qsr, None)`: static, divided inside the run."""
    if qsr is None:
        return None, None
    # with or without a metric (the optimiser's, known inside the run)
    if any(_first_order.use_first_order(method, n_state, w, qsr) for w in (False, True)):
        return qsr, None
    k = rate_factor(qsr)
    return rate_handle(scaled_rate(qsr, k)), jnp.asarray(k, dtype)
