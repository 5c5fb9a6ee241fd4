"""Projection onto the convexified dissipative set (paper eq. 13), solved by Clarabel.

Host side: one `_ProjectionSolver` per (sizes, supply rate, margin) and per thread keeps
Clarabel's symbolic structure; a new target or a new $\\tilde P$ only changes numbers
(`solver.update(q=..., A=..., b=...)`). The numbers of a whole batch are built at once
with numpy, the solves are spread over the thread pool, and the solutions are unpacked,
rounded and checked (exact float64 KYP) as one batch. JAX side: `jax.pure_callback` with
`vmap_method="broadcast_all"`, so a vmapped call reaches the host once with the whole batch.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .. import _outcome
from .._certify import fast as _certify_fast
from .._controller import LTIController
from .._progress import working
from .._rate_scale import rate_factor, scaled_rate
from .._sdp import sdp as _sdp
from .._sdp.lmi import certified
from .._supply import QSR
from .._validate import check_flag, no_derivative
from . import cache as _cache, first_order as _projection_fo
from .args import (
    check_eps_room as _check_eps_room,
    check_k_ref as _check_k_ref,
    check_options as _check_options,
    check_qsr as _check_qsr,
)
from .cache import P_FLOOR as P_FLOOR
from .handle import RateHandle, resolve
from .relinearise import project_rows_indefinite
from .result import Projection as Projection, raise_on_failure as _raise_on_failure
from .rows import (
    _STATS,
    _STATS_LOCK,
    indefinite_solve as _indefinite_solve,
    project_rows as _project_rows,
    solver_stats as solver_stats,
)

_SOLVED, _UNCHANGED, _SKIPPED, _NOT_CERTIFIED = (
    _outcome.code(n) for n in ("solved", "unchanged", "skipped", "not_certified"))


def _host_batch(A, B, C, D, P_ref, WA, WB, WC, WD, active, C0, D0, shard, token=None, *, qsr,
                has_ref, eps, reg, refine, shards):
    """pure_callback target: arrays carry identical leading batch axes (broadcast_all).

    Active targets already certified by `P_ref` come back unchanged; the others are
    projected as one batch (`_project_rows`). Failed rows return their target, flagged.
    `shard` is the calling device's index (broadcast like the batch) and `shards` the
    number of callbacks running at once on this host (`_sdp.shard`); each uses its share
    of the thread pool. `WA`..`WD` are the metric's weights (scaled per row to at most 1).
    `C0`, `D0` are the first linearisation points of an indefinite $Q$ (`relinearise.py`).
    With `qsr` None the rate is `token`'s (`rate_handle`; broadcast like the batch).
    """
    if qsr is None:
        assert token is not None  # `_project_one` passes one with a `RateHandle`
        qsr = resolve(token)
    dtype = np.asarray(A).dtype
    batch, n = A.shape[:-2], A.shape[-1]
    with _STATS_LOCK:
        index = int(np.ravel(shard)[0]) if np.size(shard) else 0
        _STATS["callbacks"][index, int(np.prod(batch))] += 1
    flat = [np.asarray(M, np.float64).reshape((-1,) + M.shape[len(batch):])
            for M in (A, B, C, D, P_ref)]
    act = np.asarray(active).reshape(-1)
    out = [M.copy() for M in flat]
    codes = np.full(act.shape[0], _SKIPPED, np.int32)
    todo = np.nonzero(act)[0]
    if has_ref and len(todo):
        A_, B_, C_, D_, P_ = (M[todo] for M in flat)
        keep = certified(A_, B_, C_, D_, qsr, P_)
        codes[todo[keep]] = _UNCHANGED
        todo = todo[~keep]
    if len(todo):  # minutes at high orders with an indefinite Q: a heartbeat says so
        with working("project", f"solving {len(todo)} projection SDP(s) of order {n}"):
            _solve_rows(flat, todo, codes, out, batch, qsr, has_ref, WA, WB, WC, WD, C0,
                        D0, eps=eps, reg=reg, refine=refine, dtype=dtype, shards=shards)
    return (*(o.reshape(batch + o.shape[1:]).astype(dtype) for o in out),
            codes.reshape(batch))


def _solve_rows(flat, todo, codes, out, batch, qsr, has_ref, WA, WB, WC, WD, C0, D0, *,
                eps, reg, refine, dtype, shards):
    """`_host_batch`'s projections of the rows `todo` (Clarabel), written into `out` and
    `codes` in place."""
    n = flat[0].shape[-1]
    layout = _cache.lmi(qsr, n).layout
    targets = layout.pack(*(M[todo] for M in flat[:4]))
    w = layout.pack(*(np.asarray(W, np.float64).reshape((-1,) + W.shape[len(batch):])[todo]
                      for W in (WA, WB, WC, WD)))
    w /= w.max(axis=1, keepdims=True)
    P_tilde = flat[4][todo] if has_ref else np.broadcast_to(np.eye(n), (len(todo), n, n))
    if _cache.lmi(qsr, n).indefinite:
        H0 = tuple(np.asarray(M, np.float64).reshape((-1,) + M.shape[len(batch):])[todo]
                   for M in (C0, D0))
        solve = partial(_indefinite_solve, qsr, eps=eps, reg=reg, dtype=dtype, shards=shards)
        sol, codes[todo] = project_rows_indefinite(solve, layout, qsr, targets, P_tilde, H0,
                                                   w, max(1, refine))
    else:
        kw = dict(eps=eps, reg=reg, dtype=dtype, shards=shards)
        sol, c = _project_rows(qsr, targets, P_tilde, w, 1 if has_ref else max(1, refine), **kw)
        retry = np.nonzero(c != _SOLVED)[0] if has_ref else ()
        if len(retry):
            # A P_ref that leaves the linearised set (almost) empty, e.g. one whose smallest
            # eigenvalue sits on the margin eps: start again from a multiple of the identity
            # and re-linearise, as without P_ref.
            scale = np.trace(P_tilde[retry], axis1=1, axis2=2) / n
            scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
            sol2, c2 = _project_rows(qsr, targets[retry], scale[:, None, None] * np.eye(n),
                                     w[retry], max(1, refine), **kw)
            for S, S2 in zip(sol, sol2):
                S[retry[c2 == _SOLVED]] = S2[c2 == _SOLVED]
            c[retry[c2 == _SOLVED]] = _SOLVED
        codes[todo] = c
    done = todo[codes[todo] == _SOLVED]
    for o, M in zip(out, sol):
        o[done] = M[codes[todo] == _SOLVED]
    # `certify` of a returned controller then finds its storage without an SDP
    A_, B_, C_, D_, P_ = (M[codes[todo] == _SOLVED] for M in sol)
    _certify_fast.remember(A_, B_, C_, D_, qsr, P_)


def _project_one(K: LTIController, P_ref, W: LTIController, active, K_ref, *,
                 qsr: QSR | RateHandle, eps, reg, refine):
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
    handle = isinstance(qsr, RateHandle)
    callback = partial(_host_batch, qsr=None if handle else qsr, has_ref=has_ref,
                       eps=float(eps), reg=float(reg), refine=int(refine), shards=shards)
    token = (qsr.token,) if handle else ()
    A, B, C, D, P, codes = jax.pure_callback(
        callback, (*shapes, jax.ShapeDtypeStruct((), jnp.int32)),
        *(no_derivative("dj.project", M) for M in (K.A, K.B, K.C, K.D)), P_ref, W.A, W.B, W.C,
        W.D, jnp.asarray(active, bool), K_ref.C.astype(dtype), K_ref.D.astype(dtype), shard,
        *token, vmap_method="broadcast_all")
    return LTIController(A, B, C, D), P, codes


def _project_fo_cold(*args, **kwargs):
    return _projection_fo.project_one(*args, fallback=_host_batch, floor=P_FLOOR, **kwargs)[:3]


def project_first_order_warm(K: LTIController, qsr: QSR | RateHandle, P_ref, state, *, active, eps: float,
                             reg: float = 1e-6, metric: LTIController | None = None,
                             tol: float | None = None):
    """`project(K, qsr, P_ref, method="first_order", throw=False, active=active, eps=eps,
    metric=metric)` for a batch (one leading axis), started from the ADMM `state` of a
    previous projection (batched like `K`; `first_order.cold_state` for none, with the
    target when there is a `metric`). PGD carries it across its steps. `tol`: ADMM's
    residual tolerance, by default `first_order.TOL_FO_PGD` (PGD's; `project` uses
    `TOL_FO`).

    **Returns:** `(Projection, state)`, the latter for the next call.
    """
    tol = _projection_fo.TOL_FO_PGD if tol is None else tol
    fn = partial(_projection_fo.project_one, qsr=qsr, eps=eps, reg=reg, refine=1,
                 fallback=_host_batch, floor=P_FLOOR, weighted=metric is not None, tol=tol)
    W = jax.tree.map(jnp.ones_like, K) if metric is None else metric
    K_out, P, codes, state = jax.vmap(
        lambda K, P, W, a, s: fn(K, P, W, a, K, state=s))(K, P_ref, W, active, state)
    return Projection(K_out, P, _outcome.item(codes)), state


def project(
    K: LTIController, qsr: QSR, P_ref=None, *, throw: bool = True, active=True,
    eps: float = 1e-6, reg: float = 1e-6, refine: int = 3, metric: LTIController | None = None,
    K_ref: LTIController | None = None, method: str = "auto",
) -> Projection:
    """Project `K` onto the convexified $(Q,S,R)$-dissipative set (paper eq. 13).

    $$\\begin{aligned}\\Pi(\\tilde K) = \\arg\\min_{A,B,C,D,P}\\ & \\lVert (A,B,C,D) - (\\tilde A,
    \\tilde B,\\tilde C,\\tilde D)\\rVert_W^2 + \\mu\\lVert P-\\tilde P\\rVert^2\\\\
    \\text{s.t.}\\ & \\mathcal M(A,B,C,D,P;\\tilde P) \\preceq -\\varepsilon I,\\end{aligned}$$

    where $\\mathcal M$ is the convexified KYP LMI (paper Corollary 1 + Remark 1, with
    $-Q = LL^\\top$; see [`ConvexifiedLMI`](concepts.md)). For an indefinite
    $Q = Q_+ - Q_-$ the concave $-H^\\top Q_+H$ ($H = [C\\ D]$) is replaced by its
    linearisation around a point $H_0$
    ([Concepts](concepts.md#indefinite-q-linearising-the-positive-part)): the target's, or
    `K_ref`'s when given (a certified reference, e.g. the previous iterate); a target whose
    first set is empty starts again from a static controller that is dissipative for every
    $P$. Each round re-linearises $H_0$ and $\\tilde P$ at the solution, at most `refine`
    times (also with `P_ref`), and stops once a round shortens the distance by less than
    0.1 %. The set is an inner
    approximation: every point in it is truly dissipative, and the exact float64 KYP
    check is run on the returned (dtype-rounded) controller and $P$ before it leaves the
    host. $\\mu$ (`reg`) is a tiny proximal weight that makes $P$ unique. For
    $\\hat n\\ge2$ the set also asks $P\\succeq\\frac{\\rho}{\\hat n}\\operatorname{tr}(P)\\,I$
    with $\\rho = 10^{-2}$ (`P_FLOOR`): a storage whose smallest eigenvalue fell to the
    margin $\\varepsilon$ would leave the next projection, linearised there, a feasible set
    of zero width (a `not_certified` failure), and PGD stalls on such storages. The distance is
    Frobenius ($W = 1$) unless a `metric` gives each entry its own weight,
    $\\lVert X\\rVert_W^2 = \\sum_{ij} W_{ij} X_{ij}^2$ over the four matrices.

    - `P_ref` given: $\\tilde P$ is `P_ref`; a target already certified by `P_ref` comes
      back unchanged without a solve (`result` is `Outcome.unchanged`), so a certified
      controller projects onto itself. A projection that fails at `P_ref` is retried from
      $\\tilde P = \\frac{\\operatorname{tr}P_{\\text{ref}}}{\\hat n} I$ with `refine` rounds
      (for an indefinite $Q$: from the static point, as above).
    - `P_ref` is None: start at $\\tilde P = I$ and re-linearise at the new $P$ up to
      `refine` times; each round can only move closer to the target.

    Works eagerly, under `jax.jit` and under `jax.vmap` (the host then solves the whole
    batch on a thread pool); under `jax.shard_map` (e.g. [`sweep`][dissil_jax.sweep])
    each device sends its own batch to its own host; not under `jax.grad`/`jax.jacfwd` (a
    `ValueError`: the SDP has no derivative). `qsr` is static: close over it or pass it as
    a static argument. In float64 a call works under `with jax.enable_x64(True):` (its
    callback runs on the calling thread); inside a compiled loop enable x64 process-wide.

    **Arguments:**

    - `K`: the target controller (may carry leading batch axes).
    - `qsr`: the supply rate (any symmetric $Q$; one with no strictly dissipative static
      controller, hence none at all, raises a `ValueError`).
    - `P_ref`: reference storage matrix $\\tilde P\\succ0$: `[n, n]`, shared by a batch, or
      batched like `K`.
    - `throw`: raise when a projection fails (`ValueError` eagerly, a `JaxRuntimeError`
      under `jax.jit`, an `EquinoxRuntimeError` under `eqx.filter_jit`). With `throw=False` nothing is raised and
      `result` says what happened; a failed entry then holds its *uncertified* target,
      which must not be used.
    - `active`: bool, scalar or batched like `K`; inactive entries are returned as they
      are (`Outcome.skipped`) without a solve.
    - `eps`: strictness margin of the LMI, guarding the certificate against rounding. It
      is absolute for rates whose largest entry lies in $[1/64, 64]$; a rate outside is
      solved divided by the power of two nearest that entry (`P` multiplied back, exactly),
      and `eps` is the margin there. It must be small against the rate: for $Q\\prec0$
      a margin at or above $\\lambda_{\\min}(R - S^\\top Q^{-1}S)$, the most any feedthrough
      leaves in the LMI's input block (e.g. $10^{-8}$ for a gain bound of $10^{-4}$), is
      refused with a `ValueError` naming `eps` (as in `fit_pgd` and `fit_ico`). A narrow
      cone far from zero (a centre's term $-S^\\top Q^{-1}S$ over 64 times that room along
      some direction) is
      solved about its centre, $D + Q^{-1}S$, an exact change of variables that leaves
      the distance and the KYP matrix as they are
      ([concepts](concepts.md#narrow-cones-far-from-zero)); the check is in the rate as
      given.
    - `reg`: proximal weight $\\mu$ on $P$.
    - `refine`: re-linearisation rounds when `P_ref` is None.
    - `metric`: positive weights $W$ as an `LTIController` shaped (and batched) like `K`;
      only their ratios matter. Projected adaptive optimisers need it (see
      [`fit_pgd`][dissil_jax.fit_pgd] and [Concepts](concepts.md#projecting-an-adaptive-step)).
    - `K_ref`: for an indefinite $Q$, the first linearisation point of $Q_+$'s term (an
      `LTIController` shaped and batched like `K`, ideally certified with `P_ref`); ignored
      for $Q\\preceq0$. Default: the target itself.
    - `method`: `"clarabel"`, `"first_order"` (ADMM in JAX, the same float64 check,
      Clarabel where it fails; $Q\\preceq0$ only;
      [Scaling out](scaling.md#a-first-order-projection)) or `"auto"` (first-order from
      `first_order.AUTO_MIN_ORDER` = 12 states on, and with a `metric` from
      `first_order.AUTO_MIN_ORDER_METRIC` = 12, for $Q\\preceq0$; Clarabel otherwise).

    **Returns:** a [`Projection`][dissil_jax.Projection] `(K_proj, P)` with `.result`. (SDPs
    that take over 10 s, e.g. at high orders with an indefinite $Q$, say so on standard
    error every 10 s, except inside a trainer, which reports itself.)

    ```python
    K_proj, P = dj.project(K, qsr)
    proj = dj.project(K, qsr, throw=False)
    ok = proj.result == dj.Outcome.solved
    ```
    """
    check_flag("throw", throw)
    _sdp.num_workers()  # a bad DISSIL_JAX_THREADS raises its ValueError here, on the host
    if isinstance(qsr, RateHandle):  # a trainer's: checked and scaled
        _check_options(K, P_ref, active, eps, reg, refine, metric)
        k = 1.0
    else:
        _check_qsr(K, qsr)
        _check_options(K, P_ref, active, eps, reg, refine, metric)
        _check_eps_room(qsr, eps)
        k = rate_factor(qsr)  # a rate far from unit size: divided by a power of two (exact)
        qsr = scaled_rate(qsr, k)
    first_order = _projection_fo.use_first_order(method, K.n_state, metric is not None, qsr)
    _check_k_ref(K, K_ref)
    P_ref = None if P_ref is None else jnp.asarray(P_ref) / k  # checked real above
    fn = partial(partial(_project_fo_cold, weighted=metric is not None) if first_order else
                 _project_one, qsr=qsr, eps=eps, reg=reg, refine=refine)
    W = jax.tree.map(jnp.ones_like, K) if metric is None else metric
    in_ref = 0 if P_ref is not None and jnp.ndim(P_ref) > 2 else None
    for _ in K.batch_shape:  # an [n, n] P_ref and a scalar `active` are shared by the batch
        fn = jax.vmap(fn, in_axes=(0, in_ref, 0, 0 if jnp.ndim(active) else None, 0))
    K_out, P, codes = fn(K, P_ref, W, active, K if K_ref is None else K_ref)
    if throw:
        P = _raise_on_failure(P, codes)
    return Projection(K_out, P * k if k != 1.0 else P, _outcome.item(codes))
