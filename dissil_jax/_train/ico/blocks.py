"""The cone blocks of the ICO SDP (see `sdp.py` for the maths).

A block is a run of consecutive rows of the constraint $b - Ax \\in \\mathcal K$ with its
cones. It fixes its sparsity once (`pattern`) and gives its numbers at each iterate (`fill`),
in the same order; `ICOProblem` stacks the blocks and concatenates their numbers. The window
blocks are in `windows.py`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..._sdp.lmi import ConvexifiedLMI, svec, svec_indices
from .layout import SQRT2, TwoStepData, VariableLayout, svec_len, svec_pos

_NO_COLS, _NO_VALS = np.zeros(0, np.int64), np.zeros(0)


class Iterate(NamedTuple):
    """The linearisation point of one SDP and what every block computes from it."""

    theta: np.ndarray  # theta_0
    A: np.ndarray  # (A, B, C, D) of theta_0
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    P: np.ndarray | None  # P~ (None for ICO-NC)
    w: float  # w~
    eps: float  # KYP margin, absolute part
    ps: np.ndarray | float  # P~^{1/2}, the unit of the SDP's P variable (`ICOProblem.p_scale`)
    z: np.ndarray  # [N, n] A_0 x0 + B_0 u0
    ebar: np.ndarray  # [N, m] step-1 residual at delta = 0
    rel: float = 0.0  # KYP margin, part proportional to tr P (`KYPBlock`)


class ConeBlock:
    """The protocol of a block: `rows` (its number of rows), `cones` (its Clarabel cones, in
    order), `pattern()`, `fill(it)` and `objective(it)`."""

    rows: int
    cones: list
    _rows: np.ndarray  # `pattern`, set by every block's `__init__`
    _cols: np.ndarray

    def pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """`(rows, cols)` of the block's nonzeros (rows counted from the block's first row)."""
        return self._rows, self._cols

    def fill(self, it: Iterate) -> tuple[np.ndarray, np.ndarray]:
        """`(vals, b)`: the nonzeros of $A$ in `pattern` order and the block's part of $b$."""
        raise NotImplementedError

    def objective(self, it: Iterate) -> tuple[np.ndarray, np.ndarray]:
        """`(cols, q)`: entries of the linear objective that depend on the iterate (none)."""
        return _NO_COLS, _NO_VALS


class KYPBlock(ConeBlock):
    """The convexified KYP LMI $\\mathcal M_0 + \\sum_k x_k J_k \\preceq -(\\varepsilon +
    \\rho\\operatorname{tr}P) E$, balanced by
    $T = \\mathrm{diag}(\\tilde P^{-1/2}, I, I, \\tilde P^{-1/2})$ (one PSD cone).

    The margin has an absolute part $\\varepsilon$ (`Iterate.eps`) and a part $\\rho$
    (`Iterate.rel`) per unit of $\\operatorname{tr}P$. The float64 check that accepts a step
    allows round-off relative to the size of the KYP matrix, which grows with $P$; an absolute
    margin alone let the iterates inflate $P$ until the margin sank below that allowance.
    The part in $\\operatorname{tr}P$ is linear in the decision variable $P$, so the new
    iterate has it again at its own $P$ at the next linearisation.

    It owns $P$: its columns hold $X$ with $P = \\tilde P^{1/2}X\\tilde P^{1/2}$
    (`layout.colP`, `Iterate.ps` $= \\tilde P^{1/2}$), so that $X \\approx I$ and the balanced
    LMI's coefficients of $X$ are of order one however ill-conditioned $\\tilde P$ is; and the
    linear part of the proximal term $\\frac\\nu2\\lVert X - I\\rVert^2$ (`reg` $= \\nu$).
    """

    def __init__(self, lmi: ConvexifiedLMI, layout: VariableLayout, reg: float):
        import clarabel

        self.lmi, self.layout, self.reg = lmi, layout, reg
        self.size = lmi.N
        self.rows = svec_len(lmi.N)
        self.cones = [clarabel.PSDTriangleConeT(lmi.N)]
        self._idx = svec_indices(lmi.N)
        n = layout.n
        dense = np.ones((n, n)) + np.eye(n)  # generic P~: every possible nonzero present
        rng = np.random.default_rng(0)  # a generic H0 for an indefinite Q, likewise
        H0 = (rng.standard_normal((layout.m, n)), rng.standard_normal((layout.m, layout.p)))
        # a generic P~^{1/2} and margin in tr P (a round number could cancel an entry)
        G = rng.standard_normal((n, n))
        sJ = self._jacobian(dense, H0, G @ G.T + n * np.eye(n), rng.uniform(0.1, 1.0))[0]
        nonzero = sJ != 0  # [nx_lmi, rows]
        self._var, self._rows = np.nonzero(nonzero)  # lmi variable, svec row
        lmi_cols = np.concatenate([layout.col_theta, layout.colP])  # lmi variable -> column
        self._cols = lmi_cols[self._var]

    def blocks(self, P_tilde, H0=None):
        """`(M0, J, E)` of the balanced LMI $M_0 + \\sum_k x_k J_k \\preceq -\\varepsilon E$
        (`H0 = (C0, D0)`: the linearisation point of an indefinite $Q$, the iterate)."""
        n = self.layout.n
        P_tilde = np.asarray(P_tilde, np.float64)
        M0, J = self.lmi.blocks(P_tilde, H0)
        E = np.eye(self.size)
        E[-n:, -n:] = P_tilde @ P_tilde
        lam, V = np.linalg.eigh(P_tilde)
        Ph = (V / np.sqrt(lam)) @ V.T  # P~^{-1/2}
        T = np.eye(self.size)
        T[:n, :n] = Ph
        T[-n:, -n:] = Ph
        M0, E = T @ M0 @ T, T @ E @ T
        J = T @ J @ T  # broadcast over the variables (einsum here was 10x slower)
        return M0, J, E

    def _jacobian(self, P_tilde, H0, Ph, rel):
        """svec of the balanced LMI's coefficients, `[nx_lmi, rows]`, in the variables
        $(\\delta\\theta, X)$, the margin's part in $\\operatorname{tr}P$ moved to the left;
        and `(M0, E)` of `blocks`."""
        nth = self.layout.ntheta
        M0, J, E = self.blocks(P_tilde, H0)
        sJ = svec(J, self._idx)
        sE = svec(E, self._idx)
        r, c = self.lmi.p_rows, self.lmi.p_cols
        sJ[nth:][r == c] += rel * sE  # + rel tr(P) E: tr P is the sum of P's diagonal entries
        sJ[nth:] = self.unit_map(Ph).T @ sJ[nth:]  # P = Ph X Ph
        return sJ, M0, sE

    def unit_map(self, Ph) -> np.ndarray:
        """$K$ with $\\operatorname{triu}(\\Phi X\\Phi) = K\\operatorname{triu}(X)$ for
        symmetric $X$ and `Ph` $= \\Phi$ (the triangles row-major, as `layout.colP`)."""
        Ph = np.asarray(Ph, np.float64)
        r, c = self.lmi.p_rows, self.lmi.p_cols
        # column (i, j) is triu(Ph E_ij Ph), E_ij = e_i e_j' + e_j e_i' (once on the diagonal)
        K = Ph[r][:, r] * Ph[c][:, c].T
        return K + np.where(r != c, 1.0, 0.0) * Ph[r][:, c] * Ph[r][:, c].T

    def fill(self, it):
        nth = self.layout.ntheta
        sJ, M0, sE = self._jacobian(it.P, (it.C, it.D), it.ps, it.rel)
        b = -svec(M0, self._idx) - it.eps * sE - it.theta @ sJ[:nth]
        return sJ[self._var, self._rows], b

    def objective(self, it):
        r, c = self.lmi.p_rows, self.lmi.p_cols
        return self.layout.colP, -self.reg * (r == c)  # nu/2 |X - I|^2: X~ = I

    def margin(self, theta, P) -> float:
        """Margin $\\mu$ of δ = 0 at $\\tilde P = P$:
        $\\mathcal M \\preceq -\\mu\\,\\mathrm{diag}(I, P^2)$.

        Equivalently $-\\lambda_{\\max}$ of the un-congruenced Schur form of the KYP LMI.
        """
        n = self.layout.n
        P = np.asarray(P, np.float64)
        x = np.concatenate([theta, P[self.lmi.p_rows, self.lmi.p_cols]])
        T = np.eye(self.size)
        T[-n:, -n:] = np.linalg.inv(P)
        M = T @ self.lmi.evaluate(x, P, tuple(self.layout.mats(theta)[2:])) @ T
        return -float(np.linalg.eigvalsh((M + M.T) / 2)[-1])


class DeltaZCone(ConeBlock):
    """$\\lVert[\\delta A\\ \\delta B]F\\rVert_F^2/w \\le \\tau$ as the rotated SOC
    $\\lVert(2\\operatorname{vec}([\\delta A\\ \\delta B]F), w - \\tau)\\rVert \\le w + \\tau$."""

    def __init__(self, data: TwoStepData, layout: VariableLayout):
        import clarabel

        n, p, F = data.n, data.p, data.F
        r = F.shape[1]
        self.rows = 2 + n * r
        self.cones = [clarabel.SecondOrderConeT(self.rows)]
        # entry (i, l) of [dA dB] F: sum_j dAB[i, j] F[j, l]
        ii, ll, jj = np.meshgrid(np.arange(n), np.arange(r), np.arange(n + p), indexing="ij")
        ii, ll, jj = ii.ravel(), ll.ravel(), jj.ravel()
        ow, otau = layout.ow, layout.otau
        self._rows = np.concatenate([np.array([0, 0, 1, 1]), 2 + ii * r + ll])
        self._cols = np.concatenate([np.array([ow, otau, ow, otau]), layout.colAB[ii, jj]])
        self._vals = np.concatenate([[-1.0, -1.0, -1.0, 1.0], -2.0 * F[jj, ll]])
        self._b = np.zeros(self.rows)

    def fill(self, it):
        return self._vals, self._b


class YoungLMI(ConeBlock):
    """$[[Y, \\delta C], [\\delta C^\\top, \\phi(w) I]] \\succeq 0$ with the tangent
    $\\phi(w) = 2/\\tilde w - w/\\tilde w^2 \\le 1/w$ (one PSD cone of size $m + n$),
    balanced by the congruence $\\mathrm{diag}(I_m, \\tilde w^{1/2} I_n)$:

    $$\\begin{bmatrix} Y & \\tilde w^{1/2}\\delta C \\\\ \\tilde w^{1/2}\\delta C^\\top &
    (2 - w/\\tilde w) I\\end{bmatrix} \\succeq 0,$$

    the same constraint. Unbalanced, its entries $2/\\tilde w$ and $1/\\tilde w^2$ sat in
    one cone with $Y$'s, which Clarabel's equilibration scales uniformly (a cone's rows
    share one factor): when a run froze $A$ and $B$ and $\\tilde w$ fell by 4x a step to
    $6\\cdot10^{-5}$, $1/\\tilde w^2\\approx 3\\cdot10^8$ and Clarabel stopped on
    `NumericalError` at its first iteration.
    """

    def __init__(self, layout: VariableLayout):
        import clarabel

        m, n = layout.m, layout.n
        d = m + n
        self.rows = svec_len(d)
        self.cones = [clarabel.PSDTriangleConeT(d)]
        yi, yj, ycol, yw = layout.y_svec
        aa, jn = np.meshgrid(np.arange(m), np.arange(n), indexing="ij")
        aa, jn = aa.ravel(), jn.ravel()
        self._w_rows = svec_pos(m + np.arange(n), m + np.arange(n))  # the phi(w) I block
        self._rows = np.concatenate([svec_pos(yi, yj), svec_pos(aa, m + jn), self._w_rows])
        self._cols = np.concatenate([ycol, layout.colC[aa, jn], np.full(n, layout.ow)])
        self._Y = -yw
        self._dC = np.full(m * n, -SQRT2)
        self._n = n

    def fill(self, it):
        b = np.zeros(self.rows)
        b[self._w_rows] = 2.0
        return np.concatenate([self._Y, np.sqrt(it.w) * self._dC,
                               np.full(self._n, 1.0 / it.w)]), b
