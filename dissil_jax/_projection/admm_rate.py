"""The supply rate as the first-order projection's ADMM uses it: arrays, not a static value.

A [`QSR`][dissil_jax.QSR] is hashable and static, so a compiled ADMM that closed over one
was compiled again for every rate, each compilation keeping its code mapped for the life
of the process (a long sweep over rates ran out of Linux's memory maps). `AdmmRate` holds
the rate's values and the host-computed constants of the updates as arrays; only the
sizes $(p, m, r)$ are static, so rates of one shape share one compilation.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._rate_scale import centring
from .._supply import QSR


class AdmmRate(eqx.Module):
    """$(S, R, L)$ with $-Q = LL^\\top$, the constant systems of the $\\hat C$- and
    $D$-updates (`constant_systems`) and the strictly dissipative static gain of `repair`
    (`static_point`), as arrays; `p`, `m`, `r` static. A narrow cone far from zero is held
    about its centre (`centring`): ADMM then projects controllers whose $D$ is moved by
    `offset` $= Q^{-1}S$ (zero for every other rate)."""

    S: jax.Array
    R: jax.Array
    L: jax.Array
    G: jax.Array
    g: jax.Array
    Qg: jax.Array
    h: jax.Array
    Qd: jax.Array
    D0: jax.Array
    g0: jax.Array
    offset: jax.Array
    p: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    r: int = eqx.field(static=True)


def admm_rate(qsr: QSR | AdmmRate, dtype) -> AdmmRate:
    """`qsr` as an `AdmmRate` of `dtype` (host; needs $Q\\preceq0$). An `AdmmRate` passes
    through."""
    if isinstance(qsr, AdmmRate):
        return qsr
    found = centring(qsr)
    offset = np.zeros_like(qsr.S) if found is None else found[0]
    qsr = qsr if found is None else found[1]
    L = qsr.neg_q_factor()
    D0, g0 = static_point(qsr)
    arr = lambda M: jnp.asarray(M, dtype)
    G, g, Qg, h, Qd = (arr(M) for M in constant_systems(qsr))
    return AdmmRate(arr(qsr.S), arr(qsr.R), arr(L), G, g, Qg, h, Qd, arr(D0), arr(g0),
                    arr(offset), qsr.n_in, qsr.n_out, L.shape[1])


@functools.lru_cache(maxsize=32)
def constant_systems(qsr: QSR):
    """Host, float64, cached: the eigenbases of $GG^\\top$ ($\\hat C$-update) and of the
    $D$-update's Hessian $H_1$ (its system is $(I+\\rho H_1)\\operatorname{vec}D = g$)."""
    p, m = qsr.n_in, qsr.n_out
    S, L = qsr.S, qsr.neg_q_factor()
    G = np.concatenate([-S, L], 1)
    g, Qg = np.linalg.eigh(G @ G.T)
    H1 = np.zeros((m * p, m * p))
    for k in range(m * p):  # column k: the gradient along the basis matrix E_k
        E = np.zeros((m, p))
        E.flat[k] = 1.0
        M22 = -E.T @ S - S.T @ E
        H1[:, k] = (-(S @ (M22 + M22.T)) + 2 * L @ (E.T @ L).T).reshape(-1)
    h, Qd = np.linalg.eigh((H1 + H1.T) / 2)
    return G, g, Qg, h, Qd


@functools.lru_cache(maxsize=32)
def static_point(qsr: QSR):
    """A strictly dissipative static gain $D_0 = \\tau S$ (host, cached), with $g_0$ minus the
    largest eigenvalue of $\\begin{bmatrix}-D_0^\\top S-S^\\top D_0-R & D_0^\\top L\\\\
    L^\\top D_0 & -I\\end{bmatrix}$; $\\tau$ of a few maximises $\\min(g_0, 1) / (1 +
    \\lVert D_0\\rVert_F)$, the depth of the point relative to how far `repair` moves towards
    it. $g_0\\le0$ if no $\\tau$ gives a dissipative gain (then `repair` does not move)."""
    S, R, L = qsr.S, qsr.R, qsr.neg_q_factor()
    r = L.shape[1]
    best, score = (np.zeros_like(S), -np.inf), -np.inf
    for tau in np.concatenate([[0.0], np.logspace(-3, 3, 61)]):
        D = tau * S
        M = np.block([[-D.T @ S - S.T @ D - R, D.T @ L], [L.T @ D, -np.eye(r)]])
        g = -np.linalg.eigvalsh((M + M.T) / 2).max()
        value = min(g, 1.0) / (1.0 + np.linalg.norm(D))
        if value > score:
            best, score = (D, g), value
    return best
