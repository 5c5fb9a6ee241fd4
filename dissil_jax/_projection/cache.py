"""The projection's host-side state kept across calls: the LMI of each (supply rate,
order) and, per thread, its Clarabel solver (whose symbolic structure a new target only
refills with numbers), both least-recently-used caches of `CACHE_SIZE` entries."""

from __future__ import annotations

import threading

from .._lru import LRU
from .._sdp.lmi import ConvexifiedLMI
from .._supply import QSR
from .solver import _ProjectionSolver

#: (rate, order) pairs whose LMI and per-thread solver are kept, the least recently used
#: dropped first (a solver holds ~10 MB at order 24: unbounded, a sweep over rates grew).
CACHE_SIZE = 16
# The conditioning bound of the projection's P: lambda_min(P) >= P_FLOOR * mean eigenvalue
# (`_projection/solver.py`; redundant, so left out, for n = 1).
P_FLOOR = 1e-2

_LOCAL = threading.local()
_LMI_CACHE = LRU(CACHE_SIZE)
_LMI_LOCK = threading.Lock()


def lmi(qsr: QSR, n: int) -> ConvexifiedLMI:
    """The convexified LMI of `qsr` at order `n` (shared by all threads)."""
    with _LMI_LOCK:
        return _LMI_CACHE.get_or_build((qsr, n),
                                       lambda: ConvexifiedLMI(n, qsr.n_in, qsr.n_out, qsr))


def thread_solver(qsr: QSR, n: int, eps: float, reg: float) -> _ProjectionSolver:
    """This thread's Clarabel solver of the projection for `qsr` at order `n`."""
    cache = _LOCAL.__dict__.setdefault("solvers", LRU(CACHE_SIZE))  # per thread
    return cache.get_or_build((qsr, n, eps, reg), lambda: _ProjectionSolver(
        lmi(qsr, n), eps=eps, reg=reg, floor=P_FLOOR if n > 1 else 0.0))
