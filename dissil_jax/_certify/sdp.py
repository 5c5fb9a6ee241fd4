"""The certificate SDP of [`certify`][dissil_jax.certify], assembled straight for Clarabel.

$$\\max_{P,\\,t}\\ t \\quad\\text{s.t.}\\quad \\mathrm{KYP}(P) \\preceq -tI,\\quad
P\\succeq tI,\\quad t\\le 1,$$

with $\\mathrm{KYP}(P) = F^\\top P F - \\operatorname{diag}(P, 0) + K_0$, $F = [A\\ B]$ and
$K_0$ the supply-rate part (paper Lemma 2). The variables are the upper triangle of $P$
(row-major) and $t$; the column of $P_{ab}$ in the first cone is the svec of
$F_a^\\top F_b + F_b^\\top F_a - \\operatorname{diag}(E_{ab}, 0)$ ($F_a$ the $a$-th row of
$F$), dense, so the problem has $\\sim\\hat n^2(\\hat n + p)^2/4$ nonzeros.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._sdp import sdp as _sdp
from .._sdp.lmi import kyp_matrix, svec, svec_indices, svec_pos
from .._supply import QSR

# Clarabel's gap and feasibility tolerances for the certificate: tight, because nearly
# lossless systems have margins of order 1e-7 (the verdict re-checks P anyway).
_TOL, _MAX_ITER = 1e-11, 400
# Clarabel's statuses in the words `Certificate.status` has always used.
_STATUS = {"Solved": "optimal", "AlmostSolved": "optimal_inaccurate",
           "PrimalInfeasible": "infeasible", "AlmostPrimalInfeasible": "infeasible_inaccurate",
           "DualInfeasible": "unbounded", "AlmostDualInfeasible": "unbounded_inaccurate",
           "MaxIterations": "max_iterations", "MaxTime": "max_time",
           "NumericalError": "numerical_error", "InsufficientProgress": "insufficient_progress"}


def solve(A, B, C, D, qsr: QSR, weights=None):
    """Solve the certificate SDP for one controller; returns `(P or None, status string)`.

    `weights = (W1, W2)`, positive definite, measure the margin in other units:
    $\\mathrm{KYP}(P)\\preceq -tW_1$, $P\\succeq tW_2$ (the identities by default)."""
    import clarabel

    n, p = B.shape
    k = n + p
    rows, cols = np.triu_indices(n)
    nP = len(rows)
    F = np.concatenate([A, B], axis=1)  # [n, k]
    # d KYP / d P[a, b] = F_a' F_b + F_b' F_a - diag(E_ab, 0), E_ab = e_a e_b' + e_b e_a'
    # (halved on the diagonal a = b)
    outer = F[rows][:, :, None] * F[cols][:, None, :]  # [nP, k, k]
    G = outer + outer.swapaxes(1, 2)
    G[rows == cols] /= 2
    G[np.arange(nP), rows, cols] -= 1.0
    G[np.arange(nP), cols, rows] -= np.where(rows == cols, 0.0, 1.0)
    idx = svec_indices(k)
    L2 = n * (n + 1) // 2
    K0 = kyp_matrix(np.zeros((n, n)), np.zeros((n, p)), C, D, qsr, np.zeros((n, n)))
    W1, W2 = (np.eye(k), np.eye(n)) if weights is None else weights
    eye1, eye2 = svec(W1, idx), np.zeros(L2)
    eye2[svec_pos(rows, cols)] = W2[rows, cols] * np.where(rows == cols, 1.0, np.sqrt(2.0))
    # s = b - A x: cone 1 svec(-KYP(P) - tI), cone 2 svec(P - tI), cone 3 1 - t
    A1 = np.concatenate([svec(G, idx).T, eye1[:, None]], axis=1)  # [L1, nP + 1]
    w = np.where(rows == cols, 1.0, np.sqrt(2.0))
    A2 = sp.coo_matrix((-w, (svec_pos(rows, cols), np.arange(nP))), shape=(L2, nP + 1))
    A2 = A2 + sp.coo_matrix((eye2, (np.arange(L2), np.full(L2, nP))), shape=(L2, nP + 1))
    A3 = sp.coo_matrix(([1.0], ([0], [nP])), shape=(1, nP + 1))
    Amat = sp.vstack([sp.csc_matrix(A1), A2, A3], format="csc")
    b = np.concatenate([svec(-K0, idx), np.zeros(L2), [1.0]])
    q = np.zeros(nP + 1)
    q[-1] = -1.0
    cones = [clarabel.PSDTriangleConeT(k), clarabel.PSDTriangleConeT(n),
             clarabel.NonnegativeConeT(1)]
    settings = _sdp.clarabel_settings(max_iter=_MAX_ITER, equilibrate=True, tol=_TOL)
    settings.presolve_enable = True  # a one-off solve: no in-place updates
    Pobj = sp.csc_matrix((nP + 1, nP + 1))
    with _sdp.single_threaded_blas():
        sol = clarabel.DefaultSolver(Pobj, q, Amat, b, cones, settings).solve()
    status = _STATUS.get(str(sol.status), str(sol.status))
    if status not in ("optimal", "optimal_inaccurate", "max_iterations"):
        return None, status
    x = np.asarray(sol.x)
    P = np.zeros((n, n))
    P[rows, cols] = x[:nP]
    P[cols, rows] = x[:nP]
    return P, status
