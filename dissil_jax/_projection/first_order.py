"""A first-order projection onto the convexified dissipative set (ADMM, pure JAX).

It solves the problem of [`project`][dissil_jax.project] (paper eq. 13):

$$\\min_{A,B,C,D,P}\\ \\tfrac12\\lVert(A,B,C,D)-(\\tilde A,\\tilde B,\\tilde C,\\tilde D)
\\rVert_W^2 + \\tfrac\\mu2\\lVert P-\\tilde P\\rVert_F^2 \\quad\\text{s.t.}\\quad
\\mathcal M(A,B,C,D,P;\\tilde P)\\preceq-\\varepsilon I,$$

the distance Frobenius unless `project`'s `metric` gives per-entry weights $W$, with
$\\mathcal M$ the convexified KYP matrix (`ConvexifiedLMI`, built densely in JAX), and
for $\\hat n\\ge2$ the conditioning bound $P\\succeq\\frac{\\rho}{\\hat n}\\operatorname{tr}(P)I$
of Clarabel's problem. ADMM (`admm.py`) runs in the eigenbasis of $\\tilde P$ after the
congruence by $\\tilde P^{-1/2}$, where the LMI no longer carries $\\tilde P$'s scale and
every block of the $x$-update is elementwise (a per-entry metric $W$ is not elementwise
there; a consensus copy of the controller in the original basis carries it, `admm.solve`'s
`metric`). $\\tilde P$'s eigen-decomposition is done once per projection, outside the
loop (on a CPU by the host, `_eigh`). The PSD projections use a scaled Newton-Schulz
sign (matrix products only: a batched `eigh` inside a compiled loop can deadlock XLA's CPU
thread pool, docs/scaling.md "Thread-pool deadlocks").

ADMM aims at a slack `MARGIN_FO` beyond $\\varepsilon$ and stops at residuals `TOL_FO`
relative to the scaled LMI; `admm.repair` then moves its answer towards a strictly
dissipative static point just enough to satisfy $\\mathcal M\\preceq-\\varepsilon I$, so an
approximate solution is still feasible. The result is rounded and checked exactly in
float64 on the host, and a row that fails goes to Clarabel. A projection can start from
the ADMM state of a previous one (`project_one`'s `state`; PGD carries it across steps).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import _outcome
from .._certify import fast as _certify_fast
from .._controller import LTIController
from .._rate_scale import rate_factor, scaled_rate
from .._sdp import lmi as _lmi, sdp as _sdp
from .._sdp.indefinite import is_indefinite
from .._supply import QSR
from .._validate import no_derivative
from . import admm as _admm
from .admm_rate import AdmmRate, admm_rate
from .handle import RateHandle, rate_handle, resolve

lmi_matrix, psd_part = _admm.lmi_matrix, _admm.psd_part


def _eigh_host(P):
    """pure_callback target: the eigen-decompositions of a batch of $\\tilde P$ (numpy)."""
    w, V = np.linalg.eigh(np.asarray(P, np.float64))
    return w.astype(P.dtype), V.astype(P.dtype)


def _eigh_callback(P):
    n, dtype = P.shape[-1], P.dtype
    return jax.pure_callback(
        _eigh_host, (jax.ShapeDtypeStruct((n,), dtype), jax.ShapeDtypeStruct((n, n), dtype)),
        P, vmap_method="broadcast_all")


def _eigh(P):
    """$\\tilde P = V\\operatorname{diag}(\\lambda)V^\\top$, once per projection, outside the
    ADMM loop. On a CPU on the host (numpy): a batched LAPACK call inside XLA, here inside
    PGD's training loop, can deadlock XLA's CPU thread pool (see `_linalg.py`). On other
    platforms (GPU, TPU) on the device, chosen when the program is lowered, so that the
    ADMM solve there has no host round trip before the final check."""
    return jax.lax.platform_dependent(P, cpu=_eigh_callback, default=_eigh_device)


def _eigh_device(P):
    w, V = jnp.linalg.eigh(P)
    return w, V


def _rate(qsr: QSR | RateHandle | AdmmRate, dtype) -> AdmmRate:
    """The ADMM's rate: a `RateHandle`'s arrays (a trainer's, traced), or built from a
    static `QSR` (needs $Q\\preceq0$)."""
    if isinstance(qsr, RateHandle):
        if qsr.admm is None:
            raise ValueError("This `RateHandle` carries no first-order rate.")
        return qsr.admm
    return admm_rate(qsr, dtype)


def _centred(K, rate: AdmmRate, sign=1.0):
    """`(A, B, C, D)` with $D$ moved by the rate's `offset` (`sign` -1: back)."""
    A, B, C, D = K
    return A, B, C, D + sign * rate.offset


def _frame(V, n, N):
    """The rotation $\\operatorname{diag}(V, I_{p+r}, V)$ between the eigenbasis of
    $\\tilde P$ and the original basis (warm starts are kept in the original one)."""
    R = jnp.eye(N, dtype=V.dtype)
    return R.at[:n, :n].set(V).at[N - n:, N - n:].set(V)


def cold_state(n: int, qsr: QSR | RateHandle | AdmmRate, dtype, target=None):
    """The ADMM state of a cold start: $Z = U = Z_2 = U_2 = 0$, $\\rho$ = `RHO_FO`; with a
    metric, also the consensus block's $Y$ = `target` ($(A, B, C, D)$) and $U_Y = 0$."""
    rate = _rate(qsr, dtype)
    *_, N = _admm.sizes(rate, n)
    zero, zero2 = jnp.zeros((N, N), dtype), jnp.zeros((n, n), dtype)
    cold = (zero, zero, zero2, zero2, jnp.asarray(RHO_FO, dtype))
    if target is None:
        return cold
    Y = _centred(tuple(jnp.asarray(M, dtype) for M in target), rate)
    return cold + ((Y, tuple(jnp.zeros_like(M) for M in Y)),)


def admm_round(target, P_tilde, rate: AdmmRate, state, *, eps, margin, reg, tol, max_iter,
               floor=0.0, weights=None):
    """One ADMM solve of the projection at $\\tilde P$ (unbatched; vmap for batches), from
    `state = (Z, U, Z2, U2, rho)` given in the original basis (a previous solve's, or
    `cold_state`); `floor`: the conditioning bound's coefficient (`project`'s `P_FLOOR`).
    `weights`: the metric's per-entry weights of $(A, B, C, D)$ (largest 1), or None for
    the Frobenius distance; with them `state` also holds the consensus block
    (`admm.solve`'s `metric`).

    **Returns:** `((A, B, C, D, P), state, iterations, t)`, `t` the repair's step towards
    the static point (`admm.repair`; 0 when ADMM's answer already met the constraint).
    """
    n = target[0].shape[0]
    *_, N = _admm.sizes(rate, n)
    lam, V = _eigh(P_tilde)
    usable = jnp.all(jnp.isfinite(lam)) & (jnp.min(lam) > 0)  # else: no iterations, fallback
    lam = jnp.where(usable, lam, 1.0)
    V = jnp.where(usable, V, jnp.eye(n, dtype=V.dtype))
    # c: project's constraint M <= -eps I as Mhat <= -eps T^2; ADMM aims at c + margin I
    # (a slack relative to the scaled LMI, whose identity blocks are O(1)).
    tgt, scaled_weights, c = _admm.scale(target, lam, V, eps, reg, rate)
    R = _frame(V, n, N)
    Z, U, Z2, U2, rho, *cons = state
    # Without a strictly dissipative static gain (`repair`) the iterate itself must be
    # feasible: Mhat = -c - margin I - Z + E with Z >= 0 satisfies Mhat <= -c once the
    # primal residual |E|_F is below the slack margin.
    feas = jnp.where(rate.g0 > 0, jnp.inf, 0.5 * margin)
    x, (Z, U, Z2, U2, rho, *cons), it, _ = _admm.solve(
        tgt, scaled_weights, c + margin, rate, tol=tol, feas=feas,
        max_iter=jnp.where(usable, max_iter, 0), floor=floor if n > 1 else 0.0, lam=lam,
        state=(R.T @ Z @ R, R.T @ U @ R, V.T @ Z2 @ V, V.T @ U2 @ V, rho, *cons),
        metric=None if weights is None else (target, weights, V))
    # to project's own constraint; ADMM aimed beyond it, so t is ~0 mostly (and 0 without
    # a strictly dissipative static gain: `repair` does not move then)
    x, t = _admm.repair(x, c, rate)
    state = (R @ Z @ R.T, R @ U @ R.T, V @ Z2 @ V.T, V @ U2 @ V.T, rho, *cons)
    return _admm.unscale(x, lam, V), state, it, t


#: Defaults of the first-order path: the margin aimed at (above `project`'s eps, so that a
#: solution with residual below it still satisfies the strict LMI), the residual tolerance
#: relative to 1 + |M|_F, the iteration budget and the penalty.
MARGIN_FO, TOL_FO, MAX_ITER_FO, RHO_FO = 1e-4, 1e-4, 5000, 0.1
#: The largest repair step (`admm.repair`'s $t$, the fraction of the way from ADMM's answer
#: to the static point) whose row is kept; a larger one goes to Clarabel. ADMM's residual
#: tolerance is relative to the scaled LMI, so on a rate with little room (a gain bound of
#: 0.01: $R = 10^{-4}$) its answer can be far from feasible: the repair then moved 85-90 %
#: of the way to the zero controller, twice Clarabel's distance from the target (orders 12
#: and 16); at a bound of 0.1, 7 % and 4 % farther. Measured `t` on well-scaled rates: 0
#: to 5e-4.
REPAIR_MAX = 1e-2
#: The residual tolerance of PGD's projections (`project_first_order_warm`), looser than a
#: single projection's: each starts from the previous step's ADMM state, and the repair
#: keeps every result feasible, so an inexact projection costs only a slightly different
#: iterate. Chosen on the mass-spring chains (`bench_fo_projection.py --tol`, n = 12, 16,
#: 24, two chains each, projected Adam and the paper's rule): against 1e-4, 3e-4 took a
#: third of the ADMM iterations, with median final losses from 5 % lower to 12 % higher
#: and worst runs from 9 % lower to 3 % higher; 1e-3 took a tenth, with medians up to 17 %
#: and worst runs up to 19 % higher.
TOL_FO_PGD = 3e-4


_SKIPPED, _UNCHANGED, _SOLVED = (_outcome.code(n) for n in ("skipped", "unchanged", "solved"))


def _host_check(A, B, C, D, P, tA, tB, tC, tD, P_ref, WA, WB, WC, WD, active, shard, iters,
                repair, token=None, *, qsr, has_ref, eps, reg, refine, shards, fallback):
    """pure_callback target: the exact float64 check of the ADMM results, Clarabel for the
    rows that fail it or whose `repair` step exceeded `REPAIR_MAX` (`fallback`,
    `_projection._host_batch`), codes as `project`'s. With `qsr` None the rate is
    `token`'s (a `RateHandle`'s, broadcast like the batch)."""
    qsr = resolve(token) if qsr is None else qsr
    dtype = np.asarray(A).dtype
    batch = A.shape[:-2]
    flat = lambda M: np.asarray(M, np.float64).reshape((-1,) + M.shape[len(batch):])
    sol = [flat(M) for M in (A, B, C, D, P)]
    tgt = [flat(M) for M in (tA, tB, tC, tD)]
    ref = flat(P_ref)
    weights = [flat(M) for M in (WA, WB, WC, WD)]
    act = np.asarray(active).reshape(-1)
    with _FALLBACK_LOCK:
        FALLBACKS["projections"] += int(np.sum(act))
        FALLBACKS["iterations"] += int(np.sum(np.asarray(iters).reshape(-1)[act]))
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
        near = np.asarray(repair).reshape(-1)[todo] <= REPAIR_MAX
        with _FALLBACK_LOCK:
            FALLBACKS["far_repairs"] += int(np.sum(~near))
        ok = finite & near & _lmi.certified(rA, rB, rC, rD, qsr, rP)
        for o, M in zip(out, rounded):
            o[todo[ok]] = M[ok]
        codes[todo[ok]] = _SOLVED
        # as Clarabel's path: `certify` of a returned controller then finds its storage
        _certify_fast.remember(rA[ok], rB[ok], rC[ok], rD[ok], qsr, rP[ok])
        bad = todo[~ok]
        if len(bad):
            # C0, D0: the linearisation point of an indefinite Q, which this path refuses
            res = fallback(
                *(t[bad] for t in tgt), ref[bad], *(w[bad] for w in weights),
                np.ones(len(bad), bool),
                tgt[2][bad], tgt[3][bad], np.zeros(len(bad), np.int32), qsr=qsr,
                has_ref=has_ref, eps=eps, reg=reg, refine=refine, shards=shards)
            for o, M in zip(out, res[:5]):
                o[bad] = M
            codes[bad] = res[5]
            with _FALLBACK_LOCK:
                FALLBACKS["rows"] += len(bad)
    return (*(o.reshape(batch + o.shape[1:]).astype(dtype) for o in out),
            codes.reshape(batch))


#: Rows the first-order path handed to Clarabel, active projections and their ADMM
#: iterations (all rounds), since import (tests and benchmarks read them).
FALLBACKS = {"rows": 0, "projections": 0, "iterations": 0, "far_repairs": 0}
_FALLBACK_LOCK = __import__("threading").Lock()


def project_one(K, P_ref, W, active, K_ref, *, qsr: QSR | RateHandle, eps, reg, refine, fallback,
                margin=None, tol=None, max_iter=None, state=None, floor=0.0, weighted=False):
    """The unbatched first-order projection (vmap for batches): ADMM at $\\tilde P$ =
    `P_ref`, or from $\\tilde P = I$ with `refine` re-linearisations, then one
    `pure_callback` for the exact check (and the Clarabel fallback). `W`: the metric's
    weights (`LTIController`), used when `weighted` (static; else the distance is
    Frobenius and `W` only reaches the fallback). `K_ref` (the linearisation
    point of an indefinite $Q$, which `use_first_order` refuses) keeps `project`'s signature;
    `fallback` is the Clarabel batch solve (`_projection._host_batch`, passed in so that
    this module does not import the one that dispatches to it). `state`: the ADMM state to
    start from (a previous projection's, e.g. the previous PGD step's), or None for a cold
    start.

    **Returns:** `(K_proj, P, code, state)`, `state` the final ADMM state (`admm_round`).
    """
    # module constants read at call time (the tests shrink the budget to force the fallback)
    margin = MARGIN_FO if margin is None else margin
    tol = TOL_FO if tol is None else tol
    max_iter = MAX_ITER_FO if max_iter is None else max_iter
    n, dtype = K.n_state, K.A.dtype
    has_ref = P_ref is not None
    P_ref = jnp.asarray(P_ref, dtype) if has_ref else jnp.eye(n, dtype=dtype)
    target = tuple(no_derivative("dj.project", M) for M in (K.A, K.B, K.C, K.D))
    weights = None
    if weighted:  # only ratios matter: the largest weight 1, as Clarabel's path
        weights = tuple(jnp.asarray(M, dtype) for M in (W.A, W.B, W.C, W.D))
        top = jnp.max(jnp.stack([jnp.max(M) for M in weights]))
        weights = tuple(M / top for M in weights)
    rate = _rate(qsr, dtype)
    state = cold_state(n, rate, dtype, target if weighted else None) if state is None else state
    centred = _centred(target, rate)  # ADMM's coordinates (a far cone's centre at zero)
    # an inactive lane (a stopped PGD run) takes no ADMM iteration; its row is skipped
    max_iter = jnp.where(jnp.asarray(active, bool), max_iter, 0)

    def one_round(carry):
        _, state, P_tilde, iters, _ = carry
        x, state, it, t = admm_round(centred, P_tilde, rate, state, eps=eps, margin=margin,
                                     reg=reg, tol=tol, max_iter=max_iter, floor=floor,
                                     weights=weights)
        # the next round linearises at the new P (if it is usable; else keep P~)
        good = jnp.all(jnp.isfinite(x[4])) & (jnp.min(jnp.diag(x[4])) > 0)
        return x, state, jnp.where(good, x[4], P_tilde), iters + it, t

    rounds = 1 if has_ref else max(1, refine)
    carry = ((*(jnp.zeros_like(M) for M in target), jnp.zeros_like(P_ref)), state, P_ref,
             jnp.zeros((), jnp.int32), jnp.zeros((), dtype))
    # Several re-linearisation rounds in a loop, so that ADMM is compiled once, not once
    # per round; one round (PGD's steps, at P_ref) as it is.
    x, state, _, iters, t = (one_round(carry) if rounds == 1 else
                             jax.lax.fori_loop(0, rounds, lambda _, c: one_round(c), carry))
    x = (*_centred(x[:4], rate, -1.0), x[4])
    shard, shards = _sdp.shard()
    shapes = tuple(jax.ShapeDtypeStruct(M.shape, dtype) for M in (*target, P_ref))
    handle = isinstance(qsr, RateHandle)
    callback = functools.partial(_host_check, qsr=None if handle else qsr, has_ref=has_ref,
                                 eps=float(eps), reg=float(reg), refine=int(refine),
                                 shards=shards, fallback=fallback)
    *mats, codes = jax.pure_callback(
        callback, (*shapes, jax.ShapeDtypeStruct((), jnp.int32)), *x, *target, P_ref,
        *(jnp.asarray(M, dtype) for M in (W.A, W.B, W.C, W.D)), jnp.asarray(active, bool),
        shard, iters, t, *((qsr.token,) if handle else ()), vmap_method="broadcast_all")
    return LTIController(*mats[:4]), mats[4], codes, state


#: `method="auto"` uses the first-order path from this controller order on; None: never.
#: Measured (`benchmarks/bench_fo_projection.py`, PGD per step, same run as Clarabel): 0.6-0.9x
#: at n = 6, 3.7x at 12, 5.2x at 16, 13.6x at 24, all iterates certified; so the paper's
#: sizes (n = 1, 6) keep Clarabel.
AUTO_MIN_ORDER: int | None = 12
#: The same with a `metric`. Measured (`bench_fo_projection.py --adam`, PGD's default
#: projected Adam, per step, same run as Clarabel): 0.4x at n = 6, 1.8x at 12, 3.3x at 16,
#: 7.3x at 24 (ADMM tolerance 1e-4); 4.9x, 9.1x and 19x at 12, 16, 24 with `TOL_FO_PGD`.
AUTO_MIN_ORDER_METRIC: int | None = 12
METHODS = ("clarabel", "first_order", "auto")


def use_first_order(method, n_state: int, weighted: bool, qsr: QSR | RateHandle) -> bool:
    """Whether `project(..., method=method)` of controllers of order `n_state` takes the
    first-order path (checks `method`); `weighted`: whether the projection has a
    `metric`. A `RateHandle` allows it only when it carries the ADMM's rate
    (`trainer_rate` adds it where the path may run, never for an indefinite $Q$)."""
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {METHODS}, got {method!r}.")
    # a handle carries the ADMM's rate only where Q <= 0 (`trainer_rate`)
    indefinite = qsr.admm is None if isinstance(qsr, RateHandle) else is_indefinite(qsr)
    if method == "first_order" and indefinite:
        raise ValueError("`method='first_order'` needs `qsr.Q` negative semidefinite; for "
                         "an indefinite Q pass `method='clarabel'` (or 'auto').")
    if method == "auto":
        lo = AUTO_MIN_ORDER_METRIC if weighted else AUTO_MIN_ORDER
        return not indefinite and lo is not None and n_state >= lo
    return method == "first_order"


def trainer_rate(qsr: QSR | None, method: str, n_state: int, dtype):
    """`(rate, k)` for `fit_pgd`'s compiled run: the rate divided by `k = rate_factor(qsr)`
    as a `RateHandle` (traced, so that another rate does not compile the run again), with
    `k` as an array of `dtype` (P is multiplied back by it). Where the first-order
    projection may run (with or without a metric: the optimiser's is known inside the
    run), the handle carries the ADMM's rate of `dtype` too. `(None, None)` for no rate."""
    if qsr is None:
        return None, None
    k = rate_factor(qsr)
    scaled = scaled_rate(qsr, k)
    fo = any(use_first_order(method, n_state, w, scaled) for w in (False, True))
    return (rate_handle(scaled, admm_rate(scaled, dtype) if fo else None),
            jnp.asarray(k, dtype))
