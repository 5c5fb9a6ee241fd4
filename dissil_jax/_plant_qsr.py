"""Supply rates of plants from coarse knowledge (paper Lemma 8) and LTI passivity indices.

All supply rates here describe the **plant operator** $u\\mapsto y$ ($u\\in\\mathbb R^m$,
$y\\in\\mathbb R^p$): $w(u, y) = y^\\top Qy + 2y^\\top Su + u^\\top Ru$ with $Q$ $p\\times p$,
$S$ $p\\times m$, $R$ $m\\times m$, ready for
[`stabilising_qsr`][dissil_jax.stabilising_qsr] and
[`closed_loop_certificate`][dissil_jax.closed_loop_certificate] (paper Theorem 1).
The SDPs are solved in float64 by cvxpy + Clarabel with single-threaded BLAS, on the plant
in balanced units (states balanced, outputs divided by a power of two near the plant's
gain; `_plant_units.py`), and the rate is mapped back exactly: the answers do not depend
on the realisation or on the signals' units. Static LTI plants ($n = 0$, $y = Du$) are
accepted: their rates follow from $D$ alone.
"""

from __future__ import annotations

import functools

import numpy as np

from . import _plant_common as common
from ._frequency import vanishing_supply as _vanishing_supply
from ._plant_sector import (
    sector_lemma_matrix as sector_lemma_matrix,  # re-exported
    sector_plant_qsr as sector_plant_qsr,
)
from ._plant_units import PlantUnits
from ._supply import QSR
from ._validate import check_real, real_scalar

# -- LTI plants: discrete KYP (paper Lemma 2) with the plant's supply rate ------------------


def _kyp_expr(A, B, C, D, P, Q, S, R):
    """The Lemma 2 KYP matrix as a cvxpy expression (⪯ 0 means dissipative)."""
    import cvxpy as cp

    top = cp.hstack([A.T @ P @ A - P - C.T @ Q @ C, A.T @ P @ B - C.T @ S - C.T @ Q @ D])
    bot = cp.hstack([B.T @ P @ A - S.T @ C - D.T @ Q @ C,
                     B.T @ P @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R])
    return common.sym(cp.vstack([top, bot]))


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
    common.solve(prob, kind_names[kind], A)
    val = lambda e: float(common.value(e)) if isinstance(e, cp.Expression) else float(e)
    return val(rho_e), val(nu_e)


def _certified(A, B, C, D, qsr: QSR) -> bool:
    from ._certify.certify import certify
    from ._controller import LTIController

    return bool(certify(LTIController(A, B, C, D), qsr).holds)


def _backed_off(A, B, C, D, make, value: float, backoff: float, what: str,
                units: PlantUnits, k: float, unit: float) -> QSR:
    """Shrink `value` until `make(value)` is strictly certified by `dj.certify` (all in the
    scaled units of `units`); returns that rate in the plant's units, times `k`
    (`PlantUnits.rate`). `unit`: one scaled unit of `value` in the plant's units (for the
    error message)."""
    step = backoff * max(abs(value), 1e-6)  # the plant's gain is about 1 here
    for _ in range(6):
        cand = value - step
        qsr = make(cand)
        if _certified(A, B, C, D, qsr):
            return units.rate(qsr, k)
        step *= 10
    hint = common.hint(what, A) if common.radius(A) >= 1 else (
        _vanishing_supply(A, B, C, D, qsr) or
        f"The plant `A` is stable (spectral radius {common.radius(A):.4g} < 1), so it may be "
        "nearly lossless.")
    raise common.SolverFailure(f"could not certify the {what} strictly near its optimum "
                     f"{value * unit:.6g}. {hint}")


def _balanced_retry(fn):
    """`fn(plant, ...)`, and when its SDP or certificate fails on the numbers, `fn` once more
    on the plant's balanced realisation (`balanced_realisation`; the rate is the same for
    every realisation); the first error if that fails too, or if there is none."""

    @functools.wraps(fn)
    def wrapper(plant, **kwargs):
        try:
            return fn(plant, **kwargs)
        except common.SolverFailure as err:
            balanced = common.balanced_realisation(*common.abcd(plant))
            if balanced is None:
                raise
            try:
                return fn(balanced, **kwargs)
            except common.SolverFailure:
                raise err from None

    return wrapper


def _scaled(plant, square: str | None = None):
    """`(units, A, B, C, D)`: the plant read, a static one given a state (`with_state`),
    checked square (for `square`, the quantity asked for) and scaled (`PlantUnits`)."""
    A, B, C, D = common.with_state(*common.abcd(plant))
    if square is not None:
        _square(A, B, C, D, square)
    units = PlantUnits(A, B, C, D)
    return (units, *units.plant(A, B, C, D))


def _check_backoff(backoff) -> None:
    # a relative back-off of 1 or more would change the index's sign
    if not 0 < real_scalar(backoff) < 1:
        raise ValueError(f"`backoff` must be a number in (0, 1) (relative), got {backoff!r}.")


def _square(A, B, C, D, what: str) -> None:
    if B.shape[1] != C.shape[0]:
        raise ValueError(f"`plant` has {B.shape[1]} inputs and {C.shape[0]} outputs; {what} "
                         "needs a square plant (S = I/2).")


@_balanced_retry
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
    units, A, B, C, D = _scaled(plant, "an input passivity index")
    _, nu = _index_sdp(A, B, C, D, "nu")
    p = C.shape[0]
    make = lambda v: QSR.degenerate_conic(v, dim=p)
    return _backed_off(A, B, C, D, make, nu, backoff, "input passivity index", units,
                       units.g, units.g)


@_balanced_retry
def output_passivity_qsr(plant, *, backoff: float = 1e-3) -> QSR:
    """Largest output-feedback passivity index $\\rho$: $Q = -\\rho I$, $S = \\tfrac12I$, $R = 0$.

    $w = y^\\top u - \\rho|y|^2$; same SDP and back-off as
    [`input_passivity_qsr`][dissil_jax.input_passivity_qsr].
    """
    _check_backoff(backoff)
    units, A, B, C, D = _scaled(plant, "an output passivity index")
    rho, _ = _index_sdp(A, B, C, D, "rho")
    p = C.shape[0]
    make = lambda r: QSR(-r * np.eye(p), 0.5 * np.eye(p), np.zeros((p, p)))
    return _backed_off(A, B, C, D, make, rho, backoff, "output passivity index", units,
                       units.g, 1 / units.g)


@_balanced_retry
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
    nu = None if nu is None else check_real("nu", nu)
    units, A, B, C, D = _scaled(plant, "joint passivity indices")
    p, g = C.shape[0], units.g
    if nu is None:
        rho_max, _ = _index_sdp(A, B, C, D, "rho")
        _, nu_max = _index_sdp(A, B, C, D, "nu")
        rho, nu_v = _index_sdp(A, B, C, D, "ray", ray=(rho_max, nu_max))
        scale = lambda s: QSR(-s * rho * np.eye(p), 0.5 * np.eye(p), -s * nu_v * np.eye(p))
        return _backed_off(A, B, C, D, scale, 1.0, backoff, "joint passivity indices",
                           units, g, 1.0)
    nu_s = nu / g  # in the scaled units, exactly (g is a power of two)
    rho, _ = _index_sdp(A, B, C, D, "rho_at_nu", nu_fixed=nu_s)
    make = lambda r: QSR(-r * np.eye(p), 0.5 * np.eye(p), -nu_s * np.eye(p))
    return _backed_off(A, B, C, D, make, rho, backoff, "output index at the given `nu`",
                       units, g, 1 / g)


@_balanced_retry
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
    units, A, B, C, D = _scaled(plant)
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
    prob = cp.Problem(cp.Minimize(t), [common.sym(M) >> 0, P >> 0])
    common.solve(prob, "cone", A)
    Sv, tv = common.value(S), float(common.value(t))
    make = lambda neg_t: QSR(-np.eye(p), Sv, -neg_t * np.eye(m) - Sv.T @ Sv)
    return _backed_off(A, B, C, D, make, -tv, backoff, "cone radius", units, units.g**2,
                       units.g**2)
