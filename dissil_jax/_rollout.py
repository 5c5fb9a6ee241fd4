"""Controller rollouts: observability/Toeplitz matrices and a `lax.scan` loop (paper eq. 15)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._controller import LTIController
from ._data import Windows

# Below this horizon the explicit (O, T) product beats the sequential scan on CPU
# (one batched matmul instead of h dependent steps); see benchmarks/bench_rollout.py.
_TOEPLITZ_MAX_HORIZON = 32


def observability_toeplitz(
    K: LTIController, horizon: int
) -> tuple[Float[Array, "*batch hm n"], Float[Array, "*batch hm hp"]]:
    """The observability matrix $\\mathcal O$ and block-Toeplitz matrix $\\mathcal T$ (paper eq. 15).

    $$\\begin{bmatrix}\\hat y_0\\\\ \\vdots\\\\ \\hat y_{h-1}\\end{bmatrix} = \\underbrace{\\begin{bmatrix}
    C\\\\ CA\\\\ \\vdots\\\\ CA^{h-1}\\end{bmatrix}}_{\\mathcal O}\\hat x_0 + \\underbrace{\\begin{bmatrix}
    D & & \\\\ CB & D & \\\\ \\vdots & \\ddots & \\ddots \\\\ CA^{h-2}B & \\cdots & CB\\quad D\\end{bmatrix}}_{\\mathcal T}
    \\begin{bmatrix}\\hat u_0\\\\ \\vdots\\\\ \\hat u_{h-1}\\end{bmatrix}$$

    **Arguments:** a controller `K` (leading batch axes allowed) and the `horizon` $h\\ge1$.

    **Returns:** `(O, T)` with shapes `[*batch, h*m, n]` and `[*batch, h*m, h*p]`
    (time-major blocks), where `batch` is `K.batch_shape` (empty for one controller).
    """
    if isinstance(horizon, bool) or np.ndim(horizon) != 0 or int(horizon) != horizon or horizon < 1:
        raise ValueError(f"`horizon` must be a positive integer, got {horizon!r}.")
    horizon = int(horizon)
    if not isinstance(K, LTIController):
        raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__}.")
    fn = functools.partial(_observability_toeplitz, horizon=horizon)
    for _ in K.batch_shape:
        fn = jax.vmap(fn)
    return fn(K)


def _observability_toeplitz(K: LTIController, horizon: int):
    m, n, p = K.n_out, K.n_state, K.n_in

    def step(CAk, _):
        return CAk @ K.A, CAk

    _, CA = jax.lax.scan(step, K.C, None, length=horizon)  # [h, m, n]: C A^t
    markov = jnp.concatenate([K.D[None], CA[:-1] @ K.B], axis=0)  # [h, m, p]: D, CB, CAB, ...
    t = jnp.arange(horizon)
    lag = t[:, None] - t[None, :]
    blocks = jnp.where((lag >= 0)[:, :, None, None], markov[jnp.clip(lag, 0)], 0.0)
    T = blocks.transpose(0, 2, 1, 3).reshape(horizon * m, horizon * p)
    return CA.reshape(horizon * m, n), T


def rollout(
    K: LTIController, x0: Float[Array, " n"], u_in: Float[Array, "h p"]
) -> Float[Array, "h m"]:
    """Simulate the controller from state `x0` on inputs `u_in` with `lax.scan`.

    Returns the outputs $\\hat y_0..\\hat y_{h-1}$ (`[h, m]`). Unbatched; vmap for batches.
    """

    def step(x, u):
        x_next, y = K(x, u)
        return x_next, y

    _, y = jax.lax.scan(step, x0, u_in)
    return y


def predict(K: LTIController, windows: Windows) -> Float[Array, "N h m"]:
    """Controller outputs on every window (vmapped), via (O, T) or a scan by horizon.

    Unbatched `K`; vmap for batches.
    """
    if K.batch_shape:
        raise ValueError("`K` must be a single controller; vmap `predict` for batches.")
    h = windows.horizon
    if h <= _TOEPLITZ_MAX_HORIZON:
        O, T = observability_toeplitz(K, h)
        N = windows.num_windows
        y = windows.x0 @ O.T + windows.y.reshape(N, -1) @ T.T
        return y.reshape(N, h, K.n_out)
    return jax.vmap(rollout, in_axes=(None, 0, 0))(K, windows.x0, windows.y)


def imitation_loss(K: LTIController, windows: Windows) -> Float[Array, ""]:
    """The paper's imitation loss (paper eq. 16), with the target $-u$ fixed by `Windows`.

    $$J(K) = \\frac{1}{N}\\sum_{i=1}^{N}\\sum_{k=0}^{h-1} \\lVert \\hat y^{(i)}_k - (-u^{(i)}_k) \\rVert_2^2$$

    i.e. the squared 2-norm of each window's stacked error over the horizon, summed over the
    $h$ time steps and averaged over the $N$ windows (paper eq. 16 compares the stacked
    prediction of eq. 15 with the stacked inputs). The trainers' stopping rule
    $|\\Delta J| <$ `tol` refers to this $J$.
    """
    err = predict(K, windows) - windows.target
    return jnp.mean(jnp.sum(err**2, axis=(-2, -1)))
