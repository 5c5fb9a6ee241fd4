"""QSR supply rates, the closed-loop QSR theorem and the controller-supply recipe.

Conventions (see `docs/concepts.md`): an operator with input $u\\in\\mathbb{R}^{p}$ and
output $y\\in\\mathbb{R}^{m}$ is $(Q,S,R)$-dissipative when for every horizon $T$

$$\\sum_{k\\le T} w(u_k, y_k) \\ge \\beta, \\qquad
w(u, y) = y^\\top Q y + 2 y^\\top S u + u^\\top R u,$$

with $Q$ ($m\\times m$), $S$ ($m\\times p$), $R$ ($p\\times p$). For a controller $K$ the
input is the plant output and the output is (minus) the plant input.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, cast

import equinox as eqx
import numpy as np
import scipy.optimize

from ._outcome import Outcome
from ._validate import check_int, check_positive, check_real

_SYM_TOL = 1e-9


def _as_matrix(name: str, value, shape: tuple[int, int] | None = None) -> np.ndarray:
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


class ClosedLoopCertificate(eqx.Module):
    """What [`closed_loop_certificate`][dissil_jax.closed_loop_certificate] returns.

    - `result`: the [`Outcome`][dissil_jax.Outcome], `solved` when Theorem 1's condition
      holds, `no_multiplier` when no $\\alpha$ tried satisfies it;
    - `alpha`: the best multiplier found (the one minimising $\\lambda_{\\max}$);
    - `holds` (read-only): `result == Outcome.solved`, a `bool`;
    - `message` (read-only): what `result` means here, as a sentence.

    It unpacks like the pair `(holds, alpha)`.
    """

    result: Outcome
    alpha: float

    @property
    def holds(self) -> bool:
        """`result == Outcome.solved`: Theorem 1's condition holds at `alpha`."""
        return bool(self.result == Outcome.solved)

    @property
    def message(self) -> str:
        """What `result` means for Theorem 1 (the `Outcome` item's own sentence is the
        projection's and the certificates')."""
        if self.holds:
            return (f"Theorem 1 holds: M(alpha) is negative definite at alpha = "
                    f"{self.alpha:.6g} beyond round-off (a float64 eigenvalue check), so the "
                    "loop is l2-stable")
        return ("no multiplier found: lambda_max(M(alpha)) is not negative for any alpha "
                f"scanned (least at alpha = {self.alpha:.6g}); the two supply rates do not "
                "certify the loop, which may still be stable")

    def __iter__(self) -> Iterator[Any]:
        return iter((self.holds, self.alpha))


def _theorem1_matrix(plant: QSR, ctrl: QSR, alpha: float) -> np.ndarray:
    return np.block(
        [
            [plant.Q + alpha * ctrl.R, -plant.S + alpha * ctrl.S.T],
            [(-plant.S + alpha * ctrl.S.T).T, plant.R + alpha * ctrl.Q],
        ]
    )


def _check_interconnection(plant_qsr: QSR, controller_qsr: QSR) -> None:
    if not isinstance(plant_qsr, QSR) or not isinstance(controller_qsr, QSR):
        raise ValueError("`plant_qsr` and `controller_qsr` must be `dj.QSR` instances.")
    # plant: u in R^m -> y in R^p, so plant S is p x m; controller maps R^p -> R^m.
    if controller_qsr.S.shape != plant_qsr.S.T.shape:
        raise ValueError(
            f"`controller_qsr` has S of shape {controller_qsr.S.shape} but the plant's S is "
            f"{plant_qsr.S.shape}; the controller's input is the plant's output, so its S "
            f"must be {plant_qsr.S.T.shape}."
        )


def closed_loop_certificate(plant_qsr: QSR, controller_qsr: QSR) -> ClosedLoopCertificate:
    """Decide the QSR input-output stability theorem (paper Theorem 1) for a feedback pair.

    The negative-feedback loop $u_1 = r_1 - y_2$, $u_2 = r_2 + y_1$ of a
    $(Q_1,S_1,R_1)$-dissipative plant and a $(Q_2,S_2,R_2)$-dissipative controller is
    $\\ell_2$-stable if some $\\alpha>0$ gives

    $$M(\\alpha) = \\begin{bmatrix} Q_1 + \\alpha R_2 & -S_1 + \\alpha S_2^\\top \\\\
    \\ast & R_1 + \\alpha Q_2 \\end{bmatrix} \\prec 0.$$

    $\\lambda_{\\max}(M(\\alpha))$ is convex in $\\alpha$, so it is minimised by a
    log-spaced scan over $\\alpha\\in\\alpha_0[10^{-8}, 10^{8}]$ followed by Brent
    refinement, where $\\alpha_0$ is the ratio of the two rates' sizes (largest entries),
    the scale at which their terms in $M(\\alpha)$ compare: a rate and its multiples admit
    the same systems, so the answer must not depend on their scales (with the scan fixed at
    $[10^{-8}, 10^8]$, a plant rate of size 1 against a controller rate of size $10^{11}$
    found no multiplier where $\\alpha = 10^{-11}$ works).

    **Arguments:**

    - `plant_qsr`: the plant's supply rate (input $u\\in\\mathbb{R}^m$, output $y\\in\\mathbb{R}^p$).
    - `controller_qsr`: the controller's supply rate (input $y$, output $\\hat y\\in\\mathbb{R}^m$).

    **Returns:** a [`ClosedLoopCertificate`][dissil_jax.ClosedLoopCertificate] (`result`,
    `alpha`, `holds`); `alpha` is the best multiplier found (the one minimising
    $\\lambda_{\\max}$), returned even when the condition fails.
    """
    _check_interconnection(plant_qsr, controller_qsr)
    f = lambda la: np.linalg.eigvalsh(_theorem1_matrix(plant_qsr, controller_qsr, 10**la))[-1]
    size = lambda q: max(float(np.abs(M).max(initial=0.0)) for M in (q.Q, q.S, q.R))
    s1, s2 = size(plant_qsr), size(controller_qsr)
    centre = np.log10(s1 / s2) if s1 > 0 and s2 > 0 else 0.0
    grid = centre + np.linspace(-8, 8, 321)
    vals = np.array([f(g) for g in grid])
    i = int(np.argmin(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best_la, best = grid[i], vals[i]
    if hi > lo:
        # scipy types the result as `object`; it is an `OptimizeResult`
        res = cast(scipy.optimize.OptimizeResult,
                   scipy.optimize.minimize_scalar(f, bounds=(lo, hi), method="bounded",
                                                  options={"xatol": 1e-10}))
        if res.fun < best:
            best_la, best = res.x, res.fun
        # Brent stops at about sqrt(eps) relative in log(alpha), wider than the feasible
        # window of a pair at the edge (gain bounds 2 and 0.5 - 1e-9: alpha in (4, 4 +
        # 1.6e-8)); lambda_max is convex in alpha itself, so a golden-section search there
        # resolves it to float64
        la = np.log10(_golden(lambda a: f(np.log10(a)), 10**lo, 10**hi))
        if f(la) < best:
            best_la, best = la, f(la)
    scale = 1.0 + np.abs(_theorem1_matrix(plant_qsr, controller_qsr, 10**best_la)).max()
    holds = bool(best < -1e-12 * scale)
    return ClosedLoopCertificate(Outcome.solved if holds else Outcome.no_multiplier,
                                 float(10**best_la))


def _golden(g, a: float, b: float, iters: int = 200) -> float:
    """The minimiser of the convex `g` on [a, b], by golden-section search."""
    r = (np.sqrt(5.0) - 1) / 2
    c, d = b - r * (b - a), a + r * (b - a)
    gc, gd = g(c), g(d)
    for _ in range(iters):
        if b - a <= 4 * np.finfo(float).eps * max(abs(a), abs(b)):
            break
        if gc < gd:
            b, d, gd = d, c, gc
            c = b - r * (b - a)
            gc = g(c)
        else:
            a, c, gc = c, d, gd
            d = a + r * (b - a)
            gd = g(d)
    return c if gc < gd else d


def stabilising_qsr(plant_qsr: QSR, *, alpha: float = 1.0, margins=(1e-2, 1e-2)) -> QSR:
    """A controller supply rate that Theorem 1 pairs with `plant_qsr` (the recipe of `docs/concepts.md`, *The closed-loop theorem*).

    $$S_2 = S_1^\\top/\\alpha,\\quad R_2 = -(Q_1 + M_1)/\\alpha,\\quad Q_2 = -(R_1 + M_2)/\\alpha,$$

    so that $M(\\alpha) = \\operatorname{diag}(-M_1, -M_2) \\prec 0$ for $M_1, M_2 \\succ 0$.
    The paper's nonlinear example ($\\alpha=1$, margins $0.399$, $0.534$) maps the plant
    $(-1, 3.556, 29.333)$ to the controller $(-29.867, 3.556, 0.601)$.

    **Arguments:**

    - `plant_qsr`: the plant's supply rate.
    - `alpha`: the multiplier $\\alpha>0$.
    - `margins`: `(M1, M2)`, positive scalars or positive definite matrices of the plant's
      output and input sizes.

    `alpha` and `margins` are keyword-only.

    **Returns:** the controller's `QSR`.
    """
    if not isinstance(plant_qsr, QSR):
        raise ValueError("`plant_qsr` must be a `dj.QSR`.")
    a = np.asarray(alpha)
    if a.ndim != 0 or a.dtype.kind not in "iuf" or not np.isfinite(a) or a <= 0:
        raise ValueError(f"`alpha` must be positive and finite, got {alpha!r}.")
    try:
        M1, M2 = margins
    except (TypeError, ValueError):
        raise ValueError("`margins` must be a pair (M1, M2).") from None
    p, m = plant_qsr.S.shape
    mats = []
    for name, M, d in (("margins[0]", M1, p), ("margins[1]", M2, m)):
        M = np.asarray(M)
        if M.dtype.kind not in "iuf" or not np.all(np.isfinite(M)):
            raise ValueError(f"`{name}` must be a positive scalar or matrix of real numbers, "
                             f"got {M!r}.")
        M = M.astype(np.float64)
        M = M * np.eye(d) if M.ndim == 0 else _as_matrix(name, M, (d, d))
        if not np.allclose(M, M.T):
            raise ValueError(f"`{name}` must be symmetric (a quadratic form's matrix); "
                             f"pass ({name} + {name}.T) / 2.")
        if np.linalg.eigvalsh(M).min() <= 0:
            raise ValueError(f"`{name}` must be positive (definite), got eigenvalues "
                             f"{np.linalg.eigvalsh(M)}.")
        mats.append(M)
    M1, M2 = mats
    return QSR(
        Q=-(plant_qsr.R + M2) / alpha,
        S=plant_qsr.S.T / alpha,
        R=-(plant_qsr.Q + M1) / alpha,
    )
