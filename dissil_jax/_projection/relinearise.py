"""The projection's re-linearisation loop for an indefinite $Q$ (host side, float64 numpy).

The convex set of one solve is an inner approximation exact at its linearisation point
$(H_0, \\tilde P)$ (`_sdp/indefinite.py`): a certified point that is its own linearisation point
stays in the next set, so each round can only move closer to the target. The first round
linearises at the caller's point (the target, or a feasible reference); a row whose first
set is empty (the target far from the dissipative set) starts again at a static controller
that is strictly dissipative for every $P$ (`static_point`, the one nearest the target's
$D$ among the deep ones), where the set is never empty.
"""

from __future__ import annotations

import numpy as np

from .. import _outcome
from .._sdp.indefinite import static_point

# A row stops re-linearising once a round shortens its distance by less than this fraction.
SETTLE_RTOL = 1e-3


def project_rows_indefinite(solve, layout, qsr, targets, P_tilde, H0, weights, rounds):
    """Project every row, re-linearising $Q_+$'s and $P^{-1}$'s bounds up to `rounds` times.

    **Arguments:** `solve(targets, P_tilde, weights, H0) -> (solution, found, codes)` (the
    certified batch solve of `_projection`), the `layout`, `qsr`, `targets` and `weights`
    `[B, ntheta]`, `P_tilde` `[B, n, n]`, `H0 = (C0, D0)` (first linearisation points) and
    the number of `rounds` (at least one; a fallback to the static point adds one).

    **Returns:** `((A, B, C, D, P), codes)`; rows without a certified solution hold NaN.
    """
    count = len(targets)
    n = P_tilde.shape[-1]
    P_t = np.array(P_tilde, np.float64)
    C0, D0 = (np.array(M, np.float64) for M in H0)
    best_dist = np.full(count, np.inf)
    codes = np.full(count, _outcome.code("solver_failed"), np.int32)
    fell_back = np.zeros(count, bool)
    live, best = np.arange(count), None
    budget = np.full(count, max(1, rounds))
    while len(live):
        sols, found, codes[live] = solve(targets[live], P_t[live], weights[live],
                                         (C0[live], D0[live]))
        if best is None:
            best = [np.full((count,) + M.shape[1:], np.nan) for M in sols]
        dist = np.sum(weights[live] * (layout.pack(*sols[:4]) - targets[live]) ** 2, axis=-1)
        prev = best_dist[live]
        better = found & (dist < prev)
        for Bm, S in zip(best, sols):
            Bm[live[better]] = S[better]
        best_dist[live[better]] = dist[better]
        budget[live] -= 1
        # a first set that is empty: once more from the static point (not counted)
        retry = ~found & ~np.isfinite(prev) & ~fell_back[live]
        gain = np.full(len(live), np.inf)
        seen = np.isfinite(prev)
        gain[seen] = prev[seen] - best_dist[live][seen]
        go_on = found & (gain > SETTLE_RTOL * best_dist[live]) & (budget[live] > 0)
        rows_retry, rows_on = live[retry], live[go_on]
        if len(rows_retry):
            fell_back[rows_retry] = True
            budget[rows_retry] += 1
            P_t[rows_retry] = np.eye(n)
            C0[rows_retry] = 0.0
            # in the component of dissipative static gains nearest each row's target
            D_target = layout.mats(targets[rows_retry])[3]
            D0[rows_retry] = [static_point(qsr, near=D) for D in D_target]
        P_t[rows_on] = best[4][rows_on]
        C0[rows_on], D0[rows_on] = best[2][rows_on], best[3][rows_on]
        live = np.concatenate([rows_retry, rows_on])
    assert best is not None  # set by the first round (`targets` is never empty)
    codes[np.isfinite(best_dist)] = _outcome.code("solved")
    return best, codes
