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

Before the SDP, `disproof` looks for a cheap proof that no storage exists, from two
necessary conditions of $\\mathrm{KYP}(P)\\prec0$ with $P\\succ0$:

- **Frequency response.** At $x = (zI-A)^{-1}Bu$ with $|z| = 1$ the KYP form is
  $-u^H\\Phi(z)u$, with $\\Phi(z) = G^HQG + G^HS + S^\\top G + R$ and
  $G(z) = C(zI-A)^{-1}B + D$ (the storage terms cancel, as $Ax + Bu = zx$), so every
  certified controller has $\\Phi(z)\\succ0$ on the unit circle; at $x = 0$ the form is
  $u^\\top(B^\\top PB - \\Phi_\\infty)u$, so also $\\Phi_\\infty = D^\\top QD + D^\\top S +
  S^\\top D + R\\succ0$.
- **Stability when $Q\\preceq0$.** The $(1,1)$ block gives $A^\\top PA - P\\prec C^\\top QC
  \\preceq 0$: $A$ is Schur stable.

A disproof needs a violation well beyond round-off (see `disproof`); anything less goes on
to the SDP.
"""

from __future__ import annotations

import threading
import warnings

import numpy as np

from .._lru import LRU
from .._supply import QSR

_CACHE = LRU(256)
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
            _CACHE.put(_key(A[i], B[i], C[i], D[i], qsr), P[i].copy())


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


#: Frequencies of the unit circle's upper half (a real system's response is conjugate below).
_OMEGAS = np.linspace(0.0, np.pi, 257)
#: A violation must exceed this times the size of the terms to disprove (round-off of
#: evaluating $\\Phi$ is ~1e-16 relative times the conditioning of $zI - A$, capped below).
_DISPROOF_RTOL = 1e-6
_MAX_COND = 1e6


def unstable(A, qsr: QSR) -> str | None:
    """Why no storage can certify a controller with this $A$: unstable with $Q\\preceq0$.

    None means "not disproved", not "dissipative". One eigenvalue computation, so
    `certify` runs it before the Riccati storages (which are slow to fail on such $A$).
    """
    if np.linalg.eigvalsh(np.asarray(qsr.Q, np.float64))[-1] > 0.0:
        return None
    rho = np.abs(np.linalg.eigvals(A)).max(initial=0.0)
    if rho > 1.0 + _DISPROOF_RTOL:
        return f"disproved: unstable (spectral radius {rho:.6g}) with Q <= 0"
    return None


def disproof(A, B, C, D, qsr: QSR) -> str | None:
    """A reason why no storage can certify this (unbatched) controller, or None.

    Checks the necessary conditions of the module docstring: `unstable`, then
    $\\lambda_{\\min}(\\Phi)$ at $z=\\infty$ and on a grid of the unit circle, skipping
    frequencies where $zI - A$ is ill-conditioned. None means "not disproved", not
    "dissipative".
    """
    reason = unstable(A, qsr)
    if reason is not None:
        return reason
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    nQ, nS, nR = (np.linalg.norm(M, 2) for M in (Q, S, R))

    def violated(G) -> bool:
        Phi = G.conj().T @ Q @ G + G.conj().T @ S + S.T @ G + R
        g = np.linalg.norm(G, 2)
        size = nQ * g * g + 2 * nS * g + nR
        return np.linalg.eigvalsh((Phi + Phi.conj().T) / 2)[0] < -_DISPROOF_RTOL * size

    if violated(D):
        return "disproved: feedthrough supply not positive"
    eye = np.eye(A.shape[0])
    for w in _OMEGAS:
        M = np.exp(1j * w) * eye - A
        if np.linalg.cond(M) > _MAX_COND:
            continue
        if violated(C @ np.linalg.solve(M, B) + D):
            return f"disproved: frequency response at omega = {w:.4g}"
    return None
