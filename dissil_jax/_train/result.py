"""The result type shared by every trainer."""

from __future__ import annotations

import time
from typing import Any, TypeVar

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .. import _outcome, _progress as progress
from .._outcome import Outcome
from .._validate import warn_user


class FitResult(eqx.Module):
    """What every `dj.fit_*` returns; the leading axis of each field is the initialisation.

    - `controllers`: the learned controllers, batched (`LTIController` with `[num_inits]`
      leading axes, or an `MLPController` for `fit_mlp`).
    - `P`: `[num_inits, n, n]` storage matrices certifying each controller (None for
      unconstrained methods).
    - `certified`: `[num_inits]` bool, the exact float64 KYP check of (controller, `P`)
      (None for unconstrained methods).
    - `loss_history`: `[num_inits, max_steps + 1]`; column 0 is the initial controller's
      loss, column k the loss after step k, NaN after a controller stopped (so the
      compiled trainers cannot run with `jax_debug_nans` on, which stops at the first
      NaN: use `with jax.debug_nans(True):` around your own code only).
    - `final_loss`: `[num_inits]` loss of the returned controller. The certified trainers
      (`fit_pgd`, `fit_direct`, `fit_ico`, `fit_ren`) return each run's *best* iterate,
      the certified one of lowest loss, which is not always the last (a noisy or too long
      step can raise the loss); the unconstrained baselines (`fit_gd`, `fit_mlp`) return
      their last iterate, as the paper's baselines do.
    - `kept_step`: `[num_inits]` the step the returned controller came from (0: the
      initial controller; equal to `steps` when the last iterate was kept).
    - `converged`: `[num_inits]` True when the stopping rule fired (`result` is
      `converged`). The rule looks at one step's change of the loss, so this does not
      prove a stationary point: a run whose loss oscillates can stop at a quiet step.
    - `steps`: `[num_inits]` number of steps taken.
    - `wall_time`: total training wall time in seconds, compilation included, as a 0-d
      array of the data's dtype (a leaf like the others; `float(res.wall_time)` for a
      number; NaN inside a traced sweep).
    - `result`: `[num_inits]` [`Outcome`][dissil_jax.Outcome], how each run ended
      (decode with [`result_names`][dissil_jax.FitResult.result_names]): `converged`
      (the stopping rule of the trainer's `atol`/`rtol`), `max_steps`, `non_finite` (the loss
      became NaN or infinite; the constrained trainers keep their best certified iterate), `infeasible`, `solver_failed` or `not_certified` (a projection or an ICO SDP
      failed; the best certified iterate is kept), `loss_increased` (ICO's float64 guard
      refused a step), `stalled` (after accepted steps, ICO found no step that passes
      the float64 check, even shortened; its last certified iterate is kept, and
      `throw=True` does not raise for it). Compare with `res.result == dj.Outcome.converged`. (Called
      `stop_reason` before; that name remains a read-only alias.)
    - `projected`: `[num_inits]` bool or None. Only
      [`fit_direct`][dissil_jax.fit_direct] sets it: True where the direct map's controller
      failed the final float64 check and was replaced by its projection
      ([`project`][dissil_jax.project]); None for the other trainers.
    """

    controllers: Any  # LTIController or MLPController, batched
    P: Float[Array, "inits n n"] | None
    certified: Bool[Array, " inits"] | None
    loss_history: Float[Array, "inits steps"]
    final_loss: Float[Array, " inits"]
    converged: Bool[Array, " inits"]
    steps: Int[Array, " inits"]
    wall_time: Float[Array, ""]
    result: Outcome | None = None
    projected: Bool[Array, " inits"] | None = None
    kept_step: Int[Array, " inits"] | None = None

    @property
    def stop_reason(self) -> Outcome | None:
        """The former name of `result`."""
        return self.result

    @property
    def initial_loss(self) -> Float[Array, " inits"]:
        """`[num_inits]` the initial controllers' losses (column 0 of `loss_history`)."""
        return self.loss_history[..., 0]

    @property
    def percent_change_cost(self) -> Float[Array, " inits"]:
        """$100\\,(J_\\text{final} - J_\\text{initial}) / J_\\text{initial}$ (paper Tables 2-5)."""
        return 100.0 * (self.final_loss - self.initial_loss) / self.initial_loss

    @property
    def num_inits(self) -> int:
        """The number of initialisations (runs) in this result."""
        return self.final_loss.shape[-1]

    def best(self) -> Any:
        """The controller of lowest final loss among the runs that may be used.

        For the certified trainers (`certified` is not None) only certified runs count: a
        run whose every projection failed keeps its uncertified initial draw, flagged by
        `certified` and `result`, and is never returned here, however low its loss. For
        the unconstrained baselines every run with a finite loss counts.

        **Raises** a `ValueError` when no run qualifies (none certified, or every loss
        non-finite), and when the result has more than one batch axis (a sweep: index it
        first, e.g. `jax.tree.map(lambda a: a[k], res).best()`).
        """
        loss = np.asarray(self.final_loss, np.float64)
        if loss.ndim != 1:
            raise ValueError(f"`best()` needs one initialisation axis; this result has batch "
                             f"shape {loss.shape} (a sweep?): index it first.")
        ok = np.isfinite(loss)
        if self.certified is not None:
            ok &= np.asarray(self.certified, bool)
            if not ok.any():
                raise ValueError(f"`best()`: none of the {loss.size} runs is certified (and "
                                 f"finite); see `certified` and `result_names()`.")
        elif not ok.any():
            raise ValueError(f"`best()`: every one of the {loss.size} runs ended with a "
                             "non-finite loss; see `result_names()`.")
        i = int(np.argmin(np.where(ok, loss, np.inf)))
        return jax.tree.map(lambda x: x[i], self.controllers)

    def result_names(self) -> list:
        """`result` decoded into `Outcome` names (nested lists for sweeps)."""
        if self.result is None:
            raise ValueError("this FitResult has no `result` (`stop_reason`; built by hand?).")
        return list(_outcome.names(self.result))

    stop_reasons = result_names  # the former name


_Result = TypeVar("_Result", bound="FitResult")


def raise_if_failed(res: _Result, caller: str | None = None) -> _Result:
    """The trainers' `throw=True`: raise if a run ended other than `converged`/`max_steps`.

    Eagerly a `ValueError` that counts the reasons; under `jax.jit` a `JaxRuntimeError`
    (an `EquinoxRuntimeError` under `eqx.filter_jit`) with the message of the worst
    outcome.
    """
    codes = _outcome.codes(res.result)
    bad = ~_outcome.is_in(codes, _outcome.FINE)
    if isinstance(codes, jax.core.Tracer):
        return eqx.tree_at(lambda r: r.final_loss, res,
                           _outcome.worst(codes, bad).error_if(res.final_loss, jnp.any(bad)))
    bad = np.asarray(bad)
    if bad.any():
        names = np.asarray(_outcome.names(codes), dtype=object)[bad]
        counts = {n: int((names == n).sum()) for n in sorted(set(names))}
        # One explanation (and its fix) per kind of failure, and what the failed runs kept:
        # only the constrained trainers have certified iterates to fall back on.
        why = "; ".join(f"{n}: {_outcome.message(n, caller).rstrip('.')}" for n in counts)
        # The certified trainers (they have a storage P) keep each run's best iterate; the
        # unconstrained baselines return the iterate at which they stopped.
        kept = ("kept its best certified iterate (`kept_step`)" if res.P is not None
                else "returns the iterate at which it stopped")
        raise ValueError(
            f"{int(bad.sum())} of {bad.size} runs ended in failure {counts}. {why}. Each "
            f"failed run {kept}; pass `throw=False` to get the result and inspect "
            "`result`.")
    return res


def fit_timed(run, hyper, dtype, finish, throw: bool, token=None) -> FitResult:
    """The host side shared by the `fit_*` trainers: `run(*hyper)` (the compiled run, its
    hyperparameters cast to the data's `dtype`), then `finish` (the float64 check, which
    the progress reporter of `token` announces when it is long), the wall time, and
    `throw`."""
    start = time.perf_counter()
    res = jax.block_until_ready(run(*(jnp.asarray(v, dtype) for v in hyper)))
    if token is not None:
        progress.phase(token, progress.CHECKING)
    res = finish(res)
    # traced (`fit_gd` under a user's `jax.jit`): a time measured while tracing would be
    # frozen into the compiled function, so NaN as in every traced sweep
    traced = isinstance(res.final_loss, jax.core.Tracer)
    res = eqx.tree_at(lambda r: r.wall_time, res, jnp.asarray(
        jnp.nan if traced else time.perf_counter() - start, dtype))
    if not traced:
        warn_if_untrained(res)
    return raise_if_failed(res) if throw else res


def warn_if_untrained(res: FitResult, given_start: bool = False) -> None:
    """Warn when runs that took steps returned their initial controller (`kept_step` 0
    with `keep="best"`): no step lowered the loss, the mark of a step too large for the
    problem (a loss rising from 55 to 7e13 ended as `max_steps`, without a word)."""
    if res.kept_step is None:
        return
    kept, steps = np.asarray(res.kept_step), np.asarray(res.steps)
    hist = np.asarray(res.loss_history, np.float64)
    with np.errstate(invalid="ignore"):  # NaN after a run stopped
        rose = np.any(hist[:, 1:] > hist[:, :1], axis=1)  # not a zero step's flat loss
    untrained = (kept == 0) & (steps > 0) & rose & ~np.asarray(_outcome.failed(
        _outcome.codes(res.result)))
    if untrained.any():
        if given_start:  # `fit_ren(init=...)`: the start may be a minimum already
            warn_user(f"{int(untrained.sum())} of {untrained.size} runs returned their start "
                      "(`init`) unchanged: none of their steps lowered the loss below it. "
                      "The start may be a minimum already, or the step too large (the loss "
                      "rose from the first step on): try a smaller `learning_rate`.")
            return
        warn_user(f"{int(untrained.sum())} of {untrained.size} runs returned their initial "
                  "controller: none of their steps lowered the loss below it. The step is "
                  "probably too large for this problem (the loss rose from the first step "
                  "on): pass a smaller `learning_rate`, or check the `optimizer`'s.")
