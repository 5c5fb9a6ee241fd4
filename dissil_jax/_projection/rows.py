"""The projection's host-side solves (Clarabel): a batch of rows at their $\\tilde P$,
re-solved with a larger margin where the rounded solution fails the exact float64 check,
and re-linearised at the new $P$ (`project_rows`). Counters for the benchmarks."""

from __future__ import annotations

import collections
import threading

import numpy as np

from .. import _outcome
from .._rate_scale import centring
from .._sdp import sdp as _sdp
from .._sdp.lmi import cast, certified
from . import cache as _cache

_STATS = {"solve_time": 0.0, "solves": 0, "callbacks": collections.Counter()}
_STATS_LOCK = threading.Lock()
_SOLVED, _NOT_CERTIFIED = (_outcome.code(n) for n in ("solved", "not_certified"))
# A solution that fails the exact check after rounding is re-solved with the margin
# enlarged by this factor, at most `_ATTEMPTS - 1` times.
_ATTEMPTS, _EPS_GROWTH = 3, 100.0


def solver_stats() -> dict:
    """The projection's counters since import, live (benchmarks take differences):
    Clarabel's own reported `solve_time` and number of `solves`, summed over all threads,
    and the number of host `callbacks` by `(shard, batch size)`."""
    return _STATS


def solve_batch(qsr, targets, P_tilde, eps, weights, *, base_eps, reg, dtype, shards,
                 H0=None):
    """Solve Π for every row; returns `(A, B, C, D, P)` rounded to `dtype`, codes, certified.

    A narrow cone far from zero is solved about its centre (`centring`: the targets'
    $D$ shifted by $M$, the solutions' back), and checked in the rate as given."""
    n = P_tilde.shape[-1]
    given, centred = qsr, centring(qsr)
    if centred is not None:
        offset, qsr = centred
        A, B, C, D = _cache.lmi(qsr, n).layout.mats(targets)
        targets = _cache.lmi(qsr, n).layout.pack(A, B, C, D + offset)
    lmi = _cache.lmi(qsr, n)
    count = len(targets)
    extra = () if H0 is None else (H0,)  # the Q <= 0 path calls `data` exactly as before
    q, vals, b, diag = _cache.thread_solver(qsr, n, base_eps, reg).data(targets, P_tilde, eps, weights,
                                                                  *extra)
    xs = np.full((count, lmi.nx), np.nan)
    codes = np.empty(count, np.int32)

    def work(rows):
        solver, spent = _cache.thread_solver(qsr, n, base_eps, reg), 0.0
        for i in rows:
            x, codes[i], t = solver.solve(q[i], vals[i], b[i], diag[i])
            spent += t
            if x is not None:
                xs[i] = x
        with _STATS_LOCK:
            _STATS["solve_time"] += spent
            _STATS["solves"] += len(rows)

    _sdp.thread_map(work, range(count), shards=shards)
    A, B, C, D, P = lmi.layout.unpack(xs)
    if centred is not None:
        D = D - centred[0]
    sol = tuple(cast(M, dtype) for M in (A, B, C, D, P))
    ok = (codes == _SOLVED) & certified(*sol[:4], given, sol[4])
    return sol, codes, ok


def certified_solve(qsr, targets, P_tilde, weights, *, eps, reg, dtype, shards, H0=None):
    """Solve Π for every row at its $\\tilde P$ and keep only certified solutions.

    A solution that fails the exact check after rounding is re-solved with the margin
    enlarged `_EPS_GROWTH`-fold, at most `_ATTEMPTS - 1` times; a solve that fails after an
    uncertified solution counts as `not_certified`. Returns `(solution, found, codes)`.
    """
    count = len(targets)
    cur_eps, todo = np.full(count, eps), np.arange(count)
    found, codes, sols = np.zeros(count, bool), np.empty(count, np.int32), None
    for attempt in range(_ATTEMPTS):
        sol, c, ok = solve_batch(qsr, targets[todo], P_tilde[todo], cur_eps[todo],
                                  weights[todo], base_eps=eps, reg=reg, dtype=dtype, shards=shards,
                                  H0=None if H0 is None else tuple(M[todo] for M in H0))
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
    assert sols is not None  # set by the first attempt (_ATTEMPTS >= 1)
    return sols, found, codes


def project_rows(qsr, targets, P_tilde, weights, rounds, *, eps, reg, dtype, shards):
    """Project every row, re-linearising $P^{-1}$'s overbound `rounds` times.

    Each round starts at the $P$ of the row's closest certified solution so far; a row
    keeps that solution and stops refining at its first failure. Returns
    `((A, B, C, D, P), codes)`; rows without any certified solution hold NaN.
    """
    count = len(targets)
    layout = _cache.lmi(qsr, P_tilde.shape[-1]).layout
    best_dist = np.full(count, np.inf)
    codes = np.full(count, _outcome.code("solver_failed"), np.int32)
    live, P_tilde, best = np.arange(count), P_tilde.copy(), None
    for _ in range(rounds):
        sols, found, codes[live] = certified_solve(
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
    assert best is not None  # set by the first round (rounds >= 1)
    codes[np.isfinite(best_dist)] = _SOLVED
    return best, codes


def indefinite_solve(qsr, targets, P_tilde, weights, H0, **kwargs):
    return certified_solve(qsr, targets, P_tilde, weights, H0=H0, **kwargs)
