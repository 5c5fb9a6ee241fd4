"""Supply rates with an indefinite $Q$: the split $Q = Q_+ - Q_-$, feasibility, a feasible point.

The KYP matrix contains $-H^\\top QH$ with $H = [C\\ D]$. Its part $+H^\\top Q_-H$ is convex
and is Schur-complemented with $Q_- = L_-L_-^\\top$ like a negative semidefinite $Q$. The part
$-H^\\top Q_+H$ is concave; since $(H - H_0)^\\top Q_+(H - H_0) \\succeq 0$,

$$-H^\\top Q_+H \\preceq -H_0^\\top Q_+H - H^\\top Q_+H_0 + H_0^\\top Q_+H_0,$$

with equality at $H = H_0$. Replacing the term by this affine bound gives a convex inner
approximation of the dissipative set that is exact at the linearisation point $H_0$
(`docs/concepts.md`, *Indefinite Q*; the term itself is assembled by `ConvexifiedLMI`).
Plain float64 numpy; no solver code.
"""

from __future__ import annotations

import numpy as np

from .._rate_scale import balanced_blocks, rate_factor, scaled_rate
from .._supply import QSR

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
    qsr = scaled_rate(qsr, rate_factor(qsr))  # its tolerance is for rates of unit size
    p = qsr.n_in
    # The count is an inertia, which a congruence keeps (Sylvester): the blocks are scaled to
    # unit size by powers of two first, so that a small R beside a large Q (a gain bound of
    # 1e-6: eigenvalues -1 and 1e-12) is not taken for round-off; a zero block takes its
    # unit from S (a degenerate cone with a tiny S: eigenvalue ~|S|^2/|R|).
    w = np.linalg.eigvalsh(_supply_matrix(balanced_blocks(qsr, cross=True)[2]))
    scale = max(1.0, float(np.abs(w).max(initial=0.0)))
    n_pos = int(np.sum(w > _TOL * scale))
    if n_pos < p:
        n_pos = max(n_pos, _positive_by_schur(qsr))
    if n_pos < p:
        raise ValueError(
            f"`qsr` is infeasible: its supply form [[Q, S], [S', R]] has {n_pos} positive "
            f"eigenvalue(s) but the controller has {p} input(s), so no controller of any order "
            "is strictly dissipative (D'QD + D'S + S'D + R > 0 has no solution D). Check the "
            "signs of R and S, or derive the rate with `dj.stabilising_qsr` with smaller margins."
        )


def _positive_by_schur(qsr: QSR) -> int:
    """The positive eigenvalues of $\\Phi$ counted through the Schur complement when
    $Q\\prec0$ (Haynsworth: inertia$(\\Phi)$ = inertia$(Q)$ + inertia$(R - S^\\top Q^{-1}S)$),
    0 otherwise. A narrow cone far from zero, $[10^5, 10^5 + 1]$, has $\\Phi$ with entries
    of $10^{10}$ and one positive eigenvalue of $2.5\\cdot10^{-11}$, below the round-off of
    an eigen-decomposition of $\\Phi$; its Schur complement, $(b - a)^2/4 = 0.25$, is
    computed with an error of about $\\varepsilon\\lVert S\\rVert^2\\lVert Q^{-1}\\rVert$."""
    found = schur_complement(qsr, _TOL)
    if found is None:
        return 0
    schur, q_max = found
    noise = 64 * np.finfo(np.float64).eps * (np.abs(qsr.R).max(initial=0.0)
                                             + np.abs(qsr.S).max(initial=0.0) ** 2 / -q_max)
    return int(np.sum(np.linalg.eigvalsh(schur) > noise))


def schur_complement(qsr: QSR, tol: float):
    """`(R - S'Q^-1 S, lambda_max(Q))` (symmetrised) when $Q\\prec0$ beyond `tol` relative,
    else None: the input block's largest value over all feedthroughs, $\\Phi(D)\\preceq
    R - S^\\top Q^{-1}S$ (the feasibility count and the margin's room use it)."""
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    q = np.linalg.eigvalsh((Q + Q.T) / 2)
    if not q.size or q[-1] >= -tol * max(1.0, float(np.abs(q).max())):
        return None
    schur = R - S.T @ np.linalg.solve(Q, S)
    return (schur + schur.T) / 2, float(q[-1])


def static_point(qsr: QSR, near=None) -> np.ndarray:
    """A real $D$ ($m\\times p$) with $D^\\top QD + D^\\top S + S^\\top D + R \\succ 0$.

    The static controller $(0, 0, 0, D)$ is strictly dissipative for every $P \\succ 0$, so
    it is a feasible linearisation point. Built from the $p$ leading eigenvectors
    $V = [V_y; V_u]$ of $\\Phi$ (then $D = V_yV_u^{-1}$), tilted by a fixed perturbation when
    $V_u$ is singular (the positive cone is open). Call `check_feasible` first.

    Depth is measured by $\\lambda_{\\min}(\\Phi(D))/(1 + \\lVert D\\rVert_{\\max}^2)$, which
    for some rates only grows with $\\lVert D\\rVert$ (for $w = \\hat y^2 - 0.1\\hat u^2$ it
    tends to 1 as $|D|\\to\\infty$, and the deepest tilt gave $|D|\\approx10^8$, a point
    too far out for any projection linearised there to pass the float64 check). So the
    candidates, their rescalings $sD$ and their negatives are ranked by depth, and of those
    with at least half the largest depth the one nearest `near` (default: 0, the smallest)
    is returned. The dissipative static gains of such a rate can form several components
    ($D\\ge0.32$ and $D\\le-0.32$ there): the projection passes its target's $D$, so that
    it is linearised in the component nearest that target.
    """
    m, p = qsr.S.shape
    Phi = _supply_matrix(qsr)
    w, V = np.linalg.eigh(Phi)
    V = V[:, ::-1][:, :p]
    G = np.random.default_rng(0).standard_normal(V.shape)

    def depth(D):
        F = D.T @ qsr.Q @ D + D.T @ qsr.S + qsr.S.T @ D + qsr.R
        return np.linalg.eigvalsh((F + F.T) / 2)[0] / (1 + np.abs(D).max() ** 2)

    cands = []
    for t in (0.0, *(0.5**k for k in range(40))):
        Vt = V + t * G
        Vy, Vu = Vt[:m], Vt[m:]
        if np.linalg.cond(Vu) > 1e8:
            continue
        cands.append(np.linalg.solve(Vu.T, Vy.T).T)
        if t == 0.0 and depth(cands[-1]) > 0:
            break
    if not cands:  # pragma: no cover - a tilt of 1 is regular for the fixed seed
        raise ValueError("`qsr` admits no strictly dissipative static controller.")
    deepest = max(cands, key=depth)
    cands += [s * deepest for s in 2.0 ** np.arange(-30.0, 1.0)]
    cands += [-D for D in cands]
    depths = np.array([depth(D) for D in cands])
    if depths.max() <= 0:  # pragma: no cover - excluded by check_feasible
        raise ValueError("`qsr` admits no strictly dissipative static controller.")
    near = np.zeros((m, p)) if near is None else np.asarray(near, np.float64)
    deep = [D for D, d in zip(cands, depths) if d >= 0.5 * depths.max()]
    return min(deep, key=lambda D: np.abs(D - near).max())
