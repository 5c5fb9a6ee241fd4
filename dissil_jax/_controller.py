"""Linear dynamic output-feedback controllers as equinox modules."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ._validate import (
    check_abcd,
    check_int,
    check_key,
    check_precision,
    has_non_finite,
    real_array,
)


def _collect_systems(sys) -> tuple[tuple[int, ...], list]:
    """Shape and row-major members of an object array or (nested) list of systems."""
    if isinstance(sys, np.ndarray):
        return sys.shape, list(sys.reshape(-1))
    if not isinstance(sys, (list, tuple)):
        return (), [sys]
    parts = [_collect_systems(s) for s in sys]
    if len({shape for shape, _ in parts}) > 1:
        raise ValueError("`sys` is a ragged nested sequence; every entry needs the same shape.")
    inner = parts[0][0] if parts else ()
    return (len(parts),) + inner, [s for _, members in parts for s in members]


def _statespace_matrices(sys) -> tuple[np.ndarray, ...]:
    """`(A, B, C, D)` (float64) of one discrete-time StateSpace; refuses continuous ones."""
    if isinstance(sys, LTIController) or not all(hasattr(sys, k) for k in "ABCD"):
        raise ValueError(f"`sys` must be a `control.StateSpace` (with matrices A, B, C, D), "
                         f"got {type(sys).__name__}; convert a transfer function with "
                         "`control.ss(sys)`.")
    if not getattr(sys, "dt", None):
        raise ValueError(
            "`sys` must be a discrete-time StateSpace (dt=True or dt>0); discretise it "
            "first, e.g. `sys.sample(0.1, method='bilinear')`."
        )
    return tuple(np.asarray(M, np.float64) for M in (sys.A, sys.B, sys.C, sys.D))


def _map_batch(fn, K: LTIController) -> np.ndarray:
    """`fn(A_i, B_i, C_i, D_i)` (float64) per member, in an object array of shape `K.batch_shape`."""
    mats = [real_array(name, M) for name, M in zip("ABCD", (K.A, K.B, K.C, K.D))]
    out = np.empty(K.batch_shape, dtype=object)
    for idx in np.ndindex(*K.batch_shape):
        out[idx] = fn(*(M[idx] for M in mats))
    return out


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
    `D` ($m\\times p$): real matrices of one floating dtype (integer ones are cast to
    it, or to JAX's default float when all four are integers).
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
        # integer entries (`np.eye(2, dtype=int)`, `[[1]]`) take the floats' dtype, as in
        # `Windows` and `QSR`: the other matrices' when they share one, else JAX's default
        floats = {M.dtype for M in mats if jnp.issubdtype(M.dtype, jnp.floating)}
        target = floats.pop() if len(floats) == 1 else jnp.result_type(float)
        mats = [M.astype(target) if jnp.issubdtype(M.dtype, jnp.integer) else M
                for M in mats]
        self.A, self.B, self.C, self.D = mats

    def __check_init__(self):
        names = ("A", "B", "C", "D")
        mats = (self.A, self.B, self.C, self.D)
        for name, M in zip(names, mats):
            if M.ndim < 2:
                raise ValueError(f"`{name}` must be a matrix, got shape {M.shape}.")
            if not jnp.issubdtype(M.dtype, jnp.floating):
                raise ValueError(f"`{name}` must be a floating-point array, got {M.dtype}.")
            check_precision(name, M.dtype)
        if len({M.dtype for M in mats}) > 1:  # a projection would round the wider ones
            raise ValueError(f"`A`, `B`, `C` and `D` must share one dtype, got "
                             f"{', '.join(str(M.dtype) for M in mats)}; cast them alike (e.g. "
                             "`K.astype(jnp.float64)` or `.astype` on each).")
        check_abcd(*mats)
        for name, M in zip(names, mats):
            if has_non_finite(M):
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
        check_step(self, x, u)
        return self.A @ x + self.B @ u, self.C @ x + self.D @ u

    @classmethod
    def random(
        cls,
        key: PRNGKeyArray,
        n_state: int,
        n_in: int,
        n_out: int,
        *,
        scale: float = 0.1,
        dtype=None,
    ) -> LTIController:
        """Entries i.i.d. $\\mathcal N(0, \\text{scale}^2)$ (the trainers' random initialisation).

        **Arguments:**

        - `key`: a JAX PRNG key (first, as in the trainers and `jax.random`).
        - `n_state`: state size $\\hat n$ (0: a static controller, $\\hat y = D\\hat u$).
        - `n_in`: input size $p$ (plant outputs).
        - `n_out`: output size $m$ (plant inputs).
        - `scale`: standard deviation of the entries ($\\ge 0$; may be traced).
        - `dtype`: floating dtype (default: JAX's default float).

        **Returns:** an unbatched `LTIController`; `jax.vmap` over keys for a batch:

        ```python
        K = dj.LTIController.random(jax.random.PRNGKey(0), 2, 1, 1, scale=0.5)
        Ks = jax.vmap(lambda k: dj.LTIController.random(k, 2, 1, 1))(keys)
        ```
        """
        n = check_int("n_state", n_state, minimum=0)
        n_in, n_out = (check_int(name, d) for name, d in (("n_in", n_in), ("n_out", n_out)))
        if not isinstance(scale, jax.core.Tracer) and not (np.ndim(scale) == 0
                                                            and 0 <= float(scale) < np.inf):
            raise ValueError(f"`scale` must be a finite number >= 0 (a standard deviation), "
                             f"got {scale!r}.")
        check_key(key)
        dtype = dtype or jnp.result_type(float)
        kA, kB, kC, kD = jr.split(key, 4)
        shapes = ((n, n), (n, n_in), (n_out, n), (n_out, n_in))
        return cls(*(scale * jr.normal(k, s, dtype) for k, s in zip((kA, kB, kC, kD), shapes)))

    def to_statespace(self, dt: bool | float = True):
        """Convert to discrete-time `control.StateSpace` systems (float64).

        **Arguments:** `dt`, the sampling time (`True`: discrete with unspecified period).

        **Returns:** one `control.StateSpace` for an unbatched controller. With leading
        batch axes (python-control has no batched systems) a numpy object array of shape
        `K.batch_shape` whose entries are the members' `StateSpace` systems, so that
        `K.to_statespace()[i]` is `K_i.to_statespace()` with `K_i` the `i`-th member;
        [`from_statespace`][dissil_jax.LTIController.from_statespace] inverts both forms.
        """
        import control

        if not (dt is True or (isinstance(dt, (int, float)) and not isinstance(dt, bool)
                               and np.isfinite(dt) and dt > 0)):
            raise ValueError(f"`dt` must be True or a positive finite sampling time (the "
                             f"controller is discrete-time), got {dt!r}.")
        to_ss = lambda A, B, C, D: control.ss(A, B, C, D, dt=dt)
        if self.batch_shape:
            return _map_batch(to_ss, self)
        return to_ss(*(real_array(name, M)  # refuses traced matrices by name
                       for name, M in zip("ABCD", (self.A, self.B, self.C, self.D))))

    @classmethod
    def from_statespace(cls, sys) -> LTIController:
        """Build from a discrete-time `control.StateSpace` (continuous systems are refused).

        **Arguments:** `sys`, one `StateSpace`, or an array (or nested sequence) of
        `StateSpace` systems of equal sizes, such as the output of
        [`to_statespace`][dissil_jax.LTIController.to_statespace] for a batch.

        **Returns:** an `LTIController`, with the array's shape as leading batch axes.
        """
        if isinstance(sys, (list, tuple, np.ndarray)):
            shape, systems = _collect_systems(sys)
            if not systems:
                raise ValueError("`sys` is an empty collection of systems.")
            mats = [_statespace_matrices(s) for s in systems]
            sizes = {tuple(M.shape for M in m) for m in mats}
            if len(sizes) > 1:
                raise ValueError(f"`sys` holds systems of different sizes (shapes of A, B, C, "
                                 f"D: {sorted(sizes)}); a batch needs equal sizes.")
            return cls(*(np.stack([m[i] for m in mats]).reshape(shape + mats[0][i].shape)
                         for i in range(4)))
        return cls(*_statespace_matrices(sys))

    def astype(self, dtype) -> LTIController:
        """Cast all four matrices."""
        return LTIController(*(M.astype(dtype) for M in (self.A, self.B, self.C, self.D)))


def check_step(K, x, u) -> None:
    """A `ValueError` naming `x` or `u` unless they are one state (`[K.n_state]`) and one
    input (`[K.n_in]`) of a single controller `K` (shapes are static: this holds under jit
    and vmap, per member)."""
    for name, v, size, what in (("x", x, K.n_state, "the controller's state, `K.n_state`"),
                                ("u", u, K.n_in, "the controller's input, `K.n_in`")):
        if jnp.shape(v) != (size,):
            raise ValueError(f"`{name}` must have shape ({size},) ({what}), got "
                             f"{jnp.shape(v)}; one step is unbatched: vmap it for batches.")
