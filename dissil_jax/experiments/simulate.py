"""Noisy closed-loop simulation: expert loops and learned-controller loops (paper §5).

Noise model (the paper gives only the two variances; the entry points are ours, see
`docs/problems.md`), for $k = 0..T-1$:

$$u_k = \\pi_k + e_k,\\quad y_k = h(x_k, u_k),\\quad x_{k+1} = f(x_k, u_k) + w_k,\\qquad
w_k\\sim\\mathcal N(0, \\sigma_w^2 I_n),\\ e_k\\sim\\mathcal N(0,\\sigma_e^2 I_m),$$

where $\\pi_k$ is the controller's nominal command: the expert's $\\pi(x_k)$ (state
feedback), or $-\\hat y_k$ for a learned controller in negative feedback with
$\\hat u_k = y_k$. The recorded/observed $u_k$ and $y_k$ are the noisy applied input and
the resulting (noise-free) output; there is no separate measurement noise. The learner and
the expert it is compared with see the same $(w, e)$ realisation.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._controller import LTIController
from .._linalg import solve
from .._validate import check_int, has_non_finite

PLANT_NOISE = 0.04
CONTROL_NOISE = 0.02


class Noise(eqx.Module):
    """One noise realisation per trajectory: process noise `w` `[N, T, n]`, control noise `e` `[N, T, m]`."""

    w: Float[Array, "N T n"]
    e: Float[Array, "N T m"]

    @property
    def steps(self) -> int:
        return self.w.shape[1]


class Trajectories(eqx.Module):
    """Simulated loops: states `x` `[..., N, T+1, n]` ($x_0..x_T$), outputs `y` `[..., N, T, p]`,
    applied inputs `u` `[..., N, T, m]`, and controller states `xhat` `[..., N, T+1, n̂]`
    (None for experts)."""

    x: Float[Array, "*b N T1 n"]
    y: Float[Array, "*b N T p"]
    u: Float[Array, "*b N T m"]
    xhat: Float[Array, "*b N T1 nh"] | None = None


def _check_sigma(name: str, value) -> float:
    value = float(value)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"`{name}` must be a non-negative standard deviation, got {value}.")
    return value


def _check_steps(steps) -> int:
    return check_int("steps", steps)


def _check_x0(x0, n_state: int) -> Array:
    x0 = jnp.asarray(x0)
    if x0.ndim != 2 or x0.shape[1] != n_state:
        raise ValueError(f"`x0` must have shape [N, {n_state}] (one plant state per row), "
                         f"got {x0.shape}.")
    if has_non_finite(x0):
        raise ValueError("`x0` contains NaN or inf.")
    return x0


def sample_noise(
    key: PRNGKeyArray,
    num: int,
    steps: int,
    plant,
    plant_noise: float = PLANT_NOISE,
    control_noise: float = CONTROL_NOISE,
    dtype=None,
) -> Noise:
    """Draw $w\\sim\\mathcal N(0,\\sigma_w^2)$ and $e\\sim\\mathcal N(0,\\sigma_e^2)$ for `num` trajectories.

    **Arguments:** `key`, number of trajectories `num`, `steps` $T$, the `plant` (for $n$,
    $m$), the standard deviations `plant_noise` $\\sigma_w$ (paper: 0.04) and
    `control_noise` $\\sigma_e$ (paper: 0.02), optional `dtype`.
    """
    sw, se = _check_sigma("plant_noise", plant_noise), _check_sigma("control_noise", control_noise)
    steps = _check_steps(steps)
    check_int("num", num)
    dtype = dtype or plant.A.dtype
    kw, ke = jr.split(key)
    return Noise(sw * jr.normal(kw, (num, steps, plant.n_state), dtype),
                 se * jr.normal(ke, (num, steps, plant.n_in), dtype))


def _check_noise(noise: Noise, num: int, plant) -> None:
    if not isinstance(noise, Noise):
        raise ValueError(f"`noise` must be a `Noise` (see `sample_noise`), got {type(noise)}.")
    if noise.w.shape[0] != num or noise.w.shape[2] != plant.n_state or noise.e.shape[2] != plant.n_in:
        raise ValueError(
            f"`noise` has w {noise.w.shape}, e {noise.e.shape}; for {num} initial states it must "
            f"be [{num}, T, {plant.n_state}] and [{num}, T, {plant.n_in}]."
        )


@eqx.filter_jit
def _expert_loop(plant, expert, x0, w, e):
    def one(x0, w, e):
        def step(carry, we):
            x, c = carry
            wk, ek = we
            u_nom, c = expert(x, c)
            u = u_nom + ek
            y = plant.output(x, u)
            x_next = plant.step(x, u) + wk
            return (x_next, c), (x_next, y, u)

        _, (xs, y, u) = jax.lax.scan(step, (x0, expert.init(x0)), (w, e))
        return jnp.concatenate([x0[None], xs], axis=0), y, u

    return jax.vmap(one)(x0, w, e)


def simulate_expert(plant, expert, x0: Float[Array, "N n"], noise: Noise) -> Trajectories:
    """Run the expert in closed loop from each row of `x0` with the given noise (vmapped).

    $u_k = \\pi(x_k) + e_k$, $y_k = h(x_k, u_k)$, $x_{k+1} = f(x_k, u_k) + w_k$ for
    $k < T$ = `noise.steps`. The expert's carry (e.g. the NMPC warm start: the shifted
    previous solution) is threaded through the scan.

    **Returns:** [`Trajectories`][dissil_jax.experiments.Trajectories] with `x` `[N, T+1, n]`.
    """
    x0 = _check_x0(x0, plant.n_state)
    _check_noise(noise, x0.shape[0], plant)
    x, y, u = _expert_loop(plant, expert, x0, noise.w, noise.e)
    return Trajectories(x, y, u)


def _loop_input(plant, controller, x, xhat, e, iterations: int, tol: float):
    """Solve the algebraic loop $u = -\\hat y(\\hat x, h(x, u)) + e$ by Newton.

    The residual is $g(u) = u + \\hat y(\\hat x, h(x, u)) - e$. Newton stops as soon as
    $\\lVert g(u)\\rVert \\le \\varepsilon^{3/4}(1 + \\lVert u\\rVert + \\lVert e\\rVert)$
    ($\\varepsilon$ the machine epsilon), or after `iterations` steps; the loop counts as
    solved if the residual is then within `tol` on the same scale. One step is exact when the controller output and the plant
    output are affine in their inputs (LTI controller, both benchmark plants): it gives
    $u = (I + D_cD)^{-1}(-C_c\\hat x - D_cCx + e)$. An unsolved loop (ill-posed
    interconnection, e.g. $I + D_cD$ singular) yields NaN, which the metrics count as
    unstable.
    """

    def g(u):
        r = u + controller(xhat, plant.output(x, u))[1] - e
        return r, r

    def converged(u, r, tol=tol):
        return jnp.linalg.norm(r) <= tol * (1 + jnp.linalg.norm(u) + jnp.linalg.norm(e))

    fine = float(jnp.finfo(e.dtype).eps) ** 0.75

    def newton(carry):
        i, u, _ = carry
        J, r = jax.jacfwd(g, has_aux=True)(u)
        u = u - solve(J, r)
        return i + 1, u, g(u)[0]

    def go_on(carry):
        i, u, r = carry
        return (i < iterations) & ~converged(u, r, fine)

    u = e - controller(xhat, plant.output(x, jnp.zeros_like(e)))[1]
    _, u, r = jax.lax.while_loop(go_on, newton, (0, u, g(u)[0]))
    return jnp.where(converged(u, r), u, jnp.nan)


@eqx.filter_jit
def _controller_loop(plant, controller, x0, xhat0, w, e, iterations, tol):
    def one(x0, xhat0, w, e):
        def step(carry, we):
            x, xh = carry
            wk, ek = we
            u = _loop_input(plant, controller, x, xh, ek, iterations, tol)
            y = plant.output(x, u)
            xh_next, _ = controller(xh, y)
            x_next = plant.step(x, u) + wk
            return (x_next, xh_next), (x_next, xh_next, y, u)

        _, (xs, xhs, y, u) = jax.lax.scan(step, (x0, xhat0), (w, e))
        return (jnp.concatenate([x0[None], xs]), jnp.concatenate([xhat0[None], xhs]), y, u)

    return jax.vmap(one)(x0, xhat0, w, e)


def _batch_size(controllers) -> int:
    leaves = [l for l in jax.tree.leaves(eqx.filter(controllers, eqx.is_array)) if l.ndim > 0]
    if not leaves:
        raise ValueError("`controllers` has no array leaves with a leading batch axis.")
    sizes = {l.shape[0] for l in leaves}
    if len(sizes) != 1:
        raise ValueError(f"`controllers` leaves disagree on the batch axis: sizes {sorted(sizes)}.")
    return sizes.pop()


def _check_controller(plant, controller, xhat0) -> None:
    """Shape-check one unbatched controller against the plant with `jax.eval_shape`."""
    y = jax.ShapeDtypeStruct((plant.n_out,), xhat0.dtype)
    try:
        xh, yh = jax.eval_shape(controller, jax.ShapeDtypeStruct(xhat0.shape[1:], xhat0.dtype), y)
    except Exception as err:  # the controller's own shape error, re-raised with context
        raise ValueError(
            f"`controllers` cannot take a plant output of size {plant.n_out} and a state of "
            f"size {xhat0.shape[1]} ({type(err).__name__}: {err})."
        ) from err
    if yh.shape != (plant.n_in,):
        raise ValueError(f"`controllers` output has shape {yh.shape}; the plant has "
                         f"{plant.n_in} inputs, so it must be ({plant.n_in},).")
    if xh.shape != xhat0.shape[1:]:
        raise ValueError(f"`controllers` state has shape {xh.shape} but `xhat0` rows have "
                         f"{xhat0.shape[1:]}; pass `xhat0` of the controller's state size.")


def _initial_controller_state(plant, controllers, x0, xhat0) -> Array:
    """`xhat0` as an `[N, n̂]` array: None -> `x0`, "rest" -> zeros of the controllers' order."""
    if xhat0 is None:
        return x0
    if isinstance(xhat0, str):
        if xhat0 != "rest":
            raise ValueError(f'`xhat0` must be None, "rest" or an [N, n̂] array, got {xhat0!r}.')
        n_hat = getattr(controllers, "n_state", None)
        if not isinstance(n_hat, int):  # memoryless (e.g. MLPController): any size is carried
            n_hat = plant.n_state
        return jnp.zeros((x0.shape[0], n_hat), x0.dtype)
    xhat0 = jnp.asarray(xhat0)
    if xhat0.ndim != 2 or xhat0.shape[0] != x0.shape[0]:
        raise ValueError(f"`xhat0` must have shape [{x0.shape[0]}, n̂], got {xhat0.shape}.")
    if has_non_finite(xhat0):
        raise ValueError("`xhat0` contains NaN or inf.")
    return xhat0


def simulate_controllers(
    plant,
    controllers: Any,
    x0: Float[Array, "N n"],
    noise: Noise,
    xhat0: Float[Array, "N nh"] | str | None = None,
    *,
    loop_iterations: int | None = None,
) -> Trajectories:
    """Simulate a batch of controllers in negative feedback with the plant (vmapped twice).

    For each controller (leading batch axis of `controllers`) and each initial state:
    $\\hat x_0 = x_0$ by default, $\\hat x_0 = 0$ with `xhat0="rest"`, or the given
    `xhat0`; and for $k < T$

    $$u_k = -\\hat y_k + e_k,\\quad y_k = h(x_k,u_k),\\quad (\\hat x_{k+1}, \\hat y_k) =
    K(\\hat x_k, y_k),\\quad x_{k+1} = f(x_k,u_k) + w_k,$$

    where the algebraic loop through the feedthroughs is solved exactly (Newton; one step
    for an `LTIController`). `controllers` is an `LTIController` with a leading batch axis
    or any equinox module, batched the same way, with `__call__(xhat, uhat) -> (xhat_next,
    yhat)`; a memoryless controller returns `xhat` unchanged.

    The default $\\hat x_0 = x_0$ matches controllers trained on windows that record the
    plant state (their order is the plant's $n$). Controllers trained at rest
    (`dj.Windows(None, y, u)`) start at rest: `xhat0="rest"` gives $\\hat x_0 = 0$ of size
    `controllers.n_state`, any order $\\hat n$ (for a controller without `n_state`, e.g. the
    memoryless `MLPController`, zeros of the plant's state size, which it carries unchanged).

    **Arguments:** the `plant`, the batched `controllers`, initial states `x0` `[N, n]`, one
    `noise` realisation shared by all controllers, the initial controller state `xhat0`
    (None: $\\hat x_0 = x_0$; `"rest"`: $\\hat x_0 = 0$; or an `[N, n̂]` array),
    `loop_iterations` (default 1 for `LTIController`, 10 otherwise).

    **Returns:** [`Trajectories`][dissil_jax.experiments.Trajectories] with a leading
    controller axis: `x` `[K, N, T+1, n]`, `xhat` `[K, N, T+1, n̂]`.
    """
    x0 = _check_x0(x0, plant.n_state)
    _check_noise(noise, x0.shape[0], plant)
    xhat0 = _initial_controller_state(plant, controllers, x0, xhat0)
    _batch_size(controllers)
    if isinstance(controllers, LTIController):
        if controllers.A.ndim != 3:
            raise ValueError("`controllers` must carry exactly one leading batch axis, got "
                             f"A of shape {controllers.A.shape}.")
        if controllers.n_state != xhat0.shape[1]:
            raise ValueError(
                f"`controllers` have {controllers.n_state} states but the initial controller "
                f"state has {xhat0.shape[1]} (x̂0 = x0 by default); pass `xhat0=\"rest\"` to "
                "start them at rest, or an [N, n̂] `xhat0`."
            )
    first = jax.tree.map(lambda l: l[0] if eqx.is_array(l) and l.ndim > 0 else l, controllers)
    _check_controller(plant, first, xhat0)
    if loop_iterations is None:
        loop_iterations = 1 if isinstance(controllers, LTIController) else 10
    tol = 1e-6 if x0.dtype == jnp.float64 else 1e-3

    sim = lambda K: _controller_loop(plant, K, x0, xhat0, noise.w, noise.e,
                                     int(loop_iterations), tol)
    x, xh, y, u = eqx.filter_vmap(sim)(controllers)
    return Trajectories(x, y, u, xh)


def equilibrium_horizon(
    key: PRNGKeyArray,
    plant,
    expert,
    x0: Float[Array, "N n"],
    *,
    max_steps: int,
    band: float = 2.0,
    tail: float = 0.25,
    plant_noise: float = PLANT_NOISE,
    control_noise: float = CONTROL_NOISE,
) -> int:
    """The number of steps the expert's noisy loop needs to reach equilibrium from `x0`.

    The paper tests its controllers by "controlling the plant to equilibrium" (paper §5.2).
    With noise the loop never settles exactly; it reaches a noise floor. The expert is
    simulated for `max_steps` steps from every row of `x0`; the floor $\\bar r$ is the RMS of
    $\\lVert x_e(k)\\rVert$ over all trajectories and the last `tail` fraction of the steps,
    and the horizon is the first $T$ by which **every** trajectory has entered the band
    $\\lVert x_e(k)\\rVert \\le$ `band`$\\cdot\\bar r$.

    **Returns:** $T \\ge 1$ (an int). Raises a ValueError naming `max_steps` when some
    trajectory enters the band only inside the tail window (the run is too short to tell).
    """
    x0 = _check_x0(x0, plant.n_state)
    steps = _check_steps(max_steps)
    if not (0 < tail < 1) or not band > 1:
        raise ValueError(f"need 0 < `tail` < 1 and `band` > 1, got {tail}, {band}.")
    noise = sample_noise(key, x0.shape[0], steps, plant, plant_noise, control_noise, x0.dtype)
    x = np.asarray(simulate_expert(plant, expert, x0, noise).x, np.float64)
    norm = np.linalg.norm(x, axis=-1)  # [N, T+1]
    start = int(np.ceil((1 - tail) * steps))
    floor = float(np.sqrt(np.mean(norm[:, start:] ** 2)))
    inside = norm <= band * floor
    first = np.where(inside.any(axis=1), np.argmax(inside, axis=1), steps + 1)
    T = int(first.max())
    if T >= start:
        raise ValueError(
            f"a trajectory of the expert's loop enters its noise band only at step {T}; "
            f"increase `max_steps` (now {steps}) so that the last {tail:.0%} is at equilibrium."
        )
    return max(T, 1)
