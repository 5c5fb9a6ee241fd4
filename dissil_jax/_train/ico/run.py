"""One ICO run (paper Alg. 1 for one initialisation, host, float64): the iteration, its
safeguards against the solver's inaccuracy, and why it stopped."""

from __future__ import annotations

import numpy as np

from ... import _outcome
from ..._sdp import lmi as _lmi
from .sdp import ICOProblem
from .solver import ICOSolver
from .step import shortened, step_with_fallbacks

#: A rise of the loss smaller than this, in units of the zero controller's loss (the SDP's
#: data are scaled so that it is 1), is the SDP's accuracy (Clarabel's duality-gap
#: tolerance is 1e-8), not a failed step: the run ends converged. An audit's cone
#: [10, 1000] rose by 5e-8 at a loss of 1e-6, after 19 steps, and raised with defaults.
_SOLVER_FLOOR = 1e-6
CONVERGED, MAX_STEPS, _LOSS_INCREASED, _NOT_CERTIFIED, _STALLED = (
    _outcome.code(n) for n in ("converged", "max_steps", "loss_increased", "not_certified",
                               "stalled"))


# Bounds on the Young weight's linearisation point, relative to its data-derived scale.
_W_RANGE = 1e4


def _young_scale(pb: ICOProblem, theta) -> float:
    """$\\lVert z\\rVert / (\\lVert C\\rVert\\lVert e\\rVert)$: balances the two Young terms
    when the step moves $C$ and $z = A\\hat x_0 + B\\hat u_0$ by the same relative amount."""
    A, B, C, D = pb.mats(theta)
    z = pb.x0 @ A.T + pb.u0 @ B.T
    e = pb.t1 - z @ C.T - pb.u1 @ D.T
    rz = np.sqrt(np.mean(np.sum(z**2, 1)))
    re = np.sqrt(np.mean(np.sum(e**2, 1)))
    nc = np.linalg.norm(C, 2)
    w = rz / max(nc * re, 1e-12)
    return float(np.clip(w if np.isfinite(w) and w > 0 else 1.0, 1e-6, 1e6))


def run_one(pb: ICOProblem, theta, P, *, max_steps, atol, rtol, dtype, index, callback):
    """Algorithm 1 for one initialisation (host, float64). Returns a dict of results."""
    qsr = pb.qsr
    solver = ICOSolver(pb)
    J = pb.loss(theta)
    hist = np.full(max_steps + 1, np.nan)
    hist[0] = J
    w_scale = _young_scale(pb, theta)
    w_tilde = w_scale
    reason, steps = MAX_STEPS, 0
    if callback is not None:
        callback(index, 0, theta, P, J)
    for step in range(1, max_steps + 1):
        dtheta, P_new, w_new, status, P = step_with_fallbacks(pb, solver, theta, P, w_tilde)
        if dtheta is None:
            reason = status
            break
        assert w_new is not None  # a solve returns the whole step or none of it
        theta_new = _lmi.cast(theta + dtheta, dtype)
        if qsr is not None:
            assert P_new is not None  # ICO's step has a P (ICO-NC's has none)
            P_new = _lmi.cast((P_new + P_new.T) / 2, dtype)
        J_new = pb.loss(theta_new)
        # Guards against solver inaccuracy (the SDP guarantees both in exact arithmetic):
        # a rise of the loss, or near the edge (after the iterates' P, A and B have grown)
        # a check whose round-off allowance passes the step's margin. Either way take a
        # shorter step along the SDP's (convex overbound: no longer rise, if it was solved
        # to its tolerance).
        rose = not J_new <= J
        if rose or (qsr is not None and not _lmi.certified(*pb.mats(theta_new), qsr, P_new)):
            short = None if qsr is None else shortened(pb, theta, P, J, dtheta, P_new, dtype)
            if short is None and rose:
                # a rise below the stopping rule's tolerance or the solver's accuracy: the
                # run is at its floor, where the SDP's step moves the loss by round-off;
                # keep the iterate
                rise = abs(J_new - J)
                small = rise < atol + rtol * abs(hist[0]) or rise < _SOLVER_FLOOR
                reason = CONVERGED if small else _LOSS_INCREASED
                break
            if short is None:
                # after accepted steps the run keeps its last certified iterate, stalled
                # (float32 data: rounding the step can leave the set near convergence)
                reason = _STALLED if steps else _NOT_CERTIFIED
                break
            theta_new, P_new, J_new = short
        dJ = J - J_new  # of the step taken, as in every trainer's stopping rule
        theta, P, J = theta_new, P_new, J_new
        steps = step
        hist[step] = J
        w_tilde = float(np.clip(w_new, max(w_tilde / 4, w_scale / _W_RANGE),
                                min(2 * w_tilde, w_scale * _W_RANGE)))
        if callback is not None:
            callback(index, step, theta, P, J)
        if abs(dJ) < atol + rtol * abs(hist[0]):  # the trainers' rule (`_iterate.terminate`)
            reason = CONVERGED
            break
    return dict(theta=theta, P=P, J=J, hist=hist, steps=steps, reason=reason)


def not_started(pb: ICOProblem, theta, P, outcome, max_steps):
    """The result of a run whose initial projection failed: its (uncertified) draw, flagged."""
    hist = np.full(max_steps + 1, np.nan)
    hist[0] = J = pb.loss(theta)
    return dict(theta=theta, P=P, J=J, hist=hist, steps=0, reason=int(outcome))
