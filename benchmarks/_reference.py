"""cvxpy references for the benchmarks: the same convexified projection, built in cvxpy."""

import cvxpy as cp
import numpy as np


def cvxpy_projection_problem(qsr, n, eps=1e-6, reg=1e-6, weights=None, floor=1e-2):
    """A DPP-parametrised cvxpy problem of paper eq. 13 (target and P~ are Parameters).

    With `dj.project`'s conditioning bound $P \\succeq \\frac{\\rho}{n}\\operatorname{tr}(P) I$
    ($\\rho$ = `floor`, left out for n = 1 as in `dj.project`; 0 drops it).

    `weights`: optional per-entry weights of the distance (`dj.project`'s `metric`), the
    four arrays `(W_A, W_B, W_C, W_D)`, fixed in the problem."""
    m, p = qsr.S.shape
    L = qsr.neg_q_factor()
    r = L.shape[1]
    A, B = cp.Variable((n, n)), cp.Variable((n, p))
    C, D = cp.Variable((m, n)), cp.Variable((m, p))
    P = cp.Variable((n, n), symmetric=True)
    tA, tB = cp.Parameter((n, n)), cp.Parameter((n, p))
    tC, tD = cp.Parameter((m, n)), cp.Parameter((m, p))
    Pt = cp.Parameter((n, n), symmetric=True)
    S, R = qsr.S, qsr.R
    Dblk = -D.T @ S - S.T @ D - R
    if r:
        blocks = [
            [-P, -C.T @ S, C.T @ L, (Pt @ A).T],
            [-(C.T @ S).T, Dblk, D.T @ L, (Pt @ B).T],
            [(C.T @ L).T, (D.T @ L).T, -np.eye(r), np.zeros((r, n))],
            [Pt @ A, Pt @ B, np.zeros((n, r)), P - 2 * Pt],
        ]
    else:
        blocks = [[-P, -C.T @ S, (Pt @ A).T], [-(C.T @ S).T, Dblk, (Pt @ B).T],
                  [Pt @ A, Pt @ B, P - 2 * Pt]]
    M = cp.bmat(blocks)
    N = M.shape[0]
    diffs = [X - T for X, T in ((A, tA), (B, tB), (C, tC), (D, tD))]
    if weights is not None:
        diffs = [cp.multiply(np.sqrt(np.asarray(w, np.float64)), d)
                 for w, d in zip(weights, diffs)]
    obj = sum(cp.sum_squares(d) for d in diffs) + reg * cp.sum_squares(P - Pt)
    cons = [(M + M.T) / 2 << -eps * np.eye(N)]
    if floor > 0 and n > 1:
        cons.append(P - (floor / n) * cp.trace(P) * np.eye(n) >> 0)
    prob = cp.Problem(cp.Minimize(obj), cons)
    return prob, (tA, tB, tC, tD, Pt), (A, B, C, D, P)


def solve_reference(prob, params, variables, K, P_ref):
    for par, val in zip(params, (*K, P_ref)):
        par.value = np.asarray(val, np.float64)
    prob.solve(solver=cp.CLARABEL)
    return tuple(v.value for v in variables)
