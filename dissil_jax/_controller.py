"""Linear dynamic output-feedback controllers as equinox modules."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


class LTIController(eqx.Module):
    """A discrete-time LTI controller $K = (A, B, C, D)$ (paper §3).

    $$\\hat x_{k+1} = A\\hat x_k + B\\hat u_k, \\qquad \\hat y_k = C\\hat x_k + D\\hat u_k,$$

    with state $\\hat x\\in\\mathbb{R}^{\\hat n}$, input $\\hat u = y\\in\\mathbb{R}^p$ (the plant
    output) and output $\\hat y\\in\\mathbb{R}^m$; the plant input is $u = \\hat r - \\hat y$
    (negative feedback).

    A controller may carry leading batch axes on all four matrices (e.g. one per random
    initialisation, as returned by the trainers); `__call__` handles one unbatched
    controller, so `jax.vmap` it for batches.

    **Arguments:** `A` ($\\hat n\\times\\hat n$), `B` ($\\hat n\\times p$), `C` ($m\\times\\hat n$),
    `D` ($m\\times p$).
    """

    A: Float[Array, "*batch n n"]
    B: Float[Array, "*batch n p"]
    C: Float[Array, "*batch m n"]
    D: Float[Array, "*batch m p"]

    def __init__(self, A, B, C, D):
        mats = []
        for name, M in zip("ABCD", (A, B, C, D)):
            try:
                mats.append(jnp.asarray(M))
            except TypeError:
                raise ValueError(f"`{name}` must be a floating-point array, got {M!r}.") from None
        self.A, self.B, self.C, self.D = mats

    def __check_init__(self):
        names = ("A", "B", "C", "D")
        mats = (self.A, self.B, self.C, self.D)
        for name, M in zip(names, mats):
            if M.ndim < 2:
                raise ValueError(f"`{name}` must be a matrix, got shape {M.shape}.")
            if not jnp.issubdtype(M.dtype, jnp.floating):
                raise ValueError(f"`{name}` must be a floating-point array, got {M.dtype}.")
        batch = self.A.shape[:-2]
        n, p, m = self.A.shape[-1], self.B.shape[-1], self.C.shape[-2]
        expected = {"A": (n, n), "B": (n, p), "C": (m, n), "D": (m, p)}
        for name, M in zip(names, mats):
            if M.shape[:-2] != batch or M.shape[-2:] != expected[name]:
                raise ValueError(
                    f"`{name}` has shape {M.shape}; with A {self.A.shape}, B {self.B.shape}, "
                    f"C {self.C.shape} it must be {batch + expected[name]}."
                )
        for name, M in zip(names, mats):
            if _is_concrete(M) and not bool(jnp.all(jnp.isfinite(M))):
                raise ValueError(f"`{name}` contains NaN or inf.")

    @property
    def n_state(self) -> int:
        """Controller state dimension $\\hat n$."""
        return self.A.shape[-1]

    @property
    def n_in(self) -> int:
        """Controller input dimension $p$ (plant outputs)."""
        return self.B.shape[-1]

    @property
    def n_out(self) -> int:
        """Controller output dimension $m$ (plant inputs)."""
        return self.C.shape[-2]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch axes shared by the four matrices (empty for one controller)."""
        return self.A.shape[:-2]

    def __call__(
        self, x: Float[Array, " n"], u: Float[Array, " p"]
    ) -> tuple[Float[Array, " n"], Float[Array, " m"]]:
        """One step: returns $(\\hat x_{k+1}, \\hat y_k)$. Unbatched; vmap for batches."""
        return self.A @ x + self.B @ u, self.C @ x + self.D @ u

    @classmethod
    def random(
        cls,
        key: PRNGKeyArray,
        n: int,
        n_in: int,
        n_out: int,
        scale: float = 0.1,
        dtype=None,
    ) -> LTIController:
        """Entries i.i.d. $\\mathcal N(0, \\text{scale}^2)$ (the trainers' random initialisation).

        **Arguments:** `key`, state size `n`, input size `n_in` ($p$), output size `n_out`
        ($m$), `scale` (standard deviation), optional `dtype`.
        """
        for name, d in (("n", n), ("n_in", n_in), ("n_out", n_out)):
            if int(d) != d or d < 1:
                raise ValueError(f"`{name}` must be a positive integer, got {d!r}.")
        dtype = dtype or jnp.result_type(float)
        kA, kB, kC, kD = jr.split(key, 4)
        shapes = ((n, n), (n, n_in), (n_out, n), (n_out, n_in))
        return cls(*(scale * jr.normal(k, s, dtype) for k, s in zip((kA, kB, kC, kD), shapes)))

    def to_statespace(self, dt=True):
        """Convert to a discrete-time `control.StateSpace` (float64); `dt=True` = unspecified."""
        import control

        if self.batch_shape:
            raise ValueError("`to_statespace` needs one controller; index the batch first.")
        return control.ss(*(np.asarray(M, np.float64) for M in (self.A, self.B, self.C, self.D)),
                          dt=dt)

    @classmethod
    def from_statespace(cls, sys) -> LTIController:
        """Build from a discrete-time `control.StateSpace` (continuous systems are refused)."""
        if not getattr(sys, "dt", None):
            raise ValueError(
                "`sys` must be a discrete-time StateSpace (dt=True or dt>0); discretise it "
                "first, e.g. `sys.sample(0.1, method='bilinear')`."
            )
        return cls(*(np.asarray(M, np.float64) for M in (sys.A, sys.B, sys.C, sys.D)))

    def astype(self, dtype) -> LTIController:
        """Cast all four matrices."""
        return LTIController(*(M.astype(dtype) for M in (self.A, self.B, self.C, self.D)))
