"""Projection onto the convexified dissipative set (paper eq. 13), solved by Clarabel.

Host side: one `_ProjectionSolver` per (sizes, supply rate, margin) and per thread keeps
Clarabel's symbolic structure; a new target or a new $\\tilde P$ only changes numbers
(`solver.update(q=..., A=..., b=...)`). JAX side: `jax.pure_callback` with
`vmap_method="broadcast_all"`, so a vmapped call reaches the host once with the whole
batch, which is solved on a thread pool.
"""

from __future__ import annotations

import enum
import threading
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ._controller import LTIController
from ._lmi import ConvexifiedLMI, kyp_certified
from ._projection_args import check_options as _check_options, check_qsr as _check_qsr
from ._supply import QSR
from ._threads import num_workers, pool, single_threaded_blas


class Status(enum.IntEnum):
    """Outcome codes of one projection (returned per controller)."""

    SOLVED = 0  # projected and verified by the exact float64 KYP check
    UNCHANGED = 1  # target already certified by P_ref: returned as is, no solve
    SKIPPED = 2  # inactive (e.g. a converged trainer lane): returned as is
    INFEASIBLE = 3  # Clarabel: primal infeasible, the supply rate admits no such controller
    SOLVER_FAILED = 4  # Clarabel stopped without a solution (iterations, numerics)
    NOT_CERTIFIED = 5  # solved, but the returned point failed the exact KYP check


MESSAGES = {
    Status.INFEASIBLE: (
        "the projection SDP is infeasible: `qsr` admits no strictly dissipative controller of "
        "these sizes near the reference P. Check the supply rate (e.g. R and S signs), or pass "
        "a different `P_ref`."
    ),
    Status.SOLVER_FAILED: (
        "Clarabel failed to solve the projection SDP (max iterations or numerical trouble); "
        "the target may be badly scaled."
    ),
    Status.NOT_CERTIFIED: (
        "the projection's solution failed the exact float64 KYP check even with an enlarged "
        "margin; no controller is returned without a certificate."
    ),
}


_INFEASIBLE = {"PrimalInfeasible", "AlmostPrimalInfeasible"}
_OK = {"Solved", "AlmostSolved"}


def _settings():
    import clarabel

    s = clarabel.DefaultSettings()
    s.verbose = False
    s.presolve_enable = False  # required for in-place data updates
    s.chordal_decomposition_enable = False
    s.input_sparse_dropzeros = False
    s.max_iter = 100
    # A reused solver keeps the equilibration of the problem that built it, which made
    # results depend (at ~1e-5) on which thread's solver got which target. Our data are
    # well scaled, so equilibration is off and results are reproducible bit for bit.
    s.equilibrate_enable = False
    return s


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
        M0 = lmi.M0.copy()
        self.b_fixed = lmi.svec(-M0 - eps * np.eye(N))
        i3 = N - n
        sel = np.zeros((n * n, N, N))
        for c in range(n):
            for a in range(n):
                sel[c * n + a, i3 + c, i3 + a] = 2.0
        self.b_g = lmi.svec(sel).T  # [L, n*n]
        self.eps_svec = lmi.svec(np.eye(N))
        nth, nP = lmi.ntheta, lmi.nP
        diag = np.concatenate([np.ones(nth), np.full(nP, reg)])
        self.P_obj = sp.diags(diag).tocsc()
        self.cones = [clarabel.PSDTriangleConeT(N)]
        self.solver = None
        self._clarabel = clarabel

    def _data(self, P_tilde, target, eps):
        Pt = np.asarray(P_tilde, np.float64).ravel()
        vals = self.vals0.copy()
        vals[self.ab_pos] = self.vals_g @ Pt
        b = self.b_fixed + self.b_g @ Pt - (eps - self.eps) * self.eps_svec
        p_tilde = np.asarray(P_tilde, np.float64)[self.lmi.p_rows, self.lmi.p_cols]
        q = -np.concatenate([target, self.reg * p_tilde])
        return q, vals, b

    def solve(self, target: np.ndarray, P_tilde: np.ndarray, eps: float):
        """Solve Π at this P̃; returns (x or None, clarabel status string, solve time)."""
        q, vals, b = self._data(P_tilde, target, eps)
        if self.solver is None:
            A = sp.csc_matrix((vals, self.indices, self.indptr), shape=self.csc_shape)
            self.solver = self._clarabel.DefaultSolver(self.P_obj, q, A, b, self.cones,
                                                       _settings())
        else:
            self.solver.update(q=q, A=vals, b=b)
        sol = self.solver.solve()
        status = str(sol.status)
        x = np.asarray(sol.x) if status in _OK else None
        return x, status, float(sol.solve_time)


_LOCAL = threading.local()
# Clarabel's own reported solve time and solve count, summed over all threads (benchmarks).
SOLVER_STATS = {"solve_time": 0.0, "solves": 0}
_STATS_LOCK = threading.Lock()
_LMI_CACHE: dict = {}
_LMI_LOCK = threading.Lock()


def _config_key(qsr: QSR, n: int, eps: float, reg: float):
    return (n, qsr.n_in, qsr.n_out, qsr.Q.tobytes(), qsr.S.tobytes(), qsr.R.tobytes(), eps, reg)


def _get_solver(key, qsr: QSR) -> _ProjectionSolver:
    cache = getattr(_LOCAL, "solvers", None)
    if cache is None:
        cache = _LOCAL.solvers = {}
    solver = cache.get(key)
    if solver is None:
        with _LMI_LOCK:
            lmi = _LMI_CACHE.get(key[:6])
            if lmi is None:
                lmi = _LMI_CACHE[key[:6]] = ConvexifiedLMI(key[0], key[1], key[2], qsr)
        solver = cache[key] = _ProjectionSolver(lmi, eps=key[6], reg=key[7])
    return solver


def _cast(x, dtype):
    return np.asarray(x).astype(dtype).astype(np.float64)


def _solve_once(qsr: QSR, A, B, C, D, P_tilde, *, eps, reg, dtype):
    """One Clarabel solve at this P̃; returns ((A, B, C, D, P) rounded to dtype | None, status, t)."""
    solver = _get_solver(_config_key(qsr, A.shape[0], eps, reg), qsr)
    x, cl_status, t = solver.solve(solver.lmi.pack(A, B, C, D), P_tilde, eps)
    if x is None:
        return None, (Status.INFEASIBLE if cl_status in _INFEASIBLE else Status.SOLVER_FAILED), t
    return tuple(_cast(M, dtype) for M in solver.lmi.unpack(x)), Status.SOLVED, t


def project_one(
    qsr: QSR, A, B, C, D, P_ref, *, has_ref: bool, eps: float, reg: float, refine: int,
    dtype=np.float64,
):
    """Host-side projection of one controller. Returns (A, B, C, D, P, status, solve_time).

    The returned controller is always the target or a solution that passed the exact KYP
    check *after* rounding to `dtype`; on failure the status says so and the caller must
    not use the returned controller (it is the unchanged target).
    """
    target_mats = (A, B, C, D)
    if has_ref and kyp_certified(A, B, C, D, qsr, P_ref):
        return (*target_mats, P_ref, Status.UNCHANGED, 0.0)
    target = np.concatenate([np.ravel(M) for M in target_mats])
    P_tilde = np.asarray(P_ref, np.float64) if has_ref else np.eye(A.shape[0])
    best, best_dist, status, total_time = None, np.inf, Status.SOLVER_FAILED, 0.0
    for _ in range(1 if has_ref else max(1, refine)):
        cur_eps, sol = eps, None
        for _attempt in range(3):  # enlarge the margin if rounding breaks the certificate
            sol, status, t = _solve_once(qsr, A, B, C, D, P_tilde, eps=cur_eps, reg=reg,
                                         dtype=dtype)
            total_time += t
            if sol is None:
                if _attempt:  # a larger margin failed after a solution that was not certified
                    status = Status.NOT_CERTIFIED
                break
            if kyp_certified(*sol[:4], qsr, sol[4]):
                dist = np.sum((np.concatenate([np.ravel(M) for M in sol[:4]]) - target) ** 2)
                if dist < best_dist:
                    best, best_dist = sol, dist
                break
            status, sol = Status.NOT_CERTIFIED, None
            cur_eps *= 100.0
        if sol is None:
            break
        P_tilde = best[4]  # re-linearise the P^{-1} overbound at the new P (the convexified LMI of `docs/concepts.md`)
    if best is not None:
        return (*best, Status.SOLVED, total_time)
    return (*target_mats, np.asarray(P_tilde), status, total_time)


def _host_batch(A, B, C, D, P_ref, active, *, qsr, has_ref, eps, reg, refine):
    """pure_callback target: arrays carry identical leading batch axes (broadcast_all).

    With a reference P the hot path is: one batched KYP check of all targets (certified
    ones come back unchanged), one Clarabel solve per remaining target on the thread pool,
    one batched KYP check of all solutions; the rare failures go through `project_one`'s
    retry logic. Without a reference every target goes through `project_one`.
    """
    dtype = np.asarray(A).dtype
    batch = A.shape[:-2]
    n, p, m = A.shape[-1], B.shape[-1], C.shape[-2]
    flat = [np.asarray(M, np.float64).reshape((-1,) + M.shape[len(batch):])
            for M in (A, B, C, D, P_ref)]
    act = np.asarray(active).reshape(-1)
    out = [M.copy() for M in flat]
    status = np.full(act.shape[0], int(Status.SKIPPED), np.int32)
    kw = dict(eps=eps, reg=reg)

    if has_ref:
        unchanged = act & kyp_certified(*flat[:4], qsr, flat[4])
        status[unchanged] = int(Status.UNCHANGED)
        todo = np.nonzero(act & ~unchanged)[0]
    else:
        todo = np.nonzero(act)[0]

    def work(indices):
        spent, solves = 0.0, 0
        for i in indices:
            if has_ref:
                sol, st, t = _solve_once(qsr, *(M[i] for M in flat), dtype=dtype, **kw)
                res = (*(sol or ()), st, t)
            else:
                res = project_one(qsr, *(M[i] for M in flat), has_ref=False, refine=refine,
                                  dtype=dtype, **kw)
            if res[-2] == Status.SOLVED:
                for o, M in zip(out, res[:5]):
                    o[i] = M
            status[i] = int(res[-2])
            spent += res[-1]
            solves += 1
        with _STATS_LOCK:
            SOLVER_STATS["solve_time"] += spent
            SOLVER_STATS["solves"] += solves

    with single_threaded_blas():
        workers = min(num_workers(), len(todo))
        if workers <= 1:
            work(todo)
        else:
            list(pool().map(work, np.array_split(todo, workers)))
        if has_ref and len(todo):
            # Exact float64 check of every new solution at once; retry the rare failures.
            solved = todo[status[todo] == Status.SOLVED]
            bad = solved[~np.atleast_1d(kyp_certified(*(o[solved] for o in out[:4]), qsr,
                                                      out[4][solved]))]
            for i in bad:
                res = project_one(qsr, *(M[i] for M in flat), has_ref=True, refine=1,
                                  dtype=dtype, eps=eps * 100, reg=reg)
                if res[5] == Status.SOLVED:
                    for o, M in zip(out, res[:5]):
                        o[i] = M
                status[i] = int(res[5])
    failed = status >= Status.INFEASIBLE
    for o, M in zip(out, flat):  # failures return the (uncertified) target, flagged
        o[failed] = M[failed]
    shapes = [batch + s for s in ((n, n), (n, p), (m, n), (m, p), (n, n))]
    return (*(o.reshape(s).astype(dtype) for o, s in zip(out, shapes)),
            status.reshape(batch))


def project_with_status(
    K: LTIController, qsr: QSR, P_ref=None, active=True, *, eps: float = 1e-6,
    reg: float = 1e-6, refine: int = 3,
):
    """Like [`project`][dissil_jax.project] but never raises on solver failure.

    **Returns:** `(K_proj, P, status)` with `status` an int32 [`Status`][dissil_jax.Status]
    code; for codes >= 3 (`INFEASIBLE`, `SOLVER_FAILED`, `NOT_CERTIFIED`) `K_proj` is the
    *uncertified* target and must not be used (the trainers keep their previous iterate).
    """
    _check_qsr(K, qsr)
    _check_options(K, P_ref, active, eps, reg, refine)
    if K.batch_shape:
        in_ref = None if P_ref is None else 0
        in_act = 0 if jnp.ndim(active) else None
        fn = lambda K_, P_, a_: project_with_status(K_, qsr, P_, a_, eps=eps, reg=reg,
                                                    refine=refine)
        for _ in K.batch_shape:
            fn = jax.vmap(fn, in_axes=(0, in_ref, in_act))
        return fn(K, P_ref, active)
    n = K.n_state
    dtype = K.A.dtype
    has_ref = P_ref is not None
    if has_ref:
        P_ref = jnp.asarray(P_ref, dtype)
        if P_ref.shape != (n, n):
            raise ValueError(f"`P_ref` must be {n}x{n}, got {P_ref.shape}.")
    else:
        P_ref = jnp.eye(n, dtype=dtype)
    shapes = (
        jax.ShapeDtypeStruct(K.A.shape, dtype),
        jax.ShapeDtypeStruct(K.B.shape, dtype),
        jax.ShapeDtypeStruct(K.C.shape, dtype),
        jax.ShapeDtypeStruct(K.D.shape, dtype),
        jax.ShapeDtypeStruct((n, n), dtype),
        jax.ShapeDtypeStruct((), jnp.int32),
    )
    callback = partial(_host_batch, qsr=qsr, has_ref=has_ref, eps=float(eps), reg=float(reg),
                       refine=int(refine))
    A, B, C, D, P, status = jax.pure_callback(
        callback, shapes, K.A, K.B, K.C, K.D, P_ref, jnp.asarray(active, bool),
        vmap_method="broadcast_all",
    )
    return LTIController(A, B, C, D), P, status


def project(
    K: LTIController, qsr: QSR, P_ref=None, *, eps: float = 1e-6, reg: float = 1e-6,
    refine: int = 3,
):
    """Project `K` onto the convexified $(Q,S,R)$-dissipative set (paper eq. 13).

    $$\\Pi(\\tilde K) = \\arg\\min_{A,B,C,D,P}\\ \\lVert (A,B,C,D) - (\\tilde A,\\tilde B,\\tilde C,
    \\tilde D)\\rVert_F^2 + \\mu\\lVert P-\\tilde P\\rVert^2 \\quad\\text{s.t.}\\quad
    \\mathcal M(A,B,C,D,P;\\tilde P) \\preceq -\\varepsilon I,$$

    where $\\mathcal M$ is the convexified KYP LMI (paper Corollary 1 + Remark 1, with
    $-Q = LL^\\top$; see [`ConvexifiedLMI`](concepts.md)). The set is an inner
    approximation: every point in it is truly dissipative, and the exact float64 KYP
    check is run on the returned (dtype-rounded) controller and $P$ before it leaves the
    host. $\\mu$ (`reg`) is a tiny proximal weight that makes $P$ unique.

    - `P_ref` given: $\\tilde P = $ `P_ref`; a target already certified by `P_ref` comes
      back unchanged without a solve (so a certified controller projects onto itself).
    - `P_ref` is None: start at $\\tilde P = I$ and re-linearise at the new $P$ up to
      `refine` times; each round can only move closer to the target.

    Works eagerly, under `jax.jit` and under `jax.vmap` (the host then solves the whole
    batch on a thread pool). `qsr` must be closed over, not traced. For float64 set JAX's
    `jax_enable_x64` flag globally in your application (or `JAX_ENABLE_X64=1`); the
    thread-local `jax.enable_x64` context does not reach the host-callback thread.

    **Arguments:**

    - `K`: the target controller (may carry leading batch axes).
    - `qsr`: the supply rate; `qsr.Q` must be negative semidefinite.
    - `P_ref`: reference storage matrix $\\tilde P\\succ0$ (`[n, n]`, batched like `K`).
    - `eps`: strictness margin of the LMI, guarding the certificate against rounding.
    - `reg`: proximal weight $\\mu$ on $P$.
    - `refine`: re-linearisation rounds when `P_ref` is None.

    **Returns:** `(K_proj, P)`. A failed solve raises: `ValueError` eagerly, an
    `EquinoxRuntimeError` under `jit`.
    """
    K_out, P, status = project_with_status(K, qsr, P_ref, eps=eps, reg=reg, refine=refine)
    if not isinstance(status, jax.core.Tracer):
        worst = int(np.max(np.asarray(status)))
        if worst >= Status.INFEASIBLE:
            raise ValueError(f"dj.project: {MESSAGES[Status(worst)]}")
        return K_out, P
    failed = status >= int(Status.INFEASIBLE)
    index = jnp.clip(jnp.max(status) - int(Status.INFEASIBLE), 0, 2)
    msgs = [MESSAGES[s] for s in (Status.INFEASIBLE, Status.SOLVER_FAILED, Status.NOT_CERTIFIED)]
    P = eqx.branched_error_if(P, jnp.any(failed), index, msgs)
    return K_out, P
