"""The ADMM iterations of the first-order projection, in the scaled eigenbasis of $\\tilde P$.

The problem is `project`'s (paper eq. 13, Frobenius distance, $\\mathcal M\\preceq-\\varepsilon I$).
With $\\tilde P = V\\Lambda V^\\top$ and the congruence by
$T = \\operatorname{diag}(\\Lambda^{-1/2}, I_p, I_r, \\Lambda^{-1/2})$ after the rotation
$\\operatorname{diag}(V, I, I, V)$, the variables

$$\\hat A = \\Lambda^{1/2}V^\\top AV\\Lambda^{-1/2},\\quad \\hat B = \\Lambda^{1/2}V^\\top B,\\quad
\\hat C = CV\\Lambda^{-1/2},\\quad X = \\Lambda^{-1/2}V^\\top PV\\Lambda^{-1/2}$$

turn $T\\,\\mathcal M(A,B,C,D,P;\\tilde P)\\,T$ into $\\mathcal M(\\hat A,\\hat B,\\hat C,D,X;I)$: the
LMI no longer carries the scale of $\\tilde P$ (whose condition number reaches $10^3$ along a
PGD run, where the unscaled ADMM stalled). The constraint is kept exactly:
$\\mathcal M\\preceq-\\varepsilon I \\iff \\hat{\\mathcal M}\\preceq-\\varepsilon T^2$, so
ADMM splits $Z = -\\hat{\\mathcal M} - \\varepsilon T^2\\succeq0$. The distance becomes a
diagonally weighted one ($\\lVert A-\\tilde A\\rVert_F^2 = \\sum_{ij}\\frac{\\lambda_j}
{\\lambda_i}(\\hat A-\\hat{\\tilde A})_{ij}^2$, and so on), so every block of the $x$-update
is elementwise (for $\\hat C$: elementwise in the eigenbasis of $GG^\\top$, $G = [-S\\ L]$; for
$D$: in the eigenbasis of its constant $mp\\times mp$ Hessian). A per-entry metric in the
original basis (projected Adam's) is not diagonal there; a consensus block carries it
(`solve`'s `metric`), so that every update stays elementwise.

The penalty $\\rho$ follows the residuals (doubled or halved every `ADAPT_EVERY` iterations
when one exceeds the other ten-fold, with the scaled dual rescaled), the iterates are
over-relaxed (`RELAX`), and the PSD projection $\\frac12(Y + Y\\operatorname{sign}Y)$ takes
the matrix sign by a Newton-Schulz iteration with a precomputed per-step scaling
(`SIGN_ALPHAS`): matrix products only, no `eigh` (a batched LAPACK call inside a compiled
loop can deadlock XLA's CPU thread pool; docs/scaling.md, "Thread-pool deadlocks").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._supply import QSR
from .admm_rate import AdmmRate, admm_rate

#: Over-relaxation of the ADMM iterates (1: none; 1.5-1.8 is the usual range).
RELAX = 1.6
#: Iterations between two adaptations of the penalty.
ADAPT_EVERY = 10


def sign_schedule(floor: float = 1e-7, cap: float = 1.7) -> np.ndarray:
    """Per-step scalings $\\alpha_k$ of the Newton-Schulz sign iteration
    $Y\\leftarrow\\frac32\\alpha_kY-\\frac12(\\alpha_kY)^3$.

    The spectrum's magnitudes start in $[\\ell, 1]$ (`floor`); each $\\alpha_k$ is the
    largest with $\\alpha_k u\\le$ `cap` $<\\sqrt3$ that maps the current interval $[\\ell,u]$
    into one with the largest lower end (the two ends balanced), until the interval is
    $[1-10^{-9}, 1]$, then two plain steps: small magnitudes grow about $2.5\\times$ per
    step instead of $1.5\\times$, 23 steps instead of 40 for $\\ell = 10^{-7}$ (18 for $10^{-5}$).
    """
    f = lambda x: 1.5 * x - 0.5 * x ** 3
    lo, hi, out = floor, 1.0, []
    while 1 - lo > 1e-9 and len(out) < 100:
        a_lo, a_hi = 1 / hi, cap / hi
        if f(a_hi * lo) >= f(a_hi * hi):  # the top end is the lower: balance the ends
            for _ in range(200):
                mid = 0.5 * (a_lo + a_hi)
                a_lo, a_hi = (mid, a_hi) if f(mid * lo) < f(mid * hi) else (a_lo, mid)
        a = a_hi
        vals = (f(a * lo), f(a * hi))
        lo, hi = min(vals), (1.0 if a * lo <= 1 <= a * hi else max(vals))
        out.append(a)
    return np.array(out + [1.0, 1.0])  # quadratic convergence: 1e-9 -> 1e-18


SIGN_ALPHAS = sign_schedule()
#: The ADMM iterations' schedule: eigenvalues below 1e-5 |X|_F are left unresolved (an error
#: of at most their size, below the residual tolerance `TOL_FO` = 1e-4 relative); 25% fewer
#: steps than `SIGN_ALPHAS`. The repair's bound uses the full one.
ADMM_SIGN_ALPHAS = sign_schedule(1e-5)


def psd_part(X, alphas=None):
    """The projection of symmetric `X` onto the PSD cone, $\\frac12(X + X\\,\\mathrm{sign}X)$,
    with the sign by the scaled Newton-Schulz iteration (`sign_schedule`, matrix products
    only). Eigenvalues below about $10^{-7}\\lVert X\\rVert_F$ are not resolved; the error on
    each is at most its size."""
    alphas = jnp.asarray(SIGN_ALPHAS if alphas is None else alphas, X.dtype)
    X = (X + X.T) / 2
    nrm = jnp.sqrt(jnp.sum(X * X))
    Y = X / jnp.where(nrm > 0, nrm, 1.0)
    eye = jnp.eye(X.shape[0], dtype=X.dtype)

    def step(Y, a):
        Ya = a * Y
        return 0.5 * Ya @ (3.0 * eye - Ya @ Ya), None

    Y, _ = jax.lax.scan(step, Y, alphas)
    out = 0.5 * (X + X @ Y)
    return (out + out.T) / 2


def sizes(rate: AdmmRate, n: int):
    """$(p, m, r, N)$: the rate's sizes and the LMI's order $N = 2\\hat n + p + r$."""
    return rate.p, rate.m, rate.r, 2 * n + rate.p + rate.r


def lmi_matrix(A, B, C, D, P, P_tilde, qsr: QSR | AdmmRate):
    """$\\mathcal M(A,B,C,D,P;\\tilde P)$ (dense, JAX; the `ConvexifiedLMI` matrix)."""
    n, dtype = A.shape[0], A.dtype
    rate = admm_rate(qsr, dtype)
    p, m, r, N = sizes(rate, n)
    S, R, L = rate.S, rate.R, rate.L
    Z = lambda a, b: jnp.zeros((a, b), dtype)
    rows = [
        [-P, -C.T @ S, C.T @ L, A.T @ P_tilde],
        [-S.T @ C, -D.T @ S - S.T @ D - R, D.T @ L, B.T @ P_tilde],
        [L.T @ C, L.T @ D, -jnp.eye(r, dtype=dtype), Z(r, n)],
        [P_tilde @ A, P_tilde @ B, Z(n, r), P - 2 * P_tilde],
    ]
    M = jnp.concatenate([jnp.concatenate(row, 1) for row in rows], 0)
    return (M + M.T) / 2


def to_eigen(K, lam, V):
    """$(A, B, C, D)$ into the scaled eigenbasis: $(\\hat A, \\hat B, \\hat C, D)$."""
    A, B, C, D = K
    s = jnp.sqrt(lam)
    return ((s[:, None] / s[None, :]) * (V.T @ A @ V), s[:, None] * (V.T @ B),
            (C @ V) / s[None, :], D)


def from_eigen(x, lam, V):
    """The inverse of `to_eigen`."""
    Ah, Bh, Ch, D = x
    s = jnp.sqrt(lam)
    return (V @ ((s[None, :] / s[:, None]) * Ah) @ V.T, V @ (Bh / s[:, None]),
            (Ch * s[None, :]) @ V.T, D)


def scale(target, lam, V, eps, reg, rate: AdmmRate):
    """The scaled problem's data: targets, weights and the margin's diagonal $\\varepsilon T^2$."""
    p, m, r, N = sizes(rate, target[0].shape[0])
    Ah, Bh, Ch, Dt = to_eigen(target, lam, V)
    weights = (lam[None, :] / lam[:, None], 1.0 / lam[:, None], lam[None, :],
               reg * lam[:, None] * lam[None, :])
    one = jnp.ones(p + r, lam.dtype)
    c = eps * jnp.concatenate([1.0 / lam, one, 1.0 / lam])
    return (Ah, Bh, Ch, Dt), weights, c


def unscale(x, lam, V):
    """Back from the scaled eigenbasis: $(A, B, C, D, P)$."""
    s = jnp.sqrt(lam)
    P = V @ (s[:, None] * x[4] * s[None, :]) @ V.T
    return (*from_eigen(x[:4], lam, V), (P + P.T) / 2)


def _x_update(target, weights, W, rate: AdmmRate, rho, floor=None):
    """argmin over the scaled x of the weighted distance + (rho/2)|M(x; I) - W|_F^2
    (+ (rho/2)|F(X) - W_2|_F^2 with `floor = (a, lam, W_2)`, `floor_map`)."""
    Ah, Bh, Ch, Dt = target
    wA, wB, wC, wX = weights
    n, dtype = Ah.shape[0], Ah.dtype
    p, m, r, _ = sizes(rate, n)
    G, g, Qg, h, Qd = rate.G, rate.g, rate.Qg, rate.h, rate.Qd
    S, R, L = rate.S, rate.R, rate.L
    i1, i2, i3 = n, n + p, n + p + r
    W11, W44 = W[:i1, :i1], W[i3:, i3:]
    W21, W31, W41 = W[i1:i2, :i1], W[i2:i3, :i1], W[i3:, :i1]
    W22, W23, W42 = W[i1:i2, i1:i2], W[i1:i2, i2:i3], W[i3:, i1:i2]
    A = (wA * Ah + 2 * rho * W41) / (wA + 2 * rho)
    B = (wB * Bh + 2 * rho * W42) / (wB + 2 * rho)
    # C: per column j, (lam_j I + 2 rho G G') c_j = lam_j ch_j + 2 rho G w_j; in G G''s basis.
    rhs = Qg.T @ (wC * Ch + 2 * rho * G @ jnp.concatenate([W21, W31], 0))
    C = Qg @ (rhs / (wC + 2 * rho * g[:, None]))
    # D: (I + rho H1) vec D = D~ + rho S (V22 + V22') + 2 rho L W23', V22 = -R - W22.
    V22 = -R - W22
    rhs = (Dt + rho * S @ (V22 + V22.T) + 2 * rho * L @ W23.T).reshape(-1)
    D = (Qd @ ((Qd.T @ rhs) / (1 + rho * h))).reshape(m, p)
    # X: mu lam_i lam_j (X - I) + rho (X + W11) + rho (X - 2I - W44) = 0.
    eye = jnp.eye(n, dtype=dtype)
    X = (wX * eye - rho * W11 + rho * (2 * eye + W44)) / (wX + 2 * rho)
    if floor is not None:
        X = _x_floor(wX, W11, W44, rho, *floor)
    return A, B, C, D, (X + X.T) / 2


def floor_map(X, a, lam):
    """The scaled conditioning bound $F(X) = X - a\\operatorname{tr}(\\Lambda X)\\Lambda^{-1}
    \\succeq 0$, i.e. $P\\succeq a\\operatorname{tr}(P)I$ after the congruence
    ($a = \\rho/\\hat n$)."""
    return X - a * jnp.sum(lam * jnp.diag(X)) * jnp.diag(1.0 / lam)


def _x_floor(wX, W11, W44, rho, a, lam, W2):
    """The X-update with the conditioning bound's term: off the diagonal elementwise; the
    diagonal x solves (diag(w + 3 rho) + rho (J'J - I)) x = b + rho J' w2, J = I - a mu lam'
    (mu = 1/lam), whose low-rank part rho [lam mu] C [lam mu]' (C = [[a^2 |mu|^2, -a],
    [-a, 0]]) is inverted by Woodbury (a 2x2 system)."""
    n = W11.shape[0]
    eye = jnp.eye(n, dtype=W11.dtype)
    X = rho * (-W11 + W44 + W2) / (wX + 3 * rho)
    mu, wd = 1.0 / lam, jnp.diag(wX)
    w2 = jnp.diag(W2)
    rhs = wd - rho * jnp.diag(W11) + rho * (2 + jnp.diag(W44)) + rho * (w2 - a * lam * (mu @ w2))
    dg = wd + 3 * rho
    Uk = jnp.stack([lam, mu], 1)  # n x 2
    m2 = mu @ mu
    # C^{-1} / rho for C = rho [[a^2 m2, -a], [-a, 0]]
    Cinv = jnp.array([[0.0, -1.0 / a], [-1.0 / a, -m2]], W11.dtype) / rho
    y = rhs / dg
    Ud = Uk / dg[:, None]
    K = Cinv + Uk.T @ Ud
    det = K[0, 0] * K[1, 1] - K[0, 1] * K[1, 0]
    Kinv = jnp.array([[K[1, 1], -K[0, 1]], [-K[1, 0], K[0, 0]]]) / det
    x = y - Ud @ (Kinv @ (Uk.T @ y))
    return X * (1 - eye) + jnp.diag(x)


def solve(target, weights, c, rate: AdmmRate, *, tol, feas, max_iter, state, floor=0.0, lam=None,
          metric=None):
    """ADMM on the scaled problem (unbatched; vmap for batches).

    **Arguments:** the scaled `target`, `weights` and margin diagonal `c` (`scale`), the
    tolerance on the residuals relative to $1+\\lVert\\hat{\\mathcal M}\\rVert_F$, the
    bound `feas` on the primal residual that keeps the solution strictly feasible, `max_iter`,
    the start `state = (Z, U, Z2, U2, rho)` (zeros for a cold start), and the conditioning
    bound's coefficient `floor` ($P\\succeq\\frac{\\text{floor}}{\\hat n}\\operatorname{tr}(P)I$,
    a second PSD block $Z_2 = F(X)$, `floor_map`; none when 0) with $\\tilde P$'s
    eigenvalues `lam`.

    `metric = (K0, W0, V)` weighs the distance per entry in the original basis,
    $\\tfrac12\\sum W_0\\circ(K-K_0)^2$, which is not elementwise in the scaled eigenbasis.
    A consensus block then carries it: a copy $Y$ of $(A,B,C,D)$ in the original basis with
    the constraint $Y = T^{-1}(\\hat x)$ (`from_eigen`, $V$ the eigenvectors) and its scaled
    dual $U_Y$. Every update stays elementwise: the $\\hat x$-update is the Frobenius one
    with target `to_eigen`$(Y - U_Y)$ (the penalty $\\rho$ on the consensus makes its
    weights `weights` again, since $\\lVert T^{-1}(\\hat x)\\rVert_F^2$ is that weighted
    norm of $\\hat x$), and $Y = (W_0K_0 + \\rho v)/(W_0 + \\rho)$ with $v$ the relaxed
    $T^{-1}(\\hat x) + U_Y$. `target` is then unused and `state` carries `(Y, U_Y)` too.
    The consensus shares the LMI's penalty $\\rho$. Measured alternatives: a fixed 0.3-10
    times $\\rho$ changed the iterations of PGD's own projections (mass-spring chains,
    $\\hat n = 12$) by under 5 %; on random weights spread over $e^{\\pm4}$, $10\\rho$ took
    2.5 times the iterations and $0.1\\rho$ 12 % fewer; a penalty adapted on the consensus
    residuals alone took the same iterations. With weights spread that far ADMM needs
    several times the Frobenius path's iterations (one scalar penalty cannot match every
    entry's curvature); with Adam's own weights along a PGD run, 19 % more (159 against 134
    per projection on the $\\hat n = 12$ chain).

    **Returns:** `(x, state, iterations, converged)`, `x` scaled as `target`.
    """
    dtype = c.dtype
    C_diag = jnp.diag(c)
    n = target[0].shape[0]
    a = floor / n
    wA, wB, wC, wX = weights
    sub = lambda P, Q: tuple(p - q for p, q in zip(P, Q))

    def step(carry):
        Z, U, Z2, U2, rho, cons, _, it, _ = carry
        fl = (a, lam, Z2 + U2) if floor else None
        Y, UY = cons if cons else ((), ())
        if metric is None:
            x = _x_update(target, weights, -C_diag - Z - U, rate, rho, fl)
        else:  # the x-objective divided by rho: the consensus and the LMI both weigh 1
            x = _x_update(to_eigen(sub(Y, UY), lam, metric[2]), (wA, wB, wC, wX / rho),
                          -C_diag - Z - U, rate, 1.0, fl)
        M = lmi_matrix(*x, jnp.eye(n, dtype=dtype), rate)
        K = -M - C_diag  # the constraint asks K >= 0
        K_rel = RELAX * K + (1 - RELAX) * Z
        Z_new = psd_part(K_rel - U, ADMM_SIGN_ALPHAS)
        U_new = U + Z_new - K_rel
        nrm = 1.0 + jnp.sqrt(jnp.sum(M * M))
        primal2 = jnp.sum((Z_new - K) ** 2)
        dual2 = jnp.sum((Z_new - Z) ** 2)
        if floor:
            K2 = floor_map(x[4], a, lam)
            K2_rel = RELAX * K2 + (1 - RELAX) * Z2
            Z2_new = psd_part(K2_rel - U2, ADMM_SIGN_ALPHAS)
            U2 = U2 + Z2_new - K2_rel
            primal2 += jnp.sum((Z2_new - K2) ** 2)
            dual2 += jnp.sum((Z2_new - Z2) ** 2)
            Z2 = Z2_new
        if metric is not None:
            K0, W0, V = metric
            Tx = from_eigen(x[:4], lam, V)
            Tx_rel = tuple(RELAX * t + (1 - RELAX) * y for t, y in zip(Tx, Y))
            Y_new = tuple((w * k + rho * (t + u)) / (w + rho)
                          for w, k, t, u in zip(W0, K0, Tx_rel, UY))
            UY = tuple(u + t - y for u, t, y in zip(UY, Tx_rel, Y_new))
            primal2 += sum(jnp.sum((t - y) ** 2) for t, y in zip(Tx, Y_new))
            dual2 += sum(jnp.sum((y1 - y0) ** 2) for y1, y0 in zip(Y_new, Y))
            cons = (Y_new, UY)
        primal, dual = jnp.sqrt(primal2), rho * jnp.sqrt(dual2)
        done = (primal < jnp.minimum(feas, tol * nrm)) & (dual < tol * nrm)
        adapt = (it % ADAPT_EVERY) == ADAPT_EVERY - 1
        factor = jnp.where(adapt & (primal > 10 * dual), 2.0,
                           jnp.where(adapt & (dual > 10 * primal), 0.5, 1.0))
        if metric is not None:  # the scaled dual follows the penalty
            cons = (cons[0], tuple(u / factor for u in cons[1]))
        return Z_new, U_new / factor, Z2, U2 / factor, rho * factor, cons, x, it + 1, done

    def cond(carry):
        return (carry[7] < max_iter) & ~carry[8]

    Z, U, Z2, U2, rho, *cons = state
    cons = tuple(cons[0]) if cons else ()
    x0 = tuple(jnp.zeros_like(a) for a in target) + (jnp.zeros_like(target[0]),)
    Z, U, Z2, U2, rho, cons, x, it, done = jax.lax.while_loop(
        cond, step, (Z, U, Z2, U2, jnp.asarray(rho, dtype), cons, x0,
                     jnp.zeros((), jnp.int32), jnp.zeros((), bool)))
    return x, (Z, U, Z2, U2, rho) + ((cons,) if cons else ()), it, done


def repair(x, c, qsr: QSR | AdmmRate):
    """Move the scaled solution `x` towards the strictly feasible point
    $x_0 = (0, 0, 0, D_0, I)$ (`admm_rate.static_point`) just enough that $\\hat{\\mathcal M}
    \\preceq -\\operatorname{diag}(c)$: $\\hat{\\mathcal M}$ is affine in $x$, so with
    $\\delta\\ge\\lambda_{\\max}(\\hat{\\mathcal M}(x) + c)$ and $\\gamma = \\min(1, g_0) -
    \\max c$, the point $(1-t)x + tx_0$, $t = \\delta/(\\delta + \\gamma)$, satisfies it. $\\delta$:
    the Frobenius norm of the PSD part (an upper bound of its largest eigenvalue) plus the
    sign iteration's resolution. An approximate ADMM solution thus needs no residual below
    the margin, only an accurate direction. Returns `(x, t)`."""
    n, dtype = x[0].shape[0], x[0].dtype
    rate = admm_rate(qsr, dtype)
    D0, g0 = rate.D0, rate.g0
    A, B, C, D, P = x
    M = lmi_matrix(A, B, C, D, P, jnp.eye(n, dtype=dtype), rate) + jnp.diag(c)
    nrm = jnp.sqrt(jnp.sum(M * M))
    plus = psd_part(M)
    delta = jnp.sqrt(jnp.sum(plus * plus)) + 1e-6 * nrm
    gamma = jnp.minimum(1.0, g0) - jnp.max(c)
    t = jnp.where(gamma > 0, delta / (delta + gamma), 0.0)
    x0 = (jnp.zeros_like(x[0]), jnp.zeros_like(x[1]), jnp.zeros_like(x[2]),
          D0, jnp.eye(n, dtype=dtype))
    return tuple((1 - t) * a + t * b for a, b in zip(x, x0)), t
