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
- $C_1 = -\\Lambda^{-1}M_{wx}$, $D_{12} = 0$;
- $[C_2\\ D_{21}] = C_z$ and $D_{22} = D$.

Then the REN's dissipation matrix (`_ren_certify.ren_lmi`) at $(P,\\Lambda)$ has the
same supply and storage-difference terms as the extended LTI system's KYP matrix at $M$,
except that the successor's storage is $P$ on $x^+$ instead of $M$ on $z^+$, which can only
lower it: $M_{\\mathrm{REN}}(P,\\Lambda)\\preceq -\\varepsilon\\operatorname{diag}(M,\\Phi_0)
\\prec 0$ for every $\\theta$. No step inverts $Q$ (the LTI map's loop transformation
covers $Q\\preceq0$, passivity included), and width $q = 0$ is exactly the LTI map.

$D_{12} = 0$ is the price of reusing that map: a nonzero $D_{12}$ couples $w$ and $\\hat u$
in the storage block, which changes the supply rate's input weight with $\\theta$. The
network still sees the plant output through the state.
"""

from __future__ import annotations

import jax.numpy as jnp

from . import _linalg
from ._direct_map import MARGIN, DirectParams, direct_map, init_params
from ._ren_controller import RENController
from ._supply import QSR


def ren_map(theta: DirectParams, qsr: QSR, width: int, activation="relu",
            margin: float = MARGIN):
    """The REN controller and certificate of one parameter $\\theta$ (unbatched; vmap for
    batches).

    $$\\theta = (X, W, V)\\mapsto (K, P, \\Lambda),\\qquad M_{\\mathrm{REN}}(P,\\Lambda)
    \\preceq-\\varepsilon\\operatorname{diag}(M,\\Phi_0)$$

    (module docstring). `qsr`, `width` $q$, `activation` and `margin` are static; `theta`
    has $X$: $(\\hat n+q)^2$, $W$: $m\\times(\\hat n+q+p)$, $V$: $(\\hat n+q)\\times
    (\\hat n+q+p)$.

    **Returns:** `(K, P, lam)`: a [`RENController`][dissil_jax.RENController], its storage
    and the diagonal of its multiplier, in `theta`'s dtype.
    """
    q = int(width)
    nz = theta.X.shape[0]
    n = nz - q
    Kz, M = direct_map(theta, qsr, margin)
    G_M = _linalg.cholesky(M).T  # M = G_M' G_M; the LTI map's [A_z B_z] = G_M^{-1} U K_F
    UK = (G_M @ jnp.concatenate([Kz.A, Kz.B], 1))[:n]
    P = (M[:n, :n] + M[:n, :n].T) / 2
    G_P = _linalg.cholesky(P).T
    Xi = _linalg.solve_triangular(G_P, UK, lower=False)  # [A B1 B2]
    lam = jnp.diagonal(M[n:, n:]) / 2
    D11 = -jnp.tril(M[n:, n:], -1) / lam[:, None]
    C1 = -M[n:, :n] / lam[:, None]
    p = Kz.B.shape[1]
    K = RENController(Xi[:, :n], Xi[:, n:nz], Xi[:, nz:], C1, D11,
                      jnp.zeros((q, p), M.dtype), Kz.C[:, :n], Kz.C[:, n:], Kz.D,
                      activation=activation)
    return K, P, lam


def init_ren_params(key, num_inits: int, n: int, width: int, p: int, m: int, scale,
                    dtype) -> DirectParams:
    """`num_inits` parameters of [`ren_map`]: the LTI map's initial draw at order
    $\\hat n + q$ ($X = I$, $W$ and $V$ i.i.d. $\\mathcal N(0,\\text{scale}^2)$)."""
    return init_params(key, num_inits, n + int(width), p, m, scale, dtype)
