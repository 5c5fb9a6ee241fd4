"""Plants as equinox modules: a discrete LTI plant and the paper's sector-bounded plant."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._validate import check_abcd, has_non_finite


def _matrix(name: str, value) -> Array:
    arr = jnp.asarray(value)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    if arr.ndim != 2:
        raise ValueError(f"`{name}` must be a matrix (or a scalar), got shape {arr.shape}.")
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = arr.astype(jnp.result_type(float))
    if has_non_finite(arr):
        raise ValueError(f"`{name}` contains NaN or inf.")
    return arr


_check_abcd = check_abcd


class _ABCDPlant(eqx.Module):
    """Shared part of the plants: the matrices (A, B, C, D), sizes and the output map."""

    A: Float[Array, "n n"]
    B: Float[Array, "n m"]
    C: Float[Array, "p n"]
    D: Float[Array, "p m"]

    def __check_init__(self):
        _check_abcd(self.A, self.B, self.C, self.D)

    @property
    def n_state(self) -> int:
        """State dimension $n$."""
        return self.A.shape[0]

    @property
    def n_in(self) -> int:
        """Input dimension $m$."""
        return self.B.shape[1]

    @property
    def n_out(self) -> int:
        """Output dimension $p$."""
        return self.C.shape[0]

    def output(self, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " p"]:
        """$y_k = Cx_k + Du_k$. Unbatched; vmap for batches."""
        return self.C @ x + self.D @ u

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`(A, B, C, D)` as float64 numpy arrays (for host-side SDPs and python-control)."""
        A, B, C, D = (np.asarray(M, np.float64) for M in (self.A, self.B, self.C, self.D))
        return A, B, C, D


class LinearPlant(_ABCDPlant):
    """A discrete-time LTI plant $G = (A, B, C, D)$.

    $$x_{k+1} = Ax_k + Bu_k, \\qquad y_k = Cx_k + Du_k,$$

    with state $x\\in\\mathbb R^n$, input $u\\in\\mathbb R^m$, output $y\\in\\mathbb R^p$
    (see *Signs and conventions* in `docs/concepts.md`). The plant is noise free; the simulators in `dissil_jax.experiments` add
    process noise to $x_{k+1}$ and control noise to $u_k$. `step` and `output` handle one
    unbatched sample; vmap them for batches.

    **Arguments:** `A` ($n\\times n$), `B` ($n\\times m$), `C` ($p\\times n$), `D`
    ($p\\times m$); scalars are $1\\times1$ matrices.

    ```python
    plant = dj.LinearPlant(A, B, C, D)
    x1 = plant.step(x0, u0); y0 = plant.output(x0, u0)
    ```
    """

    def __init__(self, A, B, C, D):
        self.A, self.B, self.C, self.D = (_matrix(k, M) for k, M in zip("ABCD", (A, B, C, D)))

    def step(self, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " n"]:
        """$x_{k+1} = Ax_k + Bu_k$ (noise free). Unbatched; vmap for batches."""
        return self.A @ x + self.B @ u

    def to_statespace(self, dt=True):
        """The plant as a discrete-time `control.StateSpace` (`dt=True`: unspecified)."""
        import control

        return control.ss(*self.matrices(), dt=dt)


class SectorPlant(_ABCDPlant):
    """The paper's nonlinear plant (paper eq. 20), sector bounded through $|\\sin x|\\le|x|$.

    $$x_{k+1} = Ax_k + \\alpha\\sin(x_k) + Bu_k, \\qquad y_k = Cx_k + Du_k,$$

    with $\\sin$ applied elementwise. The paper's example is
    `SectorPlant(0.5, 1, 1, -2, 0.4)` (see `dj.systems.paper_nonlinear_plant`). Its
    supply rate from coarse knowledge is [`sector_plant_qsr`][dissil_jax.sector_plant_qsr]
    (paper Lemma 8). Noise free, unbatched; vmap for batches. `matrices()` returns the
    linear part.

    **Arguments:** `A`, `B`, `C`, `D` as for [`LinearPlant`][dissil_jax.LinearPlant] and the
    scalar gain `alpha` of the nonlinearity.
    """

    alpha: Float[Array, ""]

    def __init__(self, A, B, C, D, alpha):
        self.A, self.B, self.C, self.D = (_matrix(k, M) for k, M in zip("ABCD", (A, B, C, D)))
        alpha = jnp.asarray(alpha, dtype=self.A.dtype)
        if alpha.ndim != 0:
            raise ValueError(f"`alpha` must be a scalar, got shape {alpha.shape}.")
        if has_non_finite(alpha):
            raise ValueError("`alpha` must be finite.")
        self.alpha = alpha

    def step(self, x: Float[Array, " n"], u: Float[Array, " m"]) -> Float[Array, " n"]:
        """$x_{k+1} = Ax_k + \\alpha\\sin x_k + Bu_k$ (noise free). Unbatched; vmap for batches."""
        return self.A @ x + self.alpha * jnp.sin(x) + self.B @ u


def paper_nonlinear_plant() -> SectorPlant:
    """The paper's nonlinear benchmark (paper eq. 20): $x^+ = 0.5x + 0.4\\sin x + u$, $y = x - 2u$."""
    return SectorPlant(0.5, 1.0, 1.0, -2.0, 0.4)
