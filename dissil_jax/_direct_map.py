"""A direct parameterisation of the $(Q,S,R)$-dissipative controllers.

A smooth map $\\theta = (X, W, V) \\mapsto (A, B, C, D, P)$ whose every value satisfies

$$\\mathrm{KYP}(P) \\preceq -\\varepsilon\\,\\operatorname{diag}(P, \\Phi_0), \\qquad
P \\succeq \\varepsilon I,$$

for every supply rate with $Q\\preceq 0$ (strict: $Q\\prec0$, passivity and the degenerate
cones: $Q = 0$, and rank-deficient $Q$), and whose image is the whole set of controllers
with such a certificate. Training through it is unconstrained gradient descent in pure
JAX. The maps and their proof are in `docs/concepts.md` ("A direct parameterisation");
the code follows the same names:

1. a **feedthrough centre** $D_0$ with $\\Phi_0 = \\Phi(D_0)\\succ0$, where
   $\\Phi(D) = R + S^\\top D + D^\\top S + D^\\top QD$ (host, float64, once per supply rate);
2. $P = X^\\top X + \\varepsilon I = G_P^\\top G_P$ and $G = \\operatorname{diag}(G_P, G_\\Phi)$;
3. the **loop transformation** of $(C, D)$: $T_u = (S + QD_0)G_\\Phi^{-1}$,
   $N = T_uT_u^\\top - (1-\\varepsilon)Q \\succeq 0$, a matrix $Z = WG_W^{-1}$ with
   $G_W^\\top G_W = I + W^\\top N W$ (so $Z^\\top N Z\\prec I$), $Y = I - T^\\top Z$ with
   $T = [0\\ \\ T_u]$, and $[C\\ \\ D] = [0\\ \\ D_0] + (1-\\varepsilon)\\,ZY^{-1}G$;
4. a **contraction** for $(A, B)$: $U = VG_V^{-1}$ with $G_V^\\top G_V = I + V^\\top V$,
   $K_F = \\sqrt{1-\\varepsilon}\\,G_W^{-1}Y^{-1}G$ and $[A\\ \\ B] = G_P^{-1}UK_F$.

No step inverts $Q$, so the map is continuous in $Q$ up to and including $Q = 0$.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import jax.random as jr
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float

from . import _linalg
from ._controller import LTIController
from ._rate_scale import balanced_blocks, rate_factor, scaled_rate
from ._supply import QSR

#: Default margin eps of the map: KYP(P) <= -eps diag(P, Phi0) and P >= eps I. The float64
#: check asks for a margin above 1e-11 times the size of the KYP terms, which grows like
#: |P| |A|^2. On the paper's linear example (ill-conditioned P, large A) eps = 1e-3 left the
#: worst controller only ~2x above that threshold, eps = 1e-2 ~1000x (float32 too), at a
#: training loss within 25 % of eps = 1e-3's (`benchmarks/bench_direct.py`).
MARGIN = 1e-2

# Candidate regularisations mu of the centre search: D0(mu) = (mu I - Q)^{-1} S.
_MUS = 2.0 ** np.arange(-40.0, 40.25, 0.25)


class DirectParams(eqx.Module):
    """The free parameters $\\theta$ of the direct map (any real values; vmap for batches).

    - `X`: $\\hat n\\times\\hat n$, the storage $P = X^\\top X + \\varepsilon I$;
    - `W`: $m\\times(\\hat n+p)$, the output matrices $(C, D)$ after the loop transformation;
    - `V`: $\\hat n\\times(\\hat n+p)$, the state matrices $(A, B)$ through a contraction.
    """

    X: Float[Array, "n n"]
    W: Float[Array, "m n+p"]
    V: Float[Array, "n n+p"]


def feedthrough_centre(qsr: QSR) -> tuple[np.ndarray, np.ndarray]:
    """A feedthrough $D_0$ deep inside the static dissipative set, and $\\Phi_0 = \\Phi(D_0)$.

    $D_0(\\mu) = (\\mu I - Q)^{-1}S$ maximises $\\Phi(D) - \\mu D^\\top D$ in the
    positive-semidefinite order; the search keeps the $\\mu$ with the largest
    $\\lambda_{\\min}(\\Phi(D_0))/(1 + \\lVert D_0\\rVert_2^2)$. For $Q\\prec0$ and small $\\mu$
    this tends to the classical centre $(-Q)^{-1}S$, but the normalisation keeps $D_0$ of
    order one when that centre runs away as $Q\\to0$ (e.g. $D_0\\approx I$ for passivity and for
    $Q = -10^{-4}I$, where $(-Q)^{-1}S = 5000\\,I$). If any $D$ has $\\Phi(D)\\succ 0$, some
    $\\mu>0$ gives $\\Phi(D_0(\\mu))\\succ0$, since
    $\\Phi(D_0(\\mu))\\succeq\\Phi(D) - \\mu D^\\top D$ for every $D$.

    **Raises** a `ValueError` naming `qsr` when no feedthrough is strictly dissipative: then
    no LTI controller is (the KYP matrix's input block needs $\\Phi(D)\\succ B^\\top PB$).
    """
    best = _centre_search(qsr.Q, qsr.S, qsr.R)
    if best is None:
        # Blocks of very different sizes (a gain bound of 1e-6: Q = -1, R = 1e-12) put the
        # whole static set below the search's round-off floor. Search again with the blocks
        # balanced by powers of two, y = t_y y~ and u = t_u u~ (a congruence), and map back:
        # D = (t_y / t_u) D~ and Phi(D) = Phi~(D~) / t_u^2. Rates that pass unbalanced keep
        # their centre.
        # A zero block (a degenerate cone, Q = 0) takes its unit from S (`cross`).
        for cross in (False, True):
            t_y, t_u, balanced = balanced_blocks(qsr, cross)
            best = _centre_search(balanced.Q, balanced.S, balanced.R)
            if best is not None:
                best = (t_y / t_u * best[0], best[1] / t_u**2)
                break
    if best is None:
        raise ValueError(
            "`qsr` admits no strictly dissipative controller: no feedthrough D gives "
            "D'QD + D'S + S'D + R > 0, which the KYP inequality's input block requires. "
            "Check the signs of S and R (e.g. R too negative for the cone).")
    return best


def _centre_search(Q, S, R):
    """`feedthrough_centre`'s search over $\\mu$: `(D0, Phi0)`, or None when no score clears
    the round-off floor."""
    m = S.shape[0]
    best, best_score = None, 0.0
    for mu in _MUS:
        D0 = np.linalg.solve(mu * np.eye(m) - Q, S)
        Phi = R + S.T @ D0 + D0.T @ S + D0.T @ Q @ D0
        Phi = (Phi + Phi.T) / 2
        score = np.linalg.eigvalsh(Phi)[0] / (1.0 + np.linalg.norm(D0, 2) ** 2)
        if score > best_score:
            best, best_score = (D0, Phi), score
    scale = 1.0 + max(np.abs(M).max(initial=0.0) for M in (Q, S, R))
    return None if best is None or best_score <= 1e-12 * scale else best


@functools.lru_cache(maxsize=64)
def map_constants(qsr: QSR, margin: float) -> tuple[np.ndarray, ...]:
    """`(D0, Phi0, G_Phi, T_u, N)` in float64 for a supply rate and margin (cached)."""
    D0, Phi0 = feedthrough_centre(qsr)
    G_phi = np.linalg.cholesky(Phi0).T  # upper: Phi0 = G_phi' G_phi
    T_u = np.linalg.solve(G_phi.T, (qsr.S + qsr.Q @ D0).T).T  # (S + Q D0) G_phi^{-1}
    N = T_u @ T_u.T - (1.0 - margin) * qsr.Q
    return D0, Phi0, G_phi, T_u, (N + N.T) / 2


class MapRate(eqx.Module):
    """A supply rate ($Q\\preceq0$) with its map constants (`map_constants`) as arrays.

    The maps accept a [`QSR`][dissil_jax.QSR] too, but a `QSR` is a static value: every
    rate compiles its own copy of a jitted training run, and a process that trains under a
    hundred rates holds a hundred executables (their code pages exhausted Linux's default
    limit of 65,530 memory maps after about 70 `fit_ren` or 100 `fit_direct` calls with
    distinct rates, aborting the process). The trainers pass this form instead, whose
    values are traced: one compilation per shape. `units` are the REN map's input units
    (`_ren/map.py: ren_rate`), None for the LTI map; `margin` is static.
    """

    Q: Array
    S: Array
    R: Array
    D0: Array
    Phi0: Array
    G_phi: Array
    T_u: Array
    N: Array
    units: Array | None
    margin: float = eqx.field(static=True)


def map_rate(qsr, margin: float = MARGIN, dtype=None, units=None) -> MapRate:
    """The `MapRate` of a [`QSR`][dissil_jax.QSR] in `dtype` (host, float64 constants);
    a `MapRate` is returned as it is (its margin must be `margin`)."""
    if isinstance(qsr, MapRate):
        if qsr.margin != margin:
            raise ValueError(f"the map's constants were built for margin {qsr.margin}, "
                             f"not {margin}.")
        return qsr
    arrays = (qsr.Q, qsr.S, qsr.R, *map_constants(qsr, margin))
    return MapRate(*(jnp.asarray(M, dtype) for M in arrays),
                   units=None if units is None else jnp.asarray(units, dtype), margin=margin)


def solved_rate(qsr: QSR, margin: float, dtype, build=map_rate) -> tuple[MapRate, Array]:
    """`(rate, k)`: the rate the trainers solve, $(Q,S,R)/\\kappa$ with $\\kappa$ =
    `rate_factor(qsr)` (a power of two, 1 for rates near unit size), as a `MapRate` built
    by `build`, and $\\kappa$ (the storage found is multiplied back by it)."""
    k = rate_factor(qsr)
    return build(scaled_rate(qsr, k), margin, dtype), jnp.asarray(k, dtype)


def check_margin(margin) -> float:
    """`margin` as a float in (0, 1), or a ValueError naming it."""
    if isinstance(margin, jax.core.Tracer) or not (np.ndim(margin) == 0
                                                   and np.isfinite(margin)
                                                   and 0.0 < margin < 1.0):
        raise ValueError(f"`margin` must be a number in (0, 1) (static), got {margin!r}.")
    return float(margin)


# The factorisations and solves run inside the training loop, batched over initialisations:
# they are the loop-based ones of `_linalg.py`, not LAPACK's (which can deadlock there; see
# docs/scaling.md, "Thread-pool deadlocks").
def _upper_chol(M):
    return _linalg.cholesky(M).T  # M = G' G with G upper triangular


def _right_inv(Z, G):
    """$Z G^{-1}$ for upper-triangular $G$."""
    return _linalg.solve_triangular(G, Z.T, lower=False, trans=True).T


def output_map(W: Float[Array, "m n+p"], G_P: Float[Array, "n n"], qsr: QSR | MapRate,
               margin: float = MARGIN):
    """Step 3 of the map, the loop transformation: `(C, D, K_F)` from `W` and the storage's
    upper Cholesky factor $G_P$ ($P = G_P^\\top G_P$).

    $[C\\ \\ D] = [0\\ \\ D_0] + (1-\\varepsilon)ZY^{-1}G$ with $G = \\operatorname{diag}(G_P,
    G_\\Phi)$ and $K_F = \\sqrt{1-\\varepsilon}\\,G_W^{-1}Y^{-1}G$ (module docstring). With
    $\\hat n = 0$ ($G_P$ empty) it maps $W$ ($m\\times p$) onto the static feedthroughs with
    $\\Phi(D)\\succeq\\varepsilon\\Phi_0$, which the REN map uses.
    """
    n, p, dtype = G_P.shape[0], W.shape[1] - G_P.shape[0], W.dtype
    rate = map_rate(qsr, margin, dtype)
    D0, G_phi, T_u, N = (jnp.asarray(M, dtype) for M in (rate.D0, rate.G_phi, rate.T_u,
                                                           rate.N))
    eye = lambda k: jnp.eye(k, dtype=dtype)
    G = jsl.block_diag(G_P, G_phi)
    # (C, D): the loop transformation, Z' N Z < I, Y = I - T'Z invertible since N >= T T'.
    G_W = _upper_chol(eye(n + p) + W.T @ N @ W)
    Z = _right_inv(W, G_W)
    # Y = [[I, 0], [-T_u'Z_x, I - T_u'Z_u]] is block lower triangular: one p x p solve.
    TZ = T_u.T @ Z
    lower = _linalg.solve(eye(p) - TZ[:, n:], jnp.concatenate([TZ[:, :n], eye(p)], 1))
    Y_inv = jnp.concatenate([jnp.concatenate([eye(n), jnp.zeros((n, p), dtype)], 1), lower])
    CD = (1.0 - margin) * Z @ Y_inv @ G
    K_F = jnp.sqrt(1.0 - margin) * _linalg.solve_triangular(G_W, Y_inv @ G, lower=False)
    return CD[:, :n], D0 + CD[:, n:], K_F


def direct_map(theta: DirectParams, qsr: QSR | MapRate, margin: float = MARGIN):
    """The controller and certificate of one parameter $\\theta$ (unbatched; vmap for batches).

    $$\\theta = (X, W, V)\\ \\mapsto\\ (K, P), \\qquad \\mathrm{KYP}(P)\\preceq
    -\\varepsilon\\operatorname{diag}(P,\\Phi_0), \\quad P\\succeq\\varepsilon I,$$

    for every $\\theta$ (steps 1-4 of the module docstring; `docs/concepts.md`). Pure JAX,
    smooth in $\\theta$; `margin` is static.

    **Arguments:** `theta` ([`DirectParams`]), the supply rate `qsr` ($Q\\preceq0$; a
    static `QSR`, or a `MapRate` whose values may be traced) and the margin
    $\\varepsilon\\in(0,1)$.

    **Returns:** `(K, P)`: an `LTIController` and its storage matrix, in `theta`'s dtype.
    """
    X, W, V = theta.X, theta.W, theta.V
    n, dtype = X.shape[0], X.dtype
    p = W.shape[1] - n
    eye = lambda k: jnp.eye(k, dtype=dtype)
    P = X.T @ X + margin * eye(n)
    G_P = _upper_chol(P)
    C, D, K_F = output_map(W, G_P, qsr, margin)
    # (A, B): [A B]' P [A B] = K_F' U'U K_F < K_F' K_F = F(C, D) - eps G'G.
    U = _right_inv(V, _upper_chol(eye(n + p) + V.T @ V))
    AB = _linalg.solve_triangular(G_P, U @ K_F, lower=False)
    return LTIController(AB[:, :n], AB[:, n:], C, D), (P + P.T) / 2


def init_params(key, num_inits: int, n: int, p: int, m: int, scale, dtype) -> DirectParams:
    """`num_inits` parameters: $X = I$ ($P\\approx I$), $W, V$ with i.i.d. $\\mathcal N(0,
    \\text{scale}^2)$ entries (one key per initialisation; `scale` may be traced)."""
    keys = jr.split(key, num_inits)

    def one(k):
        kW, kV = jr.split(k)
        return DirectParams(jnp.eye(n, dtype=dtype), scale * jr.normal(kW, (m, n + p), dtype),
                            scale * jr.normal(kV, (n, n + p), dtype))

    return jax.vmap(one)(keys)
