"""Supply rates with an indefinite $Q$: the split $Q = Q_+ - Q_-$ and the linearised $Q_+$ term.

The KYP matrix contains $-H^\\top QH$ with $H = [C\\ D]$. Its part $+H^\\top Q_-H$ is convex
and is Schur-complemented with $Q_- = L_-L_-^\\top$ like a negative semidefinite $Q$. The part
$-H^\\top Q_+H$ is concave; since $(H - H_0)^\\top Q_+(H - H_0) \\succeq 0$,

$$-H^\\top Q_+H \\preceq -H_0^\\top Q_+H - H^\\top Q_+H_0 + H_0^\\top Q_+H_0,$$

with equality at $H = H_0$. Replacing the term by this affine bound gives a convex inner
approximation of the dissipative set that is exact at the linearisation point $H_0$
(`docs/concepts.md`, *Indefinite Q*). Plain float64 numpy; no solver code.
"""

from __future__ import annotations

import numpy as np

from ._supply import QSR

_TOL = 1e-10


def split_q(Q) -> tuple[np.ndarray, np.ndarray]:
    """`(L_minus, L_plus)` with $Q = L_+L_+^\\top - L_-L_-^\\top$ (columns: the nonzero
    eigen-directions of each sign, scaled by the square roots of the eigenvalues)."""
    # eigh of -Q, as `QSR.neg_q_factor`, so that L_minus is that factor for Q <= 0
    w, V = np.linalg.eigh(-np.asarray(Q, np.float64))
    scale = max(1.0, float(np.abs(w).max(initial=0.0)))
    neg, pos = w > _TOL * scale, w < -_TOL * scale
    return V[:, neg] * np.sqrt(w[neg]), V[:, pos] * np.sqrt(-w[pos])


def is_indefinite(qsr: QSR) -> bool:
    """True when $Q$ has a positive eigenvalue (beyond round-off), i.e. $Q_+ \\neq 0$."""
    return split_q(qsr.Q)[1].shape[1] > 0


def _supply_matrix(qsr: QSR) -> np.ndarray:
    return np.block([[qsr.Q, qsr.S], [qsr.S.T, qsr.R]])


def check_feasible(qsr: QSR) -> None:
    """Raise a `ValueError` naming `qsr` when no controller is strictly dissipative.

    A strictly dissipative controller has $D^\\top QD + D^\\top S + S^\\top D + R \\succ 0$ (the
    lower-right block of its KYP matrix is $\\prec 0$ and $B^\\top PB \\succeq 0$), i.e. the
    supply form $\\Phi = [[Q, S], [S^\\top, R]]$ is positive definite on the $p$-dimensional
    graph $\\{(Du, u)\\}$; then the static controller $D$ itself is one. Such a $D$ exists iff
    $\\Phi$ has at least $p$ positive eigenvalues: a positive subspace of dimension $p$ exists
    then, the positive subspaces are open and the graphs are dense among $p$-subspaces.
    """
    p = qsr.n_in
    w = np.linalg.eigvalsh(_supply_matrix(qsr))
    scale = max(1.0, float(np.abs(w).max(initial=0.0)))
    n_pos = int(np.sum(w > _TOL * scale))
    if n_pos < p:
        raise ValueError(
            f"`qsr` is infeasible: its supply form [[Q, S], [S', R]] has {n_pos} positive "
            f"eigenvalue(s) but the controller has {p} input(s), so no controller of any order "
            "is strictly dissipative (D'QD + D'S + S'D + R > 0 has no solution D). Check the "
            "signs of R and S, or derive the rate with `dj.stabilising_qsr` with smaller margins."
        )


def static_point(qsr: QSR) -> np.ndarray:
    """A real $D$ ($m\\times p$) with $D^\\top QD + D^\\top S + S^\\top D + R \\succ 0$.

    The static controller $(0, 0, 0, D)$ is strictly dissipative for every $P \\succ 0$, so
    it is a feasible linearisation point. Built from the $p$ leading eigenvectors
    $V = [V_y; V_u]$ of $\\Phi$ (then $D = V_yV_u^{-1}$), tilted by a fixed perturbation when
    $V_u$ is singular (the positive cone is open). Call `check_feasible` first.
    """
    m, p = qsr.S.shape
    Phi = _supply_matrix(qsr)
    w, V = np.linalg.eigh(Phi)
    V = V[:, ::-1][:, :p]
    G = np.random.default_rng(0).standard_normal(V.shape)
    best, best_margin = None, -np.inf
    for t in (0.0, *(0.5**k for k in range(40))):
        Vt = V + t * G
        Vy, Vu = Vt[:m], Vt[m:]
        if np.linalg.cond(Vu) > 1e8:
            continue
        D = np.linalg.solve(Vu.T, Vy.T).T
        F = D.T @ qsr.Q @ D + D.T @ qsr.S + qsr.S.T @ D + qsr.R
        margin = np.linalg.eigvalsh((F + F.T) / 2)[0] / (1 + np.abs(D).max() ** 2)
        if margin > best_margin:
            best, best_margin = D, margin
        if margin > 0 and t == 0.0:
            break
    if best is None or best_margin <= 0:  # pragma: no cover - excluded by check_feasible
        raise ValueError("`qsr` admits no strictly dissipative static controller.")
    return best


class QPlusTerm:
    """The linearised $-H^\\top Q_+H$ inside the convexified KYP matrix.

    In the matrix $\\mathcal M$ of `ConvexifiedLMI` the rows and columns $0..n+p$ are the
    $(x, u)$ blocks, indexed exactly like the columns of $H = [C\\ D]$. The bound adds

    - to $\\mathcal M_0$ the constant $H_0^\\top Q_+H_0$ in that block, and
    - to the Jacobian column of $H_{aj}$ the matrix $-(w_a e_j^\\top + e_jw_a^\\top)$ with
      $w_a = (H_0^\\top Q_+)_{:,a}$, where $H_{aj}$ is $C_{aj}$ ($j < n$) or $D_{a,j-n}$.

    Both depend on $H_0$ only, like the $\\tilde P$-dependent $A$, $B$ columns.
    """

    def __init__(self, n: int, p: int, m: int, L_plus: np.ndarray, oC: int, oD: int):
        self.n, self.p, self.m = n, p, m
        self.Qp = L_plus @ L_plus.T
        aa, jj = np.meshgrid(np.arange(m), np.arange(n + p), indexing="ij")
        self.a, self.j = aa.ravel(), jj.ravel()  # one entry per variable of H
        self.var = np.where(self.j < n, oC + self.a * n + self.j, oD + self.a * p + self.j - n)

    def H0(self, C0, D0) -> np.ndarray:
        return np.concatenate([np.asarray(C0, np.float64), np.asarray(D0, np.float64)], -1)

    def dense(self, C0, D0, N: int) -> tuple[np.ndarray, np.ndarray]:
        """`(dM0 [N, N], dJ [n_H, N, N])` at one $H_0$, `dJ[k]` for variable `var[k]`."""
        H0 = self.H0(C0, D0)
        W = H0.T @ self.Qp  # [n+p, m]
        k = self.n + self.p
        dM0 = np.zeros((N, N))
        dM0[:k, :k] = W @ H0
        dJ = np.zeros((len(self.var), N, N))
        idx = np.arange(len(self.var))
        dJ[idx, :k, self.j] -= W[:, self.a].T
        dJ[idx, self.j, :k] -= W[:, self.a].T
        return dM0, dJ

    def sparse_entries(self):
        """`(var, row, col, a, i)` of every nonzero of the Jacobian part (upper triangle):
        the entry $(\\min(i,j), \\max(i,j))$ of variable $H_{aj}$ has value
        $-c\\,(H_0^\\top Q_+)_{i,a}$, $c = 2$ on the diagonal ($i = j$), else 1."""
        k = self.n + self.p
        var = np.repeat(self.var, k)
        a = np.repeat(self.a, k)
        j = np.repeat(self.j, k)
        i = np.tile(np.arange(k), len(self.var))
        return var, np.minimum(i, j), np.maximum(i, j), a, i

    def W(self, C0, D0) -> np.ndarray:
        """$H_0^\\top Q_+$ for a batch of linearisation points `[B, m, n]`, `[B, m, p]`."""
        # einsum (not BLAS) so that a row's numbers do not depend on the batch size
        return np.einsum("bai,ak->bik", self.H0(C0, D0), self.Qp)


class QPlusData:
    """The linearised $-H^\\top Q_+H$ of an indefinite $Q$ in Clarabel's numbers
    (`QPlusTerm`): extra Jacobian entries in the $C$, $D$ columns and a constant in $b$, both
    computed from the batch's linearisation points $H_0$ without dense $N\\times N$ tensors."""

    def __init__(self, lmi):
        term = self.term = lmi.qplus
        var, r, c, self.a, self.i = term.sparse_entries()
        pos = _svec_pos(r, c)
        self.var, self.rows = var, pos
        self.coef = np.where(r == c, 2.0, np.sqrt(2.0))  # -c W[i, a], times svec's weight
        k = lmi.n + lmi.p
        self.const_r, self.const_c = np.triu_indices(k)  # H0' Q+ H0 in the (x, u) block
        self.const_pos = _svec_pos(self.const_r, self.const_c)
        self.const_w = np.where(self.const_r == self.const_c, 1.0, np.sqrt(2.0))

    def locate(self, rows, cols):
        """Bind to the CSC order: where each entry's value goes in the `vals` array."""
        key = {(int(r), int(c)): k for k, (r, c) in enumerate(zip(rows, cols))}
        self.vals_pos = np.array([key[(int(r), int(c))] for r, c in zip(self.rows, self.var)])
        return self

    def add(self, vals, b, H0):
        if H0 is None:  # pragma: no cover - a bug guard
            raise AssertionError("an indefinite Q needs linearisation points")
        W = self.term.W(*H0)  # [B, n+p, m]
        # each (variable, position) is listed once, so a plain scatter suffices
        vals[:, self.vals_pos] -= self.coef * W[:, self.i, self.a]
        G = np.einsum("bia,baj->bij", W, self.term.H0(*H0))  # H0' Q+ H0
        b[:, self.const_pos] -= self.const_w * G[:, self.const_r, self.const_c]


def _svec_pos(r, c):
    """Position of the upper-triangle entry (r <= c) in Clarabel's column-major svec."""
    return c * (c + 1) // 2 + r
