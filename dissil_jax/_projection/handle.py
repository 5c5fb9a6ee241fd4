"""A supply rate by reference, for the projection inside a trainer's compiled run.

A [`QSR`][dissil_jax.QSR] is a static value, so a compiled run that closes over one is
compiled again for every rate, and every compiled run keeps its code mapped for the life
of the process (a few hundred rates exhausted Linux's default memory-map limit). The
projection's Clarabel path needs the rate only on the host, in its callback: a run can
pass a traced token instead, which the callback resolves here. The first-order
projection runs its ADMM inside the run: the handle then carries the rate's values as
arrays too (`AdmmRate`).
"""

from __future__ import annotations

import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._supply import QSR
from .admm_rate import AdmmRate

_LOCK = threading.Lock()
_TOKENS: dict[QSR, int] = {}
_RATES: list[QSR] = []  # the rate of token t is _RATES[t - 1] (token 0: none)


class RateHandle(eqx.Module):
    """A supply rate for `project` inside a compiled run, by reference: a traced `token`
    that the host callback resolves (`resolve`), so that runs under rates of one shape
    share one compilation. `admm`: the rate's values for the first-order path's ADMM, or
    None (Clarabel's path only). The caller checks the rate and divides it by
    `rate_factor` first (`first_order.trainer_rate`)."""

    token: jax.Array
    n_in: int = eqx.field(static=True)
    n_out: int = eqx.field(static=True)
    admm: AdmmRate | None = None


def rate_handle(qsr: QSR, admm: AdmmRate | None = None) -> RateHandle:
    """The `RateHandle` of `qsr` (one token per distinct rate, kept for the process's life:
    a few hundred bytes each), carrying `admm` (`admm_rate(qsr, dtype)`) if given."""
    with _LOCK:
        if qsr not in _TOKENS:
            _RATES.append(qsr)
            _TOKENS[qsr] = len(_RATES)
        token = _TOKENS[qsr]
    return RateHandle(jnp.asarray(token, jnp.int32), qsr.n_in, qsr.n_out, admm)


def resolve(token) -> QSR:
    """The rate of a token (an array broadcast like the callback's batch)."""
    with _LOCK:
        return _RATES[int(np.ravel(np.asarray(token))[0]) - 1]
