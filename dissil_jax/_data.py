"""Demonstration windows: the one place where the feedback sign is fixed."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


class Windows(eqx.Module):
    """A batch of $N$ demonstration windows of horizon $h$.

    Each window holds the controller's initial state (the plant state at the window
    start, $\\hat x_0 = x_0$), the plant outputs $y_0..y_{h-1}$ (the controller's inputs)
    and the expert's plant inputs $u_0..u_{h-1}$.

    **Input-output logs alone.** When the plant state was not recorded, pass `x0=None`:
    the controller then starts every window **at rest**, $\\hat x_0 = 0$, whatever its
    order $\\hat n$. This is exact when each window is the beginning of a run from rest
    (a logged experiment started at equilibrium); for windows cut from the middle of a
    trajectory it neglects the unknown initial state, whose effect $\\mathcal O\\hat x_0$
    (see [`observability_toeplitz`][dissil_jax.observability_toeplitz]) the loss then
    charges to the controller. With `x0=None`, `x0` stays None, `n_state` is None (the
    controller order is a free choice: the trainers take it as `n_state=`) and the number
    of windows comes from `y`.

    **The sign convention lives here.** The loop is negative feedback, $u = \\hat r - \\hat y$,
    so a controller that imitates the expert must output $\\hat y_k = -u_k$; `target`
    returns exactly that. An LQR-like expert $u = -ky$ ($k>0$) is therefore imitated by the
    passive controller $\\hat y = ky$.

    **Arguments:**

    - `x0`: `[N, n]` initial controller states, or None: every window starts at rest
      ($\\hat x_0 = 0$).
    - `y`: `[N, h, p]` plant outputs (controller inputs).
    - `u`: `[N, h, m]` expert plant inputs.

    ```python
    W = dj.Windows(x0, y, u)      # controller starts at the recorded plant state
    W = dj.Windows(None, y, u)    # input-output logs only: controller starts at rest
    ```
    """

    x0: Float[Array, "N n"] | None
    y: Float[Array, "N h p"]
    u: Float[Array, "N h m"]

    def __init__(self, x0, y, u):
        self.x0 = None if x0 is None else jnp.asarray(x0)
        self.y, self.u = jnp.asarray(y), jnp.asarray(u)

    def __check_init__(self):
        if self.x0 is not None and self.x0.ndim != 2:
            raise ValueError(f"`x0` must have shape [N, n] (or be None: start at rest), "
                             f"got {self.x0.shape}.")
        if self.y.ndim != 3:
            raise ValueError(f"`y` must have shape [N, h, p], got {self.y.shape}.")
        if self.u.ndim != 3:
            raise ValueError(f"`u` must have shape [N, h, m], got {self.u.shape}.")
        N = self.y.shape[0]
        if self.x0 is None:
            if self.u.shape[0] != N:
                raise ValueError(f"`y` and `u` must share the window axis N; got "
                                 f"{self.y.shape[0]} and {self.u.shape[0]}.")
        elif self.x0.shape[0] != N or self.u.shape[0] != N:
            raise ValueError(
                f"`x0`, `y` and `u` must share the window axis N; got {self.x0.shape[0]}, "
                f"{self.y.shape[0]}, {self.u.shape[0]}."
            )
        if self.y.shape[1] != self.u.shape[1]:
            raise ValueError(
                f"`y` and `u` must share the horizon h; got {self.y.shape[1]} and {self.u.shape[1]}."
            )
        if N < 1 or self.y.shape[1] < 1:
            raise ValueError("`Windows` needs at least one window of horizon at least 1.")
        for name in ("x0", "y", "u"):
            arr = getattr(self, name)
            if arr is not None and not isinstance(arr, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(arr))):
                raise ValueError(f"`{name}` contains NaN or inf; clean the demonstrations first.")

    @property
    def num_windows(self) -> int:
        """Number of windows $N$."""
        return self.y.shape[0]

    @property
    def horizon(self) -> int:
        """Horizon $h$ (steps per window)."""
        return self.y.shape[1]

    @property
    def n_state(self) -> int | None:
        """Controller state size $\\hat n$ implied by `x0`; None when the windows start at rest."""
        return None if self.x0 is None else self.x0.shape[1]

    @property
    def n_in(self) -> int:
        """Controller input size $p$."""
        return self.y.shape[2]

    @property
    def n_out(self) -> int:
        """Controller output size $m$."""
        return self.u.shape[2]

    @property
    def target(self) -> Float[Array, "N h m"]:
        """The imitation target of the controller output, $\\hat y_k = -u_k$."""
        return -self.u

