"""The linear benchmark's expert: LQR state feedback from the continuous Riccati equation."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jaxtyping import Array, Float


class LQRExpert(eqx.Module):
    """State feedback $u = -Kx$ (paper §5.1). Noise $e$ is added by the simulator.

    Experts share one small interface so the simulators can scan them: `init(x0)` returns
    the expert's carry (here `None`) and `__call__(x, carry)` returns `(u, carry)`.
    Unbatched; vmap for batches.

    **Arguments:** the gain `K` ($m\\times n$).
    """

    K: Float[Array, "m n"]

    def __init__(self, K):
        K = jnp.asarray(K)
        if K.ndim != 2:
            raise ValueError(f"`K` must be an m x n matrix, got shape {K.shape}.")
        self.K = K

    def init(self, x0: Float[Array, " n"]) -> None:
        """The (empty) carry of a memoryless expert."""
        return None

    def __call__(self, x: Float[Array, " n"], carry=None) -> tuple[Float[Array, " m"], None]:
        """$u = -Kx$ and the unchanged carry."""
        return -self.K @ x, carry


def _weight(name: str, value, dim: int) -> np.ndarray:
    W = np.asarray(value, np.float64)
    if W.ndim == 0:
        W = W * np.eye(dim)
    if W.shape != (dim, dim):
        raise ValueError(f"`{name}` must be a scalar or a {dim}x{dim} matrix, got {W.shape}.")
    if not np.all(np.isfinite(W)) or not np.allclose(W, W.T):
        raise ValueError(f"`{name}` must be a finite symmetric matrix.")
    return (W + W.T) / 2


def lqr_gain(A, B, C, E=10.0, F=1.0) -> tuple[np.ndarray, np.ndarray]:
    """$K = E^{-1}B^\\top\\Pi$ with $\\Pi$ solving the continuous ARE (paper §5.1).

    $$A^\\top\\Pi + \\Pi A - \\Pi B E^{-1}B^\\top\\Pi + C^\\top F C = 0.$$

    **Arguments:** continuous-time `A` ($n\\times n$), `B` ($n\\times m$), `C`
    ($p\\times n$); input weight `E` ($m\\times m$ or a scalar times $I$, must be positive
    definite) and output weight `F` ($p\\times p$ or a scalar, positive semidefinite).

    **Returns:** `(K, Pi)` as float64 numpy arrays.
    """
    A, B, C = (np.asarray(M, np.float64) for M in (A, B, C))
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"`A` must be square, got shape {A.shape}.")
    n = A.shape[0]
    if B.ndim != 2 or B.shape[0] != n:
        raise ValueError(f"`B` must have {n} rows to match `A`, got shape {B.shape}.")
    if C.ndim != 2 or C.shape[1] != n:
        raise ValueError(f"`C` must have {n} columns to match `A`, got shape {C.shape}.")
    E = _weight("E", E, B.shape[1])
    F = _weight("F", F, C.shape[0])
    if np.linalg.eigvalsh(E).min() <= 0:
        raise ValueError("`E` must be positive definite (it weights the control effort).")
    if np.linalg.eigvalsh(F).min() < -1e-12:
        raise ValueError("`F` must be positive semidefinite.")
    Pi = scipy.linalg.solve_continuous_are(A, B, C.T @ F @ C, E)
    K = np.linalg.solve(E, B.T @ Pi)
    return K, Pi


def lqr_expert(A, B, C, E=10.0, F=1.0) -> LQRExpert:
    """The paper's linear-problem expert $u = -Kx$ with $K$ from [`lqr_gain`][dissil_jax.experts.lqr_gain].

    Designed on the continuous model (as in the paper) and applied to the discretised plant
    (zero-order hold by default), whose state is the continuous state at the sampling
    instants; defaults $E = 10I$,
    $F = I$ are the paper's values.

    ```python
    chain = dj.systems.mass_spring_chain(jax.random.PRNGKey(0))
    expert = dj.experts.lqr_expert(chain.Ac, chain.Bc, chain.Cc)
    ```
    """
    K, _ = lqr_gain(A, B, C, E, F)
    return LQRExpert(jnp.asarray(K))
