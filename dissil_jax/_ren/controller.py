"""Recurrent equilibrium network (REN) controllers: an LTI system in feedback with a
slope-restricted static nonlinearity, with an explicit (strictly lower-triangular) layer."""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._controller import LTIController, check_step
from .._data import Windows
from .._rollout import check_window_sizes, scan_outputs
from .._validate import check_int, check_precision, has_non_finite
from .activation import ACTIVATIONS, check_activation


def _as_array(name, M):
    try:
        return jnp.asarray(M)
    except TypeError:
        raise ValueError(f"`{name}` must be a floating-point array, got {M!r}.") from None


_NAMES = ("A", "B1", "B2", "C1", "D11", "D12", "C2", "D21", "D22")


def _sweep(D11, b, f):
    """One pass over the rows of a strictly lower-triangular `D11`:
    $z_i = f_i\\bigl(b_i + \\sum_{j<i}(D_{11})_{ij}z_j\\bigr)$, with `f(i, a)`.

    A `lax.fori_loop` over the rows: its compile time does not grow with the width. The
    pass unrolled into static slices ran 10-20 % faster per step but compiled 0.3 s (width
    4 and 8) to 1.5 s (width 16) longer, so a single `fit_ren` call, even with 600 steps,
    took longer unrolled (`benchmarks/bench_ren.py`).
    """
    return jax.lax.fori_loop(0, b.shape[0],
                             lambda i, z: z.at[i].set(f(i, b[i] + D11[i] @ z)),
                             jnp.zeros_like(b))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _explicit_layer(sigma, D11, b):
    """$w = \\sigma(b + D_{11}w)$ for strictly lower-triangular $D_{11}$ (one `_sweep`).

    Its derivative is a pass of the same shape: with $s = \\sigma'(v)$ at the solution's
    $v = b + D_{11}w$, $\\dot w_i = s_i\\bigl(\\dot b_i + (\\dot D_{11}w)_i +
    \\sum_{j<i}(D_{11})_{ij}\\dot w_j\\bigr)$, which is linear in the tangents, so reverse
    mode is its transpose (a backward pass). Differentiating the forward pass op by op
    instead costs about 1.5x the time of the loss gradient at width 16
    (`benchmarks/README.md`, "REN controllers").
    """
    return _sweep(D11, b, lambda i, a: sigma(a))


@_explicit_layer.defjvp
def _explicit_layer_jvp(sigma, primals, tangents):
    (D11, b), (dD11, db) = primals, tangents
    w = _explicit_layer(sigma, D11, b)
    v = b + D11 @ w
    s = jax.jvp(sigma, (v,), (jnp.ones_like(v),))[1]  # sigma' elementwise
    dw = _sweep(D11, db + dD11 @ w, lambda i, a: s[i] * a)
    return w, dw


class RENController(eqx.Module):
    """A recurrent equilibrium network controller with an explicit equilibrium layer.

    $$\\begin{aligned} x_{k+1} &= A x_k + B_1 w_k + B_2\\hat u_k, \\\\
    v_k &= C_1 x_k + D_{11} w_k + D_{12}\\hat u_k, \\qquad w_k = \\sigma(v_k), \\\\
    \\hat y_k &= C_2 x_k + D_{21} w_k + D_{22}\\hat u_k, \\end{aligned}$$

    with state $x\\in\\mathbb R^{\\hat n}$, $q$ neurons ($v, w\\in\\mathbb R^q$, the `width`),
    input $\\hat u = y\\in\\mathbb R^p$ and output $\\hat y\\in\\mathbb R^m$ (the conventions of
    [`LTIController`][dissil_jax.LTIController]). $\\sigma$ acts elementwise, is
    slope-restricted in $[0, 1]$ and has $\\sigma(0) = 0$, so $w_i(v_i - w_i)\\ge0$ (the sector
    condition the certificate uses). $D_{11}$ is strictly lower triangular: neuron $i$ sees
    only neurons $j < i$, so the layer is solved explicitly in $q$ sweeps. A `D11` with
    entries on or above the diagonal is refused, except when it is traced (built inside
    `jax.jit`, where its values are unknown): the layer then uses its strictly lower part,
    `jnp.tril(D11, -1)`, and [`certify_ren`][dissil_jax.certify_ren] refuses the
    controller until it is built with that part.

    Width 0 is the LTI controller $(A, B_2, C_2, D_{22})$: see
    [`from_lti`][dissil_jax.RENController.from_lti] and
    [`to_lti`][dissil_jax.RENController.to_lti]. Leading batch axes are allowed on all
    nine matrices; `__call__` handles one controller (vmap for batches).

    **Arguments:** the nine matrices, and `activation`: `"relu"` (default), `"tanh"` or a
    callable that passes `check_activation`'s screen (static). (`fit_ren` defaults to
    `"tanh"`, chosen on the problem zoo.)

    **Raises** a `ValueError` for shapes that do not match, a $D_{11}$ with a nonzero entry
    on or above the diagonal, non-finite entries, or an activation that is not
    slope-restricted.
    """

    A: Float[Array, "*batch n n"]
    B1: Float[Array, "*batch n q"]
    B2: Float[Array, "*batch n p"]
    C1: Float[Array, "*batch q n"]
    D11: Float[Array, "*batch q q"]
    D12: Float[Array, "*batch q p"]
    C2: Float[Array, "*batch m n"]
    D21: Float[Array, "*batch m q"]
    D22: Float[Array, "*batch m p"]
    activation: str | Callable = eqx.field(static=True, default="relu")

    def __init__(self, A, B1, B2, C1, D11, D12, C2, D21, D22,
                 activation: str | Callable = "relu"):
        (self.A, self.B1, self.B2, self.C1, self.D11, self.D12, self.C2, self.D21,
         self.D22) = (_as_array(n, M) for n, M in zip(_NAMES, (A, B1, B2, C1, D11, D12, C2,
                                                                D21, D22)))
        self.activation = check_activation(activation)

    def __check_init__(self):
        mats = dict(zip(_NAMES, self.matrices))
        for name, M in mats.items():
            if M.ndim < 2 or not jnp.issubdtype(M.dtype, jnp.floating):
                raise ValueError(f"`{name}` must be a floating-point matrix, got shape "
                                 f"{M.shape} and dtype {M.dtype}.")
            check_precision(name, M.dtype)
        batch = self.A.shape[:-2]
        n, q, p, m = self.A.shape[-1], self.C1.shape[-2], self.B2.shape[-1], self.C2.shape[-2]
        expected = dict(A=(n, n), B1=(n, q), B2=(n, p), C1=(q, n), D11=(q, q), D12=(q, p),
                        C2=(m, n), D21=(m, q), D22=(m, p))
        for name, M in mats.items():
            if M.shape != batch + expected[name]:
                raise ValueError(
                    f"`{name}` has shape {M.shape}; with {n} states, width {q} (rows of C1), "
                    f"{p} inputs (columns of B2) and {m} outputs (rows of C2) it must be "
                    f"{batch + expected[name]}.")
        for name, M in mats.items():
            if has_non_finite(M):
                raise ValueError(f"`{name}` contains NaN or inf.")
        D11 = self.D11  # read in numpy: under `jit` a jnp op on a constant is traced too
        if not isinstance(D11, jax.core.Tracer) and q and np.any(np.triu(np.asarray(D11)) != 0):
            raise ValueError("`D11` must be strictly lower triangular (an explicit layer: "
                             "neuron i may only see neurons j < i); pass jnp.tril(D11, -1).")

    @property
    def matrices(self) -> tuple[Array, ...]:
        """The nine matrices in the order of the constructor."""
        return (self.A, self.B1, self.B2, self.C1, self.D11, self.D12, self.C2, self.D21,
                self.D22)

    @property
    def n_state(self) -> int:
        """State dimension $\\hat n$."""
        return self.A.shape[-1]

    @property
    def width(self) -> int:
        """Number of neurons $q$."""
        return self.C1.shape[-2]

    @property
    def n_in(self) -> int:
        """Input dimension $p$ (plant outputs)."""
        return self.B2.shape[-1]

    @property
    def n_out(self) -> int:
        """Output dimension $m$ (plant inputs)."""
        return self.C2.shape[-2]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch axes shared by the matrices."""
        return self.A.shape[:-2]

    @property
    def sigma(self) -> Callable:
        """The activation as a function."""
        # a name was checked against ACTIVATIONS at construction
        return ACTIVATIONS[self.activation] if isinstance(self.activation, str) \
            else self.activation

    def layer(self, x: Float[Array, " n"], u: Float[Array, " p"]) -> Float[Array, " q"]:
        """The equilibrium layer's output $w = \\sigma(C_1x + D_{11}w + D_{12}\\hat u)$.

        Explicit: $D_{11}$ is strictly lower triangular, so neuron $i$ needs only the
        neurons $j < i$, and one pass over the rows,
        $w_i = \\sigma\\bigl(b_i + \\sum_{j<i}(D_{11})_{ij}w_j\\bigr)$ with
        $b = C_1x + D_{12}\\hat u$, solves it in $O(q^2)$ operations (a `lax.fori_loop`
        over the rows). Its derivative is the same pass on the tangents (`_explicit_layer`).
        """
        if self.batch_shape:
            raise ValueError(f"`K` must be a single controller (batch shape "
                             f"{self.batch_shape}); vmap over the batch, e.g. "
                             "`jax.vmap(lambda k: k(x, u))(K)`.")
        check_step(self, x, u)
        b = self.C1 @ x + self.D12 @ u
        D11 = jnp.tril(self.D11, -1)  # traced D11 is not checked in __check_init__
        return b if self.width == 0 else _explicit_layer(self.sigma, D11, b)

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " p"]
                 ) -> tuple[Float[Array, " n"], Float[Array, " m"]]:
        """One step: returns $(x_{k+1}, \\hat y_k)$. Unbatched; vmap for batches."""
        w = self.layer(x, u)
        return (self.A @ x + self.B1 @ w + self.B2 @ u,
                self.C2 @ x + self.D21 @ w + self.D22 @ u)

    @classmethod
    def from_lti(cls, K: LTIController, width: int = 0, activation="relu") -> RENController:
        """The REN with $(A, B_2, C_2, D_{22}) = K$ and `width` idle neurons (all other
        matrices zero, so it computes exactly what `K` computes)."""
        if not isinstance(K, LTIController):
            raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__}.")
        q, batch = check_int("width", width, minimum=0), K.batch_shape
        z = lambda r, c: jnp.zeros(batch + (r, c), K.A.dtype)
        n, p, m = K.n_state, K.n_in, K.n_out
        return cls(K.A, z(n, q), K.B, z(q, n), z(q, q), z(q, p), K.C, z(m, q), K.D,
                   activation=activation)

    def odd_part(self) -> RENController:
        """The odd part of this REN: the REN of twice the order and width that computes
        $\\tfrac12\\bigl(K(x_1, \\hat u) - K(x_2, -\\hat u)\\bigr)$ with two copies of $K$,
        the second driven by $-\\hat u$, on the state $(x_1, x_2)$.

        Started at $(\\hat x_0, -\\hat x_0)$ (or at rest) it is odd, $\\hat y(-\\hat x_0,
        -\\hat u) = -\\hat y(\\hat x_0, \\hat u)$, as an expert is whenever the plant is odd
        and the cost even (every LTI plant with a quadratic cost, and the paper's nonlinear
        example). Its matrices are block diagonal ($A$, $B_1$, $C_1$, $D_{11}$), stacked
        ($[B_2; -B_2]$, $[D_{12}; -D_{12}]$) or halved ($\\tfrac12[C_2\\ -C_2]$,
        $\\tfrac12[D_{21}\\ -D_{21}]$), with the same $D_{22}$. For $Q\\preceq0$ it is
        $(Q,S,R)$-dissipative whenever $K$ is: with $K$'s certificate $(P, \\Lambda)$,
        $(\\tfrac12\\operatorname{diag}(P, P), \\tfrac12\\operatorname{diag}(\\Lambda,
        \\Lambda))$ certifies it (the margin `certify_ren` reports is then about half $K$'s,
        0.50-0.55 of it on random RENs: the pair is halved, the $\\hat u$ block is not),
        because the supply is concave in the
        output: $s(\\hat u, \\tfrac{a + b}2)\\ge\\tfrac12 s(\\hat u, a) + \\tfrac12 s(\\hat u, b)$,
        and $s(-\\hat u, \\hat y) = s(\\hat u, -\\hat y)$. Leading batch axes are kept.
        """
        two = lambda M: jnp.concatenate([M, -M], axis=-2)
        half = lambda M: 0.5 * jnp.concatenate([M, -M], axis=-1)
        return RENController(block_diag2(self.A), block_diag2(self.B1), two(self.B2),
                             block_diag2(self.C1), block_diag2(self.D11), two(self.D12),
                             half(self.C2), half(self.D21), self.D22,
                             activation=self.activation)

    def to_lti(self) -> LTIController:
        """The LTI controller $(A, B_2, C_2, D_{22})$ of a width-0 REN.

        **Raises** a `ValueError` for width $> 0$: the neurons make the controller nonlinear,
        and the LTI tools (`certify`, `project`, `observability_toeplitz`) assume linearity;
        use [`certify_ren`][dissil_jax.certify_ren] and [`ren_rollout`][dissil_jax.ren_rollout].
        """
        if self.width:
            raise ValueError(f"`K` has width {self.width}: only a width-0 REN is an LTI "
                             "controller; certify it with `dj.certify_ren` instead.")
        return LTIController(self.A, self.B2, self.C2, self.D22)


def block_diag2(M: Array) -> Array:
    """$\\operatorname{diag}(M, M)$ over the last two axes (leading batch axes kept)."""
    z = jnp.zeros_like(M)
    return jnp.concatenate([jnp.concatenate([M, z], -1), jnp.concatenate([z, M], -1)], -2)


def ren_rollout(K: RENController, x0: Float[Array, " n"] | None, u_in: Float[Array, "h p"]
                ) -> Float[Array, "h m"]:
    """Simulate a REN from state `x0` (None: at rest) on inputs `u_in` with `lax.scan`.

    The REN twin of [`rollout`][dissil_jax.rollout]. Unbatched; vmap for batches.

    **Returns:** the outputs $\\hat y_0..\\hat y_{h-1}$ (`[h, m]`).
    """
    return scan_outputs(K, x0, u_in, "dj.ren_rollout")


def ren_predict(K: RENController, windows: Windows) -> Float[Array, "N h m"]:
    """REN outputs on every window (vmapped over windows), from `windows.x0` or at rest.

    The twin of [`predict`][dissil_jax.predict]: **returns** `[N, h, m]` and raises a
    ValueError when `windows.y`, `windows.u` or `windows.x0` do not have `K.n_in`,
    `K.n_out` or `K.n_state` columns."""
    if K.batch_shape:
        raise ValueError("`K` must be a single controller; vmap `ren_predict` for batches.")
    check_window_sizes(K, windows)
    if windows.x0 is None:
        return jax.vmap(ren_rollout, in_axes=(None, None, 0))(K, None, windows.y)
    return jax.vmap(ren_rollout, in_axes=(None, 0, 0))(K, windows.x0, windows.y)


def mirrored(windows: Windows) -> Windows:
    """The windows with $\\hat x_0$, $y$ and $u$ negated (what an odd expert does from
    $-\\hat x_0$)."""
    x0 = None if windows.x0 is None else -windows.x0
    return Windows(x0, -windows.y, -windows.u)


def ren_imitation_loss(K: RENController, windows: Windows) -> Float[Array, ""]:
    """The paper's imitation loss (paper eq. 16) of a REN: the twin of
    [`imitation_loss`][dissil_jax.imitation_loss],
    $J = \\frac1N\\sum_i\\sum_k\\lVert\\hat y^{(i)}_k + u^{(i)}_k\\rVert^2$."""
    err = ren_predict(K, windows) - windows.target
    return jnp.mean(jnp.sum(err**2, axis=(-2, -1)))


def ren_odd_loss(K: RENController, windows: Windows) -> Float[Array, ""]:
    """The imitation loss of `K.odd_part()` started at $(\\hat x_0, -\\hat x_0)$, computed
    as two copies of `K` side by side: $\\hat y = \\tfrac12\\bigl(K(\\hat x_0, y) -
    K(-\\hat x_0, -y)\\bigr)$ on every window (what `fit_ren(odd=True)` minimises)."""
    # one rollout over the windows and their mirror images, stacked: the layer's sequential
    # pass then runs once per time step for both copies (two rollouts ran it twice)
    both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), windows, mirrored(windows))
    plus, minus = jnp.split(ren_predict(K, both), 2)
    pred = 0.5 * (plus - minus)
    return jnp.mean(jnp.sum((pred - windows.target) ** 2, axis=(-2, -1)))
