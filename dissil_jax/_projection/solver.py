"""The Clarabel problem of one projection (paper eq. 13): fixed sparsity, numbers per call.

Cones, in order: the convexified KYP LMI ($N\\times N$, `ConvexifiedLMI`) and, when
`floor` $\\rho > 0$, the conditioning bound $P \\succeq \\frac{\\rho}{\\hat n}\\operatorname{tr}(P)\\,I$
($\\hat n\\times\\hat n$), which keeps $\\lambda_{\\min}(P)$ at least $\\rho$ times the mean
eigenvalue of $P$. Without it the projection can return a $P$ whose smallest eigenvalue sits
on the LMI's margin $\\varepsilon$; the next projection, linearised at that $\\tilde P$, then
has a feasible set of zero width along that direction ($\\varepsilon I \\preceq P \\preceq
2\\tilde P - \\varepsilon I$), and Clarabel's answer fails the exact check. The bound is
homogeneous in $P$, so a previous iterate that satisfies it stays feasible at the next
linearisation point.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .. import _outcome
from .._sdp import sdp as _sdp
from .._sdp.lmi import ConvexifiedLMI, svec_pos

_SOLVED = _outcome.code("solved")


def _floor_block(lmi: ConvexifiedLMI, floor: float) -> sp.csc_matrix:
    """$A$ of the cone $s = -A x = \\operatorname{svec}(P - \\frac{\\rho}{n}\\operatorname{tr}(P) I)$."""
    n, oP = lmi.n, lmi.ntheta
    a, b = lmi.p_rows, lmi.p_cols
    rows = [svec_pos(a, b)]
    cols = [oP + np.arange(lmi.nP)]
    vals = [-np.where(a == b, 1.0, np.sqrt(2.0))]
    diag_vars = oP + np.nonzero(a == b)[0]  # P[c, c]: -rho/n on every diagonal entry
    c, d = np.meshgrid(np.arange(n), diag_vars, indexing="ij")
    rows.append(svec_pos(c, c).ravel())
    cols.append(d.ravel())
    vals.append(np.full(c.size, floor / n))
    return sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n * (n + 1) // 2, lmi.nx))  # duplicates summed


class _ProjectionSolver:
    """Clarabel problem data for Π with fixed sparsity; numbers updated per call."""

    def __init__(self, lmi: ConvexifiedLMI, eps: float, reg: float, floor: float = 0.0):
        import clarabel

        self.lmi, self.eps, self.reg, self.floor = lmi, eps, reg, floor
        # Cone s = b - A x in PSD with s = svec(-M(x) - eps I): A = J(P~) (the LMI's sparse
        # Jacobian, fixed pattern) and b = -m0(P~) - eps svec(I).
        self.cones = [clarabel.PSDTriangleConeT(lmi.N)]
        rows = lmi.L
        if floor > 0:
            extra = _floor_block(lmi, floor)
            self.cones.append(clarabel.PSDTriangleConeT(lmi.n))
            rows += lmi.n * (lmi.n + 1) // 2  # the svec length of an n x n block
            # Stack [J; extra] once with the position of every number as its value: the
            # stacked CSC's data then say where each of its numbers comes from.
            # (csc_matrix of a CSC result is no copy; it gives the checker the one format)
            src = sp.csc_matrix(sp.vstack([
                sp.csc_matrix((np.arange(1, lmi.nnz + 1.0), lmi.indices, lmi.indptr),
                              shape=(lmi.L, lmi.nx)),
                sp.csc_matrix((lmi.nnz + 1.0 + np.arange(extra.nnz), extra.indices,
                               extra.indptr), shape=extra.shape)], format="csc"))
            src.sort_indices()
            self.order = src.data.astype(np.int64) - 1
            self.extra_vals = extra.data
            self.indptr, self.indices = src.indptr, src.indices
        else:
            self.order, self.indptr, self.indices = None, lmi.indptr, lmi.indices
        self.csc_shape = (rows, lmi.nx)
        self.reg_diag = np.full(lmi.nP, reg)
        self.solver, self.diag = None, None
        self._clarabel = clarabel

    def data(self, targets, P_tilde, eps, weights, H0=None):
        """Clarabel's `(q, A values, b, P values)` for a batch: `targets` and `weights`
        [B, ntheta] (the objective is $\\sum_k w_k(\\theta_k - \\tilde\\theta_k)^2$), `P_tilde`
        [B, n, n]; `H0` = `(C0, D0)` [B, m, n], [B, m, p], the linearisation points of an
        indefinite $Q$'s positive part."""
        P_tilde = np.asarray(P_tilde, np.float64)
        vals = self.lmi.values(P_tilde, H0)
        b = (-self.lmi.offset(P_tilde, H0)
             - np.asarray(eps, np.float64)[:, None] * self.lmi.svec_eye)
        if self.order is not None:
            count = len(vals)
            vals = np.concatenate([vals, np.broadcast_to(self.extra_vals, (count,) +
                                                         self.extra_vals.shape)], 1)
            vals = vals[:, self.order]
            b = np.concatenate([b, np.zeros((count, self.lmi.n * (self.lmi.n + 1) // 2))], 1)
        p_tilde = P_tilde[:, self.lmi.p_rows, self.lmi.p_cols]
        q = -np.concatenate([weights * targets, self.reg * p_tilde], axis=1)
        diag = np.concatenate([weights, np.broadcast_to(self.reg_diag, p_tilde.shape)], axis=1)
        return q, vals, b, diag

    def solve(self, q, vals, b, diag):
        """One solve; returns `(x or None, Outcome code, Clarabel's solve time)`."""
        if self.solver is None:
            A = sp.csc_matrix((vals, self.indices, self.indptr), shape=self.csc_shape)
            k = np.arange(len(diag) + 1)  # diagonal objective, explicit zeros kept (reg = 0)
            P_obj = sp.csc_matrix((diag, k[:-1], k), shape=(len(diag),) * 2)
            settings = _sdp.clarabel_settings(**_sdp.PROJECTION_SETTINGS)
            self.solver = self._clarabel.DefaultSolver(P_obj, q, A, b, self.cones, settings)
        elif self.diag is not None and np.array_equal(diag, self.diag):  # the same distance (always, without a metric)
            self.solver.update(q=q, A=vals, b=b)
        else:
            self.solver.update(P=diag, q=q, A=vals, b=b)
        self.diag = diag
        sol = self.solver.solve()
        outcome = _sdp.clarabel_outcome(str(sol.status))
        return (np.asarray(sol.x) if outcome == _SOLVED else None), outcome, sol.solve_time
