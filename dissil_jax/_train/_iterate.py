"""The one driver loop of the gradient trainers (PGD, GD, the direct map, the MLP).

A trainer is a `Method`: an `eqx.Module` holding its data (windows, optimiser,
supply rate, ...) with three methods, and `iterate` runs it:

- `init() -> (pending_0, code_0)`: the initial iterate, not yet evaluated. Its leaves have
  the lanes' shape in front (the initialisations: `[num_inits]`, or `()` for a method
  vmapped by its caller, like the MLP); `code_0` an [`Outcome`][dissil_jax.Outcome] code
  per lane, or one for all (`_outcome.code`): `max_steps` for a lane that may start, a
  failure (e.g. a failed initial projection) for one that takes no step.
- `evaluate(pending) -> (state, J)`: an iterate evaluated: its loss `J` per lane and
  whatever the next step needs (the gradient). A method reports a non-finite gradient
  as a NaN `J`.
- `update(state, active) -> (pending, code)`: one step of every lane from an evaluated
  `state` (the optimiser's update, the projection), not yet evaluated. `active` (bool per
  lane) says which lanes are still running (a method may use it to skip work, e.g. the
  projection); `code` (per lane, or one for all) is `converged` where the step succeeded
  and the failure otherwise (a failed projection).
- `select(accept, new, old)` (optional): the next state from the lanes that accept the
  step; by default a per-lane `jnp.where` on every leaf (override it for state shared by
  all lanes, like the direct map's one optimiser state).
- `keep_non_finite` (class attribute): True for the unconstrained methods (GD, the MLP),
  which return their last iterate, the one whose loss became non-finite if it did (the
  paper's baselines); False for the constrained ones (PGD, the direct maps), which return
  their *best* iterate: the accepted one of lowest loss, every accepted iterate being
  finite and certified.

The driver (`terminate` included) does the bookkeeping once: the loss history (column 0
is $J_0$, column $k$ the loss after step $k$, NaN once a lane stopped), the number of
steps, the returned iterate (best or last, as above) with the step it came from, and the
stopping rule: a lane stops after step $k$ when

$$|J_k - J_{k-1}| < \\text{atol} + \\text{rtol}\\,|J_0|$$

or $J_k = 0$, an exact fit that no step can improve (`converged`; with all-zero data the
rule above never holds, since $J_0 = 0$), when a step fails or its loss is not finite (that code), or after
`max_steps` (`max_steps`). All lanes run in one `lax.while_loop` until every lane stopped;
stopped lanes are frozen. A new trainer (e.g. a nonlinear controller) is one more
`Method`.
"""

from __future__ import annotations

import abc
import functools
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import _outcome
from .._progress import report

#: The trainers' default stopping rule: `atol = 0` and these `rtol`, relative to the run's
#: initial loss, so that when a run stops does not depend on the data's units. Chosen on
#: the tuning half of `dissil_jax.experiments.zoo` (`benchmarks/bench_defaults.py`, table
#: `benchmarks/results/defaults_stop.md`): the largest `rtol` whose stopped loss is within
#: about 1 % of the full budget's on the median problem and within 10 % on the worst (PGD
#: and ICO at 1e-6; the MLP at 1e-9, `RTOL_MLP`). The direct map and GD take 1e-8
#: (`direct.RTOL_DIRECT`) against their larger budget of 600 steps.
RTOL = 1e-6
#: The MLP's Adam at 1e-3 descends slowly and noisily: on the nine tuning problems, at 1e-7
#: it stopped 1.04x above its 2,000-step budget's loss on the median problem and 7.1x on the
#: worst, at 1e-8 1.02x and 4.8x, at 1e-9 within 0.1 % and 2.1 %. So its budget, not the
#: rule, ends most of its runs.
RTOL_MLP = 1e-9

_CONVERGED, _MAX_STEPS, _NON_FINITE = (
    _outcome.code(r) for r in ("converged", "max_steps", "non_finite"))


def where(mask, new, old):
    """Per-lane select on pytrees whose leaves have the lanes' axes first."""
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b),
        new, old)


class Method(eqx.Module):
    """A trainer for `iterate`: `init`, `evaluate`, `update`, `select`, `keep_non_finite`
    (module doc)."""

    keep_non_finite: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self) -> tuple[Any, jax.Array]:
        """`(pending_0, code_0)`: the initial iterate, not yet evaluated."""

    @abc.abstractmethod
    def evaluate(self, pending) -> tuple[Any, jax.Array]:
        """`(state, J)`: the iterate `pending` evaluated (its loss, and what `update` needs)."""

    @abc.abstractmethod
    def update(self, state, active) -> tuple[Any, jax.Array]:
        """`(pending, code)`: one step of every lane from the evaluated `state`."""

    def select(self, accept, new, old):
        """The next state: `new` on the lanes that `accept` the step, `old` elsewhere."""
        return where(accept, new, old)


def terminate(loss, prev, loss0, ok, *, atol, rtol):
    """Per lane: the stopping rule $|J_k - J_{k-1}| <$ `atol` $+$ `rtol` $|J_0|$, an exact
    fit ($J_k = 0$, the least loss there is), or a failed step (`ok` False)."""
    return ~ok | (jnp.abs(loss - prev) < atol + rtol * jnp.abs(loss0)) | (loss == 0)


@eqx.filter_jit
def _evaluate(method, pending):
    return method.evaluate(pending)


def iterate(method: Method, *, max_steps: int, atol, rtol, keep: str = "best",
            progress=None):
    """Run `method` for at most `max_steps` steps per lane (module docstring).

    `keep="last"` returns the last accepted state of every method (the paper's Algorithm 2
    outputs its last iterate). `progress`: `(token, scale)`, a reporter's token
    (`_progress.reporting`) and the factor that brings the method's loss to the user's
    units, or None for a loop without host callbacks.

    The loop's body is `evaluate` (at iteration 0 the initial iterate), the bookkeeping,
    then `update`. So the loss and its gradient, usually the largest part of the compiled
    program, appear once in it rather than once for $J_0$ and once per step (30 % less
    compilation for the direct map, `benchmarks/bench_paper_sizes.py --compile`).

    **Returns:** `(state, loss_history, final_loss, steps, code, kept_step)`: the returned
    state (the best accepted one, or the last for `keep="last"` and `keep_non_finite`
    methods),
    `[*lanes, max_steps + 1]` losses, the loss of the returned iterate, the steps taken, the
    `Outcome` code of how each lane ended and the step the returned state came from (0: the
    initial iterate).
    """
    keep_best = keep == "best" and not method.keep_non_finite
    pending0, code0 = method.init()
    # Jitted so that its trace, made here for the carry's shapes, is reused (not redone)
    # inside the loop's body: one trace of the loss and its gradient, not two.
    evaluate = functools.partial(_evaluate, method)
    zeros = lambda s: jnp.zeros(s.shape, s.dtype)
    state_z, loss_z = jax.tree.map(zeros, jax.eval_shape(evaluate, pending0))
    lanes = loss_z.shape
    code0 = jnp.broadcast_to(jnp.asarray(code0, jnp.int32), lanes)  # a code, or one per lane
    int_z = jnp.zeros(lanes, jnp.int32)
    carry = dict(k=jnp.zeros((), jnp.int32), pending=pending0, step_code=code0, state=state_z,
                 loss=loss_z, loss0=loss_z, hist=jnp.full(lanes + (max_steps + 1,), jnp.nan,
                                                          loss_z.dtype),
                 done=jnp.zeros(lanes, bool), steps=int_z, code=code0, at=int_z)
    if keep_best:
        carry.update(best=state_z, best_loss=loss_z)

    def first(c, state, loss):
        # Iteration 0: the initial iterate; a lane whose `init` failed takes no step.
        finite = jnp.isfinite(loss)
        start = ~_outcome.failed(code0) & finite
        code = jnp.where(finite | _outcome.failed(code0), code0, _NON_FINITE)
        new = dict(c, state=state, loss=loss, loss0=loss, hist=c["hist"].at[..., 0].set(loss),
                   done=~start, code=jnp.where(start, _MAX_STEPS, code).astype(jnp.int32))
        if keep_best:
            new.update(best=state, best_loss=loss)
        return new

    def later(c, state, loss):
        # Iteration k >= 1: step k, made by the previous iteration's `update`.
        k, active, code = c["k"], ~c["done"], c["step_code"]
        failed = code != _CONVERGED
        finite = jnp.isfinite(loss)
        code = jnp.where(failed | finite, code, _NON_FINITE)
        accept = active & ~failed & (finite | method.keep_non_finite)
        state = method.select(accept, state, c["state"])
        loss = jnp.where(accept, loss, c["loss"])
        ok = ~failed & finite
        stop = active & terminate(loss, c["loss"], c["loss0"], ok, atol=atol, rtol=rtol)
        new = dict(
            c, state=state, loss=loss,
            hist=c["hist"].at[..., k].set(jnp.where(active, loss, jnp.nan)),
            done=c["done"] | stop, steps=c["steps"] + active.astype(jnp.int32),
            code=jnp.where(stop, code, c["code"]).astype(jnp.int32))
        if keep_best:
            # Accepted iterates are finite and certified here; keep the one of lowest loss.
            better = accept & (loss < c["best_loss"])
            new.update(best=method.select(better, state, c["best"]),
                       best_loss=jnp.where(better, loss, c["best_loss"]),
                       at=jnp.where(better, k, c["at"]))
        else:
            new.update(at=jnp.where(accept, k, c["at"]))
        return new

    def cond(c):
        return (c["k"] <= max_steps) & ((c["k"] == 0) | jnp.any(~c["done"]))

    def body(c):
        # Evaluate the pending iterate, book it, then make the next step. No `update` sits
        # in a `lax.cond`: under `vmap` (a swept hyperparameter) a batched predicate would
        # run it anyway. After the last step the update is made with no lane active (the
        # projection skips inactive lanes), and it is not evaluated.
        state, loss = evaluate(c["pending"])
        c = jax.lax.cond(c["k"] == 0, first, later, c, state, loss)
        if progress is not None:
            token, scale = progress
            report(token, c["k"], scale * (c["best_loss"] if keep_best else c["loss"]),
                   c["done"] | (c["k"] >= max_steps), max_steps)
        active = ~c["done"] & (c["k"] < max_steps)
        pending, code = method.update(c["state"], active)
        return dict(c, k=c["k"] + 1, pending=pending,
                    step_code=jnp.broadcast_to(code, lanes).astype(jnp.int32))

    c = jax.lax.while_loop(cond, body, carry)
    if keep_best:
        return c["best"], c["hist"], c["best_loss"], c["steps"], c["code"], c["at"]
    return c["state"], c["hist"], c["loss"], c["steps"], c["code"], c["at"]
