"""Small dense factorisations and solves in plain jnp ops: no LAPACK custom calls.

**Why.** On CPU, jaxlib runs a *batched* LAPACK call (Cholesky, LU, QR, `eigh`, SVD, the
triangular solve: any of them under `vmap`) through a `ParallelBatchMap` that splits the
batch into tasks on XLA's own intra-op thread pool and then *blocks* a pool worker until
they finish. Inside a compiled loop (`lax.while_loop`, `scan`) the custom call itself runs
on such a worker, so when every worker is waiting that way nobody runs the queued tasks and
the program hangs for ever, with all threads parked (thread-pool re-entrancy). It is
intermittent and depends on the batch size, the matrix size and the load: it hung
`fit_direct` at $\\hat n = 20$ with 32 initialisations and the NMPC expert's closed loop on
a 2-core machine. The explanation and the rule (no batched LAPACK call inside a loop, at any
size) are in `docs/scaling.md` ("Thread-pool deadlocks").

The functions here are written with `lax.fori_loop`s over rows or columns (so they compile
in constant time in the size) and are differentiable in forward and reverse mode: the
solves through `lax.custom_linear_solve` (whose derivative in the matrix comes from the
plain matrix product), the Cholesky factor through its `custom_jvp`
$\\dot L = L\\,\\Phi(L^{-1}\\dot ML^{-\\top})$. They cost $O(k^2)$ small kernels each, which
is fine for the controller sizes here ($k\\lesssim 130$).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def _cholesky_loop(M):
    k = M.shape[0]
    idx = jnp.arange(k)

    def column(j, L):
        lj = jnp.where(idx < j, L[j], 0.0)
        dj = M[j, j] - lj @ lj
        ljj = jnp.sqrt(jnp.where(dj > 0, dj, jnp.nan))
        col = (M[:, j] - L @ lj) / ljj
        return L.at[:, j].set(jnp.where(idx > j, col, jnp.where(idx == j, ljj, 0.0)))

    return jax.lax.fori_loop(0, k, column, jnp.zeros_like(M))


def _lower_loop(L, B):
    """$L^{-1}B$ for lower-triangular $L$ (forward substitution, row by row)."""
    k = L.shape[0]
    idx = jnp.arange(k)

    def row(j, X):
        return X.at[j].set((B[j] - jnp.where(idx < j, L[j], 0.0) @ X) / L[j, j])

    return jax.lax.fori_loop(0, k, row, jnp.zeros_like(B))


def _upper_loop(U, B):
    """$U^{-1}B$ for upper-triangular $U$ (back substitution)."""
    k = U.shape[0]
    idx = jnp.arange(k)

    def row(i, X):
        j = k - 1 - i
        return X.at[j].set((B[j] - jnp.where(idx > j, U[j], 0.0) @ X) / U[j, j])

    return jax.lax.fori_loop(0, k, row, jnp.zeros_like(B))


def solve_triangular(T: Float[Array, "k k"], B: Float[Array, "k r"], *, lower: bool,
                     trans: bool = False) -> Float[Array, "k r"]:
    """$T^{-1}B$ (or $T^{-\\top}B$ with `trans`) for triangular $T$; only that triangle is read.

    Differentiable in $T$ and $B$ (`lax.custom_linear_solve`); `B` may be a vector.
    """
    T, B = jnp.asarray(T), jnp.asarray(B)
    T = jnp.tril(T) if lower else jnp.triu(T)
    if trans:
        T, lower = T.T, not lower
    fwd, bwd = (_lower_loop, _upper_loop) if lower else (_upper_loop, _lower_loop)
    return _custom_solve(T, B, fwd, bwd)


@jax.custom_jvp
def cholesky(M: Float[Array, "k k"]) -> Float[Array, "k k"]:
    """Lower Cholesky factor $L$, $M = LL^\\top$, of the symmetric part of `M`.

    NaN where $M\\not\\succ0$ (as `jnp.linalg.cholesky`).
    """
    M = jnp.asarray(M)
    return _cholesky_loop((M + M.T) / 2)


@cholesky.defjvp
def _cholesky_jvp(primals, tangents):
    (M,), (dM,) = primals, tangents
    L = cholesky(M)
    dM = (dM + dM.T) / 2
    # L^{-1} dM L^{-T}, then Phi: the lower triangle with half the diagonal.
    S = solve_triangular(L, solve_triangular(L, dM, lower=True).T, lower=True)
    phi = jnp.tril(S) - 0.5 * jnp.diag(jnp.diag(S))
    return L, L @ phi


def _gauss_jordan(A, B):
    """$A^{-1}B$ by Gauss-Jordan elimination with partial pivoting (NaN/inf if singular)."""
    k = A.shape[0]
    idx = jnp.arange(k)
    M = jnp.concatenate([A, B], axis=1)

    def eliminate(j, M):
        piv = jnp.argmax(jnp.where(idx >= j, jnp.abs(M[:, j]), -1.0))
        rj, rp = M[j], M[piv]
        M = M.at[j].set(rp).at[piv].set(rj)
        row = M[j] / M[j, j]
        factors = jnp.where(idx == j, 0.0, M[:, j])
        return (M - factors[:, None] * row[None, :]).at[j].set(row)

    return jax.lax.fori_loop(0, k, eliminate, M)[:, k:]


def solve(A: Float[Array, "k k"], B: Float[Array, "k ..."]) -> Float[Array, "k ..."]:
    """$A^{-1}B$ for a square $A$ (partial pivoting; NaN/inf if singular); `B` a vector or
    a matrix. Differentiable in $A$ and $B$ (`lax.custom_linear_solve`)."""
    A, B = jnp.asarray(A), jnp.asarray(B)
    return _custom_solve(A, B, _gauss_jordan, _gauss_jordan)


def _custom_solve(M, B, fwd, bwd):
    """$M^{-1}B$ through `lax.custom_linear_solve`, so differentiable in $M$ and $B$:
    `fwd(M, b)` solves with $M$, `bwd(M^T, b)` with its transpose; `B` a vector or a matrix."""
    vec = B.ndim == 1
    B = B[:, None] if vec else B
    M0 = jax.lax.stop_gradient(M)
    X = jax.lax.custom_linear_solve(lambda x: M @ x, B, solve=lambda _, b: fwd(M0, b),
                                    transpose_solve=lambda _, b: bwd(M0.T, b))
    return X[:, 0] if vec else X


def spd_solve(H: Float[Array, "k k"], g: Float[Array, "k ..."]) -> Float[Array, "k ..."]:
    """$H^{-1}g$ for symmetric positive definite $H$ by Cholesky; NaN if $H\\not\\succ0$."""
    L = cholesky(H)
    return solve_triangular(L, solve_triangular(L, g, lower=True), lower=True, trans=True)
