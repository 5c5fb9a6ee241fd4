"""A direct parameterisation of $(Q,S,R)$-dissipative REN controllers, for every $Q\\preceq0$.

It reuses the LTI map of `_direct_map.py` on an **extended state** $z = (x, w)$ of size
$\\hat n + q$. That map returns, for free parameters $\\theta$, a storage
$M = X^\\top X + \\varepsilon I$ (size $\\hat n + q$), an output map $[C_z\\ D]$ and a
contraction $U$ with

$$[A_z\\ B_z]^\\top M[A_z\\ B_z] - \\operatorname{diag}(M, 0) - (\\text{supply of }
[C_z\\ D]) \\preceq -\\varepsilon\\operatorname{diag}(M,\\Phi_0),\\qquad
G_M[A_z\\ B_z] = UK_F.$$

The REN is read off $M$ and the map's output:

- storage $P = M_{xx}$ and $[A\\ B_1\\ B_2] = G_P^{-1}(UK_F)_{1:\\hat n}$ ($G_P^\\top G_P = P$),
  so that $[A\\ B_1\\ B_2]^\\top P[A\\ B_1\\ B_2] = K_F^\\top U_{1:\\hat n}^\\top
  U_{1:\\hat n}K_F \\preceq K_F^\\top U^\\top UK_F$;
- the sector multiplier and the explicit layer from the block $M_{ww}$, split into its
  diagonal and strictly lower part: $\\Lambda = \\tfrac12\\operatorname{diag}(M_{ww})\\succ0$,
  $D_{11} = -\\Lambda^{-1}\\operatorname{tril}(M_{ww},-1)$ (strictly lower triangular), so
  $2\\Lambda - \\Lambda D_{11} - D_{11}^\\top\\Lambda = M_{ww}$;
- $C_1 = -\\Lambda^{-1}M_{wx}$;
- $[C_2\\ D_{21}] = C_z$ and $D_{22} = D$ (for $D_{12} = 0$; see below for $D_{12}\\ne0$).

With $D_{12} = 0$, the REN's dissipation matrix (`certify.ren_lmi`) at $(P,\\Lambda)$ has the
same supply and storage-difference terms as the extended LTI system's KYP matrix at $M$,
except that the successor's storage is $P$ on $x^+$ instead of $M$ on $z^+$, which can only
lower it: $M_{\\mathrm{REN}}(P,\\Lambda)\\preceq -\\varepsilon\\operatorname{diag}(M,\\Phi_0)
\\prec 0$ for every $\\theta$. No step inverts $Q$ (the LTI map's loop transformation
covers $Q\\preceq0$, passivity included).

**The neurons' direct input $D_{12}$.** It adds the block $N = [0;\\ -\\Lambda D_{12}]$
between $z$ and $\\hat u$. The congruence $T = \\bigl[\\begin{smallmatrix}I & -M^{-1}N\\\\
0 & I\\end{smallmatrix}\\bigr]$ removes it at the price of an input weight
$R - N^\\top M^{-1}N$ and a feedthrough $D' = D - C_zM^{-1}N$. With
$N = G_M^\\top[0;\\ \\tilde N]$, $\\tilde N = \\sqrt\\rho\\,U_NG_\\Phi$ and a contraction
$U_N = Y(I + Y^\\top Y)^{-1/2}$, $N^\\top M^{-1}N = \\tilde N^\\top\\tilde N\\preceq\\rho\\Phi_0$, so
running the LTI map for the fixed rate $(Q, S, R - \\rho\\Phi_0)$ ($\\rho\\in[0,1)$, the
`input_share`; $\\Phi_0$ the LTI map's feedthrough slack, so the rate stays strictly
feasible) certifies the REN; then $D_{22} = D' + C_zM^{-1}N$ and
$B_2 = B_2' + [A\\ B_1]M^{-1}N$. $\\rho = 0$ gives $D_{12} = 0$ and, at width 0, exactly the
LTI map.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float

from .. import _linalg
from .._direct_map import MARGIN, DirectParams, direct_map, feedthrough_centre, init_params
from .._supply import QSR
from .controller import RENController


class RENParams(eqx.Module):
    """The free parameters of `ren_map`: the LTI map's $(X, W, V)$ at order
    $\\hat n + q$ (`lti`) and `Y` ($q\\times p$), the neurons' direct input."""

    lti: DirectParams
    Y: Float[Array, "q p"]


@functools.lru_cache(maxsize=64)
def _shared_input(qsr: QSR, share: float) -> tuple[QSR, np.ndarray]:
    """The supply rate $(Q, S, R - \\rho\\Phi_0)$ handed to the LTI map and $G_\\Phi$
    ($\\Phi_0 = G_\\Phi^\\top G_\\Phi$), with $\\Phi_0$ the LTI map's feedthrough slack."""
    _, Phi0 = feedthrough_centre(qsr)
    G_phi = np.linalg.cholesky(Phi0).T
    if share == 0.0:
        return qsr, G_phi
    return QSR(qsr.Q, qsr.S, qsr.R - share * Phi0), G_phi


def ren_map(theta: RENParams, qsr: QSR, width: int, activation="tanh",
            margin: float = MARGIN, input_share: float = 0.0):
    """The REN controller and certificate of one parameter $\\theta$ (unbatched; vmap for
    batches).

    $$\\theta = (X, W, V, Y)\\mapsto (K, P, \\Lambda),\\qquad M_{\\mathrm{REN}}(P,\\Lambda)
    \\prec 0$$

    (module docstring). `qsr`, `width` $q$, `activation`, `margin` and `input_share`
    $\\rho\\in[0,1)$ are static.

    **Returns:** `(K, P, lam)`: a [`RENController`][dissil_jax.RENController], its storage
    and the diagonal of its multiplier, in `theta`'s dtype.
    """
    q = int(width)
    X = theta.lti.X
    nz, dtype = X.shape[0], X.dtype
    n = nz - q
    qsr_lti, G_phi = _shared_input(qsr, float(input_share))
    Kz, M = direct_map(theta.lti, qsr_lti, margin)
    G_M = _linalg.cholesky(M).T  # M = G_M' G_M; the LTI map's [A_z B_z] = G_M^{-1} U K_F
    UK = (G_M @ jnp.concatenate([Kz.A, Kz.B], 1))[:n]
    P = (M[:n, :n] + M[:n, :n].T) / 2
    G_P = _linalg.cholesky(P).T
    Xi = _linalg.solve_triangular(G_P, UK, lower=False)  # [A B1 B2'] of the transformed loop
    lam = jnp.diagonal(M[n:, n:]) / 2
    D11 = -jnp.tril(M[n:, n:], -1) / lam[:, None]
    C1 = -M[n:, :n] / lam[:, None]
    p = Kz.B.shape[1]
    # The neurons' direct input: N = [0; -Lam D12] = G_M' [0; Nt], Nt = sqrt(rho) U_N G_phi
    # with |U_N| < 1, so N' M^{-1} N = Nt'Nt <= rho Phi0 and R - N'M^{-1}N >= R - rho Phi0.
    G_Y = _linalg.cholesky(jnp.eye(p, dtype=dtype) + theta.Y.T @ theta.Y).T
    U_N = _linalg.solve_triangular(G_Y, theta.Y.T, lower=False, trans=True).T
    Nt = jnp.sqrt(jnp.asarray(input_share, dtype)) * U_N @ jnp.asarray(G_phi, dtype)
    D12 = -(G_M[n:, n:].T @ Nt) / lam[:, None]
    MinvN = _linalg.solve_triangular(G_M, jnp.concatenate([jnp.zeros((n, p), dtype), Nt]),
                                     lower=False)  # M^{-1} N = G_M^{-1} [0; Nt]
    # undo the congruence T = [[I, -M^{-1}N], [0, I]]: D = D' + C_z M^{-1}N, B = B' + Xi_z M^{-1}N
    D22 = Kz.D + Kz.C @ MinvN
    B2 = Xi[:, nz:] + Xi[:, :nz] @ MinvN
    K = RENController(Xi[:, :n], Xi[:, n:nz], B2, C1, D11, D12, Kz.C[:, :n], Kz.C[:, n:], D22,
                      activation=activation)
    return K, P, lam


def init_ren_params(key, num_inits: int, n: int, width: int, p: int, m: int, scale,
                    dtype) -> RENParams:
    """`num_inits` parameters of `ren_map`: the LTI map's initial draw at order
    $\\hat n + q$ ($X = I$, $W$ and $V$ i.i.d. $\\mathcal N(0,\\text{scale}^2)$) and $Y$
    i.i.d. $\\mathcal N(0,\\text{scale}^2)$."""
    k1, k2 = jr.split(key)
    Y = scale * jr.normal(k2, (num_inits, int(width), p), dtype)
    return RENParams(init_params(k1, num_inits, n + int(width), p, m, scale, dtype), Y)
