"""Closed-loop evaluation of learned controllers against the expert (paper Tables 2-5, Figs 1-6).

For each learned controller the test protocol simulates the expert and the controller from
the same test initial states with the same noise realisation and reports

- a **stability verdict**: exact for an `LTIController` on a `LinearPlant` (spectral radius
  of the closed-loop matrix $<1$ and a well-posed loop), otherwise the documented
  simulation rule of [`rule_stable`][dissil_jax.experiments.rule_stable];
- the **state MSE** $\\frac{1}{N_x T}\\sum_i\\sum_{k=1}^{T}\\lVert x^{(i)}_{e}(k) - x^{(i)}(k)\\rVert^2$
  (paper §5.1), set to $+\\infty$ for unstable controllers, so that maxima are $\\infty$
  and medians/quartiles count unstable controllers as the worst ones.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._controller import LTIController
from .simulate import (
    CONTROL_NOISE,
    PLANT_NOISE,
    Trajectories,
    _check_sigma,
    sample_noise,
    simulate_controllers,
    simulate_expert,
)

# Rule for plants without an exact test (documented in docs/problems.md).
RULE_REL = 0.5
RULE_ABS = 1.0
# `rule_bounded`: states may not grow past this multiple of (|x0| + 1).
BOUND_FACTOR = 10.0
# Loops with cond(I + Dc D) above this are treated as ill posed (not stable).
_ILL_POSED_COND = 1e12


def lti_closed_loop_matrix(plant, controller: LTIController) -> np.ndarray:
    """The state matrix of plant $(A,B,C,D)$ and controller $(A_c,B_c,C_c,D_c)$ in negative feedback.

    With $u = -\\hat y$, $\\hat u = y$ and the feedthrough loop solved,
    $u = -\\Phi(D_cCx + C_c\\hat x)$ with $\\Phi = (I + D_cD)^{-1}$:

    $$\\begin{bmatrix}x\\\\ \\hat x\\end{bmatrix}^+ = \\begin{bmatrix}
    A - B\\Phi D_cC & -B\\Phi C_c \\\\ B_c(C - D\\Phi D_cC) & A_c - B_cD\\Phi C_c
    \\end{bmatrix}\\begin{bmatrix}x\\\\ \\hat x\\end{bmatrix}.$$

    **Arguments:** a plant with matrices `A, B, C, D` (e.g. `dj.LinearPlant`) and one
    unbatched `LTIController`.

    **Returns:** the float64 closed-loop matrix, `(n + n̂) x (n + n̂)`. Raises a ValueError
    naming `controller` when sizes do not match or $I + D_cD$ is singular (ill posed).
    """
    A, B, C, D = (np.asarray(M, np.float64) for M in (plant.A, plant.B, plant.C, plant.D))
    Ac, Bc, Cc, Dc = (np.asarray(M, np.float64) for M in
                      (controller.A, controller.B, controller.C, controller.D))
    if Ac.ndim != 2:
        raise ValueError("`controller` must be a single LTIController; index the batch first.")
    if Bc.shape[1] != C.shape[0] or Cc.shape[0] != B.shape[1]:
        raise ValueError(
            f"`controller` maps R^{Bc.shape[1]} -> R^{Cc.shape[0]} but the plant maps "
            f"R^{B.shape[1]} -> R^{C.shape[0]}; the controller must map R^{C.shape[0]} -> "
            f"R^{B.shape[1]}."
        )
    M = np.eye(B.shape[1]) + Dc @ D
    if np.linalg.cond(M) > _ILL_POSED_COND:
        raise ValueError("`controller` makes the loop ill posed: I + Dc D is singular.")
    Phi = np.linalg.inv(M)
    top = np.hstack([A - B @ Phi @ Dc @ C, -B @ Phi @ Cc])
    bot = np.hstack([Bc @ (C - D @ Phi @ Dc @ C), Ac - Bc @ D @ Phi @ Cc])
    return np.vstack([top, bot])


def lti_spectral_radius(plant, controllers: LTIController) -> np.ndarray:
    """Spectral radius of each closed loop (`[K]`; `inf` for an ill-posed loop)."""
    if not isinstance(controllers, LTIController) or controllers.A.ndim != 3:
        raise ValueError("`controllers` must be an LTIController with one leading batch axis.")
    out = np.empty(controllers.A.shape[0])
    for i in range(out.shape[0]):
        Ki = jax.tree.map(lambda l: l[i], controllers)
        if not all(np.all(np.isfinite(np.asarray(M))) for M in (Ki.A, Ki.B, Ki.C, Ki.D)):
            out[i] = np.inf  # a diverged training run (e.g. GD with a large step) is unstable
            continue
        try:
            out[i] = np.abs(np.linalg.eigvals(lti_closed_loop_matrix(plant, Ki))).max()
        except ValueError as err:
            if "ill posed" not in str(err):
                raise
            out[i] = np.inf
    return out


def _states_and_finite(traj: Trajectories):
    """`x` `[K, N, T+1, n]` in float64 and whether each (controller, trajectory) stayed finite."""
    x = np.asarray(traj.x, np.float64)
    if x.ndim != 4:
        raise ValueError(f"`traj.x` must be [K, N, T+1, n] (a batch of controllers), got {x.shape}.")
    finite = np.isfinite(x).all(axis=(2, 3)) & np.isfinite(np.asarray(traj.u)).all(axis=(2, 3))
    if traj.xhat is not None:
        finite &= np.isfinite(np.asarray(traj.xhat)).all(axis=(2, 3))
    return x, finite


def rule_stable(traj: Trajectories, rel: float = RULE_REL, abs_tol: float = RULE_ABS
                ) -> Bool[np.ndarray, " K"]:
    """The simulation stability rule used when no exact test applies.

    A controller is declared stable on the test set iff for **every** test trajectory
    all plant states, inputs and controller states are finite and the final plant state
    satisfies $\\lVert x_T\\rVert \\le \\text{rel}\\,\\lVert x_0\\rVert + \\text{abs\\_tol}$
    (defaults 0.5 and 1.0: the loop must at least halve a large initial state within the
    horizon and end within 25 noise standard deviations (0.04) of the origin). Controller states are not
    otherwise inspected (a memoryless controller keeps $\\hat x_0 = x_0$).

    **Arguments:** controller `Trajectories` (`x` `[K, N, T+1, n]`), `rel`, `abs_tol`.
    """
    x, finite = _states_and_finite(traj)
    with np.errstate(invalid="ignore", over="ignore"):
        n0 = np.linalg.norm(x[:, :, 0], axis=-1)
        nT = np.linalg.norm(x[:, :, -1], axis=-1)
        settled = nT <= rel * n0 + abs_tol
    return np.all(finite & settled, axis=1)


def rule_bounded(traj: Trajectories, factor: float = BOUND_FACTOR) -> Bool[np.ndarray, " K"]:
    """The weaker simulation verdict: every test trajectory stays finite and bounded.

    A controller is "bounded" on the test set iff for every test trajectory all plant
    states, inputs and controller states are finite and
    $\\max_k\\lVert x_k\\rVert \\le \\text{factor}\\,(\\lVert x_0\\rVert + 1)$ (default 10). Unlike
    [`rule_stable`][dissil_jax.experiments.rule_stable] it accepts loops that stay bounded
    without settling (for example a sustained oscillation).
    """
    x, finite = _states_and_finite(traj)
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.linalg.norm(x, axis=-1)
        ok = norm.max(axis=-1) <= factor * (norm[..., 0] + 1.0)
    return np.all(finite & ok, axis=1)


def state_mse(x_expert: Float[Array, "N T1 n"], x: Float[Array, "K N T1 n"],
              stable: Bool[np.ndarray, " K"] | None = None) -> np.ndarray:
    """Per-controller MSE $\\frac{1}{N_xT}\\sum_i\\sum_{k=1}^T\\lVert x_e(k) - x(k)\\rVert^2$.

    $k = 0$ is excluded (both loops start at the same $x_0$). Unstable controllers
    (`stable` False) and non-finite simulations get $+\\infty$.
    """
    xe, xs = np.asarray(x_expert, np.float64), np.asarray(x, np.float64)
    if xs.ndim != 4 or xe.shape != xs.shape[1:]:
        raise ValueError(f"`x` must be [K, *x_expert.shape] = [K, {xe.shape}], got {xs.shape}.")
    with np.errstate(invalid="ignore", over="ignore"):
        mse = np.sum((xs[:, :, 1:] - xe[None, :, 1:]) ** 2, axis=-1).mean(axis=(1, 2))
    mse = np.where(np.isfinite(mse), mse, np.inf)
    if stable is not None:
        mse = np.where(np.asarray(stable, bool), mse, np.inf)
    return mse


class Evaluation(eqx.Module):
    """The outcome of [`evaluate`][dissil_jax.experiments.evaluate] for `K` controllers.

    - `mse` `[K]`: state MSE against the expert (`inf` when unstable).
    - `stable` `[K]`: the stability verdict; `exact` says whether it came from the
      eigenvalue test (LTI plant and controller) or from `rule_stable`.
    - `bounded` `[K]`: the weaker simulation verdict of `rule_bounded` (for an exact test
      it equals `stable`).
    - `spectral_radius` `[K]` (exact test only, else None).
    - `expert`, `learned`: the simulated trajectories (`learned.x` `[K, N, T+1, n]`).
    """

    mse: np.ndarray
    stable: np.ndarray
    bounded: np.ndarray
    exact: bool
    spectral_radius: np.ndarray | None
    expert: Trajectories
    learned: Trajectories


def evaluate(
    key: PRNGKeyArray,
    plant,
    expert,
    controllers: Any,
    x0: Float[Array, "N n"],
    steps: int,
    *,
    plant_noise: float = PLANT_NOISE,
    control_noise: float = CONTROL_NOISE,
    xhat0: Float[Array, "N nh"] | str | None = None,
) -> Evaluation:
    """Closed-loop test of a batch of learned controllers against the expert (paper §5).

    Draws one noise realisation per test state (from `key`), simulates the expert and every
    controller with it for `steps` steps, and returns verdicts and MSEs. Paper test sets:
    $x_0\\sim\\mathcal N(0, 20^2I)$ (linear), 1,000 states $x_0\\sim\\mathcal N(0, 15^2)$
    (nonlinear); `docs/problems.md` documents the horizons we use. The protocol runs the
    test loops for at least the expert's `equilibrium_horizon`.

    `xhat0` is the controllers' initial state, passed to
    [`simulate_controllers`][dissil_jax.experiments.simulate_controllers]: None (default)
    starts them at the plant state, $\\hat x_0 = x_0$; `"rest"` starts them at
    $\\hat x_0 = 0$ of their own order (controllers trained on `dj.Windows(None, y, u)`, whose
    order may differ from the plant's); an `[N, n̂]` array is used as given. The stability
    verdict of an LTI loop does not depend on it; the MSE does.

    ```python
    ev = evaluate(key, plant, expert, fit.controllers, x0_test, steps=50)
    ev_rest = evaluate(key, plant, expert, fit.controllers, x0_test, steps=50, xhat0="rest")
    print(summarize(ev, fit))
    ```
    """
    _check_sigma("plant_noise", plant_noise)
    _check_sigma("control_noise", control_noise)
    x0 = jnp.asarray(x0)
    if x0.ndim != 2:
        raise ValueError(f"`x0` must have shape [N, n], got {x0.shape}.")
    noise = sample_noise(key, x0.shape[0], steps, plant, plant_noise, control_noise, x0.dtype)
    ref = simulate_expert(plant, expert, x0, noise)
    learned = simulate_controllers(plant, controllers, x0, noise, xhat0)
    exact = isinstance(controllers, LTIController) and _is_lti_plant(plant)
    if exact:
        rho = lti_spectral_radius(plant, controllers)
        stable = bounded = rho < 1.0
    else:
        rho = None
        stable, bounded = rule_stable(learned), rule_bounded(learned)
    mse = state_mse(ref.x, learned.x, stable)
    return Evaluation(mse, stable, bounded, exact, rho, ref, learned)


def _is_lti_plant(plant) -> bool:
    from ..systems import LinearPlant

    return isinstance(plant, LinearPlant)


def quantiles(values: np.ndarray, qs) -> np.ndarray:
    """Linear-interpolation quantiles in which $+\\infty$ absorbs (numpy gives NaN there)."""
    v = np.sort(np.asarray(values, np.float64))
    out = []
    for q in qs:
        pos = q * (len(v) - 1)
        lo, hi = int(np.floor(pos)), int(np.ceil(pos))
        t = pos - lo
        if t == 0 or v[lo] == v[hi]:
            out.append(v[lo])
        elif np.isinf(v[hi]):
            out.append(np.inf)
        else:
            out.append(v[lo] + (v[hi] - v[lo]) * t)
    return np.array(out)


class Summary(NamedTuple):
    """One row of the paper's tables and figures for one configuration.

    `percent_stable`; `percent_change_cost` (mean over controllers of the training cost
    change, from the `FitResult`; NaN without one); `train_time_per_controller` (wall
    time / number of controllers; NaN without one); `mse_min`, `mse_q1`, `mse_median`,
    `mse_q3`, `mse_max` (unstable controllers count as $+\\infty$).
    """

    percent_stable: float
    percent_change_cost: float
    train_time_per_controller: float
    mse_min: float
    mse_q1: float
    mse_median: float
    mse_q3: float
    mse_max: float


def summarize(evaluation: Evaluation, fit=None) -> Summary:
    """Aggregate an [`Evaluation`][dissil_jax.experiments.Evaluation] (and optionally the
    `FitResult` that produced the controllers) into a [`Summary`][dissil_jax.experiments.Summary]."""
    mse, stable = np.asarray(evaluation.mse), np.asarray(evaluation.stable, bool)
    q = quantiles(mse, (0.0, 0.25, 0.5, 0.75, 1.0))
    if fit is not None:
        pcc = float(np.nanmean(np.asarray(fit.percent_change_cost)))
        wall = float(np.asarray(fit.wall_time))
        ttime = wall / fit.num_inits
    else:
        pcc = ttime = float("nan")
    return Summary(100.0 * float(stable.mean()), pcc, ttime, *map(float, q))


__all__ = ["Evaluation", "Summary", "evaluate", "lti_closed_loop_matrix", "lti_spectral_radius",
           "rule_bounded", "rule_stable", "state_mse", "summarize"]
