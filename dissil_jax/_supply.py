"""QSR supply rates (the closed-loop theorem and the controller-supply recipe are in
`_theorem1.py`).

Conventions (see `docs/concepts.md`): an operator with input $u\\in\\mathbb{R}^{p}$ and
output $y\\in\\mathbb{R}^{m}$ is $(Q,S,R)$-dissipative when for every horizon $T$

$$\\sum_{k\\le T} w(u_k, y_k) \\ge \\beta, \\qquad
w(u, y) = y^\\top Q y + 2 y^\\top S u + u^\\top R u,$$

with $Q$ ($m\\times m$), $S$ ($m\\times p$), $R$ ($p\\times p$). For a controller $K$ the
input is the plant output and the output is (minus) the plant input.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import numpy as np

from ._validate import check_int, check_positive, check_real

_SYM_TOL = 1e-9


def _as_matrix(name: str, value, shape: tuple[int, int] | None = None) -> np.ndarray:
    if isinstance(value, jax.core.Tracer):
        raise ValueError(
            f"`{name}` is traced (inside `jax.vmap`, `jax.jit` or `jax.grad`), but a `QSR` is "
            "static host data in float64 that the certificates are checked against, so it "
            "cannot be built from traced values: build each `QSR` outside the "
            "transformation and loop over rates in Python (see `dj.QSR`, \"Many rates in one "
            "process\").")
    try:
        raw = np.asarray(value)
        arr = None if np.iscomplexobj(raw) else raw.astype(np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None:
        raise ValueError(f"`{name}` must be a real matrix (or a scalar), got {value!r}.")
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    if arr.ndim != 2:
        raise ValueError(f"`{name}` must be a matrix (or a scalar), got shape {arr.shape}.")
    if shape is not None and arr.shape != shape:
        raise ValueError(f"`{name}` must have shape {shape}, got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` contains NaN or inf; supply finite numbers.")
    return arr


class _FrozenMatrix:
    """A read-only float64 matrix that is hashed and compared by value.

    The static fields of [`QSR`][dissil_jax.QSR] hold these, so that JAX can use a supply
    rate as part of a treedef or as a static argument (both need `__hash__` and a
    boolean `__eq__`, which a numpy array does not have).
    """

    __slots__ = ("array", "_hash")

    def __init__(self, array: np.ndarray):
        array = np.asarray(array, dtype=np.float64) + 0.0  # a fresh copy, and -0.0 -> 0.0
        array.flags.writeable = False
        self.array = array
        self._hash = hash((array.shape, array.tobytes()))

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other) -> bool:
        if not isinstance(other, _FrozenMatrix):
            return NotImplemented
        return self._hash == other._hash and bool(np.array_equal(self.array, other.array))

    def __reduce__(self):
        return (_FrozenMatrix, (self.array,))

    def __repr__(self) -> str:
        return f"_FrozenMatrix({self.array!r})"


class QSR(eqx.Module):
    """A quadratic supply rate $w(u,y) = y^\\top Q y + 2y^\\top S u + u^\\top R u$.

    A supply rate is host-side problem data (it fixes the shapes of the SDPs), so it is a
    **static, hashable value**: it has no array leaves as a pytree, two supply rates with
    equal matrices are equal (`==` returns a plain `bool`) and hash alike, and it can be
    passed to `jax.jit` (also as a static argument), `eqx.filter_jit` or `jax.vmap` like
    any other static value. `Q`, `S` and `R` are read-only float64 numpy arrays.

    **Many rates in one process.** `fit_direct`, `direct_run`, `fit_ren` and `fit_pgd`
    pass the rate's values (or, for `fit_pgd`'s Clarabel projection, a reference the host
    resolves) into their compiled run, so rates of one shape share one compilation.
    `pgd_run`, whose rate the caller holds as a static value, compiles once per distinct
    rate, and every compiled run stays mapped in memory: a few hundred distinct rates in
    one process can exhaust Linux's memory-map limit (`vm.max_map_count`, 65,530 by
    default; 400-1,100 maps per rate), which aborts the process. Call `jax.clear_caches()`
    every fifty rates or so in such a sweep ([Scaling out](scaling.md), "Many supply rates
    in one process").

    **Arguments:**

    - `Q`: symmetric $m\\times m$ weight on the output (a scalar is a $1\\times1$ matrix).
    - `S`: $m\\times p$ cross weight.
    - `R`: symmetric $p\\times p$ weight on the input.

    Special cases (paper, Table 1) are available as constructors:
    [`QSR.passive`][dissil_jax.QSR.passive], [`QSR.bounded_gain`][dissil_jax.QSR.bounded_gain],
    [`QSR.conic`][dissil_jax.QSR.conic], [`QSR.degenerate_conic`][dissil_jax.QSR.degenerate_conic].

    ```python
    qsr = dj.QSR(-29.867, 3.556, 0.601)   # the paper's nonlinear-example controller
    ```
    """

    _Q: _FrozenMatrix = eqx.field(static=True)
    _S: _FrozenMatrix = eqx.field(static=True)
    _R: _FrozenMatrix = eqx.field(static=True)

    def __init__(self, Q, S, R):
        S = _as_matrix("S", S)
        m, p = S.shape
        if m == 0 or p == 0:
            raise ValueError(f"`S` must be m x p with m, p >= 1 (a controller with at least one "
                             f"input and one output), got shape {S.shape}.")
        Q, R = _as_matrix("Q", Q), _as_matrix("R", R)
        # neither Q nor R agrees with S: S is the odd one out (else the one that disagrees)
        square = Q.shape[0] == Q.shape[1] and R.shape[0] == R.shape[1]
        if square and Q.shape[0] != m and R.shape[0] != p and Q.size and R.size:
            raise ValueError(f"`S` must be {Q.shape[0]}x{R.shape[0]} to match `Q` "
                             f"({Q.shape[0]}x{Q.shape[0]}) and `R` ({R.shape[0]}x"
                             f"{R.shape[0]}), got {S.shape}.")
        if Q.shape != (m, m):
            raise ValueError(f"`Q` must be {m}x{m} to match `S` ({m}x{p}), got {Q.shape}"
                             + (f" (or `S` must have {Q.shape[0]} rows)." if square else "."))
        if R.shape != (p, p):
            raise ValueError(f"`R` must be {p}x{p} to match `S` ({m}x{p}), got {R.shape}"
                             + (f" (or `S` must have {R.shape[0]} columns)." if square else "."))
        for name, M in (("Q", Q), ("R", R)):
            if not np.allclose(M, M.T, atol=_SYM_TOL * max(1.0, np.abs(M).max())):
                raise ValueError(f"`{name}` must be symmetric; pass ({name} + {name}.T) / 2.")
        self._Q = _FrozenMatrix((Q + Q.T) / 2)
        self._S = _FrozenMatrix(S)
        self._R = _FrozenMatrix((R + R.T) / 2)

    @property
    def Q(self) -> np.ndarray:
        """The output weight $Q$ ($m\\times m$, symmetric; read-only float64)."""
        return self._Q.array

    @property
    def S(self) -> np.ndarray:
        """The cross weight $S$ ($m\\times p$; read-only float64)."""
        return self._S.array

    @property
    def R(self) -> np.ndarray:
        """The input weight $R$ ($p\\times p$, symmetric; read-only float64)."""
        return self._R.array

    def __hash__(self) -> int:
        return hash((self._Q, self._S, self._R))

    def __eq__(self, other) -> bool:
        if not isinstance(other, QSR):
            return NotImplemented
        return (self._Q, self._S, self._R) == (other._Q, other._S, other._R)

    @property
    def n_out(self) -> int:
        """Output dimension $m$ (rows of $S$)."""
        return self.S.shape[0]

    @property
    def n_in(self) -> int:
        """Input dimension $p$ (columns of $S$)."""
        return self.S.shape[1]

    # -- special cases (paper Table 1) -------------------------------------------------
    @classmethod
    def passive(cls, dim: int) -> QSR:
        """Passivity: $Q=0$, $S=\\tfrac12 I$, $R=0$, so $w = y^\\top u$."""
        dim = _check_dim("dim", dim)
        return cls(np.zeros((dim, dim)), 0.5 * np.eye(dim), np.zeros((dim, dim)))

    @classmethod
    def bounded_gain(cls, gamma: float, *, n_in: int, n_out: int) -> QSR:
        """$\\gamma$-bounded $\\ell_2$ gain: $Q=-I$, $S=0$, $R=\\gamma^2 I$.

        $w = \\gamma^2\\lVert u\\rVert^2 - \\lVert y\\rVert^2$: the map
        $\\mathbb R^{n_{in}}\\to\\mathbb R^{n_{out}}$ has $\\ell_2$ gain at most $\\gamma$.

        **Arguments:**

        - `gamma`: the gain bound $\\gamma>0$.
        - `n_in`: input dimension $p$ (keyword only).
        - `n_out`: output dimension $m$ (keyword only).

        **Returns:** the `QSR` with $S$ of shape `(n_out, n_in)`.
        """
        n_out, n_in = _check_dim("n_out", n_out), _check_dim("n_in", n_in)
        gamma = check_positive("gamma", gamma)
        if abs(float(gamma)) > np.sqrt(np.finfo(np.float64).max):
            raise ValueError(f"`gamma` = {gamma!r} is too large: its square, R, overflows "
                             "float64.")
        return cls(-np.eye(n_out), np.zeros((n_out, n_in)), gamma**2 * np.eye(n_in))

    @classmethod
    def conic(cls, a: float, b: float, *, dim: int) -> QSR:
        """Interior cone $[a, b]$: $Q=-I$, $S=\\tfrac{a+b}{2}I$, $R=-abI$ (needs $a<b$).

        $w = -(y - a u)^\\top (y - b u)$, non-negative exactly when $y$ lies between $au$
        and $bu$. The size `dim` is keyword-only, as in every constructor whose
        parameters come first ([`bounded_gain`][dissil_jax.QSR.bounded_gain]).
        """
        dim = _check_dim("dim", dim)
        a, b = check_real("a", a), check_real("b", b)
        if not a < b:
            raise ValueError(f"`a` must be smaller than `b`, got a={a}, b={b}.")
        if max(abs(a), abs(b)) > np.sqrt(np.finfo(np.float64).max):
            raise ValueError(f"`a` = {a!r} and `b` = {b!r} are too large: their product, R, "
                             "overflows float64.")
        return cls(-np.eye(dim), 0.5 * (a + b) * np.eye(dim), -a * b * np.eye(dim))

    @classmethod
    def degenerate_conic(cls, d: float, *, dim: int) -> QSR:
        """Degenerate cone $[d, \\infty)$: $Q=0$, $S=\\tfrac12 I$, $R=-dI$."""
        dim = _check_dim("dim", dim)
        d = check_real("d", d)
        return cls(np.zeros((dim, dim)), 0.5 * np.eye(dim), -d * np.eye(dim))

    # -- utilities ------------------------------------------------------------------
    def supply(self, u, y) -> np.ndarray:
        """Evaluate $w(u, y)$ for one pair (or batches along leading axes)."""
        u, y = np.asarray(u, np.float64), np.asarray(y, np.float64)
        return (
            np.einsum("...i,ij,...j->...", y, self.Q, y)
            + 2 * np.einsum("...i,ij,...j->...", y, self.S, u)
            + np.einsum("...i,ij,...j->...", u, self.R, u)
        )

    def check_sizes(self, n_in: int, n_out: int) -> None:
        """Raise a ValueError naming `qsr` unless it fits a map $\\mathbb R^{n_{in}}\\to\\mathbb R^{n_{out}}$."""
        if self.S.shape != (n_out, n_in):
            raise ValueError(
                f"`qsr` has S of shape {self.S.shape}, but the system maps R^{n_in} -> "
                f"R^{n_out}; S must be {(n_out, n_in)}."
            )

    def neg_q_factor(self) -> np.ndarray:
        """Return $L$ ($m\\times r$, $r=\\operatorname{rank} Q$) with $-Q = LL^\\top$.

        Raises `ValueError` when $Q$ has a positive eigenvalue: then no such factor exists
        (the learning code splits $Q = Q_+ - Q_-$ and linearises the $Q_+$ part instead).
        """
        w, V = np.linalg.eigh(-self.Q)
        scale = max(1.0, float(np.abs(w).max(initial=0.0)))
        if w.min(initial=0.0) < -1e-10 * scale:
            raise ValueError(
                "`qsr.Q` has a positive eigenvalue "
                f"({-w.min():.3g}), so -Q has no factor L L'. Only `dj.fit_direct` and "
                "`dj.fit_ren` need Q <= 0; `dj.project`, `dj.fit_pgd` and `dj.fit_ico` accept any symmetric Q."
            )
        keep = w > 1e-10 * scale
        return V[:, keep] * np.sqrt(w[keep])

    def __repr__(self) -> str:
        f = lambda M: np.array2string(M, precision=4, separator=", ")
        return f"QSR(Q={f(self.Q)}, S={f(self.S)}, R={f(self.R)})"


_check_dim = check_int
