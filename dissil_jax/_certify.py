"""Exact dissipativity certificates (paper Lemma 2) by a float64 SDP on the host."""

from __future__ import annotations

import warnings

import equinox as eqx
import numpy as np

from ._controller import LTIController
from ._lmi import VERIFY_RTOL, kyp_margin, kyp_matrix, kyp_scale
from ._sdp import single_threaded_blas
from ._supply import QSR


class Certificate(eqx.Module):
    """The outcome of [`certify`][dissil_jax.certify].

    - `holds`: True iff `P` is positive definite and the KYP matrix at `P` is negative
      definite beyond float64 round-off (an eigenvalue check, independent of the solver).
    - `P`: the storage matrix ($V(x) = x^\\top P x$), float64.
    - `margin`: $\\min(-\\lambda_{\\max}(\\mathrm{KYP}(P)), \\lambda_{\\min}(P))$; negative when
      no certificate was found.
    - `status`: the SDP solver's status string (or `"given"` when `P` was supplied).

    For one controller these are a `bool`, an $\\hat n\\times\\hat n$ array, a `float` and a
    `str`. For a controller with leading batch axes `batch` they are numpy arrays with
    those axes in front: `holds` (bool, shape `batch`), `P` (`[*batch, n, n]`), `margin`
    (float64, shape `batch`) and `status` (a numpy string array of shape `batch`); member
    `i` is the certificate `certify` returns for the `i`-th controller.
    """

    holds: bool | np.ndarray
    P: np.ndarray
    margin: float | np.ndarray
    status: str | np.ndarray = "given"


def _controller_arrays(K: LTIController, qsr: QSR):
    if not isinstance(K, LTIController):
        raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__}.")
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

    A controller with leading batch axes is certified member by member (one SDP each;
    with `P` given the eigenvalue check is vectorised over the batch).

    **Arguments:**

    - `K`: an `LTIController`, possibly with leading batch axes.
    - `qsr`: the supply rate; `qsr.S` must be `K.n_out x K.n_in`.
    - `P`: optional storage matrix to check instead of solving the SDP: `[n, n]` (the
      same for every member) or `[*K.batch_shape, n, n]`.
    - `tol`: relative round-off allowance of the final eigenvalue check.

    **Returns:** a [`Certificate`][dissil_jax.Certificate]; batched like `K`.

    ```python
    cert = dj.certify(Ks, qsr)   # Ks.batch_shape == (8,)
    cert.holds.shape, cert.P.shape, cert.status[0]   # (8,), (8, n, n), 'optimal'
    ```
    """
    A, B, C, D = _controller_arrays(K, qsr)
    batch, n = K.batch_shape, K.n_state
    if not (np.ndim(tol) == 0 and np.isfinite(tol) and tol >= 0):
        raise ValueError(f"`tol` must be a finite non-negative number, got {tol!r}.")
    if P is not None:
        P = np.asarray(P, np.float64)
        if P.shape not in ((n, n), batch + (n, n)):
            expected = f"{n}x{n}" + (f" or {batch + (n, n)}" if batch else "")
            raise ValueError(f"`P` must be {expected}, got {P.shape}.")
        if not np.all(np.isfinite(P)):
            raise ValueError("`P` contains NaN or inf.")
        if batch:
            P = np.broadcast_to(P, batch + (n, n))
        return _verdict(A, B, C, D, qsr, P, tol, "given")
    if not batch:
        return _solve(A, B, C, D, qsr, tol)
    certs = [_solve(A[i], B[i], C[i], D[i], qsr, tol) for i in np.ndindex(*batch)]
    stack = lambda name, dtype: np.array([getattr(c, name) for c in certs], dtype).reshape(
        batch + ((n, n) if name == "P" else ()))
    return Certificate(stack("holds", bool), stack("P", np.float64), stack("margin", np.float64),
                       stack("status", str))


def _solve(A, B, C, D, qsr: QSR, tol) -> Certificate:
    """The KYP SDP for one (unbatched) controller, then the eigenvalue verdict."""
    import cvxpy as cp

    n = A.shape[0]
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
    """The eigenvalue check, vectorised over leading batch axes (scalars when unbatched)."""
    margin = kyp_margin(A, B, C, D, qsr, P)
    holds = margin > tol * kyp_scale(A, B, C, D, qsr, P)
    if np.ndim(margin) == 0:
        return Certificate(bool(holds), P, float(margin), status)
    status = np.full(np.shape(margin), status)
    return Certificate(np.asarray(holds, bool), np.array(P), np.asarray(margin, np.float64),
                       status)


__all__ = ["Certificate", "certify", "kyp_matrix"]
