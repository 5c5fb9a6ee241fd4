"""Training certified REN controllers through their direct parameterisation (`_ren/map.py`).

Training is the driver loop of every gradient trainer (`_iterate.py`) with the LTI direct
map's method (`direct.MapDescent`) given the REN map's loss.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import _outcome
from .._data import Windows
from .._direct_map import MARGIN, MapRate, check_margin, solved_rate
from .._progress import CHECKING, phase, reporting
from .._ren.activation import check_activation
from .._ren.certify import certified_batch, certify_ren
from .._ren.controller import block_diag2, ren_imitation_loss, ren_odd_loss
from .._ren.map import init_ren_params, ren_map, ren_rate
from .._sdp.indefinite import is_indefinite
from .._supply import QSR
from .._validate import check_flag, check_int, check_key
from ._checks import check_eager, check_fit_args, check_keep, check_n_state
from ._iterate import iterate
from ._scale import loss_scale, scaled
from ._units import balance as balanced, balancing_units, unbalance
from .direct import MAX_STEPS, RTOL_DIRECT, MapDescent, default_hyperparameters, map_loss
from .ren_init import (
    INIT_MARGINS,
    WARM_LEARNING_RATE,
    init_controllers_order,
    initial_params,
)
from .result import FitResult, raise_if_failed, warn_if_untrained

_CONVERGED, _NOT_CERTIFIED, _NON_FINITE = (
    _outcome.code(r) for r in ("converged", "not_certified", "non_finite"))


class RENFitResult(FitResult):
    """A [`FitResult`][dissil_jax.FitResult] of [`fit_ren`][dissil_jax.fit_ren]:
    `controllers` is a batched [`RENController`][dissil_jax.RENController], `P` the storages
    and `multiplier` (`[num_inits, q]`) the diagonals of the sector multipliers $\\Lambda$;
    `certified` is the float64 check of each `(controller, P, multiplier)`; `margin` is the
    REN map's margin $\\varepsilon$ the runs trained with (`fit_ren`'s `margin`)."""

    multiplier: jax.Array | None = None
    margin: float | None = eqx.field(static=True, default=None)


def to_user_units(K, lam, s):
    """The controller trained on windows divided by $s$, in the user's units.

    With $x = s\\,x_s$, $\\hat u = s\\,\\hat u_s$, $\\hat y = s\\,\\hat y_s$ and the neurons
    kept in normalised units ($v$, $w$ unchanged), the REN is the same map with
    $C_1/s$, $D_{12}/s$, $sB_1$, $sD_{21}$ (other matrices unchanged) for any activation.
    Its certificate is $(P, s^2\\Lambda)$: the dissipation inequality in normalised units
    times $s^2$.
    """
    return eqx.tree_at(lambda k: (k.B1, k.C1, k.D12, k.D21), K,
                       (K.B1 * s, K.C1 / s, K.D12 / s, K.D21 * s)), lam * s**2


def _run(key, windows, rate: MapRate, k, learning_rate, init_scale, *, width, activation,
         optimizer, num_inits, n_state, max_steps, atol, rtol, margin, direct_input,
         odd=False, keep="best", progress=None, theta0=None):
    # Train in normalised units (`_scale.py`), as the LTI trainers do; the neurons stay in
    # those units, so the result is mapped back exactly for any activation (`to_user_units`).
    # `rate, k = solved_rate(qsr, margin, dtype, ren_rate)`: a rate far from unit size is
    # solved divided by k, (P, lam) multiplied back; traced, so one compilation per shape.
    s2 = loss_scale(windows)
    data = scaled(windows, s2)
    if theta0 is None:  # else the parameters of `init` (`ren_init.py`)
        theta0 = init_ren_params(key, num_inits, n_state, width, windows.n_in,
                                 windows.n_out, init_scale, windows.y.dtype)
    opt = optax.adam(learning_rate) if optimizer is None else optimizer
    # The driver loop of every gradient trainer, with the LTI direct map's method and the
    # REN map's loss in place of the LTI one.
    ren = lambda theta: ren_map(theta, rate, width, activation, margin, direct_input)
    loss_fn = ren_odd_loss if odd else ren_imitation_loss
    (_, _, (K, P, lam), _), hist, loss, steps, reason, kept = iterate(
        MapDescent(theta0, data, opt, map_loss(ren, loss_fn)),
        max_steps=max_steps, atol=atol / s2, rtol=rtol, keep=keep,
        progress=None if progress is None else (progress, s2))
    K, lam = to_user_units(K, lam, s2**0.5)
    if odd:  # the trained REN is the odd part of K (`RENController.odd_part`)
        K, P, lam = K.odd_part(), 0.5 * block_diag2(P), 0.5 * jnp.concatenate([lam, lam], -1)
    return RENFitResult(
        controllers=K, P=P * k, certified=None, loss_history=hist * s2, final_loss=loss * s2,
        converged=reason == _CONVERGED, steps=steps,
        wall_time=jnp.asarray(jnp.nan, hist.dtype), result=_outcome.item(reason),
        projected=None, multiplier=lam * k, kept_step=kept, margin=margin)


_run_jit = eqx.filter_jit(_run)


def _certify_all(res: RENFitResult, qsr: QSR) -> RENFitResult:
    """The float64 end check of every `(K, P, Λ)`; a failing pair gets a fresh certificate
    from the SDP of [`certify_ren`][dissil_jax.certify_ren], or is marked `not_certified`.

    The SDP's pair is rounded to the result's dtype (float32 unless x64 is enabled) and
    checked again as rounded, so the pair returned is the pair proved."""
    assert res.P is not None  # the REN map returns a storage with every controller
    dtype = res.P.dtype
    K, P, lam = res.controllers, np.array(res.P, np.float64), np.array(res.multiplier,
                                                                          np.float64)
    # a run that never had a finite iterate (e.g. a draw the map sends to NaN in float32)
    # has nothing to certify; the others are checked together
    num = P.shape[0]
    finite = np.all([np.isfinite(np.asarray(a, np.float64).reshape(num, -1)).all(1)
                     for a in (P, lam, *jax.tree.leaves(K))], axis=0)
    ok = np.zeros(num, bool)
    idx = np.nonzero(finite)[0]
    if len(idx):
        ok[idx] = certified_batch(jax.tree.map(lambda a: a[idx], K), qsr, P[idx], lam[idx])
    reason = np.asarray(_outcome.codes(res.result)).copy()
    as_returned = lambda a: np.asarray(np.asarray(a, dtype), np.float64)
    for i in np.nonzero(~ok)[0]:
        if not finite[i]:
            reason[i] = _NON_FINITE
            continue
        K_i = jax.tree.map(lambda a: a[i], K)
        cert = certify_ren(K_i, qsr)
        if cert.holds:
            P_i, lam_i = as_returned(cert.P), as_returned(cert.multiplier)
            ok[i] = bool(certified_batch(jax.tree.map(lambda a: a[None], K_i), qsr, P_i[None],
                                         lam_i[None])[0])
            if ok[i]:
                P[i], lam[i] = P_i, lam_i
        if not ok[i]:
            reason[i] = _NOT_CERTIFIED
    return eqx.tree_at(lambda r: (r.P, r.multiplier, r.certified, r.result), res,
                       (jnp.asarray(P, dtype), jnp.asarray(lam, dtype), jnp.asarray(ok),
                        _outcome.item(reason)), is_leaf=lambda x: x is None)


def _uncertified_message(res: RENFitResult, num_inits: int) -> str:
    """`fit_ren`'s error for runs that failed the end check, naming ill-conditioned storages."""
    bad = ~np.asarray(res.certified)
    P = np.asarray(res.P, np.float64)[bad]
    finite = np.isfinite(P.reshape(len(P), -1)).all(1)
    cond = float(np.max(np.linalg.cond(P[finite]))) if finite.any() else 0.0
    msg = (f"{int(bad.sum())} of {num_inits} REN controllers failed the float64 certificate "
           "check and its SDP fallback")
    non_finite = sum(r == "non_finite" for r, b in zip(res.result_names(), bad) if b)
    if non_finite:  # as `_certify_all` flagged them
        msg += (f" ({non_finite} of them never had a finite iterate: pass a "
                "smaller `init_scale` or `learning_rate`, or train in float64)")
    msg += "; pass `throw=False` to inspect them (`certified`, `result`)"
    if cond > _ILL_CONDITIONED:
        single = np.asarray(res.final_loss).dtype == np.float32
        return msg + (
            f". Their storages P reached condition number {cond:.1e}, beyond what float64 "
            "can verify. " + (
                "The runs trained in float32, whose round-off near the edge of the set can "
                "leave storages this ill-conditioned: in float64 "
                "(`jax.config.update(\"jax_enable_x64\", True)` before the data are made) "
                "they may pass. " if single else "") +
            "This happens with supply rates whose Q is far larger than R (tight "
            "gain bounds), where training can buy imitation with storage; the conditioning "
            "varies along training, so another `max_steps` (more or fewer) may pass. Or try "
            "`dj.fit_direct` (LTI controllers, whose map kept such storages verifiable in our "
            "tests) or a looser rate.")
    return msg + ", or raise `margin`."


# Storages beyond this condition number are named when the end check fails: the REN check's
# margin in P's small directions is then below its round-off in the large ones (measured
# before the map's input units: gain bounds of 1e-4 to 1e-6 failed at condition numbers 1e9
# to 1e13; with them, |Q|/R ~ 1e6 at 1e11).
_ILL_CONDITIONED = 1e8


#: The cap on `fit_ren`'s default Adam step and initial scale (`default_ren_hyperparameters`).
DEFAULT_CAP = 0.1


def default_ren_hyperparameters(n_state: int, n_in: int) -> tuple[float, float]:
    """`(learning_rate, init_scale)` of `fit_ren`: `fit_direct`'s rule at the controller's
    order $\\hat n$, each capped at 0.1 (`DEFAULT_CAP`), i.e. $(0.1, 0.1)$ up to
    $\\hat n + p = 27$, and the rule's smaller values beyond, where it shrinks the step with
    the order.

    Chosen on the problem zoo's tuning half by the smallest worst-case ratio of the median
    final loss to the best candidate's (`benchmarks/bench_ren.py --defaults tuning`): $(0.1, 0.1)$
    1.19, the uncapped rule at order $\\hat n$ 1.29 (its $(0.3, 0.5)$ on every zoo problem),
    at order $\\hat n + q$ 1.39, other fixed points 1.39-287. On the held-out half: 1.25,
    1.98 and 2.31."""
    lr, scale = default_hyperparameters(n_state, n_in)
    return min(lr, DEFAULT_CAP), min(scale, DEFAULT_CAP)


def fit_ren(
    key, windows: Windows, qsr: QSR, *, width: int = 16, activation="tanh",
    optimizer=None, learning_rate: float | None = None, init_scale: float | None = None,
    num_inits: int = 8, n_state: int | None = None, max_steps: int = MAX_STEPS,
    atol: float = 0.0, rtol: float = RTOL_DIRECT, margin: float | None = None,
    direct_input: bool = False, odd: bool = False, init=None, throw: bool = True,
    keep: str = "best", balance: bool = True, progress: bool = True,
) -> RENFitResult:
    """Learn $(Q,S,R)$-dissipative REN controllers (nonlinear, dynamic) from demonstrations.

    Every controller is the image of free parameters under the REN direct map
    ([REN controllers](ren.md)), whose values satisfy the REN certificate
    $M(P,\\Lambda)\\preceq-\\varepsilon\\operatorname{diag}(P, 2\\Lambda, \\tfrac12\\Phi_0)$
    for every supply rate with $Q\\preceq0$ (passivity included; no step inverts $Q$).
    Training is unconstrained gradient descent on the imitation loss
    ([`ren_imitation_loss`][dissil_jax.ren_imitation_loss]) in one compiled
    `lax.while_loop`, vmapped over `num_inits` initialisations; it stops after `max_steps`
    or when $|J_k - J_{k-1}| <$ `atol` $+$ `rtol`$\\,|J_0|$ (defaults 600, 0 and 1e-8,
    [`fit_direct`][dissil_jax.fit_direct]'s: on the problem zoo's tuning half 150 steps at
    1e-6 left the median loss up to 58x higher, and on its held-out half up to 1.8x, for
    at most 2.2 s of training at width 4, `benchmarks/bench_ren.py --zoo tuning`); the driver
    loop of every gradient trainer, with the REN map in place of the LTI one.

    **Certified at the end:** each returned `(K, P, multiplier)` is checked in float64 by
    eigenvalues ([`certify_ren`][dissil_jax.certify_ren] with the pair given); a pair that
    fails gets the SDP's certificate instead, and a controller with neither is marked
    `not_certified` (`throw=True` then raises). Tight gain bounds with windows that start
    at a state let the runs buy imitation with storage, and $P$'s condition number can pass
    what float64 verifies; the error then names it. A small $R$ does not (the
    map takes its input matrix in units of $\\sqrt{\\Phi_0}$: gain bounds down to
    $10^{-6}$ train storages of condition at most $3\\cdot10^3$), but a large $Q$ still can for a while:
    on 4×3 plants with $|Q|/R\\approx10^6$, 1-2 runs in 8 failed after 600 steps and none
    after 2,000 ([REN controllers](ren.md)).

    **Arguments:**

    - `key`, `windows`, `qsr` ($Q\\preceq0$), `num_inits`, `n_state`, `max_steps`, `atol`, `rtol`,
      `optimizer`, `learning_rate`, `init_scale`, `throw`, `keep`, `balance`,
      `progress`: as in
      [`fit_direct`][dissil_jax.fit_direct] (`learning_rate` is Adam's step on the REN
      map's free parameters); the defaults are `fit_direct`'s rule at the controller's
      order $\\hat n$ capped at 0.1, i.e. $(0.1, 0.1)$ up to $\\hat n + p = 27$
      (`default_ren_hyperparameters`: the smallest worst-case regret on the problem zoo's
      tuning half, `benchmarks/bench_ren.py --defaults tuning`).
    - `width` $q\\ge0$: the number of neurons (0 gives an LTI controller, as a REN).
    - `init`: start the runs at given controllers instead of random draws: an
      `LTIController` or a `RENController` (of width `width`), one or `num_inits` of them,
      or a `FitResult` (e.g. `init=dj.fit_direct(...)`, whose controllers then are the
      starts, or a `fit_ren` result to train further). Each start is carried into the
      runs' units and mapped back through the REN map (an SDP per start: the map's
      parameters are exact, [REN controllers](ren.md#starting-from-a-controller)), so the
      first loss is the start's and, with `keep="best"`, no run ends worse than its start.
      Each start is checked against the map's value; one the SDP reaches only
      approximately (ill-conditioned rates such as gain bounds of 1e-5) is tried at
      smaller margins, then used with a warning naming the deviation.
      An LTI start becomes a REN whose neurons see the state ($C_1$ drawn with
      `init_scale`) but do not yet act ($D_{21} = 0$); a REN start must have the runs'
      `activation`. The default step is then
      `WARM_LEARNING_RATE` (0.003, chosen on the problem zoo's tuning half). Not with a
      REN and `odd=True`. With windows that start at rest, `n_state` defaults to
      the starts' order.
    - `margin`: the REN map's margin $\\varepsilon$ (default `MARGIN` = 0.01). With `init`
      and no `margin`, the first of 0.01, 0.001 and 0.0001 at which the map reaches every
      start (a start outside its reach is a `ValueError` naming `init`); the margin used is
      `RENFitResult.margin`.
    - `direct_input`: train the neurons' direct input $D_{12}$ (static; default False,
      $D_{12} = 0$: the network then sees the plant output through the state only).
    - `odd`: learn an odd controller (static; default False): the returned REN is
      [`K.odd_part()`][dissil_jax.RENController.odd_part] of a trained $K$, of order
      $2\\hat n$ and width $2q$, and is trained as such. Start it at
      $(\\hat x_0, -\\hat x_0)$ (`jnp.concatenate([x0, -x0], -1)`) where the windows start at
      $\\hat x_0$. Use it when the expert is odd, $u(-x) = -u(x)$, as it is whenever the
      plant is odd and the cost even: the demonstrations then teach both signs, which
      matters when they show large states of one sign only. On the nonlinear example's
      sliding windows (N = 25, seeds 1 and 2, 20 initialisations) it tested 1.02x and
      0.094x the median error of the REN without it ([REN controllers](ren.md)); on the
      linear example's tuning plants, at that example's settings, it tested 2.9x worse,
      so measure it on your problem (both measured with ReLU). With an odd activation
      such as `"tanh"` (the default) the REN, which has no biases, is odd already:
      `odd=True` then returns the same map at twice the order and width. It is for ReLU
      and other activations that are not odd. The certificate is
      $(\\tfrac12\\operatorname{diag}(P, P), \\tfrac12\\operatorname{diag}(\\Lambda,
      \\Lambda))$, checked like any other.
    - `activation`: `"tanh"` (default: on the problem zoo's tuning half, at the default step,
      its held-out error was at most 4.95x ReLU's, ReLU's up to 5.6x tanh's; on the
      held-out half 23x against 3.2x, tanh overfitting 5 noisy windows, so measure both on
      your problem), `"relu"` (positively homogeneous,
      so it extrapolates in scale: the experiments' choice on the nonlinear example, whose
      test states are 3x the training states) or a slope-restricted callable (see
      [`RENController`][dissil_jax.RENController]). Training runs on the windows divided
      by one data scale $s$ (as in the LTI trainers), so the neurons work in units where
      the data are of order one (where tanh bends); the returned controller is the same
      map in the user's units ($C_1/s$, $D_{12}/s$, $sB_1$, $sD_{21}$, multiplier
      $s^2\\Lambda$). With `balance` the outputs' units are balanced first, as in
      `fit_direct`: then $C_2$, $D_{21}$ and $D_{22}$ come back multiplied by the power
      of two $c$, with the same $P$ and $\\Lambda$; a narrow cone far from zero is
      trained about its centre, $D_{22} + Q^{-1}S$ (as in `fit_pgd`).

    **Returns:** a [`RENFitResult`][dissil_jax.RENFitResult].
    """
    if qsr is None:
        raise ValueError("`qsr` is required: `fit_ren` learns certified controllers.")
    # screened again on every call: a callable that passed once may have been changed since
    activation = check_activation(activation, rescreen=True)
    width = check_int("width", width, minimum=0)
    if optimizer is not None and learning_rate is not None:
        raise ValueError("pass either `optimizer` or `learning_rate` (Adam's step), not both.")
    if optimizer is not None and not isinstance(optimizer, optax.GradientTransformation):
        raise ValueError(f"`optimizer` must be an `optax.GradientTransformation`, got "
                         f"{type(optimizer).__name__}.")
    given = dict(learning_rate=learning_rate, init_scale=init_scale)
    check_key(key)
    check_eager("fit_ren", key, windows, throw, learning_rate=learning_rate,
                init_scale=init_scale, atol=atol, rtol=rtol, margin=margin)
    check_fit_args(windows, qsr, num_inits, max_steps, atol=atol, rtol=rtol,
                   **{k: v for k, v in given.items() if v is not None})
    if is_indefinite(qsr):
        raise ValueError("`qsr.Q` has a positive eigenvalue: the REN map covers Q negative "
                         "semidefinite only. Pass a supply rate with Q <= 0, or train an LTI "
                         "controller with `dj.fit_pgd` / `dj.fit_ico`.")
    if n_state is None and init is not None and windows.x0 is None:
        n_state = init_controllers_order(init)
    n_state = check_n_state(windows, n_state)
    # the margin: the given one, or by default `MARGIN`, and for `init` the first of
    # `INIT_MARGINS` that reaches every start (`ren_init.py`)
    margins = (check_margin(margin),) if margin is not None else (
        INIT_MARGINS if init is not None else (MARGIN,))
    margin = margins[0]
    direct_input = check_flag("direct_input", direct_input)
    odd = check_flag("odd", odd)
    lr0, scale0 = default_ren_hyperparameters(n_state, windows.n_in)
    lr0 = lr0 if init is None else WARM_LEARNING_RATE
    learning_rate = lr0 if learning_rate is None else learning_rate
    init_scale = scale0 if init_scale is None else init_scale
    start = time.perf_counter()
    dtype = windows.y.dtype
    units = balancing_units(windows, balance, qsr)  # outputs' and states' units (`_units.py`)
    user_qsr, (windows, qsr) = qsr, balanced(windows, qsr, units)
    c = units.c
    theta0 = None
    if init is not None:
        theta0, margin = initial_params(
            init, key, qsr, units, loss_scale(windows), num_inits=int(num_inits),
            n_state=n_state, width=int(width), n_in=windows.n_in, n_out=windows.n_out,
            init_scale=float(init_scale), margins=margins, direct_input=bool(direct_input),
            odd=bool(odd), activation=activation, dtype=dtype,
            progress=check_flag("progress", progress))
    with reporting("fit_ren", max_steps, check_flag("progress", progress), c**2) as token:
        res = _run_jit(key, windows, *solved_rate(qsr, margin, dtype, ren_rate),
                       jnp.asarray(learning_rate, dtype),
                       jnp.asarray(init_scale, dtype), width=int(width), activation=activation,
                       optimizer=optimizer, num_inits=int(num_inits), n_state=n_state,
                       max_steps=int(max_steps), atol=jnp.asarray(atol / c**2, dtype),
                       rtol=jnp.asarray(rtol, dtype), margin=margin,
                       direct_input=bool(direct_input), odd=bool(odd), keep=check_keep(keep),
                       progress=token, theta0=theta0)
        jax.block_until_ready(res)
        phase(token, CHECKING)
        res = _certify_all(res, qsr)
    res = eqx.tree_at(lambda r: r.wall_time, res, jnp.asarray(time.perf_counter() - start,
                                                              dtype))
    warn_if_untrained(res, given_start=init is not None)
    if throw and not bool(np.all(res.certified)):
        raise ValueError(_uncertified_message(res, num_inits))
    return unbalance(raise_if_failed(res) if throw else res, units, user_qsr, throw)
