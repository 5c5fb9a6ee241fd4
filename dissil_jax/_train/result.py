"""The result type shared by every trainer."""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


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
    - `stop_reason`: `[num_inits]` int, why each run stopped, an index into
      `FitResult.STOP_REASONS` (decode with [`stop_reasons`][dissil_jax.FitResult.stop_reasons]):
      `"converged"` ($|\\Delta J| <$ `tol`), `"max_steps"`, `"non_finite"` (the loss became
      NaN or infinite; the last finite iterate is kept by the constrained trainers),
      `"solver_failed"` (a projection or ICO SDP was infeasible or failed; the last
      certified iterate is kept), `"loss_increased"` and `"not_certified"` (ICO's float64
      guards against solver inaccuracy refused a step).
    """

    STOP_REASONS: ClassVar[tuple[str, ...]] = (
        "converged", "max_steps", "non_finite", "solver_failed", "loss_increased",
        "not_certified",
    )

    controllers: Any
    P: Float[Array, "inits n n"] | None
    certified: Bool[Array, " inits"] | None
    loss_history: Float[Array, "inits steps"]
    final_loss: Float[Array, " inits"]
    converged: Bool[Array, " inits"]
    steps: Int[Array, " inits"]
    wall_time: Float[Array, ""]
    stop_reason: Int[Array, " inits"] | None = None

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
        """`stop_reason` decoded into the names of `STOP_REASONS` (nested lists for sweeps)."""
        import numpy as np

        if self.stop_reason is None:
            raise ValueError("this FitResult has no `stop_reason` (built by hand?).")
        names = np.asarray(self.STOP_REASONS, dtype=object)
        return names[np.asarray(self.stop_reason)].tolist()


def stop_code(name: str) -> int:
    """The `FitResult.stop_reason` code of a reason name."""
    return FitResult.STOP_REASONS.index(name)
