"""Argument checks shared by the trainers (ValueErrors that name the argument)."""

from __future__ import annotations

from typing import TypeVar, cast

import jax
import jax.core
import jax.numpy as jnp
import numpy as np
import optax

from .._data import Windows
from .._sdp.indefinite import check_feasible
from .._supply import QSR
from .._validate import check_flag, check_int, real_scalar, warn_user

_T = TypeVar("_T")


def check_fit_args(windows, qsr, num_inits, max_steps, **nonnegative) -> None:
    """Validate the common trainer arguments; `nonnegative` are named hyperparameters.

    Traced hyperparameters (a vmapped sweep) are skipped: their values are not known here.
    """
    if not isinstance(windows, Windows):
        raise ValueError(f"`windows` must be a `dj.Windows`, got {type(windows).__name__}.")
    if qsr is not None:
        if not isinstance(qsr, QSR):
            raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
        qsr.check_sizes(windows.n_in, windows.n_out)
        # a rate admitting no strictly dissipative controller (no static D even) is refused
        # here, not after the first SDP
        check_feasible(qsr)
    check_magnitude(windows)
    check_int("num_inits", num_inits)
    check_int("max_steps", max_steps, minimum=0)
    for name, v in nonnegative.items():
        # one value per run, also in a vmapped sweep (where each lane's is a scalar)
        if jnp.ndim(v) != 0:
            raise ValueError(f"`{name}` must be a scalar, got shape {jnp.shape(v)} (a sweep "
                             "over it vmaps the call: `jax.vmap` or `dj.sweep` over a 1-d "
                             "array).")
        if isinstance(v, jax.core.Tracer):
            continue
        x = real_scalar(v)  # NaN for a string, None, a complex number, ...
        if not (np.isfinite(x) and x >= 0):
            raise ValueError(f"`{name}` must be a finite non-negative number, got {v!r}.")
        if name == "learning_rate" and x == 0 and max_steps > 0:
            warn_user("`learning_rate` = 0 takes no step: every run returns its initial "
                      "controller.")
        if name == "init_scale" and x == 0 and num_inits > 1:
            warn_user(f"`init_scale` = 0 draws {num_inits} identical initialisations, which "
                      "train to the same controller: pass `num_inits=1`, or a positive "
                      "`init_scale` for distinct runs.")


def nan_unless(value: _T, ok) -> _T:
    """`value`, or NaN where a traced value fails `ok` (a lane of a vmapped sweep, whose value
    the eager checks cannot see): that lane's run then ends as `non_finite` instead of
    training with, say, a negative step (uphill)."""
    if isinstance(value, jax.core.Tracer):
        return cast(_T, jnp.where(ok(value), value, jnp.nan))
    return value


def finite_lanes(K) -> jax.Array:
    """Per controller of a batch: are all its entries finite?"""
    return jax.vmap(lambda K: jnp.all(jnp.stack(
        [jnp.all(jnp.isfinite(M)) for M in jax.tree.leaves(K)])))(K)


def check_finite_draw(K0, init_scale) -> None:
    """A ValueError naming `init_scale` when an initial draw overflows (host trainers)."""
    if not bool(np.all(np.asarray(finite_lanes(K0)))):
        raise ValueError(f"`init_scale` = {init_scale!r} draws controllers whose entries "
                         "overflow; pass a smaller one.")


def check_eager(fn: str, key, windows, throw, alternative: str = "", **hyper) -> None:
    """Refuse a traced `key`, traced windows or a traced hyperparameter among `hyper` (`fn`
    under `jax.jit` or `jax.vmap`) and a `throw` that is not a bool, naming them: the
    certified trainers check every controller in float64 on the host, which a trace cannot
    do."""
    check_flag("throw", throw)
    data = {"key": key}
    if isinstance(windows, Windows):
        data["windows"] = (windows.y, windows.u, windows.x0)
    traced = [name for name, v in {**data, **hyper}.items()
              if any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves(v))]
    if traced:
        names = " and ".join(f"`{n}`" for n in traced)
        raise ValueError(
            f"`{fn}` cannot run under `jax.jit` or `jax.vmap` (nor `jax.grad`: its {names} "
            f"{'is' if len(traced) == 1 else 'are'} traced): it solves convex programs or "
            "checks certificates in float64 on the host. It trains `num_inits` "
            "initialisations together already"
            + (f"; for sweeps inside JAX use `{alternative}`, which is traceable."
               if alternative else "; call it once per value for more."))


def check_magnitude(windows: Windows) -> None:
    """Refuse windows whose squares leave the data's floating-point range, naming `windows`.

    The loss sums squares of the data, so with entries above $\\sqrt{\\text{max}/n}$ ($n$
    the number of summed entries) it overflows, and with every entry below
    $\\sqrt{\\text{tiny}}$ (about $10^{-19}$ in float32) each square underflows: the loss
    is then NaN or 0 and no step can be taken. Traced windows are skipped.
    """
    arrays = [a for a in (windows.x0, windows.y, windows.u) if a is not None]
    if any(isinstance(a, jax.core.Tracer) for a in arrays):
        return
    info = np.finfo(np.asarray(windows.y).dtype)
    size = max(np.size(a) for a in arrays)
    top = max(float(np.max(np.abs(a), initial=0.0)) for a in arrays)
    high, low = float(np.sqrt(info.max / max(size, 1))), float(np.sqrt(info.tiny))
    hint = ("pass the data in float64, or in units where they are of order one (a common "
            "change of units does not change what the trainers learn)")
    if top > high:
        raise ValueError(f"`windows` has entries up to {top:.3g}, whose squares overflow "
                         f"{info.dtype} when summed (limit {high:.3g}): {hint}.")
    if 0.0 < top < low:
        raise ValueError(f"`windows` has no entry above {top:.3g}, whose squares underflow "
                         f"{info.dtype} (limit {low:.3g}): {hint}.")


def check_keep(keep) -> str:
    """The trainers' `keep`: which iterate of each run they return."""
    if keep not in ("best", "last"):
        raise ValueError(f"`keep` must be 'best' (the iterate of lowest loss) or 'last' (the "
                         f"final iterate, as in the paper's Algorithm 2), got {keep!r}.")
    return keep


def check_optimizer(optimizer, rule: str, **step_args) -> bool:
    """True when an `optimizer` is given; then none of `step_args` (the default rule's
    hyperparameters, named after `rule`) may be set, and it must be an optax transformation."""
    if optimizer is None:
        return False
    given = [f"`{k}`" for k, v in step_args.items() if v is not None]
    if given:
        raise ValueError(f"pass either `optimizer` or {'/'.join(given)} ({rule}), not both.")
    if not isinstance(optimizer, optax.GradientTransformation):
        raise ValueError(f"`optimizer` must be an `optax.GradientTransformation`, got "
                         f"{type(optimizer).__name__}.")
    return True


def check_n_state(windows: Windows, n_state, warn: bool = True) -> int:
    """The controller order $\\hat n$ a trainer should use for `windows`.

    With recorded plant states (`windows.x0` `[N, n]`) every window starts the controller at
    $\\hat x_0 = x_0$, so its order is fixed by the data: $\\hat n = n$, and `n_state` may be
    omitted (None) or must equal `windows.n_state`. With `windows.x0` None (input-output logs
    only) the controller starts at rest, $\\hat x_0 = 0$, and any order $\\hat n\\ge1$ fits the
    data, so `n_state` is required.

    **Arguments:** the `windows` and the requested `n_state`: None, or a positive integer
    checked like `num_inits` and `max_steps` (`check_int`: an integral float such as `2.0`
    is taken as `2`; `2.5`, `True` and arrays are refused, never truncated).

    **Returns:** $\\hat n$ (an int). Raises a ValueError naming `n_state` when it is missing
    for windows that start at rest, is not a positive integer, or disagrees with
    `windows.n_state`. Warns (unless `warn` is False) when windows from rest are shorter
    than `rest_horizon`: they then leave part of the controller unfitted.
    """
    if n_state is None:
        if windows.n_state is None:  # the windows start at rest (`x0` None)
            raise ValueError(
                "`n_state` is required when `windows.x0` is None: the controller starts at "
                "rest (x̂0 = 0), so the data do not fix its order; pass e.g. `n_state=2`."
            )
        return windows.n_state
    if not isinstance(n_state, bool) and np.ndim(n_state) == 0 and n_state == 0:
        raise ValueError(
            "`n_state` must be a positive integer, got 0: the trainers fit dynamic "
            "controllers, whose certificate has a storage P of order n_state. A static gain "
            "ŷ = Dû is checked by `dj.certify` (order 0: the test is then "
            "R + S'D + D'S + D'QD > 0, no storage)."
        )
    n_state = check_int("n_state", n_state)
    if windows.x0 is not None and n_state != windows.n_state:
        raise ValueError(
            f"`n_state` = {n_state} but `windows.x0` has width {windows.n_state}: the controller "
            "starts at the recorded plant state x0, so its order is x0's width. Omit "
            "`n_state`, or build the windows with `dj.Windows(None, y, u)` to start a "
            "controller of any order at rest."
        )
    if warn and windows.x0 is None:
        _warn_short_from_rest(windows, n_state)
    return n_state


def rest_horizon(n_state: int, n_in: int, n_out: int) -> int:
    """The shortest horizon $h$ at which windows from rest determine a generic
    order-$\\hat n$ controller with `n_in` inputs and `n_out` outputs:
    $\\lceil\\hat n/m\\rceil + \\lceil\\hat n/p\\rceil + 1$ (`dj.Windows`, "Window length
    from rest")."""
    return -(-n_state // n_out) + -(-n_state // n_in) + 1


def _warn_short_from_rest(windows: Windows, n_state: int) -> None:
    h, need = windows.horizon, rest_horizon(n_state, windows.n_in, windows.n_out)
    if h < need:
        warn_user(
            f"`windows` start at rest (x0 None) with horizon h = {h}: they show an order-"
            f"{n_state} controller's D and only its first {h - 1} Markov parameters "
            f"(CB, CAB, ...), and a generic order-{n_state} controller needs h >= {need} to "
            "be determined by them. The rest of the trained controller is fitted by nothing "
            "but still acts in closed loop. Use longer windows or a smaller `n_state` "
            "(`dj.Windows`, \"Window length from rest\")."
        )
