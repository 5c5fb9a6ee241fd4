"""Demonstration windows: the one place where the feedback sign is fixed."""

from __future__ import annotations

import equinox as eqx
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._validate import check_precision, has_non_finite


def _as_real_array(name: str, a) -> Array:
    """`a` as a real floating array: floats as they are, integers converted exactly to the
    default float dtype; a `ValueError` naming `name` for anything else (see `Windows`)."""
    try:
        arr = jnp.asarray(a)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a real floating-point array, got {a!r}.") from None
    if jnp.issubdtype(arr.dtype, jnp.floating):
        check_precision(name, arr.dtype)
        return arr
    if jnp.issubdtype(arr.dtype, jnp.integer) and arr.dtype != jnp.bool_:
        out = arr.astype(jnp.result_type(float))
        # Every integer of magnitude <= 2**(nmant + 1) is a float of that dtype.
        exact = 2 ** (jnp.finfo(out.dtype).nmant + 1)
        if not isinstance(arr, jax.core.Tracer) and arr.size and max(
                int(np.max(arr)), -int(np.min(arr))) > exact:
            raise ValueError(
                f"`{name}` is an integer array with entries too large to convert exactly to "
                f"{out.dtype}; convert it to floats yourself (and rescale the data).")
        return out
    kind = "a complex array" if jnp.issubdtype(arr.dtype, jnp.complexfloating) else "an array"
    raise ValueError(f"`{name}` must be a real floating-point array, got {kind} of dtype "
                     f"{arr.dtype}; the controller's signals are real.")


class Windows(eqx.Module):
    """A batch of $N$ demonstration windows of horizon $h$.

    Each window holds the controller's initial state (the plant state at the window
    start, $\\hat x_0 = x_0$), the plant outputs $y_0..y_{h-1}$ (the controller's inputs)
    and the expert's plant inputs $u_0..u_{h-1}$.

    **Input-output logs alone.** When the plant state was not recorded, pass `x0=None`:
    the controller then starts every window **at rest**, $\\hat x_0 = 0$, whatever its
    order $\\hat n$. What must be at rest is the *demonstrator's* internal state, not the
    plant's: the controller sees only $y$, so a window is imitated exactly from rest when
    the expert that produced it started from its own rest state. A static output-feedback
    expert ($u = -Ky$) is always at rest; an observer-based or other dynamic expert is at
    rest at the start of a log in which its state was zero, even if the plant was not at
    equilibrium then. (A state-feedback expert acts on the plant state, which is then the
    demonstrator's state: from rest is exact only when the plant started at rest.) For
    windows cut from the middle of a dynamic expert's run, starting
    at rest neglects the expert's unknown state, whose effect $\\mathcal O\\hat x_0$ (see
    [`observability_toeplitz`][dissil_jax.observability_toeplitz]) the loss then charges
    to the controller.

    **Window length from rest.** From rest, an $h$-step window shows the controller's
    response $\\hat y_k = Dy_k + \\sum_{j<k} CA^{k-1-j}By_j$, so the loss determines
    only $D$ and the Markov parameters $CB, CAB, \\dots, CA^{h-2}B$; the rest of an
    order-$\\hat n$ controller is not fitted but still acts in closed loop. A generic
    order-$\\hat n$ response with $p$ inputs and $m$ outputs is fixed by $D$ and its first
    $\\lceil\\hat n/m\\rceil + \\lceil\\hat n/p\\rceil$ Markov parameters (the Hankel matrix
    built from them then has rank $\\hat n$, and a realisation follows from it and its
    shift), so use

    $$h \\ge \\lceil\\hat n/m\\rceil + \\lceil\\hat n/p\\rceil + 1
    \\qquad (h \\ge 2\\hat n + 1 \\text{ for one input and one output}).$$

    The trainers warn when windows from rest are shorter than that.

    With `x0=None`, `x0` stays None, `n_state` is None (the controller order is a free
    choice: the trainers take it as `n_state=`) and the number of windows comes from `y`.

    **The sign convention lives here.** The loop is negative feedback, $u = \\hat r - \\hat y$,
    so a controller that imitates the expert must output $\\hat y_k = -u_k$; `target`
    returns exactly that. An LQR-like expert $u = -ky$ ($k>0$) is therefore imitated by the
    passive controller $\\hat y = ky$.

    **Arguments:**

    - `x0`: `[N, n]` initial controller states, or None: every window starts at rest
      ($\\hat x_0 = 0$).
    - `y`: `[N, h, p]` plant outputs (controller inputs).
    - `u`: `[N, h, m]` expert plant inputs.

    **Dtypes.** Floating arrays keep their dtype; half precision (float16, bfloat16) is
    refused, being too coarse for the certificates. Integer arrays (e.g. logs of a quantised
    sensor, or `[[[1]], [[2]]]` typed by hand) are converted to JAX's default float
    (float64 with `jax_enable_x64`, else float32), as `jnp.mean` or `jax.grad` would
    promote them anyway: the controllers, the loss and its gradient are real-valued, and
    the trainers draw their initialisations in the data's floating dtype. The conversion
    is exact (integers of magnitude up to $2^{53}$, or $2^{24}$ in float32); a concrete
    array it would round raises a ValueError. Complex arrays are refused: the loss
    $\\lVert\\hat y + u\\rVert^2$ of a real controller has no meaning for complex signals,
    and dropping the imaginary part would be lossy. So are boolean and non-numeric ones.

    ```python
    W = dj.Windows(x0, y, u)      # controller starts at the recorded plant state
    W = dj.Windows(None, y, u)    # input-output logs only: controller starts at rest
    ```
    """

    x0: Float[Array, "N n"] | None
    y: Float[Array, "N h p"]
    u: Float[Array, "N h m"]

    def __init__(self, x0, y, u):
        self.x0 = None if x0 is None else _as_real_array("x0", x0)
        self.y, self.u = _as_real_array("y", y), _as_real_array("u", u)

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
        if self.x0 is not None and self.x0.shape[1] < 1:
            raise ValueError(f"`x0` has no states (shape {self.x0.shape}): a dynamic controller "
                             "has at least one; for windows that start at rest pass `x0=None` "
                             "(and the controller's order as `n_state`).")
        for name in ("y", "u"):
            if getattr(self, name).shape[2] < 1:
                raise ValueError(f"`{name}` has no channels (shape {getattr(self, name).shape}): "
                                 "a controller needs at least one input and one output.")
        for name in ("x0", "y", "u"):
            arr = getattr(self, name)
            if arr is not None and has_non_finite(arr):
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

