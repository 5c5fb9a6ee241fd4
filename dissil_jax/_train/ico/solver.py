"""One Clarabel solver per ICO initialisation, updated in place every iteration."""

from __future__ import annotations

import numpy as np

from ... import _outcome
from ..._sdp import sdp as _sdp
from .sdp import ICOProblem


class ICOSolver:
    """One Clarabel solver for one initialisation (not thread-safe: one per thread)."""

    def __init__(self, problem: ICOProblem, max_iter: int = _sdp.ICO_SETTINGS["max_iter"]):
        self.problem = problem
        self.solver = None
        self.settings: _sdp.SolverSettings = {**_sdp.ICO_SETTINGS, "max_iter": max_iter}
        self.obj_val = np.nan

    def reset(self):
        """Drop the Clarabel solver: the next `solve` builds a new one from its data.

        An updated solver keeps the equilibration of the iterate it was built at. Over a
        run the SDP's data drift (the Young weight by decades, $A$ and $B$ by several times)
        and that scaling can go stale: on a realisable passive problem the updated solver
        stopped on `InsufficientProgress` where a new one solved the same SDP.
        """
        self.solver = None

    def solve(self, theta0, P_tilde, w_tilde, eps=None, rel=0.0, prox=None):
        """One ICO step with the KYP margin `eps` $+$ `rel` $\\operatorname{tr}P$ (`KYPBlock`):
        `(dtheta, P, w, outcome, solve_time)`; None fields on failure.

        `outcome` is an `Outcome` code: `solved`, `infeasible` or `solver_failed`. A `prox`
        other than the problem's is solved by a one-off solver (the shorter step of
        `step.step_with_fallbacks`); the run's own solver is left as it was.
        """
        import clarabel

        pb = self.problem
        q, vals, b, _, ps = pb.data(theta0, P_tilde, w_tilde, eps, rel)
        if prox is not None or self.solver is None:
            H = pb.H if prox is None else pb.hessian(prox)
            solver = clarabel.DefaultSolver(H, q, pb.matrix(vals), b, pb.cones,
                                            _sdp.clarabel_settings(**self.settings))
            if prox is None:
                self.solver = solver
        else:
            solver = self.solver
            solver.update(q=q, A=vals, b=b)
        sol = solver.solve()
        outcome = _sdp.clarabel_outcome(str(sol.status))
        self.obj_val = float(sol.obj_val)
        if outcome != _outcome.code("solved"):
            return None, None, None, outcome, float(sol.solve_time)
        x = np.asarray(sol.x)
        P = None if pb.qsr is None else ps @ pb.layout.P(x[pb.oP:pb.oY]) @ ps  # P = P~^{1/2} X P~^{1/2}
        return x[:pb.ntheta], P, float(x[pb.ow]), outcome, float(sol.solve_time)
