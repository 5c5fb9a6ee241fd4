"""One ICO iteration's SDP and its safeguards (host, float64).

`step` solves the convexified SDP around the current iterate with a KYP margin that the
iterate itself has (`margins`); `step_with_fallbacks` solves a failed SDP again with a new
Clarabel solver, then once around the maximum-margin certificate if that has more margin,
then with a larger proximal weight (a shorter step);
`shortened` halves a step that lowers the loss but fails the float64 check. Each keeps
the paper's guarantees: every accepted iterate is certified and the loss never rises.
"""

from __future__ import annotations

import numpy as np

from ..._certify.certify import certify
from ..._controller import LTIController
from ..._sdp import lmi as _lmi
from .sdp import ICOProblem
from .solver import ICOSolver

# The SDP's KYP margin per unit of tr P, relative to the float64 check's round-off allowance
# (`margins`): 100 times it, so solver round-off cannot take a step's margin below it.
_REL_MARGIN = 100 * _lmi.VERIFY_RTOL
# Halvings of a step that fails the float64 check before the run stops (`shortened`).
_BACKTRACK = 8
# The proximal weights, relative to the problem's, of the last tries of a failed SDP
# (`step_with_fallbacks`): shorter steps, whose KKT systems Clarabel can still factor.
_SHORT_PROX = (1e2, 1e4)


def margins(pb: ICOProblem, theta, P) -> tuple[float, float]:
    """The KYP margin `(eps, rel)` of the next SDP: `eps` $+$ `rel` $\\operatorname{tr}P$.

    The margin is imposed on the un-congruenced LMI, so the new iterate has it again at the
    next linearisation point; only solver round-off can eat into it, and then delta = 0 must
    stay feasible: never ask for more margin than the current iterate has. Within that
    budget, first `rel` $= \\rho\\,(1 + (\\lVert A\\rVert_F + \\lVert B\\rVert_F)^2)$,
    `_REL_MARGIN` times the part of the float64 check's round-off allowance that grows with
    $P$ (`kyp_scale`), then the absolute `pb.eps`.
    """
    budget = (1 - 1e-3) * pb.kyp_margin(theta, P)
    A, B = pb.mats(theta)[:2]
    tr = float(np.trace(P))
    rel = min(_REL_MARGIN * (1 + (np.linalg.norm(A) + np.linalg.norm(B)) ** 2),
              max(budget, 0.0) / tr)
    return min(pb.eps, budget - rel * tr), rel


def step(pb: ICOProblem, solver: ICOSolver, theta, P, w_tilde, prox=None):
    """One ICO SDP around (theta, P): `(dtheta, P_new, w_new, outcome)`, None on failure
    (`prox`: the proximal weight, the problem's by default)."""
    eps, rel = (None, 0.0) if pb.qsr is None else margins(pb, theta, P)
    dtheta, P_new, w_new, status, _ = solver.solve(theta, P, w_tilde, eps, rel, prox)
    return dtheta, P_new, w_new, status


def step_with_fallbacks(pb: ICOProblem, solver: ICOSolver, theta, P, w_tilde):
    """`step`, and when its SDP fails, more tries: `(dtheta, P_new, w_new, outcome, P)`
    with `P` the linearisation point of the step returned (the given one or its
    re-centred replacement, certified either way).

    The last tries take a shorter step: the same SDP with the proximal weight $\\mu$ raised
    by `_SHORT_PROX`. Along an edge where every certificate of the iterate is
    ill-conditioned (a gain bound met by $D$ alone forces $B^\\top PB$, hence $P$ along
    $B$, towards 0), the balanced KYP LMI's coefficients of $\\delta A$ grow like
    $\\kappa(\\tilde P)^{1/2}$ ($\\tilde P^{-1/2}\\delta A^\\top\\tilde P^{1/2}$), and Clarabel
    stopped on `NumericalError` at $\\kappa(\\tilde P)\\approx 10^8$; a larger $\\mu$ adds
    to the diagonal of its KKT system and it solves. The step is a valid ICO step:
    $\\delta = 0$ is still feasible, so its overbound is at most $J(\\theta_i)$ (paper
    Theorem 2), and it passes the same float64 checks.
    """
    dtheta, P_new, w_new, status = step(pb, solver, theta, P, w_tilde)
    if dtheta is not None or pb.qsr is None:
        return dtheta, P_new, w_new, status, P
    # The updated solver keeps the equilibration of the iterate it was built at, which can
    # go stale over a run (`ICOSolver.reset`): solve the same SDP with a new solver.
    solver.reset()
    dtheta, P_new, w_new, status = step(pb, solver, theta, P, w_tilde)
    if dtheta is not None:
        return dtheta, P_new, w_new, status, P
    # A certificate P on the edge of the feasible set (e.g. the projection of a large
    # random draw, which lands on the boundary) leaves the SDP almost no interior.
    # Re-centre the linearisation point on the maximum-margin P of the exact
    # certificate and try once more, if that P has more of the SDP's margin (near the
    # optimum it can have orders of magnitude less, and the step is then refused).
    cert = certify(LTIController(*pb.mats(theta)), pb.qsr, max_margin=True, progress=False)
    if cert.holds:
        P_c = np.asarray(cert.P, np.float64)
        if pb.kyp_margin(theta, P_c) > pb.kyp_margin(theta, P):
            dtheta, P_new, w_new, status = step(pb, solver, theta, P_c, w_tilde)
            if dtheta is not None:
                return dtheta, P_new, w_new, status, P_c
    for factor in _SHORT_PROX:
        dtheta, P_new, w_new, status = step(pb, solver, theta, P, w_tilde, factor * pb.prox)
        if dtheta is not None:
            break
    return dtheta, P_new, w_new, status, P


def shortened(pb: ICOProblem, theta, P, J, dtheta, P_new, dtype):
    """The longest step $\\alpha\\,\\delta\\theta$, $\\alpha = 2^{-k}$, $k = 1, \\dots,$
    `_BACKTRACK`, whose point passes the loss and float64 KYP checks with
    $P_\\alpha = (1 - \\alpha)\\tilde P + \\alpha P$: `(theta, P, J)`, or None.

    The SDP's feasible set is convex in $(\\delta\\theta, P)$ and holds $(0, \\tilde P)$
    (with its margin), so $(\\alpha\\delta\\theta, P_\\alpha)$ is feasible for it too, hence
    dissipative with the margin $\\varepsilon + \\rho\\operatorname{tr}P_\\alpha$; and the
    overbound is convex and exact at 0, so the loss is at most
    $(1 - \\alpha)J(\\theta) + \\alpha\\bar J(\\delta\\theta) \\le J(\\theta)$. A shorter step
    has a smaller round-off allowance in the float64 check (it grows with $P$, $A$, $B$).
    """
    qsr = pb.qsr
    assert qsr is not None  # ICO-NC has no check to fail
    for k in range(1, _BACKTRACK + 1):
        a = 2.0 ** -k
        theta_a = _lmi.cast(theta + a * dtheta, dtype)
        P_a = (1 - a) * P + a * P_new
        P_a = _lmi.cast((P_a + P_a.T) / 2, dtype)
        J_a = pb.loss(theta_a)
        if J_a <= J and _lmi.certified(*pb.mats(theta_a), qsr, P_a):
            return theta_a, P_a, J_a
    return None
