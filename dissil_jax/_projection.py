"""Projection onto the convexified dissipative set (paper eq. 13), solved by Clarabel.

Host side: one `_ProjectionSolver` per (sizes, supply rate, margin) and per thread keeps
Clarabel's symbolic structure; a new target or a new $\\tilde P$ only changes numbers
(`solver.update(q=..., A=..., b=...)`). The numbers of a whole batch are built at once
with numpy, the solves are spread over the thread pool, and the solutions are unpacked,
rounded and checked (exact float64 KYP) as one batch. JAX side: `jax.pure_callback` with
`vmap_method="broadcast_all"`, so a vmapped call reaches the host once with the whole batch.
"""

from __future__ import annotations

import collections
import threading
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from . import _projection_fo, _sdp
from ._controller import LTIController
from ._lmi import ConvexifiedLMI
from ._projection_args import check_options as _check_options, check_qsr as _check_qsr
from ._sdp import Outcome
from ._supply import QSR

# Clarabel's own reported solve time and solve count, summed over all threads, and the
# number of host callbacks by (shard, batch size) (benchmarks).
SOLVER_STATS = {"solve_time": 0.0, "solves": 0, "callbacks": collections.Counter()}
_STATS_LOCK = threading.Lock()
_LOCAL = threading.local()
_LMI_CACHE: dict = {}
_LMI_LOCK = threading.Lock()
_SOLVED, _UNCHANGED, _SKIPPED, _NOT_CERTIFIED = (
    _sdp.code(n) for n in ("solved", "unchanged", "skipped", "not_certified"))
# A solution that fails the exact check after rounding is re-solved with the margin
# enlarged by this factor, at most `_ATTEMPTS - 1` times.
_ATTEMPTS, _EPS_GROWTH = 3, 100.0


class _ProjectionSolver:
    """Clarabel problem data for Π with fixed sparsity; numbers updated per call."""

    def __init__(self, lmi: ConvexifiedLMI, eps: float, reg: float):
        import clarabel

        self.lmi, self.eps, self.reg = lmi, eps, reg
        n, N = lmi.n, lmi.N
        # Cone s = b - A x in PSD: s = svec(-M(x) - eps I) => A = svec(J_k) columns.
        fixed = np.stack([lmi.svec(Jk) for Jk in lmi.J_fixed], axis=1)  # [L, nx]
        Gs = lmi.svec(lmi.G)  # [nAB, n, n, L]
        Gs = Gs.reshape(lmi.nA + lmi.nB, n * n, -1).transpose(2, 0, 1)  # [L, nAB, n*n]
        pattern = fixed != 0
        pattern[:, : lmi.nA + lmi.nB] |= np.any(Gs != 0, axis=2)
        csc = sp.csc_matrix(pattern.astype(np.float64))
        csc.sort_indices()
        rows = csc.indices
        cols = np.repeat(np.arange(csc.shape[1]), np.diff(csc.indptr))
        self.vals0 = fixed[rows, cols]
        in_ab = cols < lmi.nA + lmi.nB
        self.ab_pos = np.nonzero(in_ab)[0]
        self.vals_g = Gs[rows[in_ab], cols[in_ab]]  # [nnz_ab, n*n]
        self.csc_shape, self.indptr, self.indices = csc.shape, csc.indptr, csc.indices
        # b = svec(-M0 - eps I), M0's P~-block is -2 P~.
        self.b_fixed = lmi.svec(-lmi.M0 - eps * np.eye(N))
        i3 = N - n
        sel = np.zeros((n * n, N, N))
        for c in range(n):
            for a in range(n):
                sel[c * n + a, i3 + c, i3 + a] = 2.0
        self.b_g = lmi.svec(sel).T  # [L, n*n]
        self.eps_svec = lmi.svec(np.eye(N))
        self.reg_diag = np.full(lmi.nP, reg)
        self.cones = [clarabel.PSDTriangleConeT(N)]
        self.solver, self.diag = None, None
        self._clarabel = clarabel

    def data(self, targets, P_tilde, eps, weights):
        """Clarabel's `(q, A values, b, P values)` for a batch: `targets` and `weights`
        [B, ntheta] (the objective is $\\sum_k w_k(\\theta_k - \\tilde\\theta_k)^2$), `P_tilde`
        [B, n, n]."""
        Pt = np.asarray(P_tilde, np.float64).reshape(len(targets), -1)
        vals = np.broadcast_to(self.vals0, (len(targets),) + self.vals0.shape).copy()
        # einsum (not BLAS) so that a row's numbers do not depend on the batch size
        vals[:, self.ab_pos] = np.einsum("bk,lk->bl", Pt, self.vals_g)
        b = (self.b_fixed + np.einsum("bk,lk->bl", Pt, self.b_g)
             - (np.asarray(eps)[:, None] - self.eps) * self.eps_svec)
        p_tilde = np.asarray(P_tilde, np.float64)[:, self.lmi.p_rows, self.lmi.p_cols]
        q = -np.concatenate([weights * targets, self.reg * p_tilde], axis=1)
        diag = np.concatenate([weights, np.broadcast_to(self.reg_diag, p_tilde.shape)], axis=1)
        return q, vals, b, diag

    def solve(self, q, vals, b, diag):
        """One solve; returns `(x or None, Outcome code, Clarabel's solve time)`."""
        if self.solver is None:
            A = sp.csc_matrix((vals, self.indices, self.indptr), shape=self.csc_shape)
            k = np.arange(len(diag) + 1)  # diagonal objective, explicit zeros kept (reg = 0)
            P_obj = sp.csc_matrix((diag, k[:-1], k), shape=(len(diag),) * 2)
            settings = _sdp.clarabel_settings(**_sdp.PROJECTION_SETTINGS)
            self.solver = self._clarabel.DefaultSolver(P_obj, q, A, b, self.cones, settings)
        elif np.array_equal(diag, self.diag):  # the same distance (always, without a metric)
            self.solver.update(q=q, A=vals, b=b)
        else:
            self.solver.update(P=diag, q=q, A=vals, b=b)
        self.diag = diag
        sol = self.solver.solve()
        outcome = _sdp.clarabel_outcome(str(sol.status))
        return (np.asarray(sol.x) if outcome == _SOLVED else None), outcome, sol.solve_time


def _lmi(qsr: QSR, n: int) -> ConvexifiedLMI:
    key = (qsr, n)
    with _LMI_LOCK:
        lmi = _LMI_CACHE.get(key)
        if lmi is None:
            lmi = _LMI_CACHE[key] = ConvexifiedLMI(n, qsr.n_in, qsr.n_out, qsr)
    return lmi


def _thread_solver(qsr: QSR, n: int, eps: float, reg: float) -> _ProjectionSolver:
    cache = getattr(_LOCAL, "solvers", None)
    if cache is None:
        cache = _LOCAL.solvers = {}
    key = (qsr, n, eps, reg)
    solver = cache.get(key)
    if solver is None:
        solver = cache[key] = _ProjectionSolver(_lmi(qsr, n), eps=eps, reg=reg)
    return solver


def _solve_batch(qsr, targets, P_tilde, eps, weights, *, base_eps, reg, dtype, shards):
    """Solve Π for every row; returns `(A, B, C, D, P)` rounded to `dtype`, codes, certified."""
    n = P_tilde.shape[-1]
    lmi = _lmi(qsr, n)
    count = len(targets)
    q, vals, b, diag = _thread_solver(qsr, n, base_eps, reg).data(targets, P_tilde, eps, weights)
    xs = np.full((count, lmi.nx), np.nan)
    codes = np.empty(count, np.int32)

    def work(rows):
        solver, spent = _thread_solver(qsr, n, base_eps, reg), 0.0
        for i in rows:
            x, codes[i], t = solver.solve(q[i], vals[i], b[i], diag[i])
            spent += t
            if x is not None:
                xs[i] = x
        with _STATS_LOCK:
            SOLVER_STATS["solve_time"] += spent
            SOLVER_STATS["solves"] += len(rows)

    _sdp.thread_map(work, range(count), shards=shards)
    sol = tuple(_sdp.cast(M, dtype) for M in lmi.layout.unpack(xs))
    ok = (codes == _SOLVED) & _sdp.certified(*sol[:4], qsr, sol[4])
    return sol, codes, ok


def _certified_solve(qsr, targets, P_tilde, weights, *, eps, reg, dtype, shards):
    """Solve Π for every row at its $\\tilde P$ and keep only certified solutions.

    A solution that fails the exact check after rounding is re-solved with the margin
    enlarged `_EPS_GROWTH`-fold, at most `_ATTEMPTS - 1` times; a solve that fails after an
    uncertified solution counts as `not_certified`. Returns `(solution, found, codes)`.
    """
    count = len(targets)
    cur_eps, todo = np.full(count, eps), np.arange(count)
    found, codes, sols = np.zeros(count, bool), np.empty(count, np.int32), None
    for attempt in range(_ATTEMPTS):
        sol, c, ok = _solve_batch(qsr, targets[todo], P_tilde[todo], cur_eps[todo],
                                  weights[todo], base_eps=eps, reg=reg, dtype=dtype, shards=shards)
        if sols is None:
            sols = [np.full((count,) + M.shape[1:], np.nan) for M in sol]
        for S, M in zip(sols, sol):
            S[todo[ok]] = M[ok]
        found[todo[ok]] = True
        failed_code = np.where(c == _SOLVED, _NOT_CERTIFIED, _NOT_CERTIFIED if attempt else c)
        codes[todo] = np.where(ok, _SOLVED, failed_code)
        todo = todo[(c == _SOLVED) & ~ok]
        cur_eps[todo] *= _EPS_GROWTH
        if not len(todo):
            break
    return sols, found, codes


def _project_rows(qsr, targets, P_tilde, weights, rounds, *, eps, reg, dtype, shards):
    """Project every row, re-linearising $P^{-1}$'s overbound `rounds` times.

    Each round starts at the $P$ of the row's closest certified solution so far; a row
    keeps that solution and stops refining at its first failure. Returns
    `((A, B, C, D, P), codes)`; rows without any certified solution hold NaN.
    """
    count = len(targets)
    layout = _lmi(qsr, P_tilde.shape[-1]).layout
    best_dist = np.full(count, np.inf)
    codes = np.full(count, _sdp.code("solver_failed"), np.int32)
    live, P_tilde, best = np.arange(count), P_tilde.copy(), None
    for _ in range(rounds):
        sols, found, codes[live] = _certified_solve(
            qsr, targets[live], P_tilde[live], weights[live], eps=eps, reg=reg, dtype=dtype,
            shards=shards)
        if best is None:
            best = [np.full((count,) + M.shape[1:], np.nan) for M in sols]
        dist = np.sum(weights[live] * (layout.pack(*sols[:4]) - targets[live]) ** 2, axis=-1)
        better = found & (dist < best_dist[live])
        for Bm, S in zip(best, sols):
            Bm[live[better]] = S[better]
        best_dist[live[better]] = dist[better]
        live = live[found]
        if not len(live):
            break
        P_tilde[live] = best[4][live]
    codes[np.isfinite(best_dist)] = _SOLVED
    return best, codes


def _host_batch(A, B, C, D, P_ref, WA, WB, WC, WD, active, shard, *, qsr, has_ref, eps, reg,
                refine, shards):
    """pure_callback target: arrays carry identical leading batch axes (broadcast_all).

    Active targets already certified by `P_ref` come back unchanged; the others are
    projected as one batch (`_project_rows`). Failed rows return their target, flagged.
    `shard` is the calling device's index (broadcast like the batch) and `shards` the
    number of callbacks running at once on this host (`_sdp.shard`); each uses its share
    of the thread pool. `WA`..`WD` are the metric's weights (scaled per row to at most 1).
    """
    dtype = np.asarray(A).dtype
    batch, n = A.shape[:-2], A.shape[-1]
    with _STATS_LOCK:
        index = int(np.ravel(shard)[0]) if np.size(shard) else 0
        SOLVER_STATS["callbacks"][index, int(np.prod(batch))] += 1
    flat = [np.asarray(M, np.float64).reshape((-1,) + M.shape[len(batch):])
            for M in (A, B, C, D, P_ref)]
    act = np.asarray(active).reshape(-1)
    out = [M.copy() for M in flat]
    codes = np.full(act.shape[0], _SKIPPED, np.int32)
    todo = np.nonzero(act)[0]
    if has_ref and len(todo):
        keep = _sdp.certified(*(M[todo] for M in flat[:4]), qsr, flat[4][todo])
        codes[todo[keep]] = _UNCHANGED
        todo = todo[~keep]
    if len(todo):
        layout = _lmi(qsr, n).layout
        targets = layout.pack(*(M[todo] for M in flat[:4]))
        w = layout.pack(*(np.asarray(W, np.float64).reshape((-1,) + W.shape[len(batch):])[todo]
                          for W in (WA, WB, WC, WD)))
        w /= w.max(axis=1, keepdims=True)
        P_tilde = flat[4][todo] if has_ref else np.broadcast_to(np.eye(n), (len(todo), n, n))
        sol, codes[todo] = _project_rows(qsr, targets, P_tilde, w, 1 if has_ref else max(1, refine),
                                         eps=eps, reg=reg, dtype=dtype, shards=shards)
        done = todo[codes[todo] == _SOLVED]
        for o, M in zip(out, sol):
            o[done] = M[codes[todo] == _SOLVED]
    return (*(o.reshape(batch + o.shape[1:]).astype(dtype) for o in out),
            codes.reshape(batch))


class Projection(tuple):
    """What [`project`][dissil_jax.project] returns: the pair `(controller, P)`, plus `result`.

    It unpacks like a pair (`K, P = dj.project(K, qsr)`) and indexes like one
    (`dj.project(K, qsr)[0]`); `result` is the [`Outcome`][dissil_jax.Outcome] of each
    projection (batched like `K`). It is a JAX pytree, so it can be returned from `jax.jit`.
    """

    def __new__(cls, controller, P, result):
        self = super().__new__(cls, (controller, P))
        self.result = result
        return self

    @property
    def controller(self) -> LTIController:
        return self[0]

    @property
    def P(self):
        return self[1]

    def __repr__(self):
        return f"Projection(controller={self[0]!r}, P={self[1]!r}, result={self.result!r})"


jax.tree_util.register_pytree_node(
    Projection, lambda p: ((p[0], p[1], p.result), None),
    lambda _, children: Projection(*children))


def _project_one(K: LTIController, P_ref, W: LTIController, active, *, qsr: QSR, eps, reg,
                 refine):
    """The unbatched JAX side: one `pure_callback` (vmapped calls batch on the host).

    Inside `jax.shard_map` (e.g. [`sweep`][dissil_jax.sweep]) each device calls its own
    copy with its local batch, on its own host; outside, XLA places the call
    on one device and gathers the batch there.
    """
    n, dtype = K.n_state, K.A.dtype
    has_ref = P_ref is not None
    if has_ref:
        P_ref = jnp.asarray(P_ref, dtype)
        if P_ref.shape != (n, n):
            raise ValueError(f"`P_ref` must be {n}x{n}, got {P_ref.shape}.")
    else:
        P_ref = jnp.eye(n, dtype=dtype)
    shapes = tuple(jax.ShapeDtypeStruct(M.shape, dtype) for M in (K.A, K.B, K.C, K.D, P_ref))
    shard, shards = _sdp.shard()
    callback = partial(_host_batch, qsr=qsr, has_ref=has_ref, eps=float(eps), reg=float(reg),
                       refine=int(refine), shards=shards)
    A, B, C, D, P, codes = jax.pure_callback(
        callback, (*shapes, jax.ShapeDtypeStruct((), jnp.int32)), K.A, K.B, K.C, K.D, P_ref,
        W.A, W.B, W.C, W.D, jnp.asarray(active, bool), shard, vmap_method="broadcast_all")
    return LTIController(A, B, C, D), P, codes


def _raise_on_failure(P, codes):
    """`throw=True`: a ValueError eagerly, an `EquinoxRuntimeError` under `jit`."""
    if not isinstance(codes, jax.core.Tracer):
        codes = np.asarray(codes)
        bad = codes[_sdp.failed(codes)]
        if bad.size:
            raise ValueError(f"dj.project: {Outcome[_sdp.item(bad.max())]}")
        return P
    worst = _sdp.item(jnp.max(jnp.where(_sdp.failed(codes), codes, -1)))
    return worst.error_if(P, jnp.any(_sdp.failed(codes)))


def project(
    K: LTIController, qsr: QSR, P_ref=None, *, throw: bool = True, active=True,
    eps: float = 1e-6, reg: float = 1e-6, refine: int = 3, metric: LTIController | None = None,
    method: str = "auto",
) -> Projection:
    """Project `K` onto the convexified $(Q,S,R)$-dissipative set (paper eq. 13).

    $$\\Pi(\\tilde K) = \\arg\\min_{A,B,C,D,P}\\ \\lVert (A,B,C,D) - (\\tilde A,\\tilde B,\\tilde C,
    \\tilde D)\\rVert_W^2 + \\mu\\lVert P-\\tilde P\\rVert^2 \\quad\\text{s.t.}\\quad
    \\mathcal M(A,B,C,D,P;\\tilde P) \\preceq -\\varepsilon I,$$

    where $\\mathcal M$ is the convexified KYP LMI (paper Corollary 1 + Remark 1, with
    $-Q = LL^\\top$; see [`ConvexifiedLMI`](concepts.md)). The set is an inner
    approximation: every point in it is truly dissipative, and the exact float64 KYP
    check is run on the returned (dtype-rounded) controller and $P$ before it leaves the
    host. $\\mu$ (`reg`) is a tiny proximal weight that makes $P$ unique. The distance is
    Frobenius ($W = 1$) unless a `metric` gives each entry its own weight,
    $\\lVert X\\rVert_W^2 = \\sum_{ij} W_{ij} X_{ij}^2$ over the four matrices.

    - `P_ref` given: $\\tilde P = $ `P_ref`; a target already certified by `P_ref` comes
      back unchanged without a solve (`result` is `Outcome.unchanged`), so a certified
      controller projects onto itself.
    - `P_ref` is None: start at $\\tilde P = I$ and re-linearise at the new $P$ up to
      `refine` times; each round can only move closer to the target.

    Works eagerly, under `jax.jit` and under `jax.vmap` (the host then solves the whole
    batch on a thread pool); under `jax.shard_map` (e.g. [`sweep`][dissil_jax.sweep])
    each device sends its own batch to its own host. `qsr` is a static, hashable value: close over it or pass it
    as a static argument. For float64 set JAX's `jax_enable_x64` flag globally in your
    application (or `JAX_ENABLE_X64=1`); the thread-local `jax.enable_x64` context does not
    reach the host-callback thread.

    **Arguments:**

    - `K`: the target controller (may carry leading batch axes).
    - `qsr`: the supply rate; `qsr.Q` must be negative semidefinite.
    - `P_ref`: reference storage matrix $\\tilde P\\succ0$ (`[n, n]`, batched like `K`).
    - `throw`: raise when a projection fails (`ValueError` eagerly, an
      `EquinoxRuntimeError` under `jit`). With `throw=False` nothing is raised and
      `result` says what happened; a failed entry then holds its *uncertified* target,
      which must not be used.
    - `active`: bool, scalar or batched like `K`; inactive entries are returned as they
      are (`Outcome.skipped`) without a solve.
    - `eps`: strictness margin of the LMI, guarding the certificate against rounding.
    - `reg`: proximal weight $\\mu$ on $P$.
    - `refine`: re-linearisation rounds when `P_ref` is None.
    - `metric`: positive weights $W$ as an `LTIController` shaped (and batched) like `K`;
      only their ratios matter. Projected adaptive optimisers need it (see
      [`fit_pgd`][dissil_jax.fit_pgd] and [Concepts](concepts.md#projecting-an-adaptive-step)).
    - `method`: `"clarabel"`, `"first_order"` (ADMM in JAX, the same float64 check,
      Clarabel where it fails; Frobenius only; [Scaling out](scaling.md#a-first-order-projection))
      or `"auto"` (first-order from `_projection_fo.AUTO_MIN_ORDER` states on; now never).

    **Returns:** a [`Projection`][dissil_jax.Projection] `(K_proj, P)` with `.result`.

    ```python
    K_proj, P = dj.project(K, qsr)
    proj = dj.project(K, qsr, throw=False)
    ok = proj.result == dj.Outcome.solved
    ```
    """
    _check_qsr(K, qsr)
    _check_options(K, P_ref, active, eps, reg, refine, metric)
    in_ref, in_act = None if P_ref is None else 0, 0 if jnp.ndim(active) else None
    first_order = _projection_fo.use_first_order(method, K, metric)
    fn = partial(_projection_fo.project_one if first_order else _project_one, qsr=qsr,
                 eps=eps, reg=reg, refine=refine)
    W = jax.tree.map(jnp.ones_like, K) if metric is None else metric
    for _ in K.batch_shape:
        fn = jax.vmap(fn, in_axes=(0, in_ref, 0, in_act))
    K_out, P, codes = fn(K, P_ref, W, active)
    if throw:
        P = _raise_on_failure(P, codes)
    return Projection(K_out, P, _sdp.item(codes))
