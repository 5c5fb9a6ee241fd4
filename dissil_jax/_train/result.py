"""The result type shared by every trainer."""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .. import _sdp


class FitResult(eqx.Module):
    """What every `dj.fit_*` returns; the leading axis of each field is the initialisation.

    - `controllers`: the learned controllers, batched (`LTIController` with `[num_inits]`
      leading axes, or an `MLPController` for `fit_mlp`).
    - `P`: `[num_inits, n, n]` storage matrices certifying each controller (None for
      unconstrained methods).
    - `certified`: `[num_inits]` bool, the exact float64 KYP check of (controller, `P`)
      (None for unconstrained methods).
    - `loss_history`: `[num_inits, max_steps + 1]`; column 0 is the initial controller's
      loss, column k the loss after step k, NaN after a controller stopped.
    - `final_loss`: `[num_inits]` loss of the returned controller.
    - `converged`: `[num_inits]` True when the stopping rule $|\\Delta J| <$ `tol` fired.
    - `steps`: `[num_inits]` number of steps taken.
    - `wall_time`: total training wall time in seconds (NaN inside a traced sweep).
    - `stop_reason`: `[num_inits]` [`Outcome`][dissil_jax.Outcome], why each run stopped
      (decode with [`stop_reasons`][dissil_jax.FitResult.stop_reasons]): `converged`
      ($|\\Delta J| <$ `tol`), `max_steps`, `non_finite` (the loss became NaN or infinite;
      the constrained trainers keep their last finite, certified iterate), `infeasible`,
      `solver_failed` or `not_certified` (a projection or an ICO SDP failed; the last
      certified iterate is kept), `loss_increased` (ICO's float64 guard refused a step).
      Compare with `res.stop_reason == dj.Outcome.converged`.
    - `projected`: `[num_inits]` bool or None. Only
      [`fit_direct`][dissil_jax.fit_direct] sets it: True where the direct map's controller
      failed the final float64 check and was replaced by its projection
      ([`project`][dissil_jax.project]); None for the other trainers.
    """

    STOP_REASONS: ClassVar[tuple[str, ...]] = _sdp.NAMES

    controllers: Any
    P: Float[Array, "inits n n"] | None
    certified: Bool[Array, " inits"] | None
    loss_history: Float[Array, "inits steps"]
    final_loss: Float[Array, " inits"]
    converged: Bool[Array, " inits"]
    steps: Int[Array, " inits"]
    wall_time: Float[Array, ""]
    stop_reason: Any = None
    projected: Bool[Array, " inits"] | None = None

    @property
    def initial_loss(self) -> Float[Array, " inits"]:
        return self.loss_history[..., 0]

    @property
    def percent_change_cost(self) -> Float[Array, " inits"]:
        """$100\\,(J_\\text{final} - J_\\text{initial}) / J_\\text{initial}$ (paper Tables 1-4)."""
        return 100.0 * (self.final_loss - self.initial_loss) / self.initial_loss

    @property
    def num_inits(self) -> int:
        return self.final_loss.shape[-1]

    def best(self) -> Any:
        """The controller with the lowest final loss."""
        import jax

        i = int(jnp.nanargmin(self.final_loss))
        return jax.tree.map(lambda x: x[i], self.controllers)

    def stop_reasons(self) -> list:
        """`stop_reason` decoded into `Outcome` names (nested lists for sweeps)."""
        if self.stop_reason is None:
            raise ValueError("this FitResult has no `stop_reason` (built by hand?).")
        names = np.asarray(self.STOP_REASONS, dtype=object)
        return names[np.asarray(_codes(self.stop_reason))].tolist()


def _codes(reason):
    return reason._value if isinstance(reason, _sdp.Outcome) else reason


_FINE = (_sdp.code("converged"), _sdp.code("max_steps"))


def raise_if_failed(res: FitResult) -> FitResult:
    """The trainers' `throw=True`: raise if a run ended other than `converged`/`max_steps`.

    Eagerly a `ValueError` that counts the reasons; under `jit` an `EquinoxRuntimeError`
    with the message of the worst outcome.
    """
    codes = _codes(res.stop_reason)
    bad = (codes != _FINE[0]) & (codes != _FINE[1])
    if isinstance(codes, jax.core.Tracer):
        worst = _sdp.item(jnp.max(jnp.where(bad, codes, -1)))
        return eqx.tree_at(lambda r: r.final_loss, res,
                           worst.error_if(res.final_loss, jnp.any(bad)))
    bad = np.asarray(bad)
    if bad.any():
        names = np.asarray(res.stop_reasons(), dtype=object)[bad]
        counts = {n: int((names == n).sum()) for n in sorted(set(names))}
        # One explanation (and its fix) per kind of failure, and what the failed runs kept:
        # only the constrained trainers have certified iterates to fall back on.
        why = "; ".join(f"{n}: {_sdp.Outcome[getattr(_sdp.Outcome, n)].rstrip('.')}"
                        for n in counts)
        kept = ("its last certified, finite iterate" if res.certified is not None
                else "its last finite iterate")
        raise ValueError(
            f"{int(bad.sum())} of {bad.size} runs ended in failure {counts}. {why}. Each "
            f"failed run kept {kept}; pass `throw=False` to get the result and inspect "
            "`stop_reason`.")
    return res
