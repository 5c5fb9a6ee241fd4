"""The paper's neural-network baseline: a static ReLU MLP $\\hat y = f(\\hat u)$ (NN + GD)."""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
from jaxtyping import Array, Float, PRNGKeyArray

from .. import _outcome
from .._data import Windows
from .._progress import reporting
from .._rate_scale import nearest_power_of_two
from .._validate import check_flag, check_int, check_key
from ._checks import check_fit_args
from ._iterate import RTOL_MLP, Method, iterate
from .result import FitResult, fit_timed

_CONVERGED, _MAX_STEPS = _outcome.code("converged"), _outcome.code("max_steps")


def check_hidden(hidden) -> tuple[int, ...]:
    """`hidden` as a tuple of `int` widths, or a `ValueError` naming it.

    A sequence (tuple, list or 1-D array) of equal positive integers (integral floats such
    as `8.0` too, as for every integer argument; `2.5` is refused, never truncated). The
    empty sequence `()` is allowed: no hidden layer, the affine map $\\hat y = W\\hat u + b$.
    """
    if isinstance(hidden, (str, bytes)) or not (
            isinstance(hidden, Sequence) or (isinstance(hidden, np.ndarray) and hidden.ndim == 1)):
        raise ValueError(f"`hidden` must be a sequence of hidden-layer widths such as "
                         f"(150, 150), got {hidden!r}.")
    hidden = tuple(check_int(f"hidden[{i}]", h) for i, h in enumerate(hidden))
    if len(set(hidden)) > 1:
        raise ValueError(
            f"`hidden` must list equal widths (eqx.nn.MLP has one width), got {hidden}.")
    return hidden


def _relu(x):
    """ReLU, as a function of this module so that a controller pickles (`jax.nn.relu` is a
    `custom_jvp` object that pickle cannot find by name)."""
    return jax.nn.relu(x)


def _identity(x):
    """The output layer's activation (equinox's default is a lambda, which does not pickle)."""
    return x


class MLPController(eqx.Module):
    """A memoryless controller $\\hat y = f(\\hat u)$, $f$ a ReLU MLP (paper §5, "NN").

    It has the call signature of [`LTIController`][dissil_jax.LTIController] so closed-loop
    code treats it like any controller: `__call__(xhat, uhat) -> (xhat, yhat)` passes the
    controller state through unchanged. Unbatched; vmap for batches (the trainers return
    it with a leading initialisation axis on every array).

    **Arguments:** `key` (a JAX PRNG key, first as in the trainers), `n_in` ($p$), `n_out`
    ($m$), `hidden` (widths of the hidden layers, all equal), optional `dtype`. The network has `len(hidden) + 1` weight matrices. The
    paper's baseline is "a three layer network" whose weights are
    "$(\\mathbf W_1, \\mathbf W_2, \\mathbf W_3)$" (paper §5.2), i.e. three weight matrices
    and so two hidden layers: `hidden=(150, 150)` for the linear example and `(25, 25)`
    for the nonlinear one. `hidden=()` (no hidden layer, one weight matrix) is the static
    affine controller $\\hat y = W\\hat u + b$, a linear baseline. Widths must be positive
    integers (a `ValueError` names `hidden` otherwise; nothing is truncated).
    """

    params: eqx.nn.MLP  # the array leaves of the MLP (weights and biases)
    static: eqx.nn.MLP = eqx.field(static=True)  # everything else (activations, sizes)

    def __init__(self, key: PRNGKeyArray, n_in: int, n_out: int, hidden: Sequence[int], *,
                 dtype=None):
        hidden = check_hidden(hidden)
        width = hidden[0] if hidden else 1
        mlp = eqx.nn.MLP(n_in, n_out, width, len(hidden), activation=_relu,
                         final_activation=_identity,
                         dtype=dtype, key=key)
        # Only arrays are leaves, so `jax.tree.map(lambda a: a[i], K)` indexes a batch.
        self.params, self.static = eqx.partition(mlp, eqx.is_array)

    @property
    def mlp(self) -> eqx.nn.MLP:
        """The `eqx.nn.MLP` $f$."""
        return eqx.combine(self.params, self.static)

    @property
    def n_in(self) -> int:
        """The controller's input width $p$ (the plant's outputs)."""
        return int(self.mlp.in_size)  # built from an int, never "scalar"

    @property
    def n_out(self) -> int:
        """The controller's output width $m$ (the plant's inputs)."""
        return int(self.mlp.out_size)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch axes of the parameters (empty for one controller)."""
        return self.params.layers[0].weight.shape[:-2]

    @property
    def hidden(self) -> tuple[int, ...]:
        """The hidden layers' widths."""
        return tuple(int(layer.out_features) for layer in self.static.layers[:-1])

    def __repr__(self) -> str:
        # One line instead of every layer's fields: a FitResult holds a batch of these.
        dtype = self.params.layers[0].weight.dtype
        batch = f", batch_shape={self.batch_shape}" if self.batch_shape else ""
        return (f"MLPController(n_in={self.n_in}, n_out={self.n_out}, hidden={self.hidden}"
                f"{batch}, dtype={dtype})")

    def __pdoc__(self, **kwargs):
        """The same line inside `eqx.tree_pformat` (a `FitResult`'s repr)."""
        import wadler_lindig  # equinox's pretty-printer, installed with it

        return wadler_lindig.TextDoc(repr(self))

    def __call__(
        self, xhat: Float[Array, " n"], uhat: Float[Array, " p"]
    ) -> tuple[Float[Array, " n"], Float[Array, " m"]]:
        """One step: returns $(\\hat x, f(\\hat u))$, the state unchanged. Unbatched."""
        return xhat, self.mlp(uhat)


def demonstration_pairs(windows: Windows):
    """Inputs $\\hat u = y$ `[N, h, p]` and targets $-u$ `[N, h, m]` of every window."""
    return windows.y, windows.target


def mlp_units(windows: Windows, balance) -> tuple[np.ndarray, float] | None:
    """The units `fit_mlp` trains in: per input channel $j$ the power of two $a_j$ nearest
    to the root mean square of $y_j$ over every sample, and one power of two $c$ nearest to
    that of $u$ over every sample and channel (1 for a channel or target that is all
    zero); None when `balance` is False. A `ValueError` names `balance` when it is not a
    bool, or when the windows are traced (the units are chosen from the data on the
    host)."""
    if not check_flag("balance", balance):
        return None
    if any(isinstance(a, jax.core.Tracer) for a in (windows.y, windows.u)):
        raise ValueError("`balance=True` chooses the network's units from the data on the "
                         "host, which traced `windows` (`fit_mlp` under `jax.jit` or "
                         "`jax.vmap` over its windows) do not allow: pass `balance=False` "
                         "there.")

    def power_of_two(rms):
        ok = np.isfinite(rms) & (rms > 0)
        return np.where(ok, nearest_power_of_two(np.where(ok, rms, 1.0)), 1.0)

    y = np.asarray(windows.y, np.float64).reshape(-1, windows.y.shape[-1])
    u = np.asarray(windows.u, np.float64)
    a = power_of_two(np.sqrt(np.mean(y**2, axis=0))) if y.size else np.ones(y.shape[-1])
    c = float(power_of_two(np.sqrt(np.mean(u**2)))) if u.size else 1.0
    return a, c


def in_user_units(model: MLPController, a: np.ndarray, c: float) -> MLPController:
    """The network trained on $(y/a, -u/c)$ as a map of the user's $y$ to the user's
    $-u$: $f(y) = c\\,g(y/a)$, the first layer's weights divided by $a$ (columnwise) and
    the last layer's weights and bias times $c$; exact, since both are powers of two."""
    first, last = (lambda m: m.params.layers[0]), (lambda m: m.params.layers[-1])
    W = first(model).weight
    model = eqx.tree_at(lambda m: first(m).weight, model, W / jnp.asarray(a, W.dtype))
    return eqx.tree_at(lambda m: (last(m).weight, last(m).bias), model,
                       (last(model).weight * c, last(model).bias * c))


def mlp_loss(model: MLPController, X, T) -> Float[Array, ""]:
    """The paper's loss (eq. 16) for the static network: $\\frac1N\\sum_i\\sum_k
    \\lVert f(\\hat u^{(i)}_k) - (-u^{(i)}_k)\\rVert^2$, as
    [`imitation_loss`][dissil_jax.imitation_loss]: summed over the horizon, averaged over
    windows. `X` `[N, h, p]`, `T` `[N, h, m]`."""
    pred = jax.vmap(jax.vmap(model.mlp))(X)
    return jnp.mean(jnp.sum((pred - T) ** 2, axis=(-2, -1)))


class _Adam(Method):
    """Full-batch Adam on one MLP's parameters for the driver loop (`_iterate.py`); one lane
    (shape `()`), vmapped over initialisations by `_train_batch`. The state carries the
    gradient of the current parameters, so each step evaluates the loss once; like GD, a
    run whose loss becomes non-finite returns that iterate."""

    keep_non_finite: ClassVar[bool] = True
    params: Any
    static: Any = eqx.field(static=True)
    X: Array
    T: Array
    opt: optax.GradientTransformation

    def _value_and_grad(self, params):
        return jax.value_and_grad(lambda q: mlp_loss(eqx.combine(q, self.static), self.X,
                                                     self.T))(params)

    def init(self):
        return (self.params, self.opt.init(self.params)), jnp.asarray(_MAX_STEPS)

    def evaluate(self, pending):
        params, opt_state = pending
        J, g = self._value_and_grad(params)
        return (params, g, opt_state), J

    def update(self, state, active):
        params, g, opt_state = state
        updates, opt_state = self.opt.update(g, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), jnp.asarray(_CONVERGED)


def _train_one(key, X, T, token, loss_unit, *, hidden, max_steps, learning_rate, atol, rtol):
    """Train one MLP (pure; vmapped over `key` by `fit_mlp`).

    At most `max_steps + 1` gradient evaluations: $J_0$, then one per Adam step, until
    $|J_k - J_{k-1}| <$ `atol` $+$ `rtol` $|J_0|$. Vmapped, the loop runs until every run
    has stopped, finished runs frozen. `loss_unit` ($c^2$ of `balance`) brings the
    reported losses to the user's units.
    """
    model = MLPController(key, X.shape[-1], T.shape[-1], hidden, dtype=X.dtype)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    (params, _, _), hist, J, steps, reason, kept = iterate(
        _Adam(params, static, X, T, optax.adam(learning_rate)), max_steps=max_steps,
        atol=atol, rtol=rtol, progress=None if token is None else (token, loss_unit))
    return eqx.combine(params, static), hist, J, reason == _CONVERGED, steps, reason, kept


@partial(eqx.filter_jit)
def _train_batch(keys, X, T, hidden, max_steps, learning_rate, atol, rtol, token, loss_unit):
    fn = partial(_train_one, hidden=hidden, max_steps=max_steps, learning_rate=learning_rate,
                 atol=atol, rtol=rtol)
    return eqx.filter_vmap(fn, in_axes=(0, None, None, None, None))(keys, X, T, token,
                                                                     loss_unit)


def fit_mlp(
    key, windows: Windows, *, hidden: Sequence[int] = (150, 150), num_inits: int = 8,
    max_steps: int = 2000, learning_rate: float = 1e-3, atol: float = 0.0, rtol: float = RTOL_MLP,
    throw: bool = True, balance: bool = True, progress: bool = True,
) -> FitResult:
    """Train the paper's NN baseline (NN + GD): a static ReLU MLP on the demonstration pairs.

    Every time step of every window gives one pair $(\\hat u, -u)$ = $(y_k, -u_k)$, and

    $$J(f) = \\frac{1}{N}\\sum_{i=1}^N\\sum_{k=0}^{h-1}\\lVert f(y^{(i)}_k) + u^{(i)}_k\\rVert^2$$

    (the same normalisation as [`imitation_loss`][dissil_jax.imitation_loss]) is minimised by
    full-batch Adam (`optax.adam`, a gradient method; the paper says "gradient descent"
    without details). Initialisations are vmapped (`eqx.filter_vmap`) and the loop is one
    compiled `lax.while_loop`; each run stops when $|\\Delta J| <$ `atol` $+$ `rtol` $|J_0|$
    or after `max_steps`.
    The controller ignores $\\hat x$ (memoryless), so `windows.x0` is unused.

    **Arguments:**

    - `key`: PRNG key (split into `num_inits` initialisation keys).
    - `windows`: demonstration windows (any horizon).
    - `hidden`: hidden-layer widths, equal positive integers; `len(hidden) + 1` weight
      matrices (paper: three, `(150, 150)` linear and `(25, 25)` nonlinear; `()` is the
      static affine map $\\hat y = W\\hat u + b$).
    - `num_inits`, `max_steps`, `atol`, `rtol`: as for the other trainers (default
      `atol` = 0, `rtol` = 1e-9, the relative rule of [`fit_pgd`][dissil_jax.fit_pgd]
      with the MLP's own value: on the zoo's tuning half, the largest that stops within
      1 % of the 2,000-step budget's loss on the median problem and within 10 % on the
      worst; at 1e-7 the worst problem stopped 7.1 times above it).
    - `learning_rate`: Adam's step on the network's weights and biases (about how far
      each of them moves per step), in the units `balance` chooses.
    - `throw`: raise a `ValueError` if a run's loss became non-finite (as `dj.fit_gd`).
    - `balance`: train in units of the data's own size (default True). Each input
      channel $y_j$ is divided by the power of two $a_j$ nearest to its root mean square
      over the samples, and the targets by one power of two $c$ nearest to that of $u$.
      The network $g$ trained there is returned as $f(y) = c\\,g(y/a)$ (first layer's
      weights over $a$, last layer's weights and bias times $c$; exact, powers of two),
      and losses and `atol` are in the user's units ($J = c^2 J_g$). One $c$ for every
      target keeps the loss's minimisers; per-channel $a$ only reparameterises the
      first layer. Without it, the default step and initial weights suit signals of
      order one only: on a static nonlinear expert with $y$ in units $10^3$ and $u$ in
      $10^{-3}$, the median final loss was 6.9e4 times the zero controller's, against
      8e-5 with balancing (`benchmarks/bench_mlp_units.py`). `False` trains in the
      data's units, as the paper's baseline (the experiments CLI does); under `jax.jit`
      or `jax.vmap` over the windows it is required, since the units come from the data
      on the host.
    - `progress`: as in [`fit_pgd`][dissil_jax.fit_pgd] (default True: a line on standard
      error every 10 s once training has taken 10 s).

    **Returns:** a [`FitResult`][dissil_jax.FitResult] whose `controllers` is an
    [`MLPController`][dissil_jax.MLPController] with a leading `[num_inits]` axis; `P` and
    `certified` are None.
    """
    check_key(key)
    check_flag("throw", throw)
    check_fit_args(windows, None, num_inits, max_steps, learning_rate=learning_rate, atol=atol,
                   rtol=rtol)
    hidden = check_hidden(hidden)
    units = mlp_units(windows, balance)
    a, c = (np.ones(windows.y.shape[-1]), 1.0) if units is None else units
    X, T = demonstration_pairs(windows)
    if units is not None:  # powers of two: exact
        X, T = X / jnp.asarray(a, X.dtype), T / jnp.asarray(c, T.dtype)
    keys = jr.split(key, num_inits)

    def run():
        model, hist, J, converged, steps, reason, kept = _train_batch(
            keys, X, T, hidden, int(max_steps), float(learning_rate), float(atol) / c**2,
            float(rtol), None if traced else token, jnp.asarray(c**2, X.dtype))
        if units is not None:
            model, hist, J = in_user_units(model, a, c), hist * c**2, J * c**2
        return FitResult(
            controllers=model, P=None, certified=None, loss_history=hist, final_loss=J,
            converged=converged, steps=steps, wall_time=jnp.asarray(jnp.nan, X.dtype),
            result=_outcome.item(reason), kept_step=kept)

    # no reports under a user's `jax.jit` or `jax.vmap`
    traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves((key, windows)))
    with reporting("fit_mlp", max_steps, check_flag("progress", progress) and not traced,
                   lanes=int(num_inits)) as token:
        return fit_timed(run, (), X.dtype, lambda res: res, throw)
