"""Controller rollouts: observability/Toeplitz matrices and a `lax.scan` loop (paper eq. 15)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._controller import LTIController
from ._data import Windows
from ._validate import check_int

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
    horizon = check_int("horizon", horizon)
    check_lti(K)
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
    K: LTIController, x0: Float[Array, " n"] | None, u_in: Float[Array, "h p"]
) -> Float[Array, "h m"]:
    """Simulate the controller from state `x0` on inputs `u_in` with `lax.scan`.

    $\\hat x_{k+1} = A\\hat x_k + B\\hat u_k$, $\\hat y_k = C\\hat x_k + D\\hat u_k$ for
    $k = 0..h-1$, from $\\hat x_0$ = `x0`, or from rest ($\\hat x_0 = 0$) when `x0` is None.

    **Arguments:** one controller `K`, its initial state `x0` (`[n̂]`, n̂ = `K.n_state`, or
    None) and the inputs `u_in` (`[h, p]`).

    **Returns:** the outputs $\\hat y_0..\\hat y_{h-1}$ (`[h, m]`). Unbatched; vmap for batches.
    Raises a ValueError when `K` is not an `LTIController` (a REN has `ren_rollout`) or
    when `x0` or `u_in` do not have the controller's sizes.
    """
    check_lti(K)
    return scan_outputs(K, x0, u_in)


def check_lti(K) -> None:
    """A ValueError naming `K` unless it is an `LTIController` (a REN has its own tools)."""
    if not isinstance(K, LTIController):
        raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__} (for a "
                         "REN use `dj.ren_rollout`, `dj.ren_predict`, `dj.ren_imitation_loss`).")


def scan_outputs(K, x0, u_in, name: str = "dj.rollout"):
    """`rollout` for any controller module with `n_state`, a state matrix `A` and
    `K(x, u) -> (x_next, y)` (the LTI controller and the REN): the outputs of a `lax.scan`
    from `x0`, or from rest when it is None; `name` is the public function, for the
    message that refuses a batch of controllers."""
    if K.batch_shape:
        raise ValueError(f"`K` must be a single controller (batch shape {K.batch_shape}); "
                         f"vmap the rollout over a batch, e.g. `jax.vmap({name}, (0, None, "
                         "None))(K, x0, u_in)`.")
    u_in = jnp.asarray(u_in)
    # the state's dtype is the step's: integer or lower-precision x0 and u_in are promoted
    # (else the scan's carry would change type after one step)
    x0 = None if x0 is None else jnp.asarray(x0)
    for arg, a in (("u_in", u_in), ("x0", x0)):
        if a is not None and not (jnp.issubdtype(a.dtype, jnp.floating)
                                  or jnp.issubdtype(a.dtype, jnp.integer)):
            raise ValueError(f"`{arg}` must be a real array (floats or integers; the "
                             f"controller's signals are real), got dtype {a.dtype}.")
    dtype = jnp.result_type(K.A.dtype, u_in.dtype, *(() if x0 is None else (x0.dtype,)))
    if not jnp.issubdtype(dtype, jnp.inexact):
        dtype = K.A.dtype
    x0 = jnp.zeros((K.n_state,), dtype) if x0 is None else x0.astype(dtype)
    if x0.shape != (K.n_state,):
        raise ValueError(f"`x0` must have shape ({K.n_state},) (the controller's state size), "
                         f"got {x0.shape}.")
    # Static shapes: these checks also hold under jit and vmap (per member).
    if u_in.ndim != 2 or u_in.shape[1] != K.n_in:
        raise ValueError(f"`u_in` must have shape [h, {K.n_in}] (h steps of the controller's "
                         f"{K.n_in} inputs, `K.n_in`), got {u_in.shape}.")
    _, y = jax.lax.scan(lambda x, u: K(x, u), x0, u_in)
    return y


def check_window_sizes(K, windows: Windows) -> None:
    """A `ValueError` unless the sizes of one controller `K` (any module with `n_state`,
    `n_in`, `n_out`) match the `windows`: `windows.y` has `K.n_in` columns, `windows.u`
    has `K.n_out` and `windows.x0` (when given) has `K.n_state`.

    Shapes are static, so this also holds under jit and vmap (where `K` is one member);
    without it a wrong output width broadcasts silently against the target.
    """
    if not isinstance(windows, Windows):
        raise ValueError(f"`windows` must be a `dj.Windows`, got {type(windows).__name__}.")
    if windows.n_in != K.n_in:
        raise ValueError(f"`windows.y` has {windows.n_in} columns (plant outputs) but the "
                         f"controller has {K.n_in} inputs (`K.n_in`).")
    if windows.n_out != K.n_out:
        raise ValueError(f"`windows.u` has {windows.n_out} outputs but the controller has "
                         f"{K.n_out} (`K.n_out`).")
    if windows.x0 is not None and windows.n_state != K.n_state:
        raise ValueError(
            f"`windows.x0` has width {windows.n_state} but `K` has {K.n_state} states; the "
            "controller starts at x0, so its order must be x0's width (or build the windows "
            "with `dj.Windows(None, y, u)` to start a controller of any order at rest; an "
            "odd REN of `fit_ren(odd=True)`, of twice x0's width, starts at (x0, -x0): "
            "`dj.Windows(jnp.concatenate([x0, -x0], -1), y, u)`)."
        )


def predict(K: LTIController, windows: Windows) -> Float[Array, "N h m"]:
    """Controller outputs on every window (vmapped), via (O, T) or a scan by horizon.

    $\\hat y^{(i)} = \\mathcal O\\hat x^{(i)}_0 + \\mathcal T\\hat u^{(i)}$ (see
    [`observability_toeplitz`][dissil_jax.observability_toeplitz]) with $\\hat x_0$ =
    `windows.x0`, or $\\hat x_0 = 0$ when `windows.x0` is None (windows that start at
    rest; `K` may then have any order).

    **Arguments:** one controller `K` (unbatched; vmap for batches) and the `windows`.

    **Returns:** `[N, h, m]`. Raises a ValueError when `windows.y`, `windows.u` or
    `windows.x0` do not have `K.n_in`, `K.n_out` or `K.n_state` columns.
    """
    check_lti(K)
    if K.batch_shape:
        raise ValueError("`K` must be a single controller; vmap `predict` or `imitation_loss` "
                         "for batches.")
    check_window_sizes(K, windows)
    h, N = windows.horizon, windows.num_windows
    if h <= _TOEPLITZ_MAX_HORIZON:
        O, T = observability_toeplitz(K, h)
        y = windows.y.reshape(N, -1) @ T.T
        if windows.x0 is not None:
            y = windows.x0 @ O.T + y
        return y.reshape(N, h, K.n_out)
    if windows.x0 is None:
        return jax.vmap(rollout, in_axes=(None, None, 0))(K, None, windows.y)
    return jax.vmap(rollout, in_axes=(None, 0, 0))(K, windows.x0, windows.y)


def imitation_loss(K: LTIController, windows: Windows) -> Float[Array, ""]:
    """The paper's imitation loss (paper eq. 16), with the target $-u$ fixed by `Windows`.

    $$J(K) = \\frac{1}{N}\\sum_{i=1}^{N}\\sum_{k=0}^{h-1} \\lVert \\hat y^{(i)}_k - (-u^{(i)}_k) \\rVert_2^2$$

    i.e. the squared 2-norm of each window's stacked error over the horizon, summed over the
    $h$ time steps and averaged over the $N$ windows (paper eq. 16 compares the stacked
    prediction of eq. 15 with the stacked inputs). The trainers' stopping rule
    $|\\Delta J| <$ `tol` refers to this $J$. The predictions start from `windows.x0`, or
    at rest ($\\hat x_0 = 0$) when it is None (see [`predict`][dissil_jax.predict]).
    """
    err = predict(K, windows) - windows.target
    return jnp.mean(jnp.sum(err**2, axis=(-2, -1)))
