"""Projected gradient descent (paper Alg. 2) and its unconstrained baseline (GD)."""

from __future__ import annotations

from typing import Any, cast

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .. import _outcome
from .._data import Windows
from .._progress import reporting
from .._projection import first_order as _first_order
from .._projection.args import check_eps_room
from .._projection.first_order import trainer_rate
from .._projection.project import project
from .._rate_scale import rate_factor, scaled_rate
from .._sdp import lmi as _lmi
from .._supply import QSR
from .._validate import check_callback_dtype, check_flag, check_key
from ._checks import (
    check_eager,
    check_fit_args,
    check_keep,
    check_n_state,
    check_optimizer,
    finite_lanes,
    nan_unless,
)
from ._init import init_controllers
from ._iterate import RTOL, iterate
from ._scale import loss_scale, scaled
from ._units import balance as balanced, balancing_units, unbalance
from .pgd_steps import PGDSteps
from .result import FitResult, fit_timed, raise_if_failed
from .steps import (
    ADAM_INIT_SCALE as ADAM_INIT_SCALE,  # re-exported
    ADAM_LEARNING_RATE as ADAM_LEARNING_RATE,  # re-exported
    default_init_scale,
    default_rule,
    optimizer_metric,
    paper_rule,
)

_CONVERGED, _MAX_STEPS, _NON_FINITE = (
    _outcome.code(r) for r in ("converged", "max_steps", "non_finite"))


def _run(key, windows, qsr, learning_rate, decay, init_scale, *, optimizer, num_inits,
         n_state, max_steps, atol, rtol, eps, method="clarabel", keep="best",
         progress=None, k=None) -> FitResult:
    """`pgd_run` without argument checks or `throw` (traceable; `qsr` and `optimizer` static).

    Trains on the windows divided by the data scale (`_scale.py`), so that steps do not
    depend on units; losses and `atol` are converted from and to the user's units. With
    `k` given, `qsr` is the `RateHandle` of the rate divided by `k` (`fit_pgd`'s
    `trainer_rate`): its values are traced, so another rate does not compile again.
    """
    s2 = loss_scale(windows)
    if k is None:
        # a rate far from unit size is solved divided by a power of two, P multiplied back
        k = 1.0 if qsr is None else rate_factor(qsr)
        qsr = None if qsr is None else scaled_rate(qsr, k)
    if qsr is not None:
        check_callback_dtype(windows.y.dtype, "pgd_run` or `fit_pgd")
    K0 = init_controllers(key, num_inits, windows, init_scale, n_state=n_state)
    if qsr is None:
        P0, code0 = None, jnp.full(num_inits, _MAX_STEPS, jnp.int32)
    else:
        # a non-finite draw (a lane of a sweep with a NaN or negative `init_scale`) is
        # reported as such, not as its projection's failure
        drawn = finite_lanes(K0)
        K0, P0 = proj = project(K0, qsr, throw=False, eps=eps, method=method)
        code0 = jnp.where(drawn, _outcome.codes(proj.result), _NON_FINITE).astype(jnp.int32)
    opt = paper_rule(learning_rate, decay) if optimizer is None else optimizer
    weighted = optimizer_metric(jax.vmap(opt.init)(cast(Any, K0)), K0) is not None
    warm = qsr is not None and _first_order.use_first_order(method, K0.n_state, weighted, qsr)
    pgd = PGDSteps(K0, P0, code0, scaled(windows, s2), opt, qsr, eps, method, warm, weighted)
    (K, P, *_), hist, loss, steps, reason, kept = iterate(
        pgd, max_steps=max_steps, atol=atol / s2, rtol=rtol, keep=keep,
        progress=None if progress is None else (progress, s2))
    hist, loss = hist * s2, loss * s2
    return FitResult(
        controllers=K, P=None if P is None else P * k,
        # the initial projection's verdict, of a controller that stayed finite, in a lane
        # whose hyperparameters are valid (a sweep's bad value, made NaN by `nan_unless`,
        # ends its lane `non_finite` and not certified; a run whose loss overflowed late
        # keeps its best iterate, certified)
        certified=None if qsr is None else jnp.asarray(
            ~_outcome.failed(code0) & finite_lanes(K)
            & jnp.isfinite(jnp.asarray(learning_rate)) & jnp.isfinite(jnp.asarray(decay))),
        loss_history=hist, final_loss=loss, converged=reason == _CONVERGED, steps=steps,
        wall_time=jnp.asarray(jnp.nan, hist.dtype), result=_outcome.item(reason),
        kept_step=kept)


_run_jit = eqx.filter_jit(_run)

#: The defaults of the paper's rule, in the normalised units of `_scale.py`: chosen by the
#: comparison of step rules in `benchmarks/bench_optimizers.py` (four problems) and
#: confirmed by the reproduction's own step-size sweeps (`docs/results/lr_sweep_*`).
LEARNING_RATE, DECAY = 1.0, 0.99



def _options(windows, qsr, num_inits, max_steps, *, optimizer, learning_rate, decay, atol,
             rtol, init_scale, n_state, eps=None):
    """Check the arguments; returns `(optimizer, learning_rate, decay, n_state)`.

    `optimizer` is None for the paper's rule, whose (possibly traced) `learning_rate` and
    `decay` are then used, with the defaults filled in.
    """
    if check_optimizer(optimizer, "the paper's decaying-step rule", learning_rate=learning_rate,
                       decay=decay):
        learning_rate = decay = 0.0  # unused
    learning_rate = LEARNING_RATE if learning_rate is None else learning_rate
    decay = DECAY if decay is None else decay
    rule = dict(learning_rate=learning_rate, decay=decay) if optimizer is None else {}
    check_fit_args(windows, qsr, num_inits, max_steps, atol=atol, rtol=rtol,
                   init_scale=init_scale, **rule)
    if optimizer is None and not isinstance(decay, jax.core.Tracer) and not 0.0 < decay <= 1.0:
        # the paper's step decays: eta_k = eta_0 decay^k
        raise ValueError(f"`decay` must be in (0, 1] (the step eta_0 decay^k decays), got "
                         f"{decay!r}.")
    if qsr is not None and eps is not None:
        check_eps_room(qsr, eps)
    learning_rate = nan_unless(learning_rate, lambda v: v >= 0)
    decay = nan_unless(decay, lambda v: (v > 0) & (v <= 1))
    return optimizer, learning_rate, decay, check_n_state(windows, n_state)


def pgd_run(
    key, windows: Windows, qsr: QSR | None, *, optimizer=None, learning_rate=None, decay=None,
    init_scale=None, num_inits: int = 8, n_state: int | None = None,
    max_steps: int = 150, atol: float = 0.0, rtol: float = RTOL, eps: float = 1e-6,
    throw: bool = True, method: str = "auto", keep: str = "best",
) -> FitResult:
    """The pure, traceable PGD run behind [`fit_pgd`][dissil_jax.fit_pgd].

    Unlike `fit_pgd` it is safe to `jax.vmap`/`jax.jit` over `key`, `learning_rate`,
    `decay` and `init_scale`, or over the hyperparameters an `optimizer` closes over (a
    hyperparameter sweep); `qsr` is static (hashable), so each distinct rate compiles a
    run of its own (`fit_pgd` does not; see [`QSR`][dissil_jax.QSR], "Many rates in one
    process"). `qsr=None` gives plain gradient descent, with
    `fit_gd`'s default step and initial scale for its order (`init_scale` None, the
    default: 0.3, or for plain GD $0.3\\min(1, 3/\\sqrt{\\hat n})$). `wall_time` is NaN
    and `certified` comes from the projection's own float64 check (with `throw=False`, a
    failed initial projection leaves that initialisation with `certified=False` and zero
    steps). `throw`, `method` and `keep` as in `fit_pgd`: with
    `throw=True` a failure raises a `ValueError` eagerly, a `jax.errors.JaxRuntimeError`
    under `jax.jit` (an `equinox.EquinoxRuntimeError` under `equinox.filter_jit`). A
    traced hyperparameter cannot be checked eagerly: a lane whose `learning_rate` or
    `init_scale` is NaN or negative, or whose `decay` lies outside (0, 1], ends as
    `non_finite` with `certified=False`.

    ```python
    lrs = jnp.logspace(-2, 0, 5)
    run = lambda lr: dj.pgd_run(key, windows, qsr, learning_rate=lr, throw=False)
    res = jax.jit(jax.vmap(run))(lrs)     # every field gains a leading axis of size 5
    ```
    """
    check_key(key)
    check_flag("throw", throw)
    init_scale = default_init_scale(init_scale, windows if qsr is None else None, n_state)
    optimizer, learning_rate, decay, n_state = _options(
        windows, qsr, num_inits, max_steps, optimizer=default_rule(
            optimizer, learning_rate, decay, windows if qsr is None else None, n_state),
        learning_rate=learning_rate, decay=decay, atol=atol, rtol=rtol, init_scale=init_scale,
        n_state=n_state, eps=eps)
    init_scale = nan_unless(init_scale, lambda v: v >= 0)
    res = _run(key, windows, qsr, learning_rate, decay, init_scale, optimizer=optimizer,
               num_inits=int(num_inits), n_state=n_state, max_steps=int(max_steps),
               atol=atol, rtol=rtol, eps=eps, method=method, keep=check_keep(keep))
    return raise_if_failed(res) if throw else res


def _fit(key, windows, qsr, *, optimizer, learning_rate, decay, init_scale, num_inits,
         n_state, max_steps, atol, rtol, eps, throw, method="clarabel", keep="best",
         balance=True, progress=True):
    """`pgd_run`, compiled once per static configuration, timed and certified as a batch."""
    check_key(key)
    progress = check_flag("progress", progress)
    init_scale = default_init_scale(init_scale, windows if qsr is None else None, n_state)
    if qsr is None:  # plain GD has no host check: it runs under `jax.vmap` too
        check_flag("throw", throw)
    else:
        check_eager("fit_pgd", key, windows, throw, "dj.pgd_run",
                    learning_rate=learning_rate, decay=decay, init_scale=init_scale,
                    atol=atol, rtol=rtol, eps=eps)
    optimizer, learning_rate, decay, n_state = _options(
        windows, qsr, num_inits, max_steps, optimizer=optimizer, learning_rate=learning_rate,
        decay=decay, atol=atol, rtol=rtol, init_scale=init_scale, n_state=n_state)

    units = balancing_units(windows, balance, qsr)  # outputs' and states' units (`_units.py`)
    user_qsr, (windows, qsr) = qsr, balanced(windows, qsr, units)
    c = units.c
    if qsr is not None:  # the margin applies to the rate as solved: after balancing
        check_eps_room(qsr, eps)

    def certify(res):
        if qsr is None:
            return res
        # The exact float64 check of every returned (controller, P) pair, as one batch.
        K = res.controllers
        ok = np.asarray(res.certified) & _lmi.certified(K.A, K.B, K.C, K.D, qsr, res.P)
        return eqx.tree_at(lambda r: r.certified, res, jnp.asarray(ok))

    # no reports from `fit_gd` under a user's `jax.jit` or `jax.vmap` (its only host work)
    traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves((key, windows)))
    name = "fit_gd" if qsr is None else "fit_pgd"
    with reporting(name, max_steps, progress and not traced, c**2) as token:
        rate, k = trainer_rate(qsr, method, n_state, windows.y.dtype)
        return unbalance(fit_timed(
            lambda *h: _run_jit(key, windows, rate, *h, optimizer=optimizer,
                                num_inits=int(num_inits), n_state=n_state,
                                max_steps=int(max_steps),
                                # traced: another tolerance does not recompile the run
                                atol=jnp.asarray(atol / c**2, windows.y.dtype),
                                rtol=jnp.asarray(rtol, windows.y.dtype),
                                eps=float(eps), method=method, keep=check_keep(keep),
                                progress=None if traced else token, k=k),
            (learning_rate, decay, init_scale), windows.y.dtype, certify, throw,
            None if qsr is None else token), units, user_qsr, throw)


def fit_pgd(
    key, windows: Windows, qsr: QSR, *, optimizer=None, learning_rate: float | None = None,
    decay: float | None = None, num_inits: int = 8, n_state: int | None = None,
    max_steps: int = 150, atol: float = 0.0, rtol: float = RTOL,
    init_scale: float = ADAM_INIT_SCALE, eps: float = 1e-6, throw: bool = True,
    method: str = "auto", keep: str = "best", balance: bool = True, progress: bool = True,
) -> FitResult:
    """Learn $(Q,S,R)$-dissipative controllers by projected gradient descent (paper Alg. 2).

    For each of `num_inits` random initialisations $K_0$ (entries
    $\\mathcal N(0,\\sigma^2)$, $\\sigma=$ `init_scale`, then projected), iterate

    $$\\tilde K_{i} = K_i + \\Delta_i\\bigl(\\nabla J_s(K_0),\\dots,\\nabla J_s(K_i)\\bigr),
    \\qquad K_{i+1} = \\Pi_{\\tilde P = P_i}(\\tilde K_i),$$

    with $\\Pi$ the projection of paper eq. 13 ([`project`][dissil_jax.project]) linearised
    at the previous iterate's $P$ and $\\Delta_i$ the update of an optax optimiser, whose
    state carries across steps (projected Adam by default, projected momentum, ...), or
    the paper's rule $\\Delta_i = -\\eta_0\\rho^{\\,i}\\nabla J_s(K_i)$.
    The run stops when $|J(K_{i+1}) - J(K_i)| <$ `atol` $+$ `rtol` $|J(K_0)|$ or after
    `max_steps`. All
    initialisations run in one compiled `lax.while_loop`; each step sends the whole batch
    to the host once, where Clarabel solves it on a thread pool.

    **Units do not matter.** The steps are taken on $J_s = J/s^2$, the imitation loss
    ([`imitation_loss`][dissil_jax.imitation_loss]) of the windows divided by
    $s$, the root mean power of their initial states and inputs,
    $s^2 = \\frac1N\\sum_i(\\lVert x_0^{(i)}\\rVert^2 + \\sum_k\\lVert y^{(i)}_k\\rVert^2)$.
    Scaling $x_0$, $y$ and $u$ by any $c > 0$ leaves every step unchanged; `loss_history`,
    `final_loss` and `atol` are in the user's units ($J = s^2 J_s$). **Nor do the
    outputs' own units** (`balance=True`): when the size of the outputs $u$ is far from
    that of the inputs (their ratio $r$ outside $[1/5, 5]$; a force against a velocity,
    say), the run is made on $u/c$, $c$ the power of two nearest $r$, with the supply rate
    $(c^2Q, cS, R)$ that the same controllers satisfy in those units, and the result is
    mapped back exactly: $(A, B, cC, cD)$ with the same $P$
    ([concepts](concepts.md#units-of-the-outputs)). **Nor do the states' own units**: an
    initial state $\\hat x_{0,i}$ more than 5x smaller than the outputs' $y$ (a plant
    measured in large units) is divided by the power of two $d_i$ nearest that ratio, a
    change of the controller's state coordinates; the result is mapped back exactly,
    $(DAD^{-1}, DB, CD^{-1}, D)$ with storage $D^{-1}PD^{-1}$, and checked again in the
    user's units ([concepts](concepts.md#units-of-the-states)).

    **Arguments:**

    - `key`: PRNG key for the initialisations.
    - `windows`: the demonstrations ([`Windows`][dissil_jax.Windows]).
    - `qsr`: the controller's supply rate (any symmetric $Q$; an indefinite $Q$'s positive
      part is linearised at the current iterate, see [`project`][dissil_jax.project]).
    - `optimizer`, `learning_rate`, `decay`: the step rule. With none of them given,
      `optax.adam(0.1)` (`ADAM_LEARNING_RATE`, in the normalised units above), chosen on
      the tuning half of the problem zoo (`dissil_jax.experiments.zoo`,
      `benchmarks/bench_defaults.py`): its worst regret there was 1.07 against 74 for
      the paper's rule. Any `optax.GradientTransformation` as `optimizer`; or the
      paper's rule, selected by giving `learning_rate` $\\eta_0$ and/or `decay` $\\rho$
      (the missing one defaults to $\\eta_0 = 1$, $\\rho = 0.99$; the reproduction passes
      the paper's values). `learning_rate` is always the paper rule's $\\eta_0$ here; an
      optimiser's own rate goes into the optimiser. When the optimiser's
      state holds a second moment $\\nu$ (Adam, RMSProp, ...), $\\Pi$ measures distance
      in its metric $\\sqrt\\nu$ (`project`'s `metric`), so that the fixed points of the
      projected steps are the constrained minima
      ([Concepts](concepts.md#projecting-an-adaptive-step)).
    - `num_inits`: number of random initialisations.
    - `n_state`: the controller order $\\hat n$; required when `windows.x0` is None (the
      controller starts at rest), otherwise it must equal `windows.n_state`.
    - `max_steps` (paper: 150), `atol` and `rtol`: the stopping rule
      $|\\Delta J| <$ `atol` $+$ `rtol` $|J_0|$ ($J_0$ the run's initial loss). The
      default, `atol` = 0 and `rtol` = 1e-6, does not depend on the data's units; it was
      chosen on the tuning half of `dissil_jax.experiments.zoo` (the largest `rtol` that
      stops within about 1 % of the full budget's loss, `benchmarks/bench_defaults.py`;
      `fit_gd` uses 1e-8, `fit_mlp` 1e-9). The paper's
      $|\\Delta J| <$ tol is `atol` = tol, `rtol` = 0: 1e-3 linear, 1e-5 nonlinear. With
      both `0.0` every step runs. The rule looks at one step's change, so a run whose
      loss oscillates can stop at a quiet step: `converged` says that the rule fired, not
      that the loss is stationary.
    - `init_scale`: $\\sigma$ of the initial draw (default 0.3, `ADAM_INIT_SCALE`; the
      paper's N(0, 1) draw is `init_scale=1`, see below).
    - `eps`: the LMI's strictness margin.
    - `throw`: raise a `ValueError` when a run ends in failure (`result` other than
      `converged` or `max_steps`: a failed projection, or a non-finite loss). With
      `throw=False` the result is returned and `result` says what happened; a failed
      run keeps its best certified iterate (`kept_step` says which).
    - `keep`: which iterate each run returns: `"best"` (default), the certified iterate of
      lowest loss, or `"last"`, the final one, as the paper's Algorithm 2 outputs
      $\\mathcal C_{i+1}$ (the reproduction uses it). They differ when a step raised the
      loss; `kept_step` records the step of the returned iterate.
    - `method`: $\\Pi$'s solver, as `project`'s `method`. `"first_order"`: ADMM in JAX
      (in the optimiser's metric for Adam and its kin), every result still checked in
      float64 on the host, Clarabel where the check fails; `"clarabel"`; `"auto"`
      (default): the first-order path from $\\hat n = 12$ on, where it was measured
      faster, with each step's ADMM warm-started from the previous one's; Clarabel below
      ([Scaling out](scaling.md#a-first-order-projection)).
    - `balance`: rescale the outputs when their units are far from the inputs', and the
      initial states when theirs are far from the outputs' $y$ (default True, see "Units"
      above); first, train a narrow cone far from zero about its centre $-Q^{-1}S$ (the
      outputs $u - yM^\\top$ and the feedthrough $D + M$, $M = Q^{-1}S$, for a rate whose
      centre's term $-S^\\top Q^{-1}S$ exceeds 64 times its room along some direction; an
      exact change of
      variables, [concepts](concepts.md#narrow-cones-far-from-zero)). False trains every
      signal in the one scale $s$, as the paper's reproduction does (its step sizes were
      chosen that way).
    - `progress`: report long training on standard error (default True): nothing during
      the first 10 s, then a line at most every 10 s with the step, the runs still
      training and the lowest loss so far (from inside the compiled loop, through
      `jax.debug.callback`), and before the loop's first step and after its last (compiling,
      the float64 check) a line that says which; False for silence.

    **Initialisation.** The paper draws "each matrix element from a normal distribution"
    and projects the draw (paper §4.1); `init_scale=1.0` is that N(0, 1), which the
    reproduction passes. The default is 0.3 (`ADAM_INIT_SCALE`), measured on the zoo's
    tuning half: with Adam, runs from N(0, 1) draws ended up to 9x above those from
    N(0, 0.3²); a wide draw of a high-order controller is violently unstable over the
    windows and its projection lands on the boundary of the set. Scales that shrink with
    the order $\\hat n$ and the window length $h$ ($\\min(1, 1/\\sqrt{\\hat n})$ and
    $\\min(1, 1/\\sqrt{\\hat n(h-1)})$) did worse than the constant (worst regret 9.8 and
    3.7). Much smaller scales start every run near the zero controller, which is already
    dissipative, so the constraint would rarely bind.

    **Tight gain bounds.** `converged` means only that the stop rule fired, not that the
    constrained minimum was found. On a rate with $|Q| \\gg R$ (a controller gain bound
    $\\gamma = \\sqrt{R/|Q|}$ far below the outputs' size, e.g. `stabilising_qsr` of a
    plant with a large $H_\\infty$ gain) the steepest direction is the feedthrough: the
    steps can set $|D| = \\gamma$, which uses up the whole bound, and the projection then
    keeps $C \\approx 0$, a stationary point of the projected steps. Where the plant's gain
    is large because its outputs are large against its states, the states' balancing
    (`balance`, above) removes this: on three such plants PGD stalled at 0.50-0.96 of the
    zero controller's loss with `balance=False` and matched `fit_direct` (0.001-0.014)
    with it. Where the gain comes from a resonance (states and outputs of one size), PGD
    still ended at 2.7 times `fit_direct`'s loss and 130 times `fit_ico`'s
    (`benchmarks/bench_tight_gain.py`): compare trainers on such rates.

    **Returns:** a [`FitResult`][dissil_jax.FitResult]; every controller carries a `P`
    that passes the exact float64 KYP check (`certified`).

    ```python
    res = dj.fit_pgd(key, windows, dj.QSR.passive(2))                 # projected Adam
    res = dj.fit_pgd(key, windows, dj.QSR.passive(2), learning_rate=1.0, decay=0.99,
                     init_scale=1.0)                                  # the paper's rule
    ```
    """
    if qsr is None:
        raise ValueError("`qsr` is required for PGD; use `dj.fit_gd` for the unconstrained run.")
    return _fit(key, windows, qsr, optimizer=default_rule(optimizer, learning_rate, decay),
                learning_rate=learning_rate, decay=decay, init_scale=init_scale,
                num_inits=num_inits, n_state=n_state, max_steps=max_steps, atol=atol,
                rtol=rtol, eps=eps, throw=throw, method=method, keep=keep, balance=balance,
                progress=progress)
