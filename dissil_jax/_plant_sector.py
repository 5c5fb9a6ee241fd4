"""A sector-bounded plant's cone supply rate (paper Lemma 8)."""

from __future__ import annotations

from typing import Literal, overload

import numpy as np

from . import _plant_common as common
from ._plant_units import PlantUnits
from ._supply import QSR
from ._validate import check_real

# -- paper Lemma 8 -------------------------------------------------------------------------


def sector_lemma_matrix(A, B, C, D, alpha, qsr: QSR, P, tau=None) -> np.ndarray:
    """The Lemma 8 matrix (must be $\\succeq 0$), vector form with $P\\preceq\\tau I$.

    $$\\begin{bmatrix} C^\\top QC + P - 2\\alpha^2\\tau I - 2A^\\top PA &
    C^\\top QD + C^\\top S - 2A^\\top PB \\\\ \\ast &
    D^\\top QD + S^\\top D + D^\\top S + R - 2B^\\top PB\\end{bmatrix}$$

    For a scalar state $\\tau = P$ and this is exactly paper eq. 21. `tau` defaults to
    $\\lambda_{\\max}(P)$.
    """
    A, B, C, D = common.abcd((A, B, C, D), "A, B, C, D")
    alpha = check_real("alpha", alpha, "a finite real scalar")
    if not isinstance(qsr, QSR):
        raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
    if qsr.S.shape != (C.shape[0], B.shape[1]):
        raise ValueError(f"`qsr` must be a rate of the plant's map u -> y, with S of shape "
                         f"{(C.shape[0], B.shape[1])}; got S of shape {qsr.S.shape}.")
    n = A.shape[0]
    P = np.atleast_2d(np.asarray(P))
    if P.shape != (n, n) or P.dtype.kind not in "iuf" or not np.all(np.isfinite(P)):
        raise ValueError(f"`P` must be a finite real {n}x{n} matrix, got shape {P.shape} "
                         f"({P.dtype}).")
    P = P.astype(np.float64)
    tau = np.linalg.eigvalsh(P)[-1] if tau is None else check_real("tau", tau)
    Q, S, R = qsr.Q, qsr.S, qsr.R
    top = np.hstack([C.T @ Q @ C + P - 2 * alpha**2 * tau * np.eye(n) - 2 * A.T @ P @ A,
                     C.T @ Q @ D + C.T @ S - 2 * A.T @ P @ B])
    bot = D.T @ Q @ D + S.T @ D + D.T @ S + R - 2 * B.T @ P @ B
    return common.sym(np.vstack([top, np.hstack([top[:, n:].T, bot])]))


@overload
def sector_plant_qsr(A, B, C, D, alpha, *, return_storage: Literal[False] = False) -> QSR: ...


@overload
def sector_plant_qsr(A, B, C, D, alpha, *,
                     return_storage: Literal[True]) -> tuple[QSR, np.ndarray]: ...


def sector_plant_qsr(A, B, C, D, alpha, *, return_storage: bool = False
                     ) -> QSR | tuple[QSR, np.ndarray]:
    """Smallest-radius cone supply rate of a sector-bounded plant (paper Lemma 8).

    For $x^+ = Ax + \\alpha\\sin(x) + Bu$, $y = Cx + Du$, with $V = x^\\top Px$,
    $z = Ax + Bu$, $\\varphi = \\alpha\\sin x$: Young's inequality
    $(z+\\varphi)^\\top P(z+\\varphi)\\le 2z^\\top Pz + 2\\varphi^\\top P\\varphi$ and
    $\\varphi^\\top P\\varphi\\le\\tau\\alpha^2x^\\top x$ (when $P\\preceq\\tau I$, since
    $|\\sin x_i|\\le|x_i|$) turn $w - \\Delta V\\ge 0$ into the LMI of
    [`sector_lemma_matrix`][dissil_jax.sector_lemma_matrix] $\\succeq 0$ (paper eq. 21; for a
    scalar state $\\tau = P$). With the cone supply rate

    $$Q = -I,\\quad S,\\quad R = r^2I - S^\\top S \\qquad (w = r^2|u|^2 - |y - Su|^2)$$

    the LMI is, by a Schur complement,
    $\\begin{bmatrix}\\operatorname{diag}(P - 2\\alpha^2\\tau I, r^2I) & [A\\ B]^\\top P &
    [C\\ \\ D - S]^\\top\\\\ \\ast & P/2 & 0\\\\ \\ast & \\ast & I\\end{bmatrix}\\succeq0$,
    jointly convex in $(P, \\tau, S, r^2)$, and $r^2$ is minimised (the conic-radius
    design of the paper's reference [joshi2002design]). For the paper's plant
    $(0.5, 1, 1, -2, 0.4)$ this gives $S = 32/9\\approx3.556$, $R = 88/3\\approx29.333$.

    **Arguments:** `A`, `B`, `C`, `D` (matrices or plain floats for a scalar plant) and the
    scalar sector gain `alpha`; `return_storage` also returns $P$.

    The SDP is solved with the output and the state scaled by powers of two so that the
    plant's gain is about 1 (the rate and $P$ mapped back exactly, so they scale with the
    signals' units), and asks the Schur matrix $\\succeq 10^{-8}I$ there (`MARGIN`), so
    that the returned rate's own Lemma 8 matrix is positive semidefinite, not merely to
    the solver's tolerance.

    **Returns:** the plant's `QSR` (or `(qsr, P)`), checked in float64: its Lemma 8 matrix
    with $P$ has no negative eigenvalue (a `ValueError` otherwise).

    ```python
    qsr = dj.sector_plant_qsr(0.5, 1.0, 1.0, -2.0, 0.4)   # QSR(-1, 3.556, 29.333)
    ```
    """
    A, B, C, D = common.abcd((A, B, C, D), "A, B, C, D")
    alpha = check_real("alpha", alpha, "a finite real scalar")
    # solved with the outputs and the state in units where the plant's gain is about 1
    # (`_plant_units.py`); one common state factor keeps the bound P <= tau I as it is
    units = PlantUnits(A, B, C, D, per_state=False)
    P, qsr = _lemma8(*units.plant(A, B, C, D), alpha)
    k = units.g**2  # keeps Q = -I
    qsr, P = units.rate(qsr, k), units.storage(P, k)
    return (qsr, P) if return_storage else qsr


#: The Lemma 8 SDP's Schur matrix is asked to be at least this (times I) in the scaled
#: units, so that the returned rate's own Lemma 8 matrix is positive definite by as much
#: (a Schur complement of M - MARGIN I), not merely to Clarabel's tolerance.
MARGIN = 1e-8


def _lemma8(A, B, C, D, alpha):
    """`(P, qsr)` of the minimal-radius Lemma 8 cone (plant in scaled units), checked: its
    Lemma 8 matrix must be positive semidefinite in float64."""
    import cvxpy as cp

    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    P = cp.Variable((n, n), symmetric=True)
    tau = cp.Variable()
    S = cp.Variable((p, m))
    t = cp.Variable()
    AB = np.hstack([A, B])
    top_left = cp.bmat([[P - 2 * alpha**2 * tau * np.eye(n), np.zeros((n, m))],
                        [np.zeros((m, n)), t * np.eye(m)]])
    CD = cp.hstack([C, D - S])
    M = cp.bmat([[top_left, (P @ AB).T, CD.T],
                 [P @ AB, P / 2, np.zeros((n, p))],
                 [CD, np.zeros((p, n)), np.eye(p)]])
    size = 2 * n + m + p
    cons: list[cp.Constraint] = [common.sym(M) >> MARGIN * np.eye(size), P >> 0,
                                 tau * np.eye(n) - P >> 0]
    prob = cp.Problem(cp.Minimize(t), cons)
    common.solve(prob, "Lemma 8", A)
    Pv, Sv, tv = common.sym(common.value(P)), common.value(S), float(common.value(t))
    qsr = QSR(-np.eye(p), Sv, tv * np.eye(m) - Sv.T @ Sv)
    lam = np.linalg.eigvalsh(sector_lemma_matrix(A, B, C, D, alpha, qsr, Pv))[0]
    if not lam >= 0 or not np.linalg.eigvalsh(Pv)[0] >= 0:
        raise ValueError(f"the Lemma 8 SDP returned an inaccurate solution (the returned "
                         f"rate's Lemma 8 matrix has eigenvalue {lam:.3g}; it must be >= 0): "
                         "check the plant data `A, B, C, D, alpha`.")
    return Pv, qsr
