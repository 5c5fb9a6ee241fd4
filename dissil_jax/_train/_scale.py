"""The trainers' unit normalisation: every trainer works on windows divided by one data scale.

With $s^2 = \\frac1N\\sum_i\\bigl(\\lVert x^{(i)}_0\\rVert^2 + \\sum_k\\lVert y^{(i)}_k
\\rVert^2\\bigr)$, the power of the controller's inputs and initial states, the windows
$(x_0/s, y/s, u/s)$ have the same minimisers as the originals, since the loss is quadratic
and the controller linear: $J(K) = s^2 J_s(K)$. Step sizes, the proximal and Young weights of
ICO and the SDP data are then independent of the units of the demonstrations, and the
curvature of $J_s$ in $D$ (and in $C$ at the first step), $2\\,\\mathbb E[yy^\\top]/s^2$,
is at most of order one, so one step size suits problems whose signals have very different
sizes. Losses and `tol` are converted back, so users see their own units. (With every input
and state zero the loss does not depend on the controller and $s = 1$.)
"""

from __future__ import annotations

import jax.numpy as jnp

from .._data import Windows


def loss_scale(windows: Windows, xp=jnp, *, of: str = "inputs"):
    """$s^2$ of the module docstring, or 1 when it is zero (works traced with `jnp`).

    `of="outputs"` gives instead $s^2 = J(0) = \\frac1N\\sum_i\\sum_k\\lVert u^{(i)}_k
    \\rVert^2$, the zero controller's loss, which ICO uses: it has no step size, and with
    this scale its iterates agreed to ~2e-6 under changes of units, against ~2e-5 with the
    input power (the SDP solutions are only accurate to the solver's tolerance).
    """
    if of == "outputs":
        s2 = xp.mean(xp.sum(xp.asarray(windows.u) ** 2, axis=(-2, -1)))
        return xp.where(s2 > 0, s2, 1.0)
    s2 = xp.mean(xp.sum(xp.asarray(windows.y) ** 2, axis=(-2, -1)))
    if windows.x0 is not None:
        s2 = s2 + xp.mean(xp.sum(xp.asarray(windows.x0) ** 2, axis=-1))
    return xp.where(s2 > 0, s2, 1.0)


def scaled(windows: Windows, s2) -> Windows:
    """The windows divided by $s = \\sqrt{s^2}$ (x0 stays None for windows at rest)."""
    s = s2**0.5
    x0 = windows.x0
    return Windows(None if x0 is None else x0 / s, windows.y / s, windows.u / s)
