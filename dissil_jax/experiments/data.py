"""Expert demonstrations and the paper's two data regimes (paper §5).

Demonstrations are simulated with [`simulate_expert`][dissil_jax.experiments.simulate_expert]
(noise model in `dissil_jax.experiments.simulate`) and cut into
[`Windows`][dissil_jax.Windows]:

- **initial segments**: the first $h$ steps of each of $N$ trajectories, $\\hat x_0 = x_0$;
- **sliding window**: every $h$-step window inside the first `span` (paper: 10) steps of
  as many trajectories as needed for $N$ windows, $\\hat x_0$ = the plant state at the
  window start.

A window stores the plant outputs $y_k$ (controller inputs) and the applied noisy plant
inputs $u_k$; `Windows.target` turns them into the controller target $-u_k$ (negative feedback).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import PRNGKeyArray

from .._data import Windows
from .._projection.args import solved_room
from .._validate import check_int
from .simulate import (
    CONTROL_NOISE,
    PLANT_NOISE,
    Trajectories,
    _check_sigma,
    sample_noise,
    simulate_expert,
)

REGIMES = ("initial", "sliding")


_check_positive_int = check_int

#: Seeds of the experiments and the zoo: integers in [0, 2^32). Both of their generators,
#: `jax.random.PRNGKey` and numpy's `default_rng`, take these (numpy refuses negative seeds,
#: JAX seeds of 2^63 and more), also with the small offsets the zoo adds per problem.
SEED_LIMIT = 2**32


def check_seed(seed) -> int:
    """`seed` as an `int` in $[0, 2^{32})$, or a `ValueError` naming `seed`."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not (
            0 <= seed < SEED_LIMIT):
        raise ValueError(f"`seed` must be an integer from 0 to {SEED_LIMIT - 1}, got {seed!r}.")
    return int(seed)


def _check_traj(traj) -> None:
    if not isinstance(traj, Trajectories) or traj.x.ndim != 3:
        raise ValueError("`traj` must be expert `Trajectories` with x of shape [N, T+1, n] "
                         "(see `simulate_expert`).")


def initial_segments(traj: Trajectories, num_windows: int, horizon: int = 2) -> Windows:
    """The "initial segments" regime: steps $0..h-1$ of the first `num_windows` trajectories.

    **Arguments:** expert `traj` (`x` `[N, T+1, n]`), `num_windows` ($\\le N$), `horizon`
    $h$ ($\\le T$; paper: 2).

    **Returns:** `Windows(x0=x[:, 0], y=y[:, :h], u=u[:, :h])` for the first `num_windows`.
    """
    _check_traj(traj)
    num_windows = _check_positive_int("num_windows", num_windows)
    horizon = _check_positive_int("horizon", horizon)
    N, T = traj.u.shape[:2]
    if horizon > T:
        raise ValueError(f"`horizon` ({horizon}) is longer than the trajectories ({T} steps).")
    if num_windows > N:
        raise ValueError(f"`num_windows` ({num_windows}) exceeds the {N} trajectories available; "
                         "simulate more trajectories.")
    s = slice(0, num_windows)
    return Windows(traj.x[s, 0], traj.y[s, :horizon], traj.u[s, :horizon])


def windows_per_trajectory(horizon: int, span: int = 10) -> int:
    """Number of $h$-step windows inside the first `span` steps: `span - horizon + 1`."""
    return span - horizon + 1


def sliding_windows(traj: Trajectories, num_windows: int, horizon: int = 2,
                    span: int = 10) -> Windows:
    """The "sliding window" regime: all $h$-step windows within the first `span` steps.

    Windows start at steps $s = 0, \\ldots, \\text{span} - h$ of trajectory 0, then of
    trajectory 1, and so on (trajectory-major); the first `num_windows` are kept. Each
    window's $\\hat x_0$ is the plant state $x_s$ at its start.

    **Arguments:** expert `traj`, `num_windows`, `horizon` $h$ (paper: 2), `span` (paper:
    10; needs `horizon <= span <= T`).
    """
    _check_traj(traj)
    num_windows = _check_positive_int("num_windows", num_windows)
    horizon = _check_positive_int("horizon", horizon)
    span = _check_positive_int("span", span)
    N, T = traj.u.shape[:2]
    if horizon > span:
        raise ValueError(f"`horizon` ({horizon}) is longer than the window span ({span}).")
    if span > T:
        raise ValueError(f"`span` ({span}) is longer than the trajectories ({T} steps).")
    per = windows_per_trajectory(horizon, span)
    if num_windows > N * per:
        raise ValueError(f"`num_windows` ({num_windows}) exceeds the {N * per} windows available "
                         f"({N} trajectories x {per}); simulate more trajectories.")
    idx = jnp.arange(num_windows)
    traj_i, start = idx // per, idx % per
    steps = start[:, None] + jnp.arange(horizon)[None, :]
    return Windows(traj.x[traj_i, start], traj.y[traj_i[:, None], steps],
                   traj.u[traj_i[:, None], steps])


def demonstrations(
    key: PRNGKeyArray,
    plant,
    expert,
    num: int,
    steps: int,
    x0_std: float,
    plant_noise: float = PLANT_NOISE,
    control_noise: float = CONTROL_NOISE,
) -> Trajectories:
    """Simulate `num` expert trajectories of `steps` steps from $x_0\\sim\\mathcal N(0, \\text{x0\\_std}^2 I)$.

    Paper: `x0_std` = 1 (linear), 5 (nonlinear); noises 0.04 (state) and 0.02 (control).
    """
    x0_std = _check_sigma("x0_std", x0_std)
    num = _check_positive_int("num", num)
    k0, kn = jr.split(key)
    x0 = x0_std * jr.normal(k0, (num, plant.n_state), plant.A.dtype)
    noise = sample_noise(kn, num, steps, plant, plant_noise, control_noise)
    return simulate_expert(plant, expert, x0, noise)


def demonstration_windows(
    key: PRNGKeyArray,
    plant,
    expert,
    num_windows: int,
    regime: str = "initial",
    *,
    horizon: int = 2,
    span: int = 10,
    x0_std: float = 1.0,
    plant_noise: float = PLANT_NOISE,
    control_noise: float = CONTROL_NOISE,
) -> Windows:
    """Training windows for one data regime, simulating just enough expert trajectories.

    `regime="initial"`: `num_windows` trajectories of `horizon` steps. `regime="sliding"`:
    $\\lceil N / (\\text{span} - h + 1)\\rceil$ trajectories of `span` steps.

    ```python
    W = demonstration_windows(key, plant, expert, 25, "sliding", x0_std=5.0)
    ```
    """
    if regime not in REGIMES:
        raise ValueError(f"`regime` must be one of {REGIMES}, got {regime!r}.")
    num_windows = _check_positive_int("num_windows", num_windows)
    horizon = _check_positive_int("horizon", horizon)
    if regime == "initial":
        traj = demonstrations(key, plant, expert, num_windows, horizon, x0_std,
                              plant_noise, control_noise)
        return initial_segments(traj, num_windows, horizon)
    span = _check_positive_int("span", span)
    if horizon > span:
        raise ValueError(f"`horizon` ({horizon}) is longer than the window span ({span}).")
    num = math.ceil(num_windows / windows_per_trajectory(horizon, span))
    traj = demonstrations(key, plant, expert, num, span, x0_std, plant_noise, control_noise)
    return sliding_windows(traj, num_windows, horizon, span)


def realisable_windows(
    key: PRNGKeyArray, qsr, *, n_state: int, num_windows: int, horizon: int = 2,
    noise: float = 0.0, scale: float = 1.0,
):
    """Windows that a $(Q,S,R)$-dissipative controller of order `n_state` fits exactly.

    The expert $K_\\star$ is a random draw (entries $\\mathcal N(0, 1)$) projected onto the
    dissipative set of `qsr` ([`dj.project`][dissil_jax.project]); the windows start at
    $\\hat x_0\\sim\\mathcal N(0, I)$ with inputs $y_k\\sim\\mathcal N(0, I)$, and
    $u_k = -\\hat y_k + \\nu_k$ with $\\nu_k\\sim\\mathcal N(0, \\text{noise}^2 I)$, so
    with `noise=0` the loss of $K_\\star$ is zero. `scale` multiplies $x_0$, $y$ and $u$ (a
    change of units). Used by the optimiser comparison and the tests. The projection's
    margin is its default $10^{-6}$, or a thousandth of the rate's room where that is
    smaller (a gain bound $\\gamma$ has room $\\gamma^2$): gain bounds down to $10^{-4}$
    work; at $10^{-6}$ the room ($10^{-12}$) is at float64's round-off and the
    projection's check fails.

    **Returns:** `(windows, K_star)`.
    """
    import dissil_jax as dj

    kK, kx, ky, kn = jr.split(key, 4)
    K = dj.LTIController.random(kK, n_state, qsr.n_in, qsr.n_out, scale=1.0)
    # the projection's margin, 1e-6 by default, must fit in the rate's room (a gain bound
    # of 1e-3 has room 1e-6): a thousandth of it where it is smaller
    room = solved_room(qsr)
    eps = 1e-6 if room is None or room <= 0 else min(1e-6, 1e-3 * room)
    K, _ = dj.project(K, qsr, eps=eps)
    x0 = jr.normal(kx, (num_windows, n_state))
    y = jr.normal(ky, (num_windows, horizon, qsr.n_in))
    u = -jax.vmap(lambda x, yk: dj.rollout(K, x, yk))(x0, y)
    u = u + noise * jr.normal(kn, u.shape)
    return Windows(scale * x0, scale * y, scale * u), K


__all__ = ["REGIMES", "demonstration_windows", "demonstrations", "initial_segments",
           "realisable_windows", "sliding_windows", "windows_per_trajectory"]
