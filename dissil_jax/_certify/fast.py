"""Cheap storage candidates that [`certify`][dissil_jax.certify] checks before any SDP.

- the storage matrices of recent projections (`remember`, filled by
  [`project`][dissil_jax.project]), looked up by the exact float64 numbers of the
  controller and the supply rate;
- a Riccati storage: for a tightening $\\delta > 0$, the stabilising solution $X$ of the
  discrete algebraic Riccati equation of the form $-\\mathrm{KYP}(-X) - \\delta I$ gives
  $P = -X$ with $\\mathrm{KYP}(P) \\preceq -\\delta I$ whenever the $\\delta$-tightened
  KYP inequality is feasible (the Riccati solution is an extreme point of its solution
  set). That inequality's $(1,1)$ block, $P - A^\\top PA \\succeq \\delta I$, makes such a
  $P$ positive definite. $\\delta$ is tried from large to small; each try costs
  $O(\\hat n^3)$.

A candidate is only a guess: `certify` keeps it only if its own eigenvalue check passes.
"""

from __future__ import annotations

import collections
import threading
import warnings

import numpy as np

from .._supply import QSR

_CACHE: collections.OrderedDict = collections.OrderedDict()
_CACHE_SIZE = 256
_LOCK = threading.Lock()
# Tightenings tried, relative to the size of the supply-rate terms.
_DELTAS = (1e-2, 1e-4, 1e-6, 1e-8)


def _key(A, B, C, D, qsr: QSR):
    return (qsr, A.shape, B.shape, C.shape, *(np.ascontiguousarray(M, np.float64).tobytes()
                                              for M in (A, B, C, D)))


def remember(A, B, C, D, qsr: QSR, P) -> None:
    """Keep certified `(A, B, C, D) -> P` (batched, float64) for `certify`'s lookup."""
    A, B, C, D, P = (np.asarray(M, np.float64) for M in (A, B, C, D, P))
    with _LOCK:
        for i in range(len(A)):
            key = _key(A[i], B[i], C[i], D[i], qsr)
            _CACHE[key] = P[i].copy()
            _CACHE.move_to_end(key)
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)


def cached(A, B, C, D, qsr: QSR):
    """The remembered storage of this exact controller, or None."""
    with _LOCK:
        return _CACHE.get(_key(A, B, C, D, qsr))


def riccati(A, B, C, D, qsr: QSR):
    """Riccati storages for decreasing tightenings $\\delta$ (a generator, unbatched)."""
    from scipy.linalg import solve_discrete_are

    n, p = B.shape
    Q, S, R = qsr.Q, qsr.S, qsr.R
    # -KYP(-X) = [[A'XA - X + q, A'XB + s], [., B'XB + r]]
    q = C.T @ Q @ C
    s = C.T @ (S + Q @ D)
    r = R + D.T @ Q @ D + D.T @ S + S.T @ D
    size = 1.0 + max(np.abs(q).max(initial=0.0), np.abs(s).max(initial=0.0),
                     np.abs(r).max(initial=0.0))
    for delta in _DELTAS:
        d = delta * size
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                X = solve_discrete_are(A, B, (q + q.T) / 2 - d * np.eye(n),
                                       (r + r.T) / 2 - d * np.eye(p), s=s)
        except (np.linalg.LinAlgError, ValueError):
            continue
        if np.all(np.isfinite(X)):
            yield -(X + X.T) / 2
