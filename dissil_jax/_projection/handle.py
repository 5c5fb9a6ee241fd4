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
from .._sdp.indefinite import is_indefinite
from .._supply import QSR
from . import first_order as _first_order

_LOCK = threading.Lock()
_RATES: dict = {}  # token -> QSR, and QSR -> token


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
        token = _RATES.get(qsr)
        if token is None:
            token = _RATES[qsr] = len(_RATES) // 2 + 1
            _RATES[token] = qsr
    return RateHandle(jnp.asarray(token, jnp.int32), qsr.n_in, qsr.n_out)


def resolve(token) -> QSR:
    """The rate of a token (an array broadcast like the callback's batch)."""
    with _LOCK:
        return _RATES[int(np.ravel(np.asarray(token))[0])]


def trainer_rate(qsr: QSR | None, method: str, n_state: int, dtype):
    """`(rate, k)` for `fit_pgd`'s compiled run: on Clarabel's path the rate divided by
    `k = rate_factor(qsr)` as a `RateHandle`, with `k` as an array of `dtype` (P is
    multiplied back by it); where the first-order projection may run (its ADMM is built
    around the rate's values), `(qsr, None)`: static, divided inside the run."""
    if qsr is None:
        return None, None
    orders = (_first_order.AUTO_MIN_ORDER, _first_order.AUTO_MIN_ORDER_METRIC)
    lo = min((o for o in orders if o is not None), default=None)
    if method == "first_order" or (method == "auto" and lo is not None and n_state >= lo
                                   and not is_indefinite(qsr)):
        return qsr, None
    k = rate_factor(qsr)
    return rate_handle(scaled_rate(qsr, k)), jnp.asarray(k, dtype)
