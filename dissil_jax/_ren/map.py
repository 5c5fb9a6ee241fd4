"""A direct parameterisation of $(Q,S,R)$-dissipative REN controllers, for every $Q\\preceq0$.

The certificate (`certify.ren_lmi`) asks, for $\\xi = (x, w, \\hat u)$, that
$-M(P,\\Lambda) = \\Psi - G^\\top PG\\succ0$, with $G = [A\\ B_1\\ B_2]$ and

$$\\Psi = \\begin{bmatrix} P & -C_1^\\top\\Lambda & 0\\\\ \\ast & 2\\Lambda - \\Lambda D_{11}
- D_{11}^\\top\\Lambda & -\\Lambda D_{12}\\\\ \\ast & \\ast & R\\end{bmatrix} + H^\\top QH
+ H^\\top SE_u + E_u^\\top S^\\top H,\\qquad H = [C_2\\ D_{21}\\ D_{22}],$$

$E_u$ picking $\\hat u$ out of $\\xi$. The map writes the REN in the implicit form
$Ex^+ = Fx + \\tilde B_1w + \\tilde B_2\\hat u$ with the storage $P = E^\\top\\mathcal P^{-1}E$,
as recurrent equilibrium networks are usually parameterised, and uses
$E^\\top\\mathcal P^{-1}E\\succeq E + E^\\top - \\mathcal P$: the certificate then follows from
one matrix being positive definite, the matrix $\\mathcal M$ over $(x, w, \\hat u, x^+)$ whose
$\\xi$-block is $\\Psi$ with $E + E^\\top - \\mathcal P$ in place of $P$, whose $(x^+,\\xi)$ block
is $[F\\ \\tilde B_1\\ \\tilde B_2]$ and whose $(x^+, x^+)$ block is $\\mathcal P$ (a Schur
complement). The map builds such an $\\mathcal M$ from free parameters and reads the REN off
its blocks, all linearly but for one division by a $p\\times p$ matrix:

1. $D_{22}$ from `W` by the LTI map's loop transformation at order 0
   (`_direct_map.output_map`), so that $\\Phi = R + S^\\top D_{22} + D_{22}^\\top S +
   D_{22}^\\top QD_{22}\\succeq\\varepsilon\\Phi_0$; $T = S + QD_{22}$;
2. the $\\hat u$ column of $\\mathcal M$ is $\\mathcal C = [C_2^\\top T;\\ \\Xi;\\ \\tilde B_2]$
   with $\\Xi = D_{21}^\\top T - \\Lambda D_{12}$ ($\\tilde B_2$ and $\\Lambda D_{12}$ are
   free, in units of the inputs' certified sizes, `input_units`), and its remaining block is
   $\\mathcal M_Z = X^\\top X + \\varepsilon I + \\mathcal C\\tilde\\Phi^{-1}\\mathcal C^\\top$,
   $\\tilde\\Phi = \\Phi - \\tfrac\\varepsilon2\\Phi_0\\succ0$, so that
   $\\mathcal M\\succeq\\operatorname{diag}(\\varepsilon I, \\tfrac\\varepsilon2\\Phi_0)\\succ0$;
3. from the blocks of $\\mathcal M_Z$ over $(x, w, x^+)$, with $C_2$ and $D_{21}$ free:
   $\\mathcal P = \\mathcal M_{x^+x^+}$, $[F\\ \\tilde B_1] = \\mathcal M_{x^+,(x,w)}$,
   $E = \\tfrac12[(\\mathcal M_{xx} - C_2^\\top QC_2)/(1-\\varepsilon) + \\mathcal P] +
   \\tfrac12(Y - Y^\\top)$; with $H_{ww} = \\mathcal M_{ww} - D_{21}^\\top QD_{21}$,
   $\\Lambda = \\operatorname{diag}(H_{ww})/(2(1-\\varepsilon))$ and
   $D_{11} = -\\Lambda^{-1}\\operatorname{tril}(H_{ww}, -1)$ (strictly lower triangular),
   $C_1 = -\\Lambda^{-1}(\\mathcal M_{wx} - D_{21}^\\top QC_2)$ and
   $D_{12} = \\Lambda^{-1}\\Xi_\\mathrm{free}$ (zero unless `direct_input`);
4. $[A\\ B_1\\ B_2] = E^{-1}[F\\ \\tilde B_1\\ \\tilde B_2]$ ($E + E^\\top\\succ0$, so $E$ is
   invertible) and $P = E^\\top\\mathcal P^{-1}E$.

Then $M(P,\\Lambda)\\preceq-\\varepsilon\\operatorname{diag}(P, 2\\Lambda, \\tfrac12\\Phi_0)$
**for every parameter**: the factors $1-\\varepsilon$ in step 3 leave $\\varepsilon P$ and
$2\\varepsilon\\Lambda$ over, and the $\\hat u$ block keeps $\\tfrac\\varepsilon2\\Phi_0$.
Conversely every REN with a certificate of that margin is reached ($E = \\mathcal P = P$).
No step inverts $Q$, so passivity and the degenerate cones ($Q = 0$) and rank-deficient $Q$
are covered. The factorisations are of order $\\hat n$ ($E$, $\\mathcal P$) and $p$
($\\tilde\\Phi$, step 1), not $\\hat n + q$: the width enters through one matrix product.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float

from .. import _linalg
from .._direct_map import MARGIN, MapRate, map_constants, map_rate, output_map
from .._rate_scale import nearest_power_of_two
from .._supply import QSR
from .controller import RENController


class RENParams(eqx.Module):
    """The free parameters of `ren_map` (any real values; vmap for batches).

    - `X`: $(2\\hat n + q)\\times(2\\hat n + q)$, the block $\\mathcal M_Z = X^\\top X +
      \\varepsilon I + \\dots$ over $(x, w, x^+)$;
    - `Y`: $\\hat n\\times\\hat n$, the skew part of $E$;
    - `C2`, `D21`: the output matrices ($m\\times\\hat n$, $m\\times q$);
    - `B`: $\\hat n\\times p$, the implicit input matrix $\\tilde B_2 = EB_2 =
      B\\operatorname{diag}(s)$, $s$ the inputs' units (`input_units`);
    - `W`: $m\\times p$, the feedthrough $D_{22}$ through the loop transformation;
    - `Xi`: $q\\times p$, the neurons' direct input $\\Lambda D_{12}$, which is
      `Xi` times $\\operatorname{diag}(s)$ (used with `direct_input` only).
    """

    X: Float[Array, "2n+q 2n+q"]
    Y: Float[Array, "n n"]
    C2: Float[Array, "m n"]
    D21: Float[Array, "m q"]
    B: Float[Array, "n p"]
    W: Float[Array, "m p"]
    Xi: Float[Array, "q p"]


def ren_map(theta: RENParams, qsr: QSR | MapRate, width: int, activation="tanh",
            margin: float = MARGIN, direct_input: bool = False):
    """The REN controller and certificate of one parameter $\\theta$ (unbatched; vmap for
    batches).

    $$\\theta\\mapsto (K, P, \\Lambda),\\qquad M(P,\\Lambda)\\preceq
    -\\varepsilon\\operatorname{diag}(P, 2\\Lambda, \\tfrac12\\Phi_0)$$

    (steps 1-4 of the module docstring). `qsr` ($Q\\preceq0$: a static `QSR`, or the
    `MapRate` of `ren_rate`, whose values may be traced), `width` $q$, `activation`,
    `margin` $\\varepsilon\\in(0,1)$ and `direct_input` (train $D_{12}$, else
    $D_{12} = 0$) are static.

    **Returns:** `(K, P, lam)`: a [`RENController`][dissil_jax.RENController], its storage
    and the diagonal of its multiplier, in `theta`'s dtype.
    """
    q, n = int(width), theta.Y.shape[0]
    X, C2, D21, B = theta.X, theta.C2, theta.D21, theta.B
    dtype = X.dtype
    rate = ren_rate(qsr, margin, dtype)
    Q, S, R, Phi0 = (jnp.asarray(M, dtype) for M in (rate.Q, rate.S, rate.R, rate.Phi0))
    # 1. the feedthrough: Phi(D22) >= eps Phi0
    _, D22, _ = output_map(theta.W, jnp.zeros((0, 0), dtype), rate, margin)
    Phi = R + S.T @ D22 + D22.T @ S + D22.T @ Q @ D22
    T = S + Q @ D22
    # 2. the u column of the big matrix and the Schur complement over it
    # B and Xi in units of the inputs' certified size (`input_units`)
    assert rate.units is not None  # `ren_rate` sets them
    units = jnp.asarray(rate.units, dtype)
    B = B * units
    xi = theta.Xi * units if direct_input else jnp.zeros_like(theta.Xi)
    col = jnp.concatenate([C2.T @ T, D21.T @ T - xi, B])
    M = X.T @ X + margin * jnp.eye(X.shape[0], dtype=dtype) \
        + col @ _linalg.spd_solve(Phi - 0.5 * margin * Phi0, col.T)
    M = (M + M.T) / 2
    # 3. the REN's blocks
    Pcal, FB1 = M[n + q:, n + q:], M[n + q:, :n + q]
    E = 0.5 * ((M[:n, :n] - C2.T @ Q @ C2) / (1.0 - margin) + Pcal) + 0.5 * (theta.Y - theta.Y.T)
    H_ww = M[n:n + q, n:n + q] - D21.T @ Q @ D21
    lam = jnp.diagonal(H_ww) / (2.0 * (1.0 - margin))
    D11 = -jnp.tril(H_ww, -1) / lam[:, None]
    C1 = -(M[n:n + q, :n] - D21.T @ Q @ C2) / lam[:, None]
    D12 = xi / lam[:, None]
    # 4. the explicit form and the storage
    AB = _linalg.solve(E, jnp.concatenate([FB1, B], 1))
    P = E.T @ _linalg.spd_solve(Pcal, E)
    K = RENController(AB[:, :n], AB[:, n:n + q], AB[:, n + q:], C1, D11, D12, C2, D21, D22,
                      activation=activation)
    return K, (P + P.T) / 2, lam


def ren_rate(qsr: QSR | MapRate, margin: float = MARGIN, dtype=None) -> MapRate:
    """The `MapRate` of `ren_map`: the LTI map's, with the input units (`input_units`); a
    `MapRate` that has them is returned as it is."""
    if isinstance(qsr, MapRate):
        if qsr.units is None:
            raise ValueError("the REN map needs the input units: build its rate with "
                             "`ren_rate`.")
        return map_rate(qsr, margin)
    return map_rate(qsr, margin, dtype, units=input_units(qsr, margin))


def input_units(qsr: QSR, margin: float = MARGIN) -> np.ndarray:
    """The powers of two $s_j\\approx\\sqrt{(\\Phi_0)_{jj}}$ by which `ren_map` multiplies the
    columns of `B` and `Xi` (the inputs' certified sizes; 1 where $(\\Phi_0)_{jj}$ lies
    within a factor 2 of 1).

    The $\\hat u$ column enters $\\mathcal M_Z$ through $\\mathcal C\\tilde\\Phi^{-1}
    \\mathcal C^\\top$ with $\\tilde\\Phi$ of the size of $\\Phi_0$, which is $R$'s: for a
    gain bound $\\gamma$ ($Q = -I$, $R = \\gamma^2I$) that is $\\gamma^2$, and a `B` of order
    one would make $\\mathcal P$ and the storage of order $1/\\gamma^2$. Measured on gain
    bounds $10^{-1}$-$10^{-6}$ (width 4, windows from a state, `benchmarks/bench_ren.py
    --tight`): storages of condition number up to $1.6\\cdot10^{12}$ (beyond what the
    float64 check verifies) without the units, at most $2.9\\cdot10^3$ with them, at lower
    training loss in 10 of 12 cases. A linear change of variables: the
    image of the map is unchanged; powers of two keep the rates of the paper's examples
    ($\\Phi_0 = I$, $1.02$) bit for bit where they were."""
    Phi0 = map_constants(qsr, margin)[1]
    return nearest_power_of_two(np.sqrt(np.maximum(np.diagonal(Phi0), 0.0)))


def init_ren_params(key, num_inits: int, n: int, width: int, p: int, m: int, scale,
                    dtype) -> RENParams:
    """`num_inits` parameters of `ren_map`: $X = I$, $Y = 0$, $\\Xi = 0$, and `C2`, `D21`,
    `B`, `W` with i.i.d. $\\mathcal N(0,\\text{scale}^2)$ entries (one key per
    initialisation; `scale` may be traced).

    At $X = I$ the draw is near $E = \\mathcal P\\approx I$ (so $P\\approx I$) with small
    couplings between the neurons, a REN close to the LTI controller of its output map."""
    q = int(width)

    def one(k):
        kC, kD, kB, kW = jr.split(k, 4)
        return RENParams(jnp.eye(2 * n + q, dtype=dtype), jnp.zeros((n, n), dtype),
                         scale * jr.normal(kC, (m, n), dtype), scale * jr.normal(kD, (m, q), dtype),
                         scale * jr.normal(kB, (n, p), dtype), scale * jr.normal(kW, (m, p), dtype),
                         jnp.zeros((q, p), dtype))

    return jax.vmap(one)(jr.split(key, num_inits))
