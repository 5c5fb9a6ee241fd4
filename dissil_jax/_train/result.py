"""The result type shared by every trainer."""

from __future__ import annotations

from typing import Any

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
    """

    controllers: Any
    P: Float[Array, "inits n n"] | None
    certified: Bool[Array, " inits"] | None
    loss_history: Float[Array, "inits steps"]
    final_loss: Float[Array, " inits"]
    converged: Bool[Array, " inits"]
    steps: Int[Array, " inits"]
    wall_time: Float[Array, ""]

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
