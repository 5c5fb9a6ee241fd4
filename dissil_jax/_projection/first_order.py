"""A first-order projection onto the convexified dissipative set (ADMM, pure JAX).

It solves the problem of [`project`][dissil_jax.project] (paper eq. 13, Frobenius distance):

$$\\min_{A,B,C,D,P}\\ \\tfrac12\\lVert(A,B,C,D)-(\\tilde A,\\tilde B,\\tilde C,\\tilde D)
\\rVert_F^2 + \\tfrac\\mu2\\lVert P-\\tilde P\\rVert_F^2 \\quad\\text{s.t.}\\quad
\\mathcal M(A,B,C,D,P;\\tilde P)\\preceq-\\varepsilon I,$$

with $\\mathcal M$ the convexified KYP matrix (`ConvexifiedLMI`, built here densely in JAX
from the matrices). ADMM on the splitting $Z = -\\mathcal M(x) - \\varepsilon I\\succeq0$
(scaled dual $U$):

- **$x$-update** in closed form, block by block: $A$ and $B$ appear only in
  $A^\\top\\tilde P$ and $B^\\top\\tilde P$, so $(I + 2\\rho\\tilde P^2)[A\\ B] =
  [\\tilde A\\ \\tilde B] + 2\\rho\\tilde P\\,T_{4,12}$ (one $\\hat n\\times\\hat n$ Cholesky
  per projection); $C$ only in $C^\\top[-S\\ \\ L]$ (an $m\\times m$ system), $D$ in the
  $(2,2)$ and $(2,3)$ blocks (an $mp\\times mp$ system, constant), $P$ in the diagonal
  blocks (a scalar formula);
- **$Z$-update**: the projection of a symmetric matrix onto the PSD cone,
  $\\tfrac12(X + X\\operatorname{sign}X)$, with the matrix sign by the Newton-Schulz
  iteration $Y\\leftarrow\\tfrac12Y(3I-Y^2)$: matrix products only. Not `eigh`: on CPU a
  batched `eigh` inside a loop can deadlock XLA's thread pool (docs/scaling.md,
  "Thread-pool deadlocks"); every factorisation here is loop-based (`_linalg.py`).

The solver aims at a margin `margin_fo` larger than $\\varepsilon$, so that an approximate
solution (residual below that margin) still satisfies the strict LMI. Its result is then
checked exactly in float64 on the host, and a row that fails goes to Clarabel.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import _linalg, _outcome
from .._controller import LTIController
from .._sdp import lmi as _lmi, sdp as _sdp
from .._sdp.indefinite import is_indefinite
from .._supply import QSR

#: Newton-Schulz steps of the PSD projection: eigenvalues above ~1e-6 of the matrix's
#: Frobenius norm reach their sign (a factor 1.5 per step while small, then quadratic).
SIGN_STEPS = 40


def _sizes(qsr: QSR, n: int):
    L = qsr.neg_q_factor()
    p, m, r = qsr.n_in, qsr.n_out, L.shape[1]
    return p, m, r, 2 * n + p + r


def lmi_matrix(A, B, C, D, P, P_tilde, qsr: QSR):
    """$\\mathcal M(A,B,C,D,P;\\tilde P)$ (dense, JAX; the `ConvexifiedLMI` matrix)."""
    n, dtype = A.shape[0], A.dtype
    p, m, r, N = _sizes(qsr, n)
    S, R, L = (jnp.asarray(M, dtype) for M in (qsr.S, qsr.R, qsr.neg_q_factor()))
    Z = lambda a, b: jnp.zeros((a, b), dtype)
    rows = [
        [-P, -C.T @ S, C.T @ L, A.T @ P_tilde],
        [-S.T @ C, -D.T @ S - S.T @ D - R, D.T @ L, B.T @ P_tilde],
        [L.T @ C, L.T @ D, -jnp.eye(r, dtype=dtype), Z(r, n)],
        [P_tilde @ A, P_tilde @ B, Z(n, r), P - 2 * P_tilde],
    ]
    M = jnp.concatenate([jnp.concatenate(row, 1) for row in rows], 0)
    return (M + M.T) / 2


def psd_part(X, steps: int = SIGN_STEPS):
    """The projection of symmetric `X` onto the PSD cone, $\\frac12(X + X\\,\\mathrm{sign}X)$,
    by Newton-Schulz (matrix products only). Eigenvalues below about $1.5^{-\\text{steps}}
    \\lVert X\\rVert_F$ are not resolved; the error on each is at most its size."""
    X = (X + X.T) / 2
    nrm = jnp.sqrt(jnp.sum(X * X))
    Y = X / jnp.where(nrm > 0, nrm, 1.0)
    eye = jnp.eye(X.shape[0], dtype=X.dtype)
    Y = jax.lax.fori_loop(0, steps, lambda _, Y: 0.5 * Y @ (3.0 * eye - Y @ Y), Y)
    out = 0.5 * (X + X @ Y)
    return (out + out.T) / 2


@functools.lru_cache(maxsize=32)
def _d_system(qsr: QSR, rho: float):
    """The constant $mp\\times mp$ inverse of the $D$-update (host, float64, cached)."""
    p, m = qsr.n_in, qsr.n_out
    S, L = qsr.S, qsr.neg_q_factor()
    H = np.eye(m * p)
    for k in range(m * p):  # column k of the quadratic form: image of the basis matrix E_k
        E = np.zeros((m, p))
        E.flat[k] = 1.0
        M22 = -E.T @ S - S.T @ E  # d/dD of the (2,2) block
        M23 = E.T @ L
        # gradient of (rho/2)|M22|^2 + rho|M23|^2 in D along the basis
        G = -(S @ (M22 + M22.T)) + 2 * L @ M23.T
        H[:, k] += rho * G.reshape(-1)
    return np.linalg.inv(H)


def _x_update(target, P_tilde, T, qsr, rho, reg, chol_AB, D_inv):
    """argmin_x f(x) + (rho/2)|M(x) - T|_F^2 (blocks of T as in `lmi_matrix`)."""
    At, Bt, Ct, Dt = target
    n, dtype = At.shape[0], At.dtype
    p, m, r, _ = _sizes(qsr, n)
    S, R, L = (jnp.asarray(M, dtype) for M in (qsr.S, qsr.R, qsr.neg_q_factor()))
    i1, i2, i3 = n, n + p, n + p + r
    T11, T12, T13, T14 = T[:i1, :i1], T[:i1, i1:i2], T[:i1, i2:i3], T[:i1, i3:]
    T22, T23, T24, T44 = T[i1:i2, i1:i2], T[i1:i2, i2:i3], T[i1:i2, i3:], T[i3:, i3:]
    # A, B: (I + 2 rho P~^2) [A B] = [A~ B~] + 2 rho P~ [T14' T24'].
    rhs = jnp.concatenate([At, Bt], 1) + 2 * rho * P_tilde @ jnp.concatenate([T14.T, T24.T], 1)
    AB = _linalg.solve_triangular(chol_AB, _linalg.solve_triangular(chol_AB, rhs, lower=True),
                                  lower=True, trans=True)
    # C: (I + 2 rho G G') C = C~ + 2 rho G [T12 T13]', G = [-S L].
    G = jnp.concatenate([-S, L], 1)
    C = _linalg.solve(jnp.eye(m, dtype=dtype) + 2 * rho * G @ G.T,
                      Ct + 2 * rho * G @ jnp.concatenate([T12, T13], 1).T)
    # D: the constant mp x mp system (gradient of the (2,2) and (2,3) terms).
    W22 = -R - T22
    g = Dt + rho * S @ (W22 + W22.T) + 2 * rho * L @ T23.T
    D = (jnp.asarray(D_inv, dtype) @ g.reshape(-1)).reshape(m, p)
    # P: mu (P - P~) + rho (P + T11) + rho (P - 2 P~ - T44) = 0.
    P = (reg * P_tilde - rho * T11 + rho * (2 * P_tilde + T44)) / (reg + 2 * rho)
    return AB[:, :n], AB[:, n:], C, D, (P + P.T) / 2


def admm(target, P_tilde, qsr: QSR, *, margin, reg, rho, tol, max_iter, state=None):
    """ADMM for one projection (unbatched; vmap for batches).

    **Arguments:** `target` `(A~, B~, C~, D~)`, $\\tilde P$, the supply rate (static),
    the margin aimed at (`margin`), the proximal weight $\\mu$ (`reg`), the penalty $\\rho$,
    the tolerance on the primal and dual residuals relative to $1+\\lVert\\mathcal M\\rVert_F$,
    `max_iter`, and an optional warm start `state = (Z, U)`.

    **Returns:** `((A, B, C, D, P), (Z, U), iterations, converged)`.
    """
    At = target[0]
    n, dtype = At.shape[0], At.dtype
    *_, N = _sizes(qsr, n)
    eye_N = jnp.eye(N, dtype=dtype)
    chol_AB = _linalg.cholesky(jnp.eye(n, dtype=dtype) + 2 * rho * P_tilde @ P_tilde)
    D_inv = _d_system(qsr, float(rho))
    if state is None:
        state = (jnp.zeros((N, N), dtype), jnp.zeros((N, N), dtype))

    def step(c):
        Z, U, _, it, _ = c
        x = _x_update(target, P_tilde, -margin * eye_N - Z - U, qsr, rho, reg, chol_AB, D_inv)
        M = lmi_matrix(*x, P_tilde, qsr)
        Z_new = psd_part(-M - margin * eye_N - U)
        U_new = U + M + margin * eye_N + Z_new
        scale = 1.0 + jnp.sqrt(jnp.sum(M * M))
        primal = jnp.sqrt(jnp.sum((M + margin * eye_N + Z_new) ** 2))
        dual = rho * jnp.sqrt(jnp.sum((Z_new - Z) ** 2))
        done = (primal < tol * scale) & (dual < tol * scale)
        return Z_new, U_new, x, it + 1, done

    def cond(c):
        return (c[3] < max_iter) & ~c[4]

    x0 = tuple(jnp.zeros_like(a) for a in target) + (jnp.zeros((n, n), dtype),)
    Z, U, x, it, done = jax.lax.while_loop(
        cond, step, (*state, x0, jnp.zeros((), jnp.int32), jnp.zeros((), bool)))
    return x, (Z, U), it, done


#: Defaults of the first-order path: the margin aimed at (above `project`'s eps, so that a
#: solution with residual below it still satisfies the strict LMI), the residual tolerance
#: relative to 1 + |M|_F, the iteration budget and the penalty.
MARGIN_FO, TOL_FO, MAX_ITER_FO, RHO_FO = 1e-4, 1e-6, 5000, 1.0


_SKIPPED, _UNCHANGED, _SOLVED = (_outcome.code(n) for n in ("skipped", "unchanged", "solved"))


def _host_check(A, B, C, D, P, tA, tB, tC, tD, P_ref, active, shard, *, qsr, has_ref, eps,
                reg, refine, shards, fallback):
    """pure_callback target: the exact float64 check of the ADMM results, Clarabel for the
    rows that fail it (`fallback`, `_projection._host_batch`), codes as `project`'s."""
    dtype = np.asarray(A).dtype
    batch = A.shape[:-2]
    flat = lambda M: np.asarray(M, np.float64).reshape((-1,) + M.shape[len(batch):])
    sol = [flat(M) for M in (A, B, C, D, P)]
    tgt = [flat(M) for M in (tA, tB, tC, tD)]
    ref = flat(P_ref)
    act = np.asarray(active).reshape(-1)
    out = [t.copy() for t in tgt] + [ref.copy()]
    codes = np.full(act.shape[0], _SKIPPED, np.int32)
    todo = np.nonzero(act)[0]
    if has_ref and len(todo):  # as Clarabel's path: a certified target stays unchanged
        gA, gB, gC, gD = (t[todo] for t in tgt)
        keep = _lmi.certified(gA, gB, gC, gD, qsr, ref[todo])
        codes[todo[keep]] = _UNCHANGED
        todo = todo[~keep]
    if len(todo):
        rounded = [_lmi.cast(M[todo], dtype) for M in sol]
        finite = np.all([np.all(np.isfinite(M), axis=(-2, -1)) for M in rounded], axis=0)
        rA, rB, rC, rD, rP = rounded
        ok = finite & _lmi.certified(rA, rB, rC, rD, qsr, rP)
        for o, M in zip(out, rounded):
            o[todo[ok]] = M[ok]
        codes[todo[ok]] = _SOLVED
        bad = todo[~ok]
        if len(bad):
            ones = [np.ones_like(t[bad]) for t in tgt]
            # C0, D0: the linearisation point of an indefinite Q, which this path refuses
            res = fallback(
                *(t[bad] for t in tgt), ref[bad], *ones, np.ones(len(bad), bool),
                tgt[2][bad], tgt[3][bad], np.zeros(len(bad), np.int32), qsr=qsr,
                has_ref=has_ref, eps=eps, reg=reg, refine=refine, shards=shards)
            for o, M in zip(out, res[:5]):
                o[bad] = M
            codes[bad] = res[5]
            with _FALLBACK_LOCK:
                FALLBACKS["rows"] += len(bad)
    return (*(o.reshape(batch + o.shape[1:]).astype(dtype) for o in out),
            codes.reshape(batch))


#: Rows the first-order path handed to Clarabel (tests and benchmarks read it).
FALLBACKS = {"rows": 0}
_FALLBACK_LOCK = __import__("threading").Lock()


def project_one(K, P_ref, W, active, K_ref, *, qsr: QSR, eps, reg, refine, fallback,
                margin=None, tol=None, max_iter=None, rho=None):
    """The unbatched first-order projection (vmap for batches): ADMM at $\\tilde P$ =
    `P_ref`, or from $\\tilde P = I$ with `refine` re-linearisations, then one
    `pure_callback` for the exact check (and the Clarabel fallback). `W` (the metric's
    weights, all ones: `use_first_order` admits no metric) and `K_ref` (the linearisation
    point of an indefinite $Q$, which `use_first_order` refuses) keep `project`'s signature;
    `fallback` is the Clarabel batch solve (`_projection._host_batch`, passed in so that
    this module does not import the one that dispatches to it)."""
    # module constants read at call time (the tests shrink the budget to force the fallback)
    margin = MARGIN_FO if margin is None else margin
    tol = TOL_FO if tol is None else tol
    max_iter = MAX_ITER_FO if max_iter is None else max_iter
    rho = RHO_FO if rho is None else rho
    n, dtype = K.n_state, K.A.dtype
    has_ref = P_ref is not None
    P_ref = jnp.asarray(P_ref, dtype) if has_ref else jnp.eye(n, dtype=dtype)
    target = (K.A, K.B, K.C, K.D)
    P_tilde, x = P_ref, None
    for _ in range(1 if has_ref else max(1, refine)):
        x, _, _, _ = admm(target, P_tilde, qsr, margin=max(margin, eps), reg=reg, rho=rho,
                          tol=tol, max_iter=max_iter)
        # the next round linearises at the new P (if it is usable; else keep P~)
        good = jnp.all(jnp.isfinite(x[4])) & (jnp.min(jnp.diag(x[4])) > 0)
        P_tilde = jnp.where(good, x[4], P_tilde)
    assert x is not None  # set by the first round (there is at least one)
    shard, shards = _sdp.shard()
    shapes = tuple(jax.ShapeDtypeStruct(M.shape, dtype) for M in (*target, P_ref))
    callback = functools.partial(_host_check, qsr=qsr, has_ref=has_ref, eps=float(eps),
                                 reg=float(reg), refine=int(refine), shards=shards,
                                 fallback=fallback)
    *mats, codes = jax.pure_callback(
        callback, (*shapes, jax.ShapeDtypeStruct((), jnp.int32)), *x, *target, P_ref,
        jnp.asarray(active, bool), shard, vmap_method="broadcast_all")
    return LTIController(*mats[:4]), mats[4], codes


#: `method="auto"` uses the first-order path from this controller order on; None: never.
#: On CPU it was slower than Clarabel at every order measured (13x slower per PGD step at
#: n = 6, cold-started ADMM, `benchmarks/bench_fo_projection.py`), so "auto" is Clarabel
#: until a measurement (warm starts, accelerators) shows a size where it wins.
AUTO_MIN_ORDER = None
METHODS = ("clarabel", "first_order", "auto")


def use_first_order(method, K, metric, qsr: QSR) -> bool:
    """Whether `project(..., method=method)` takes the first-order path (checks `method`)."""
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {METHODS}, got {method!r}.")
    if method == "first_order" and metric is not None:
        raise ValueError("`method='first_order'` projects in the Frobenius distance only; "
                         "pass `method='clarabel'` (or 'auto') with a `metric`.")
    if method == "first_order" and is_indefinite(qsr):
        raise ValueError("`method='first_order'` needs `qsr.Q` negative semidefinite; for "
                         "an indefinite Q pass `method='clarabel'` (or 'auto').")
    if method == "auto":
        return (metric is None and not is_indefinite(qsr) and AUTO_MIN_ORDER is not None
                and K.n_state >= AUTO_MIN_ORDER)
    return method == "first_order"
