"""Supply rates of plants from coarse knowledge (paper Lemma 8) and LTI passivity indices.

All supply rates here describe the **plant operator** $u\\mapsto y$ ($u\\in\\mathbb R^m$,
$y\\in\\mathbb R^p$): $w(u, y) = y^\\top Qy + 2y^\\top Su + u^\\top Ru$ with $Q$ $p\\times p$,
$S$ $p\\times m$, $R$ $m\\times m$, ready for
[`stabilising_qsr`][dissil_jax.stabilising_qsr] and
[`closed_loop_certificate`][dissil_jax.closed_loop_certificate] (paper Theorem 1).
The SDPs are solved in float64 by cvxpy + Clarabel with single-threaded BLAS. Static
LTI plants ($n = 0$, $y = Du$) are accepted: their rates follow from $D$ alone.
"""

from __future__ import annotations

from typing import Literal, overload

import numpy as np

from ._frequency import vanishing_supply as _vanishing_supply
from ._sdp.sdp import single_threaded_blas
from ._supply import QSR
from ._validate import check_abcd

_SOLVER_OPTS = dict(tol_gap_abs=1e-9, tol_gap_rel=1e-9, tol_feas=1e-9, max_iter=400)


def _abcd(plant, what: str = "plant"):
    """`(A, B, C, D)` (float64, 2-d) from a plant/controller module, StateSpace or 4-tuple."""
    if isinstance(plant, (tuple, list)):
        if len(plant) != 4:
            raise ValueError(f"`{what}` as a tuple must be (A, B, C, D), got {len(plant)} items.")
        mats = plant
    elif all(hasattr(plant, k) for k in "ABCD"):
        mats = (plant.A, plant.B, plant.C, plant.D)
    else:
        raise ValueError(f"`{what}` must have matrices A, B, C, D (e.g. `dj.LinearPlant`), "
                         f"got {type(plant).__name__}.")
    out = []
    for name, M in zip("ABCD", mats):
        M = np.asarray(M, np.float64)
        if M.ndim == 0:
            M = M.reshape(1, 1)
        if M.ndim != 2:
            raise ValueError(f"`{what}.{name}` must be a matrix (one plant, no batch axis), "
                             f"got shape {M.shape}.")
        if not np.all(np.isfinite(M)):
            raise ValueError(f"`{what}.{name}` contains NaN or inf.")
        out.append(M)
    A, B, C, D = out
    check_abcd(A, B, C, D, what=f"{what}.")
    if getattr(plant, "dt", None) == 0:
        raise ValueError(f"`{what}` is a continuous-time system; discretise it first.")
    return A, B, C, D


def _with_state(A, B, C, D):
    """A static plant ($n = 0$, $y = Du$) with one decoupled, unobservable state
    $x^+ = 0$ added: the same operator $u\\mapsto y$, but cvxpy cannot build the SDPs with
    a 0x0 storage."""
    if A.shape[0]:
        return A, B, C, D
    return np.zeros((1, 1)), np.zeros((1, B.shape[1])), np.zeros((C.shape[0], 1)), D


def _solve(prob, what: str, A) -> None:
    """Solve `prob` (the `what` SDP of a plant with matrix `A`); a `ValueError` otherwise."""
    import warnings

    import cvxpy as cp

    with single_threaded_blas(), warnings.catch_warnings():
        # An inaccurate solution is checked by `certify` afterwards (`_backed_off`).
        warnings.filterwarnings("ignore", message="Solution may be inaccurate",
                                category=UserWarning)
        try:
            prob.solve(solver=cp.CLARABEL, **_SOLVER_OPTS)
            status = prob.status
        except cp.SolverError as err:  # an unbounded or infeasible problem can end so
            status = f"failed ({err})"
    if status not in ("optimal", "optimal_inaccurate"):
        ended = "failed" if status.startswith("failed") else f"is {status}"
        raise ValueError(f"the {what} SDP {ended} in Clarabel. {_hint(what, A)}")


def _value(x) -> np.ndarray:
    """The value of a cvxpy variable or expression after `_solve` (which raises unless the
    problem was solved, so the value is set)."""
    value = x.value
    assert value is not None
    return np.asarray(value)


def _radius(A) -> float:
    """The spectral radius of `A` (0 without state)."""
    return float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0


def _hint(what: str, A) -> str:
    """Why the `what` SDP or its certificate may fail for a plant with matrix `A`."""
    if what == "Lemma 8":
        return ("The plant may admit no such supply rate: Lemma 8 needs a storage with "
                "2(A'PA + alpha^2 tau I) < P, so the linear part must contract strongly "
                "(||A||^2 + alpha^2 < 1/2 suffices): check `A` and `alpha`, or describe the "
                "plant by another supply rate.")
    radius = _radius(A)
    if radius >= 1:
        return (f"The plant `A` is not stable (spectral radius {radius:.4g} >= 1): no "
                "storage exists, so the plant admits no such supply rate; stabilise it "
                "first (and check that it is discrete-time).")
    if what == "cone":
        return (f"The plant `A` is stable (spectral radius {radius:.4g} < 1), so a cone "
                "exists and the solver failed on the numbers: rescale the plant's signals.")
    return (f"The plant `A` is stable (spectral radius {radius:.4g} < 1), so the plant "
            f"itself has no such {what}: it is not passive enough (e.g. a strictly proper "
            "plant that is not passive has no output passivity index); `dj.lti_cone_qsr` "
            "describes any stable plant.")


def _sym(M):
    return (M + M.T) / 2


# -- paper Lemma 8 -------------------------------------------------------------------------


def sector_lemma_matrix(A, B, C, D, alpha, qsr: QSR, P, tau=None) -> np.ndarray:
    """The Lemma 8 matrix (must be $\\succeq 0$), vector form with $P\\preceq\\tau I$.

    $$\\begin{bmatrix} C^\\top QC + P - 2\\alpha^2\\tau I - 2A^\\top PA &
    C^\\top QD + C^\\top S - 2A^\\top PB \\\\ \\ast &
    D^\\top QD + S^\\top D + D^\\top S + R - 2B^\\top PB\\end{bmatrix}$$

    For a scalar state $\\tau = P$ and this is exactly paper eq. 21. `tau` defaults to
    $\\lambda_{\\max}(P)$.
    """
    A, B, C, D = _abcd((A, B, C, D), "A, B, C, D")
    P = np.atleast_2d(np.asarray(P, np.float64))
    tau = np.linalg.eigvalsh(P)[-1] if tau is None else float(tau)
    Q, S, R = qsr.Q, qsr.S, qsr.R
    n = A.shape[0]
    top = np.hstack([C.T @ Q @ C + P - 2 * alpha**2 * tau * np.eye(n) - 2 * A.T @ P @ A,
                     C.T @ Q @ D + C.T @ S - 2 * A.T @ P @ B])
    bot = D.T @ Q @ D + S.T @ D + D.T @ S + R - 2 * B.T @ P @ B
    return _sym(np.vstack([top, np.hstack([top[:, n:].T, bot])]))


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

    **Returns:** the plant's `QSR` (or `(qsr, P)`), checked against the Lemma 8 matrix.

    ```python
    qsr = dj.sector_plant_qsr(0.5, 1.0, 1.0, -2.0, 0.4)   # QSR(-1, 3.556, 29.333)
    ```
    """
    import cvxpy as cp

    A, B, C, D = _abcd((A, B, C, D), "A, B, C, D")
    alpha = float(np.asarray(alpha, np.float64))
    if not np.isfinite(alpha):
        raise ValueError(f"`alpha` must be a finite scalar, got {alpha}.")
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
    cons: list[cp.Constraint] = [_sym(M) >> 0, P >> 0, tau * np.eye(n) - P >> 0]
    prob = cp.Problem(cp.Minimize(t), cons)
    _solve(prob, "Lemma 8", A)
    Pv, Sv, tv = _sym(_value(P)), _value(S), float(_value(t))
    qsr = QSR(-np.eye(p), Sv, tv * np.eye(m) - Sv.T @ Sv)
    lam = np.linalg.eigvalsh(sector_lemma_matrix(A, B, C, D, alpha, qsr, Pv))[0]
    scale = 1.0 + np.abs(qsr.R).max() + np.abs(Pv).max() * (1 + np.abs(AB).max()) ** 2
    if lam < -1e-6 * scale:
        raise ValueError(f"the Lemma 8 SDP returned an inaccurate solution (min eigenvalue "
                         f"{lam:.3g}); check the plant data `A, B, C, D, alpha`.")
    return (qsr, Pv) if return_storage else qsr


# -- LTI plants: discrete KYP (paper Lemma 2) with the plant's supply rate ------------------


def _kyp_expr(A, B, C, D, P, Q, S, R):
    """The Lemma 2 KYP matrix as a cvxpy expression (⪯ 0 means dissipative)."""
    import cvxpy as cp

    top = cp.hstack([A.T @ P @ A - P - C.T @ Q @ C, A.T @ P @ B - C.T @ S - C.T @ Q @ D])
    bot = cp.hstack([B.T @ P @ A - S.T @ C - D.T @ Q @ C,
                     B.T @ P @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R])
    return _sym(cp.vstack([top, bot]))


def _index_sdp(A, B, C, D, kind: str, nu_fixed: float | None = None,
               rho_fixed: float | None = None,
               ray: tuple[float, float] | None = None) -> tuple[float, float]:
    """Maximise passivity indices under the KYP LMI; returns (rho, nu)."""
    import cvxpy as cp

    kind_names = {"nu": "input passivity index", "rho": "output passivity index",
                  "rho_at_nu": "output passivity index at the given `nu`",
                  "nu_at_rho": "input passivity index at the given rho",
                  "ray": "pair of joint passivity indices"}

    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    P = cp.Variable((n, n), symmetric=True)
    rho, nu = cp.Variable(), cp.Variable()
    cons: list[cp.Constraint] = [P >> 0]
    if kind == "nu":
        objective, rho_e, nu_e = nu, 0.0, nu
    elif kind == "rho":
        objective, rho_e, nu_e = rho, rho, 0.0
    elif kind == "rho_at_nu":
        assert nu_fixed is not None  # this kind's argument
        objective, rho_e, nu_e = rho, rho, float(nu_fixed)
    elif kind == "nu_at_rho":
        assert rho_fixed is not None
        objective, rho_e, nu_e = nu, float(rho_fixed), nu
    else:  # "ray": (rho, nu) = s * (rho_max, nu_max)
        assert ray is not None
        s = cp.Variable()
        objective, rho_e, nu_e = s, s * ray[0], s * ray[1]
    Q = -rho_e * np.eye(p)
    R = -nu_e * np.eye(m)
    S = 0.5 * np.eye(p, m)
    cons.append(_kyp_expr(A, B, C, D, P, Q, S, R) << 0)
    prob = cp.Problem(cp.Maximize(objective), cons)
    _solve(prob, kind_names[kind], A)
    val = lambda e: float(_value(e)) if isinstance(e, cp.Expression) else float(e)
    return val(rho_e), val(nu_e)


def _certified(A, B, C, D, qsr: QSR) -> bool:
    from ._certify.certify import certify
    from ._controller import LTIController

    return bool(certify(LTIController(A, B, C, D), qsr).holds)


def _backed_off(A, B, C, D, make, value: float, backoff: float, what: str):
    """Shrink `value` until `make(value)` is strictly certified by `dj.certify`."""
    step = backoff * max(abs(value), 1e-6)
    for _ in range(6):
        cand = value - step
        qsr = make(cand)
        if _certified(A, B, C, D, qsr):
            return qsr
        step *= 10
    hint = _hint(what, A) if _radius(A) >= 1 else (
        _vanishing_supply(A, B, C, D, qsr) or
        f"The plant `A` is stable (spectral radius {_radius(A):.4g} < 1), so it may be "
        "nearly lossless.")
    raise ValueError(f"could not certify the {what} strictly near its optimum {value:.6g}. "
                     f"{hint}")


def _check_backoff(backoff) -> None:
    if not (np.ndim(backoff) == 0 and np.isfinite(backoff) and backoff > 0):
        raise ValueError(f"`backoff` must be a positive finite number, got {backoff!r}.")


def _square(A, B, C, D, what: str) -> None:
    if B.shape[1] != C.shape[0]:
        raise ValueError(f"`plant` has {B.shape[1]} inputs and {C.shape[0]} outputs; {what} "
                         "needs a square plant (S = I/2).")


def input_passivity_qsr(plant, *, backoff: float = 1e-3) -> QSR:
    """Largest input-feedforward passivity index $\\nu$: $Q = 0$, $S = \\tfrac12I$, $R = -\\nu I$.

    $w = y^\\top u - \\nu|u|^2$. Solves $\\max\\nu$ s.t. KYP$(P)\\preceq0$, $P\\succeq0$
    (paper Lemma 2 with the plant's $Q,S,R$), then returns $\\nu^\\star -$ `backoff` $\\cdot|\\nu^\\star|$
    (more if needed) so that [`certify`][dissil_jax.certify] holds strictly.
    A Tustin mass-spring chain with $D_c = \\varphi I$ has $\\nu^\\star = \\varphi$.

    **Arguments:** `plant` (`dj.LinearPlant`, an `LTIController`, a discrete
    `control.StateSpace` or a tuple `(A, B, C, D)`), `backoff`.
    """
    _check_backoff(backoff)
    A, B, C, D = _with_state(*_abcd(plant))
    _square(A, B, C, D, "an input passivity index")
    _, nu = _index_sdp(A, B, C, D, "nu")
    p = C.shape[0]
    make = lambda v: QSR.degenerate_conic(v, dim=p)
    return _backed_off(A, B, C, D, make, nu, backoff, "input passivity index")


def output_passivity_qsr(plant, *, backoff: float = 1e-3) -> QSR:
    """Largest output-feedback passivity index $\\rho$: $Q = -\\rho I$, $S = \\tfrac12I$, $R = 0$.

    $w = y^\\top u - \\rho|y|^2$; same SDP and back-off as
    [`input_passivity_qsr`][dissil_jax.input_passivity_qsr].
    """
    _check_backoff(backoff)
    A, B, C, D = _with_state(*_abcd(plant))
    _square(A, B, C, D, "an output passivity index")
    rho, _ = _index_sdp(A, B, C, D, "rho")
    p = C.shape[0]
    make = lambda r: QSR(-r * np.eye(p), 0.5 * np.eye(p), np.zeros((p, p)))
    return _backed_off(A, B, C, D, make, rho, backoff, "output passivity index")


def passivity_indices(plant, *, nu: float | None = None, backoff: float = 1e-3) -> QSR:
    """Joint passivity indices $(\\rho, \\nu)$: $Q = -\\rho I$, $S = \\tfrac12I$, $R = -\\nu I$.

    $w = y^\\top u - \\rho|y|^2 - \\nu|u|^2$. The pair trades off, so:

    - `nu=None` (default): the balanced pair $(s\\rho^\\star, s\\nu^\\star)$ with the largest
      $s$, where $\\rho^\\star$, $\\nu^\\star$ are the separate maxima (three SDPs);
    - `nu` given: the largest $\\rho$ with that $\\nu$.

    Both indices positive means the plant is very strictly passive, and Theorem 1 then
    certifies the loop with **any passive controller**
    (`closed_loop_certificate(qsr, dj.QSR.passive(m))` holds with $\\alpha = 1$). The result
    is backed off by `backoff` (relative) and certified strictly.
    """
    _check_backoff(backoff)
    A, B, C, D = _with_state(*_abcd(plant))
    _square(A, B, C, D, "joint passivity indices")
    p = C.shape[0]
    if nu is None:
        rho_max, _ = _index_sdp(A, B, C, D, "rho")
        _, nu_max = _index_sdp(A, B, C, D, "nu")
        rho, nu_v = _index_sdp(A, B, C, D, "ray", ray=(rho_max, nu_max))
        scale = lambda s: QSR(-s * rho * np.eye(p), 0.5 * np.eye(p), -s * nu_v * np.eye(p))
        return _backed_off(A, B, C, D, scale, 1.0, backoff, "joint passivity indices")
    nu = float(nu)
    if not np.isfinite(nu):
        raise ValueError(f"`nu` must be finite, got {nu}.")
    rho, _ = _index_sdp(A, B, C, D, "rho_at_nu", nu_fixed=nu)
    make = lambda r: QSR(-r * np.eye(p), 0.5 * np.eye(p), -nu * np.eye(p))
    return _backed_off(A, B, C, D, make, rho, backoff, "output index at the given `nu`")


def lti_cone_qsr(plant, *, backoff: float = 1e-3) -> QSR:
    """Tightest interior cone of an LTI plant: $Q = -I$, $S$, $R = r^2I - S^\\top S$.

    $w = r^2|u|^2 - |y - Su|^2$: the plant's output stays in the ball of radius $r$
    around $Su$ (in the $\\ell_2$ sense). Minimises $r^2$ over $(P, S, r^2)$ with the Schur
    form of the KYP LMI
    $\\begin{bmatrix}\\operatorname{diag}(P, r^2I) & [A\\ B]^\\top P & [C\\ \\ D-S]^\\top\\\\
    \\ast & P & 0\\\\ \\ast & \\ast & I\\end{bmatrix}\\succeq0$,
    then inflates $r^2$ by `backoff` (relative) and certifies strictly. For a scalar plant
    $S$ is the cone's centre $c$ and the cone is $[c - r, c + r]$.
    """
    import cvxpy as cp

    _check_backoff(backoff)
    A, B, C, D = _with_state(*_abcd(plant))
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    P = cp.Variable((n, n), symmetric=True)
    S = cp.Variable((p, m))
    t = cp.Variable()
    AB = np.hstack([A, B])
    top_left = cp.bmat([[P, np.zeros((n, m))], [np.zeros((m, n)), t * np.eye(m)]])
    CD = cp.hstack([C, D - S])
    M = cp.bmat([[top_left, (P @ AB).T, CD.T],
                 [P @ AB, P, np.zeros((n, p))],
                 [CD, np.zeros((p, n)), np.eye(p)]])
    prob = cp.Problem(cp.Minimize(t), [_sym(M) >> 0, P >> 0])
    _solve(prob, "cone", A)
    Sv, tv = _value(S), float(_value(t))
    make = lambda neg_t: QSR(-np.eye(p), Sv, -neg_t * np.eye(m) - Sv.T @ Sv)
    return _backed_off(A, B, C, D, make, -tv, backoff, "cone radius")
