"""Projection-free training through the direct parameterisation."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import _outcome
from .._data import Windows
from .._direct_map import MARGIN, MapRate, check_margin, direct_map, init_params, solved_rate
from .._progress import reporting
from .._projection.project import project
from .._rollout import imitation_loss
from .._sdp import lmi as _lmi
from .._sdp.indefinite import is_indefinite
from .._supply import QSR
from .._validate import check_flag, check_key, check_positive, warn_user
from ._checks import (
    check_eager,
    check_fit_args,
    check_keep,
    check_n_state,
    check_optimizer,
    nan_unless,
)
from ._iterate import Method, iterate, where
from ._scale import loss_scale, scaled
from ._units import balance as balanced, balancing_units, unbalance
from .result import FitResult, fit_timed, raise_if_failed

_CONVERGED = _outcome.code("converged")

#: Defaults at the reference width n + p = 9 (the paper's linear example, n = 6, p = 3),
#: chosen on training loss (`benchmarks/bench_direct.py`): Adam's step in the normalised
#: units of `_scale.py` and the scale of the initial draw of W and V (with 1.0 the
#: contractions start nearly saturated and the median training loss was up to 3x worse).
#: `default_hyperparameters` scales both down for wider controllers.
LEARNING_RATE, INIT_SCALE, _WIDTH = 0.3, 0.5, 9
#: The default step budget. Adam steps of the direct map are cheap (no solver), and runs
#: that converge stop earlier by the relative rule. On the zoo's tuning half, stopping
#: at 150 steps left the median run's loss up to 5.4x (`cone_siso_tiny`) and 1.5x
#: (`paper_nonlinear`) above where 600 steps took it; 300 steps, still 4.3x on the former.
MAX_STEPS = 600
#: The default `rtol` (with `atol = 0`). Chosen like the other trainers' (largest `rtol`
#: whose stop is within about 1 % of the full budget's loss on the median tuning problem
#: and within 10 % on the worst), but measured against this trainer's own 600-step budget
#: (`benchmarks/results/defaults_stop.md`): 1e-6, the value read off a 150-step budget,
#: stopped 5.6x above the 600-step loss on the worst tuning problem, 1e-7 1.18x, 1e-8
#: within 0.5 %. A loss that falls by orders of magnitude makes a rule relative to
#: $J_0$ strict; the map's steps cost milliseconds, so the full budget is cheap.
RTOL_DIRECT = 1e-8


def default_hyperparameters(n_state: int, n_in: int) -> tuple[float, float]:
    """`(learning_rate, init_scale)` of `fit_direct` for a controller of order $\\hat n$
    with $p$ inputs: with $w = \\hat n + p$ (the width of $V$ and $W$),

    $$\\sigma = 0.5\\,\\min\\bigl(1, \\sqrt{9/w}\\bigr), \\qquad
    \\eta = 0.3\\,\\min\\bigl(1, 9/w\\bigr).$$

    Why: the spectral norms of $V$ and $W$ with i.i.d. $\\mathcal N(0,\\sigma^2)$ entries grow
    like $\\sigma\\sqrt w$, which pushes the contractions $U$, $Z$ towards saturation (and the
    initial loss up: at $\\sigma = 0.5$ it grew 3x from $\\hat n = 6$ to 48 on one of the chain
    problems of `benchmarks/bench_high_order.py`); $\\sigma\\propto1/\\sqrt w$ keeps
    $\\lVert V\\rVert_2$ constant. Adam moves every entry by about $\\eta$ per step, so a
    step changes $V$ by about $\\eta\\sqrt w$ in spectral norm, and the loss's curvature
    grows with the order too; the best fixed step fell from 0.3 at $\\hat n\\le12$ to 0.1 at
    24 and 0.03 at 48 in that benchmark's sweep, which $\\eta\\propto1/w$ follows.
    """
    width = n_state + n_in
    return (LEARNING_RATE * min(1.0, _WIDTH / width),
            INIT_SCALE * min(1.0, (_WIDTH / width) ** 0.5))


def map_loss(param_map: Callable, loss: Callable) -> Callable:
    """`MapDescent`'s `loss_fn` for a direct map: `(theta, windows) -> ((J, out), grad)`,
    batched over the lanes of `theta`.

    `param_map(theta)` returns a tuple whose first entry is the controller (then its
    certificate: `(K, P)` for the LTI map, `(K, P, Λ)` for the REN map); `J = loss(K,
    windows)` and the gradient is with respect to `theta`.
    """
    def value(theta, windows):
        out = param_map(theta)
        return loss(out[0], windows), out

    return jax.vmap(jax.value_and_grad(value, has_aux=True), in_axes=(0, None))


class MapDescent(Method):
    """Unconstrained descent on $J_s(K(\\theta))$ through a direct map, for the driver loop
    (`_iterate.py`); `loss_fn(theta, windows) -> ((J, aux), grad)` batched over the lanes
    (`map_loss` of the LTI map here, of the REN map in `ren.py`).

    Pure JAX (no callback), so the run can be jitted, vmapped over the optimiser's
    hyperparameters and sharded. The state carries the gradient of the current iterate, so
    each step evaluates the map, the loss and its gradient once; a non-finite gradient
    counts as a non-finite loss; the driver returns the best finite iterate.
    """

    theta0: Any
    windows: Windows
    opt: optax.GradientTransformation
    loss_fn: Callable

    def init(self):
        return (self.theta0, self.opt.init(self.theta0)), _outcome.code("max_steps")

    def evaluate(self, pending):
        theta, opt_state = pending
        (loss, aux), grad = self.loss_fn(theta, self.windows)
        finite = jnp.isfinite(loss)
        for g in jax.tree.leaves(grad):
            finite &= jnp.all(jnp.isfinite(g), axis=tuple(range(1, g.ndim)))
        return (theta, grad, aux, opt_state), jnp.where(finite, loss, jnp.nan)

    def select(self, accept, new, old):
        # One optimiser state for the whole batch (as before the driver loop existed): it
        # moves on every step, the lanes' iterates only where accepted.
        return (*where(accept, new[:3], old[:3]), new[3])

    def update(self, state, active):
        theta, grad, _, opt_state = state
        updates, opt_state = self.opt.update(grad, opt_state, theta)
        return (optax.apply_updates(theta, updates), opt_state), _CONVERGED


def _run(key, windows, rate: MapRate, k, learning_rate, init_scale, *, optimizer, num_inits,
         n_state, max_steps, atol, rtol, margin, keep="best", progress=None) -> FitResult:
    """`direct_run` without argument checks or `throw` (traceable; `optimizer` static).

    `rate, k = solved_rate(qsr, margin, dtype)`: the rate as solved (divided by the power
    of two `k` when far from unit size; P is multiplied back) and its map constants, traced
    here so that training under another rate of the same shape does not compile again."""
    s2 = loss_scale(windows)
    dtype = windows.y.dtype
    theta0 = init_params(key, num_inits, n_state, windows.n_in, windows.n_out, init_scale,
                         dtype)
    opt = optax.adam(learning_rate) if optimizer is None else optimizer
    (_, _, (K, P), _), hist, loss, steps, reason, kept = iterate(
        MapDescent(theta0, scaled(windows, s2), opt,
                   map_loss(lambda theta: direct_map(theta, rate, margin), imitation_loss)),
        max_steps=max_steps, atol=atol / s2, rtol=rtol, keep=keep,
        progress=None if progress is None else (progress, s2))
    return FitResult(
        controllers=K, P=P * k, certified=None,
        loss_history=hist * s2, final_loss=loss * s2, converged=reason == _CONVERGED,
        steps=steps, wall_time=jnp.asarray(jnp.nan, hist.dtype),
        result=_outcome.item(reason), projected=jnp.zeros(num_inits, bool), kept_step=kept)


_run_jit = eqx.filter_jit(_run)


def _options(windows, qsr, num_inits, max_steps, *, optimizer, learning_rate, atol, rtol,
             init_scale, n_state, margin):
    """Check the arguments; returns `(optimizer, learning_rate, init_scale, n_state, margin)`
    (`learning_rate` and `init_scale` from `default_hyperparameters` where None)."""
    if qsr is None:
        raise ValueError("`qsr` is required: the direct map parameterises the (Q,S,R)-"
                         "dissipative controllers; use `dj.fit_gd` for unconstrained training.")
    if check_optimizer(optimizer, "Adam's step", learning_rate=learning_rate):
        learning_rate = 0.0  # unused (and not checked)
    given = dict(learning_rate=None if optimizer is not None else learning_rate,
                 init_scale=init_scale)
    check_fit_args(windows, qsr, num_inits, max_steps, atol=atol, rtol=rtol,
                   **{k: v for k, v in given.items() if v is not None})
    if is_indefinite(qsr):
        raise ValueError(
            "`qsr.Q` has a positive eigenvalue: the direct map parameterises the dissipative "
            "controllers only for Q negative semidefinite. Train under this `qsr` with "
            "`dj.fit_pgd` or `dj.fit_ico` (they linearise Q's positive part), or pass a "
            "supply rate with Q <= 0.")
    n_state = check_n_state(windows, n_state)
    lr0, scale0 = default_hyperparameters(n_state, windows.n_in)
    learning_rate = lr0 if learning_rate is None else learning_rate
    init_scale = scale0 if init_scale is None else init_scale
    learning_rate, init_scale = (nan_unless(v, lambda v: v >= 0)
                                 for v in (learning_rate, init_scale))
    return optimizer, learning_rate, init_scale, n_state, check_margin(margin)


def direct_run(
    key, windows: Windows, qsr: QSR, *, optimizer=None, learning_rate=None,
    init_scale=None, num_inits: int = 8, n_state: int | None = None,
    max_steps: int = MAX_STEPS, atol: float = 0.0, rtol: float = RTOL_DIRECT,
    margin: float = MARGIN,
    throw: bool = True, keep: str = "best",
) -> FitResult:
    """The pure, traceable run behind [`fit_direct`][dissil_jax.fit_direct].

    Pure JAX from the initial draw to the result: no host callback (with `throw=False`;
    `throw=True` adds equinox's error check after the loop), so it can be `jax.jit`-ed,
    `jax.vmap`-ped over `key`, `learning_rate`, `init_scale` (or the hyperparameters an
    `optimizer` closes over), differentiated and sharded over devices with `jax.sharding`
    (a `NamedSharding` on the swept axis); `qsr` and `margin` are static. Derivatives:
    reverse mode through the map (training uses it), forward mode (`jax.jvp`,
    `jax.jacfwd`) through the whole run (a `lax.while_loop`), e.g. the final loss's
    derivative in the learning rate. `wall_time` is NaN, `projected` is
    all False and `certified` is None: the exact check is float64 work on the host, which
    [`fit_direct`][dissil_jax.fit_direct] does after the run (or call
    `dj.certify(res.controllers, qsr, P=res.P)`, which accepts the sweep's batch axes).
    A traced hyperparameter cannot be checked eagerly: a lane whose `learning_rate` or
    `init_scale` is NaN or negative ends as `non_finite`.

    ```python
    lrs = jnp.array([0.01, 0.03, 0.1])
    run = lambda lr: dj.direct_run(key, windows, qsr, learning_rate=lr, throw=False)
    res = jax.jit(jax.vmap(run))(lrs)     # every field gains a leading axis of size 3
    ```
    """
    check_key(key)
    check_flag("throw", throw)
    optimizer, learning_rate, init_scale, n_state, margin = _options(
        windows, qsr, num_inits, max_steps, optimizer=optimizer, learning_rate=learning_rate,
        atol=atol, rtol=rtol, init_scale=init_scale, n_state=n_state, margin=margin)
    res = _run(key, windows, *solved_rate(qsr, margin, windows.y.dtype), learning_rate,
               init_scale, optimizer=optimizer,
               num_inits=int(num_inits), n_state=n_state, max_steps=int(max_steps),
               atol=atol, rtol=rtol, margin=margin, keep=check_keep(keep))
    return raise_if_failed(res) if throw else res


def certify_or_project(res: FitResult, qsr: QSR, windows: Windows, *, eps: float) -> FitResult:
    """The final check of `fit_direct`: exact float64 KYP of every `(controller, P)`.

    A pair that fails (rounding, or an ill-conditioned map: essentially never with the
    default margin) is replaced by its projection ([`dj.project`][dissil_jax.project]),
    linearised at the map's $P$ or, if that fails, from $\\tilde P = I$ with refinement;
    it is flagged in `projected`, and its `final_loss` is that of the projected controller.
    If both projections fail, the run keeps the map's controller with `certified` False and
    `result` the projection's failure.
    """
    K, P = res.controllers, res.P
    assert P is not None  # the direct map returns a storage with every controller
    ok = _lmi.certified(K.A, K.B, K.C, K.D, qsr, P)
    projected = np.zeros(ok.shape, bool)
    reason = np.asarray(_outcome.codes(res.result)).copy()
    final = np.asarray(res.final_loss).copy()
    loss = jax.vmap(imitation_loss, in_axes=(0, None))
    for P_ref in ("map", None):
        bad = np.nonzero(~ok)[0]
        if not len(bad):
            break
        take = lambda tree: jax.tree.map(lambda a: a[bad], tree)
        proj = project(take(K), qsr, take(P) if P_ref else None, throw=False, eps=eps)
        codes = np.asarray(_outcome.codes(proj.result))
        good = ~_outcome.failed(codes)
        idx = bad[good]
        K = jax.tree.map(lambda a, b: a.at[idx].set(b[good]), K, proj.controller)
        P = P.at[idx].set(proj.P[good])
        final[idx] = np.asarray(loss(proj.controller, windows))[good]
        reason[bad[~good]] = codes[~good]
        reason[idx] = np.asarray(_outcome.codes(res.result))[idx]
        projected[idx] = ok[idx] = True
    if projected.any():  # a projection can undo the training: say so
        ratio = final[projected] / np.asarray(res.final_loss)[projected]
        warn_user(
            f"{int(projected.sum())} of {projected.size} trained controllers failed the exact "
            f"float64 check with the map's storage (in {np.dtype(P.dtype).name}) and were "
            f"replaced by their projections (`projected`), with final losses "
            f"{ratio.min():.3g}-{ratio.max():.3g} times the trained ones. The map's storage "
            "was conditioned beyond the precision. "
            + ("It happens in float32 at high orders: train in float64 (`JAX_ENABLE_X64=1` "
               "or `jax_enable_x64`)." if np.dtype(P.dtype).itemsize < 8 else
               "In float64 it happens on rates far from balanced (|Q| far above or below "
               "R, a tight gain bound): compare with `dj.fit_pgd` or `dj.fit_ico`, or "
               "pass a larger `margin`."))
    return eqx.tree_at(
        lambda r: (r.controllers, r.P, r.certified, r.projected, r.final_loss, r.result),
        res, (K, P, jnp.asarray(ok), jnp.asarray(projected),
              jnp.asarray(final, res.final_loss.dtype), _outcome.item(reason)),
        is_leaf=lambda x: x is None)


def fit_direct(
    key, windows: Windows, qsr: QSR, *, optimizer=None, learning_rate: float | None = None,
    num_inits: int = 8, n_state: int | None = None, max_steps: int = MAX_STEPS,
    atol: float = 0.0,
    rtol: float = RTOL_DIRECT, init_scale: float | None = None, margin: float = MARGIN,
    fallback_eps: float = 1e-6, throw: bool = True, keep: str = "best", balance: bool = True,
    progress: bool = True,
) -> FitResult:
    """Learn $(Q,S,R)$-dissipative controllers without projections, through a direct map.

    Every controller is the image $K(\\theta)$ of free parameters $\\theta$ under a smooth
    map ([concepts](concepts.md#a-direct-parameterisation)) whose values satisfy

    $$\\mathrm{KYP}(P(\\theta))\\preceq-\\varepsilon\\operatorname{diag}(P(\\theta),\\Phi_0),
    \\qquad P(\\theta)\\succeq\\varepsilon I$$

    for every $\\theta$ and every supply rate with $Q\\preceq0$: $Q\\prec0$, passivity and
    the degenerate cones ($Q = 0$) and rank-deficient $Q$ alike; no step inverts $Q$. So
    training is unconstrained gradient descent on $J_s(K(\\theta))$, the imitation loss
    ([`imitation_loss`][dissil_jax.imitation_loss]) of the windows in normalised units
    (as [`fit_pgd`][dissil_jax.fit_pgd]: scaling $x_0$, $y$, $u$ by $c>0$ changes nothing,
    and outputs or states whose units are far from the inputs' are rescaled exactly,
    `balance`;
    losses and `atol` are in the user's units), all in one compiled `lax.while_loop`
    without leaving the device (no LAPACK call in the loop either: its factorisations are
    loop-based, see [Thread-pool deadlocks](scaling.md#thread-pool-deadlocks)). The run
    stops when $|J(K_{i+1}) - J(K_i)| <$ `atol` $+$ `rtol` $|J(K_0)|$ or after
    `max_steps`.

    **Certified at the end.** Each returned $(K, P)$ is checked in float64 on the host
    (the check of [`certify`][dissil_jax.certify] with `P` given), after rounding to the
    data's dtype. The margin $\\varepsilon$ makes a failure rare in float64; a controller
    that fails is replaced by its [`project`][dissil_jax.project]ion, flagged in
    `FitResult.projected`, with a warning (the projection can undo the training). In
    float32 at high orders the map's storage can be conditioned beyond the precision: on
    an order-32 problem with 6 outputs, 15 of 16 controllers were projected back to about
    their initial loss (4-5 times the trained one), and none in float64.

    **Arguments:**

    - `key`: PRNG key for the initialisations.
    - `windows`: the demonstrations ([`Windows`][dissil_jax.Windows]).
    - `qsr`: the controller's supply rate ($Q\\preceq0$; an indefinite $Q$ raises a
      `ValueError`: use [`fit_pgd`][dissil_jax.fit_pgd] or [`fit_ico`][dissil_jax.fit_ico]).
    - `optimizer`, `learning_rate`: by default `optax.adam(learning_rate)`, so
      `learning_rate` is Adam's step on the direct map's free parameters $\\theta$ (about
      how far each entry of $\\theta$ moves per step; not a factor of the gradient); or any
      `optax.GradientTransformation` as `optimizer` (then leave `learning_rate` unset). The
      default step depends on the width $w = \\hat n + p$: $0.3\\min(1, 9/w)$ (0.3 at the
      paper's sizes; parameters and loss are unit-free), see `default_hyperparameters` and
      [concepts](concepts.md#a-direct-parameterisation).
    - `num_inits`, `n_state`, `atol`: as in [`fit_pgd`][dissil_jax.fit_pgd].
    - `rtol`: the relative stopping rule of [`fit_pgd`][dissil_jax.fit_pgd], default
      1e-8 (`RTOL_DIRECT`), measured on the zoo's tuning half against the 600-step
      budget: larger values stopped runs whose loss was still falling by orders of
      magnitude below $J(K_0)$ (1e-6: 5.6x above the budget's loss on the worst tuning
      problem).
    - `max_steps`: the step budget, default 600 (`MAX_STEPS`): the map's steps are cheap,
      and on the zoo's tuning half 150 steps left the median run up to 5.4x above where
      600 took it.
    - `init_scale` $\\sigma$: the initial $\\theta$ has $X = I$ (so $P\\approx I$, the
      projection's starting point) and i.i.d. $\\mathcal N(0,\\sigma^2)$ entries in $W$
      and $V$: a random dissipative controller. Default $0.5\\min(1, \\sqrt{9/w})$, so
      that the initial loss does not grow with the order: $\\sigma = 0.5$ (a quarter to
      40 % of PGD's initial loss at the paper's sizes) trained better than $\\sigma = 1$,
      whose contractions start near saturation, where gradients are small; a fixed
      $\\sigma$ saturates them more the wider the controller.
    - `margin` $\\varepsilon\\in(0,1)$: the map's strictness margin (static).
    - `fallback_eps`: the LMI margin $\\varepsilon$ of the fallback projection (`eps` of
      [`project`][dissil_jax.project]; called `eps` before).
    - `throw`: raise a `ValueError` when a run ends in failure (a non-finite loss, or a
      failed fallback projection); with `throw=False` see `result`.
    - `keep`: `"best"` (default) returns each run's iterate of lowest loss, `"last"` its
      final iterate (`kept_step` records which step), as in `fit_pgd`.
    - `balance`: as in `fit_pgd` (default True): when the outputs' size is more than 5x
      above or below the inputs', train on outputs rescaled by a power of two and the
      matching supply rate; when an initial state is more than 5x smaller than the
      outputs' $y$, train in state coordinates rescaled by a power of two; map the result
      back exactly. A narrow cone far from zero is trained about its centre first (in
      `fit_pgd`'s words); on a cone $[10^3, 10^3 + 1]$ the map fitted 2000 times worse
      without it.
    - `progress`: as in `fit_pgd` (default True: a line on standard error every 10 s once
      training has taken 10 s).

    **Returns:** a [`FitResult`][dissil_jax.FitResult] with `certified` from the float64
    check and `projected` (bool per initialisation).

    ```python
    res = dj.fit_direct(key, windows, dj.QSR.passive(3), num_inits=20)
    assert bool(res.certified.all())
    ```
    """
    check_key(key)
    check_eager("fit_direct", key, windows, throw, "dj.direct_run",
                learning_rate=learning_rate, init_scale=init_scale, atol=atol, rtol=rtol,
                margin=margin, fallback_eps=fallback_eps)
    optimizer, learning_rate, init_scale, n_state, margin = _options(
        windows, qsr, num_inits, max_steps, optimizer=optimizer, learning_rate=learning_rate,
        atol=atol, rtol=rtol, init_scale=init_scale, n_state=n_state, margin=margin)
    fallback_eps = check_positive("fallback_eps", fallback_eps)  # used after training
    units = balancing_units(windows, balance, qsr)  # outputs' and states' units (`_units.py`)
    user_qsr, (windows, qsr) = qsr, balanced(windows, qsr, units)
    c = units.c
    rate = solved_rate(qsr, margin, windows.y.dtype)  # traced: one compilation per shape
    with reporting("fit_direct", max_steps, check_flag("progress", progress), c**2) as token:
        return unbalance(fit_timed(
            lambda *h: _run_jit(key, windows, *rate, *h, optimizer=optimizer,
                                num_inits=int(num_inits), n_state=n_state,
                                max_steps=int(max_steps),
                                # traced: another tolerance does not recompile the run
                                atol=jnp.asarray(atol / c**2, windows.y.dtype),
                                rtol=jnp.asarray(rtol, windows.y.dtype),
                                margin=margin, keep=check_keep(keep), progress=token),
            (learning_rate, init_scale), windows.y.dtype,
            lambda res: certify_or_project(res, qsr, windows, eps=fallback_eps),
            throw, token), units, user_qsr, throw)
