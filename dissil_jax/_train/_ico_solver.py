"""One Clarabel solver per ICO initialisation, updated in place every iteration."""

from __future__ import annotations

import numpy as np

from ._ico_sdp import ICOProblem

_OK = {"Solved", "AlmostSolved"}


def settings(max_iter: int = 200):
    import clarabel

    s = clarabel.DefaultSettings()
    s.verbose = False
    s.presolve_enable = False  # in-place data updates need all three off
    s.chordal_decomposition_enable = False
    s.input_sparse_dropzeros = False
    s.max_iter = max_iter
    return s


class ICOSolver:
    """One Clarabel solver for one initialisation (not thread-safe: one per thread)."""

    def __init__(self, problem: ICOProblem, max_iter: int = 200):
        self.problem = problem
        self.solver = None
        self.max_iter = max_iter
        self.obj_val = np.nan

    def solve(self, theta0, P_tilde, w_tilde, eps=None):
        """One ICO step. Returns `(dtheta, P, w, status, solve_time)`; None fields on failure."""
        import clarabel

        pb = self.problem
        q, vals, b, _, ps = pb.data(theta0, P_tilde, w_tilde, eps)
        if self.solver is None:
            self.solver = clarabel.DefaultSolver(pb.H, q, pb.matrix(vals), b, pb.cones,
                                                 settings(self.max_iter))
        else:
            self.solver.update(q=q, A=vals, b=b)
        sol = self.solver.solve()
        status = str(sol.status)
        self.obj_val = float(sol.obj_val)
        if status not in _OK:
            return None, None, None, status, float(sol.solve_time)
        x = np.asarray(sol.x)
        P = None
        if pb.qsr is not None:
            P = np.zeros((pb.n, pb.n))
            P[pb.lmi.p_rows, pb.lmi.p_cols] = ps * x[pb.oP:pb.oY]
            P = P + np.triu(P, 1).T
        return x[:pb.ntheta], P, float(x[pb.ow]), status, float(sol.solve_time)
