"""Exact dissipativity certificates (paper Lemma 2) by a float64 SDP on the host."""

from __future__ import annotations

import warnings

import equinox as eqx
import numpy as np

from ._controller import LTIController
from ._lmi import VERIFY_RTOL, kyp_margin, kyp_matrix, kyp_scale
from ._supply import QSR
from ._threads import single_threaded_blas


class Certificate(eqx.Module):
    """The outcome of [`certify`][dissil_jax.certify].

    - `holds`: True iff `P` is positive definite and the KYP matrix at `P` is negative
      definite beyond float64 round-off (an eigenvalue check, independent of the solver).
    - `P`: the storage matrix ($V(x) = x^\\top P x$), float64.
    - `margin`: $\\min(-\\lambda_{\\max}(\\mathrm{KYP}(P)), \\lambda_{\\min}(P))$; negative when
      no certificate was found.
    - `status`: the SDP solver's status string (or `"given"` when `P` was supplied).
    """

    holds: bool
    P: np.ndarray
    margin: float
    status: str = "given"


def _controller_arrays(K: LTIController, qsr: QSR):
    if not isinstance(K, LTIController):
        raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__}.")
    if K.batch_shape:
        raise ValueError("`K` must be a single controller; certify batch members one by one.")
    if not isinstance(qsr, QSR):
        raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
    qsr.check_sizes(K.n_in, K.n_out)
    return tuple(np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))


def certify(K: LTIController, qsr: QSR, *, P=None, tol: float = VERIFY_RTOL) -> Certificate:
    """Certify $(Q,S,R)$-dissipativity of `K` by the discrete KYP lemma (paper Lemma 2).

    Solves, in float64 with cvxpy + Clarabel (independently of the projection code),

    $$\\max_{P,\\,t}\\ t \\quad\\text{s.t.}\\quad \\mathrm{KYP}(P) \\preceq -tI,\\quad P\\succeq tI,
    \\quad t\\le 1,$$

    then re-checks the returned $P$ with an eigenvalue computation. Margins are absolute;
    $t\\le1$ normalises the certificate (the LMI is not homogeneous in $P$ because of the
    fixed $Q,S,R$). A system is declared dissipative when the re-checked margin exceeds
    `tol` times a bound on the size of the KYP terms, so nearly lossless systems with
    margins of order $10^{-7}$ are still decided correctly.

    **Arguments:**

    - `K`: a single `LTIController`.
    - `qsr`: the supply rate; `qsr.S` must be `K.n_out x K.n_in`.
    - `P`: optional storage matrix to check instead of solving the SDP.
    - `tol`: relative round-off allowance of the final eigenvalue check.

    **Returns:** a [`Certificate`][dissil_jax.Certificate].
    """
    A, B, C, D = _controller_arrays(K, qsr)
    n = A.shape[0]
    if not (np.ndim(tol) == 0 and np.isfinite(tol) and tol >= 0):
        raise ValueError(f"`tol` must be a finite non-negative number, got {tol!r}.")
    if P is not None:
        P = np.asarray(P, np.float64)
        if P.shape != (n, n):
            raise ValueError(f"`P` must be {n}x{n}, got {P.shape}.")
        if not np.all(np.isfinite(P)):
            raise ValueError("`P` contains NaN or inf.")
        return _verdict(A, B, C, D, qsr, P, tol, "given")
    import cvxpy as cp

    Pv = cp.Variable((n, n), symmetric=True)
    t = cp.Variable()
    Q, S, R = qsr.Q, qsr.S, qsr.R
    top = cp.hstack([A.T @ Pv @ A - Pv - C.T @ Q @ C, A.T @ Pv @ B - C.T @ S - C.T @ Q @ D])
    bot = cp.hstack([B.T @ Pv @ A - S.T @ C - D.T @ Q @ C,
                     B.T @ Pv @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R])
    M = cp.vstack([top, bot])
    M = (M + M.T) / 2
    k = M.shape[0]
    prob = cp.Problem(cp.Maximize(t), [M << -t * np.eye(k), Pv >> t * np.eye(n), t <= 1])
    # cvxpy warns "may be inaccurate" on nearly lossless systems; the verdict below does not
    # trust the solver anyway (it re-checks P by an eigenvalue computation).
    with single_threaded_blas(), warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        try:
            prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11,
                       tol_feas=1e-11, max_iter=400)
        except cp.SolverError as e:  # pragma: no cover - depends on solver internals
            return Certificate(False, np.full((n, n), np.nan), -np.inf, f"solver error: {e}")
    if Pv.value is None:
        return Certificate(False, np.full((n, n), np.nan), -np.inf, str(prob.status))
    P = (Pv.value + Pv.value.T) / 2
    return _verdict(A, B, C, D, qsr, P, tol, str(prob.status))


def _verdict(A, B, C, D, qsr, P, tol, status) -> Certificate:
    margin = float(kyp_margin(A, B, C, D, qsr, P))
    holds = bool(margin > tol * float(kyp_scale(A, B, C, D, qsr, P)))
    return Certificate(holds, P, margin, status)


__all__ = ["Certificate", "certify", "kyp_matrix"]
