"""Small dense solves in plain jnp ops (no LAPACK custom calls).

XLA:CPU intermittently deadlocked (all threads parked on futexes) when LAPACK custom calls
(`cholesky`, `cho_solve`) ran inside the vmap-of-scan-of-while_loop of the NMPC closed loop
on our 2-core machine. These loop-based versions avoid custom calls entirely, and compile
fast because the loops are `fori_loop`s rather than unrolled.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def spd_solve(H: Float[Array, "k k"], g: Float[Array, " k"]) -> Float[Array, " k"]:
    """Solve $Hd = g$ for symmetric positive definite $H$ by Cholesky; NaN if $H\\not\\succ 0$."""
    H, g = jnp.asarray(H), jnp.asarray(g)
    k = H.shape[0]
    idx = jnp.arange(k)

    def factor(j, L):
        lj = jnp.where(idx < j, L[j], 0.0)
        dj = H[j, j] - lj @ lj
        ljj = jnp.sqrt(jnp.where(dj > 0, dj, jnp.nan))
        col = (H[:, j] - L @ lj) / ljj
        return L.at[:, j].set(jnp.where(idx > j, col, jnp.where(idx == j, ljj, 0.0)))

    L = jax.lax.fori_loop(0, k, factor, jnp.zeros_like(H))

    def forward(j, z):  # L z = g
        return z.at[j].set((g[j] - jnp.where(idx < j, L[j], 0.0) @ z) / L[j, j])

    z = jax.lax.fori_loop(0, k, forward, jnp.zeros_like(g))

    def backward(i, d):  # L^T d = z, j = k-1..0
        j = k - 1 - i
        return d.at[j].set((z[j] - jnp.where(idx > j, L[:, j], 0.0) @ d) / L[j, j])

    return jax.lax.fori_loop(0, k, backward, jnp.zeros_like(g))


def solve(A: Float[Array, "k k"], b: Float[Array, " k"]) -> Float[Array, " k"]:
    """Solve $Ax = b$ by Gauss-Jordan elimination with partial pivoting (NaN/inf if singular)."""
    A, b = jnp.asarray(A), jnp.asarray(b)
    k = A.shape[0]
    idx = jnp.arange(k)
    M = jnp.concatenate([A, b[:, None]], axis=1)

    def eliminate(j, M):
        piv = jnp.argmax(jnp.where(idx >= j, jnp.abs(M[:, j]), -1.0))
        rj, rp = M[j], M[piv]
        M = M.at[j].set(rp).at[piv].set(rj)
        row = M[j] / M[j, j]
        factors = jnp.where(idx == j, 0.0, M[:, j])
        return (M - factors[:, None] * row[None, :]).at[j].set(row)

    M = jax.lax.fori_loop(0, k, eliminate, M)
    return M[:, -1]
