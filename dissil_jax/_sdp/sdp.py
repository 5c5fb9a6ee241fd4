"""The host-side SDP layer shared by the projection and ICO.

It owns, in one place:

- the Clarabel settings of each problem family ([`clarabel_settings`]) and the mapping of
  Clarabel's status strings onto [`Outcome`][dissil_jax.Outcome] codes (`_outcome.py`);
- [`Layout`], the variable vector $x = (\\operatorname{vec}A, \\operatorname{vec}B,
  \\operatorname{vec}C, \\operatorname{vec}D, \\operatorname{triu}P)$ with batched
  `pack`/`unpack`;
- `thread_map`, which spreads per-item solves over the process-wide pool with BLAS held to
  one thread, giving each of several concurrent shards its share of the pool (`shard`).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import TypedDict

import jax
import jax.numpy as jnp
import numpy as np

from .._outcome import code

_CLARABEL_OK = {"Solved", "AlmostSolved"}
_CLARABEL_INFEASIBLE = {"PrimalInfeasible", "AlmostPrimalInfeasible"}


def clarabel_outcome(status: str) -> int:
    """Clarabel's status string as an `Outcome` code: solved, infeasible or solver_failed."""
    if status in _CLARABEL_OK:
        return code("solved")
    return code("infeasible" if status in _CLARABEL_INFEASIBLE else "solver_failed")


def clarabel_settings(*, max_iter: int, equilibrate: bool, tol: float | None = None):
    """Clarabel settings for a solver whose data are later updated in place.

    In-place updates (`solver.update(q=..., A=..., b=...)`) need presolve, chordal
    decomposition and zero-dropping off. The two problem families differ in two settings:

    - the projection (`max_iter=100`, `equilibrate=False`): a solver is reused across
      targets by whichever pool thread picks them up, and a reused solver keeps the
      equilibration of the problem that built it, which made results depend (at ~1e-5) on
      the thread; the projection's data are well scaled, so equilibration is off and the
      results are reproducible bit for bit;
    - ICO (`max_iter=200`, `equilibrate=True`, gap and feasibility tolerances `1e-10`):
      one solver per initialisation, whose data (loss Jacobians) span several orders of
      magnitude and need equilibration. The tighter tolerances (Clarabel's default is
      `1e-8`) make the iterates reproducible to ~1e-6 under a change of units of the data,
      where the defaults left differences of ~3e-5 after a few steps.
    """
    import clarabel

    s = clarabel.DefaultSettings()
    s.verbose = False
    s.presolve_enable = False
    s.chordal_decomposition_enable = False
    s.input_sparse_dropzeros = False
    s.max_iter = int(max_iter)
    s.equilibrate_enable = bool(equilibrate)
    # One thread per solve: the batched solves already run on the pool's threads (more
    # made a projection at n = 24 slower, 2.8 s against 2.5 s), and the direct solver
    # stays `auto` (faer), five times faster than qdldl there.
    s.max_threads = 1
    if tol is not None:
        s.tol_gap_abs = s.tol_gap_rel = s.tol_feas = float(tol)
    return s


class _SettingsRequired(TypedDict):
    max_iter: int
    equilibrate: bool


class SolverSettings(_SettingsRequired, total=False):
    """The keyword arguments of `clarabel_settings` of one problem family."""

    tol: float


PROJECTION_SETTINGS: SolverSettings = {"max_iter": 100, "equilibrate": False}
ICO_SETTINGS: SolverSettings = {"max_iter": 200, "equilibrate": True, "tol": 1e-10}


class Layout:
    """The SDP variable vector of a controller with $n$ states, $p$ inputs, $m$ outputs.

    $x = (\\operatorname{vec}A, \\operatorname{vec}B, \\operatorname{vec}C,
    \\operatorname{vec}D, p)$, with `vec` row-major (numpy's `ravel`) and $p$ the upper
    triangle of $P$ row-major (`np.triu_indices`), $P = \\sum_k p_k E_k$. The first
    `ntheta` entries are the controller $\\theta$. `pack` and `unpack` accept leading batch
    axes.
    """

    def __init__(self, n: int, p: int, m: int):
        self.n, self.p, self.m = n, p, m
        self.nA, self.nB, self.nC, self.nD = n * n, n * p, m * n, m * p
        self.ntheta = self.nA + self.nB + self.nC + self.nD
        self.p_rows, self.p_cols = np.triu_indices(n)
        self.nP = len(self.p_rows)
        self.nx = self.ntheta + self.nP
        self._offsets = np.cumsum([0, self.nA, self.nB, self.nC, self.nD])
        self._shapes = ((n, n), (n, p), (m, n), (m, p))

    def pack(self, A, B, C, D, P=None) -> np.ndarray:
        """$x$ (or $\\theta$ when `P` is None) of a controller, batched like the inputs."""
        mats = [np.asarray(M, np.float64) for M in (A, B, C, D)]
        batch = mats[0].shape[:-2]
        parts = [M.reshape(batch + (-1,)) for M in mats]
        if P is not None:
            parts.append(np.asarray(P, np.float64)[..., self.p_rows, self.p_cols])
        return np.concatenate(parts, axis=-1)

    def mats(self, theta) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`(A, B, C, D)` from $\\theta$ (or from $x$, ignoring $P$), batched."""
        theta = np.asarray(theta)
        batch, o = theta.shape[:-1], self._offsets
        A, B, C, D = (theta[..., o[i]:o[i + 1]].reshape(batch + s)
                      for i, s in enumerate(self._shapes))
        return A, B, C, D

    def P(self, p, scale=1.0) -> np.ndarray:
        """The symmetric $P$ from its upper-triangle coordinates $p$ (times `scale`), batched."""
        p = np.asarray(p, np.float64)
        P = np.zeros(p.shape[:-1] + (self.n, self.n))
        P[..., self.p_rows, self.p_cols] = scale * p
        return P + np.triu(P, 1).swapaxes(-1, -2)

    def unpack(self, x):
        """`(A, B, C, D, P)` from $x$, batched."""
        x = np.asarray(x)
        return (*self.mats(x), self.P(x[..., self.ntheta:]))


# -- threads -----------------------------------------------------------------------------

_POOL: ThreadPoolExecutor | None = None
_CONTROLLER = None
# The BLAS limit is process-wide: it is applied by the first of several concurrent users
# (the callbacks of several shards) and restored by the last one, so that one
# caller's exit does not lift the limit under another's solves.
_BLAS_LOCK = threading.Lock()
_BLAS_USERS, _BLAS_LIMITER = 0, None


@contextlib.contextmanager
def single_threaded_blas():
    """Limit BLAS to one thread: threaded BLAS slows Clarabel's small dense cones badly.

    The threadpoolctl controller is built once (building it scans the loaded libraries,
    about 2 ms, which would dominate a small projection).
    """
    global _CONTROLLER, _BLAS_USERS, _BLAS_LIMITER
    with _BLAS_LOCK:
        if _CONTROLLER is None:
            import clarabel  # noqa: F401  (load the solver's libraries before the scan)
            from threadpoolctl import ThreadpoolController

            _CONTROLLER = ThreadpoolController()
        if _BLAS_USERS == 0:
            _BLAS_LIMITER = _CONTROLLER.limit(limits=1, user_api="blas")
        _BLAS_USERS += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_USERS -= 1
            if _BLAS_USERS == 0:
                assert _BLAS_LIMITER is not None  # set by the first user
                _BLAS_LIMITER.restore_original_limits()
                _BLAS_LIMITER = None


def pool() -> ThreadPoolExecutor:
    """A process-wide pool for batched host solves (Clarabel releases the GIL), with
    `DISSIL_JAX_THREADS` workers (default: the number of cores)."""
    global _POOL
    if _POOL is None:
        text = os.environ.get("DISSIL_JAX_THREADS", "").strip()
        try:
            workers = int(text) if text else os.cpu_count() or 1
        except ValueError:
            workers = 0
        if workers < 1:
            raise ValueError("the environment variable DISSIL_JAX_THREADS must be a positive "
                             f"integer (the number of solver threads), got {text!r}.")
        _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dissil-sdp")
    return _POOL


def num_workers() -> int:
    return pool()._max_workers  # noqa: SLF001


def shard() -> tuple:
    """At trace time: `(index, shards)` of the host callback about to be traced.

    Inside `jax.shard_map` every device runs its own copy of the callback, concurrently:
    `index` is the device's position among the shards (a traced int32) and
    `shards` how many of them call back at once on this host, the product of the manual
    mesh axes' sizes but at most this host's device count (a mesh over several hosts puts
    `jax.local_device_count()` of its shards on each). Outside `shard_map`, `(0, 1)`: one
    callback serves the whole batch.
    """
    mesh = jax.sharding.get_abstract_mesh()
    axes = tuple(mesh.manual_axes)
    index = jax.lax.axis_index(axes) if axes else 0
    shards = math.prod(mesh.shape[a] for a in axes)
    return jnp.asarray(index, jnp.int32), max(1, min(shards, jax.local_device_count()))


def thread_map(fn, items, *, balance: bool = False, shards: int = 1) -> list:
    """`fn` over `items` on the process pool, BLAS held to one thread; results in order.

    `fn` takes a list of items. By default `items` is split into one contiguous chunk per
    worker, so per-call overhead is paid once per worker (short, even tasks: the
    projection). With `balance=True` every item is its own task, so long and short tasks
    even out across workers (ICO runs of different lengths). `shards` callers running at
    once (one per device, `shard`) each split `items` into at most
    `num_workers() // shards` chunks and solve them on the pool (never on their own
    threads), so together they keep at most `num_workers()` solves running and do not
    oversubscribe the host's cores (`balance` tasks are not capped: only ICO, outside any
    callback, uses it). Returns the per-call results.
    """
    items = list(items)
    with single_threaded_blas():
        workers = min(max(1, num_workers() // max(1, shards)), len(items))
        if not items:
            return []
        if workers <= 1 and shards <= 1:  # the only caller: solve on its own thread
            return [fn(items)]
        if balance:
            return _pool_map(lambda it: fn([it]), items)
        chunks = np.array_split(np.arange(len(items)), workers)
        return _pool_map(lambda idx: fn([items[i] for i in idx]), chunks)


def _pool_map(fn, tasks) -> list:
    """`[fn(t) for t in tasks]` on the pool, or on this thread when the pool refuses work.

    The pool refuses new tasks once the interpreter has begun to shut down. A script that
    ends while a dispatched computation is still running (JAX returns before its results
    are ready) reaches its host callback only then; the solves then run here, so the
    computation finishes instead of failing inside the callback.
    """
    try:
        futures = [pool().submit(fn, t) for t in tasks]
    except RuntimeError:  # "cannot schedule new futures after (interpreter) shutdown"
        return [fn(t) for t in tasks]
    return [f.result() for f in futures]
