"""Demonstration windows: the one place where the feedback sign is fixed."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


class Windows(eqx.Module):
    """A batch of $N$ demonstration windows of horizon $h$.

    Each window holds the controller's initial state (the plant state at the window
    start, $\\hat x_0 = x_0$), the plant outputs $y_0..y_{h-1}$ (the controller's inputs)
    and the expert's plant inputs $u_0..u_{h-1}$.

    **The sign convention lives here.** The loop is negative feedback, $u = \\hat r - \\hat y$,
    so a controller that imitates the expert must output $\\hat y_k = -u_k$; `target`
    returns exactly that. An LQR-like expert $u = -ky$ ($k>0$) is therefore imitated by the
    passive controller $\\hat y = ky$.

    **Arguments:**

    - `x0`: `[N, n]` initial controller states.
    - `y`: `[N, h, p]` plant outputs (controller inputs).
    - `u`: `[N, h, m]` expert plant inputs.
    """

    x0: Float[Array, "N n"]
    y: Float[Array, "N h p"]
    u: Float[Array, "N h m"]

    def __init__(self, x0, y, u):
        self.x0, self.y, self.u = jnp.asarray(x0), jnp.asarray(y), jnp.asarray(u)

    def __check_init__(self):
        if self.x0.ndim != 2:
            raise ValueError(f"`x0` must have shape [N, n], got {self.x0.shape}.")
        if self.y.ndim != 3:
            raise ValueError(f"`y` must have shape [N, h, p], got {self.y.shape}.")
        if self.u.ndim != 3:
            raise ValueError(f"`u` must have shape [N, h, m], got {self.u.shape}.")
        N = self.x0.shape[0]
        if self.y.shape[0] != N or self.u.shape[0] != N:
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
            if not isinstance(arr, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(arr))):
                raise ValueError(f"`{name}` contains NaN or inf; clean the demonstrations first.")

    @property
    def num_windows(self) -> int:
        return self.x0.shape[0]

    @property
    def horizon(self) -> int:
        return self.y.shape[1]

    @property
    def n_state(self) -> int:
        """Controller state size $\\hat n$ implied by `x0`."""
        return self.x0.shape[1]

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

