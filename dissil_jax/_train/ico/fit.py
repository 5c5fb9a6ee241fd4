"""Iterative convex overbounding (paper §4.1, Alg. 1) and its unconstrained baseline ICO-NC."""

from __future__ import annotations

import time
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from ... import _outcome
from ..._controller import LTIController
from ..._data import Windows
from ..._progress import HostProgress
from ..._projection.args import check_eps_room
from ..._projection.project import project
from ..._rate_scale import rate_factor, scaled_rate
from ..._sdp import lmi as _lmi, sdp as _sdp
from ..._supply import QSR
from ..._validate import check_flag, check_key, check_positive
from .._checks import check_eager, check_finite_draw, check_fit_args
from .._init import INIT_SCALE, init_controllers
from .._iterate import RTOL
from .._scale import loss_scale, scaled
from .._units import balance as balanced, balancing_units, unbalance
from ..result import FitResult, raise_if_failed
from .run import CONVERGED as _CONVERGED, MAX_STEPS as _MAX_STEPS, not_started, run_one
from .sdp import ICOProblem

# The default initial scale of `fit_ico`, measured on the zoo's tuning half: from N(0, 1)
# draws (the paper's) the median run of chain3_paper ended 1.17x above the best scale's and its
# worst 464x; from N(0, 0.1^2) every problem's median was within 0.1 % of the best of
# {1, 0.3, 0.1} (benchmarks/README.md, "Defaults on the problem zoo").
ICO_INIT_SCALE = 0.1


def _check_args(windows, qsr, num_inits, max_steps, atol, rtol, init_scale):
    check_fit_args(windows, qsr, num_inits, max_steps, atol=atol, rtol=rtol,
                   init_scale=init_scale)
    if windows.x0 is None:
        raise ValueError(
            "`windows.x0` is None, but ICO needs the controller state at every window start: "
            "its convex overbound (paper eq. 17) is built around the windows' x̂0. For "
            "input-output logs without plant state use `dj.fit_direct(..., n_state=...)` or "
            "`dj.fit_pgd(..., n_state=...)`, which start the controller at rest.")
    if windows.horizon != 2:
        raise ValueError(
            f"`windows` has horizon h = {windows.horizon}, but ICO overbounds the paper's "
            "two-step loss (paper eq. 17) and needs h = 2. Cut the demonstrations into 2-step "
            "windows (e.g. `dj.Windows(x0, y[:, :2], u[:, :2])`, or sliding 2-step windows with "
            "x0 the plant state at each window start), or use `dj.fit_pgd` for longer horizons."
        )


def _fit(key, windows, qsr, *, num_inits, max_steps, atol, rtol, init_scale, eps, prox,
         window_cone, callback, throw, balance, progress=True):
    check_key(key)
    check_eager("fit_ico" if qsr is not None else "fit_ico_nc", key, windows, throw,
                init_scale=init_scale, eps=eps, prox=prox, atol=atol, rtol=rtol)
    _check_args(windows, qsr, num_inits, max_steps, atol, rtol, init_scale)
    eps, prox = check_positive("eps", eps), check_positive("prox", prox, zero=True)
    units = balancing_units(windows, balance, qsr)  # outputs' and states' units (`_units.py`)
    user_qsr, (windows, qsr) = qsr, balanced(windows, qsr, units)
    atol, c = atol / units.c**2, units.c
    k = 1.0  # a rate far from unit size is solved divided by k, P multiplied back (exact)
    if qsr is not None:
        check_eps_room(qsr, eps)
        k = rate_factor(qsr)
        qsr = scaled_rate(qsr, k)
    dtype = windows.y.dtype
    start = time.perf_counter()
    K0 = init_controllers(key, num_inits, windows, init_scale, dtype)
    check_finite_draw(K0, init_scale)
    code0 = np.full(num_inits, _MAX_STEPS, np.int32)
    if qsr is not None:
        # paper Alg. 1 "Init": random, then projected (eq. 13)
        K0, P0 = proj = project(K0, qsr, throw=False)
        P0, code0 = np.asarray(P0, np.float64), np.asarray(_outcome.codes(proj.result))
    # The SDP is built on unit-free windows (`_scale.py`): J = s2 * J_s, atol likewise.
    s2 = float(loss_scale(windows, np, of="outputs"))
    ws = scaled(windows, s2)
    pb = ICOProblem(np.asarray(ws.x0), np.asarray(ws.y), np.asarray(ws.target), qsr, eps=eps,
                    prox=prox, window_cone=window_cone)
    mats = [np.asarray(M, np.float64) for M in (K0.A, K0.B, K0.C, K0.D)]
    thetas = [pb.theta(*(M[i] for M in mats)) for i in range(num_inits)]
    name = "fit_ico" if qsr is not None else "fit_ico_nc"
    reports = HostProgress(name, max_steps, num_inits, check_flag("progress", progress))

    def in_controller_units(i, step, theta, P, J):
        reports.step(i, step, c**2 * s2 * J)
        if callback is not None:
            callback(i, step, units.controllers(LTIController(*pb.mats(theta))),
                     None if P is None else units.storages(k * P), c**2 * s2 * J)

    def one(i):
        out = (run_one(pb, thetas[i], None if qsr is None else P0[i], max_steps=max_steps,
                        atol=atol / s2, rtol=rtol, dtype=dtype, index=i,
                        callback=in_controller_units)
               if not _outcome.failed(code0[i])
               else not_started(pb, thetas[i], P0[i], code0[i], max_steps))
        reports.done(i)
        return out

    def work(indices):
        return [one(i) for i in indices]

    results = [r for chunk in _sdp.thread_map(work, range(num_inits), balance=True)
               for r in chunk]
    wall = time.perf_counter() - start
    A, B, C, D = (np.stack(Ms) for Ms in zip(*(pb.mats(r["theta"]) for r in results)))
    controllers = LTIController(*(jnp.asarray(M, dtype) for M in (A, B, C, D)))
    P = certified = None
    if qsr is not None:
        Ps = np.stack([r["P"] for r in results])
        certified = jnp.asarray(_lmi.certified(A, B, C, D, qsr, Ps) & ~_outcome.failed(code0))
        P = jnp.asarray(k * Ps, dtype)
    reasons = np.asarray([r["reason"] for r in results], np.int32)
    res = FitResult(
        controllers=controllers,
        P=P,
        certified=certified,
        loss_history=jnp.asarray(s2 * np.stack([r["hist"] for r in results]), dtype),
        final_loss=jnp.asarray([s2 * r["J"] for r in results], dtype),
        converged=jnp.asarray(reasons == _CONVERGED),
        steps=jnp.asarray([r["steps"] for r in results], jnp.int32),
        wall_time=jnp.asarray(wall, dtype),
        result=_outcome.item(reasons),
        # Every accepted step lowers the loss (the guard above), so the last is the best.
        kept_step=jnp.asarray([r["steps"] for r in results], jnp.int32),
    )
    return unbalance(raise_if_failed(res, "ico") if throw else res, units, user_qsr, throw)


def fit_ico(
    key, windows: Windows, qsr: QSR, *, num_inits: int = 8, max_steps: int = 150,
    atol: float = 0.0, rtol: float = RTOL, init_scale: float = ICO_INIT_SCALE,
    eps: float = 1e-6,
    prox: float = 1e-4,
    window_cone: str = "stacked", callback: Callable | None = None, throw: bool = True,
    balance: bool = True, progress: bool = True,
) -> FitResult:
    """Learn $(Q,S,R)$-dissipative controllers by iterative convex overbounding (paper Alg. 1).

    Minimises the two-step imitation loss (paper eq. 17, with the target $-u$ fixed by `dj.Windows`)

    $$J(\\theta) = \\frac{1}{N}\\sum_{k=1}^N \\lVert t_{k,0} - C\\hat x_{k,0} - D\\hat u_{k,0}
    \\rVert^2 + \\lVert t_{k,1} - C(A\\hat x_{k,0} + B\\hat u_{k,0}) - D\\hat u_{k,1}\\rVert^2$$

    over the dissipative set. Each iteration solves one convex program in the step
    $\\delta\\theta = (\\delta A, \\delta B, \\delta C, \\delta D)$ and $P$ (paper Problem 18):
    a convex overbound of $J(\\theta_i + \\delta\\theta)$ that is exact at $\\delta\\theta = 0$,
    subject to the convexified dissipativity LMI (paper Corollary 1 + Remark 1, `docs/concepts.md`)
    linearised around the current $\\tilde P = P_i$, imposed with a margin
    $\\preceq -(\\varepsilon + \\rho\\operatorname{tr}P) I$ on its un-congruenced form so
    that the current point stays feasible at the next linearisation. Hence
    $\\theta_{i+1} = \\theta_i + \\delta\\theta$ is dissipative and
    $J(\\theta_{i+1}) \\le J(\\theta_i)$ (paper Theorem 2).

    **The overbound.** The step-0 residual is affine in $\\delta\\theta$; its square enters the
    objective as a quadratic. The step-1 residual is $e = \\bar e(\\delta) - \\delta C\\,\\delta z$
    with $\\bar e$ affine and $\\delta z = \\delta A\\hat x_0 + \\delta B\\hat u_0$; Young's
    relation with $W = wI$ (paper Lemmas 5-7) gives

    $$\\lVert e\\rVert^2 \\le \\frac{\\lVert\\bar e\\rVert^2}{1 - y}
    + \\frac{\\lVert\\delta z\\rVert^2}{w}, \\qquad y \\ge w\\lVert\\delta C\\rVert_2^2,$$

    one shared LMI
    $\\bigl[\\begin{smallmatrix} yI & \\delta C\\\\ \\delta C^\\top & (2/\\tilde w - w/\\tilde w^2)I
    \\end{smallmatrix}\\bigr]\\succeq 0$, one cone for $\\sum_k\\lVert\\delta z_k\\rVert^2/w$
    and one rotated second-order cone for $\\sum_k\\lVert\\bar e_k\\rVert^2/(1 - y)$, the
    stacked residual compressed by a QR factorisation of its Jacobian to at most
    $n_\\theta + 3$ rows (derivation in `dissil_jax/_train/ico/sdp.py`). The SDP's size
    therefore does not depend on the number of windows $N$; only the QR (numpy, linear in
    $N$) does. This is the compact per-window bound with $\\delta C\\delta C^\\top$ replaced by
    $\\lVert\\delta C\\rVert_2^2 I$ (identical when $m = 1$). Unlike the paper's term-by-term
    Lemmas 4-7 it needs three small cones in all instead of seven LMIs per window.

    `window_cone` selects the window part: `"stacked"` (default, as above); `"soc"`, the same
    bound with one cone per window (the same optimum, an SDP that grows with $N$; kept as a
    reference); or `"psd"`, the exact per-window matrix form with a full symmetric $Y$
    instead of $yI$ (about 1.5x slower per iteration than `"soc"` for $m = 3$ and no better in
    our runs).

    **Controller order.** The KYP LMI is balanced by the congruence with
    $\\operatorname{diag}(\\tilde P^{-1/2}, I, I, \\tilde P^{-1/2})$, which fills its $A$
    columns: about $\\hat n^4$ nonzeros, and an iteration's cost grows about like
    $\\hat n^{3.3}$ from $\\hat n = 8$ to 24 (0.2-0.3 s at $\\hat n = 8$, 2-4 s at
    $\\hat n = 16$ for $m = p = 2$) and like $\\hat n^{6.3}$ beyond, where Clarabel's
    dense factors dominate (36 s at 32, 420 s at 48; see
    [Scaling up](scaling.md#scaling-up)). ICO is meant for $\\hat n \\le 24$; for larger
    controllers use [`fit_direct`][dissil_jax.fit_direct] (no SDP in the loop) or
    [`fit_pgd`][dissil_jax.fit_pgd].

    **The Young weight.** As in the paper, $w$ is a decision variable and $1/w$ (the
    $W^{-1}$ block) is replaced by its tangent $2/\\tilde w - w/\\tilde w^2 \\le 1/w$, so
    $w\\in(0, 2\\tilde w]$ and the bound is exact for any $\\tilde w$ at $\\delta = 0$. The first
    $\\tilde w$ balances the two Young terms for a step that moves $C$ and
    $z = A\\hat x_0 + B\\hat u_0$ by the same relative amount,
    $\\tilde w_0 = \\lVert z\\rVert/(\\lVert C\\rVert\\lVert e\\rVert)$; afterwards $\\tilde w$ is
    the previous optimal $w$, clipped to $[\\tilde w/4, 2\\tilde w]$ and to $10^{\\pm4}\\tilde w_0$
    (so it cannot collapse when one step happens not to move $A, B$). The Young LMI is
    solved balanced by $\\mathrm{diag}(I, \\tilde w^{1/2}I)$, so a small $\\tilde w$ does
    not ill-condition it.

    **Units do not matter.** The SDP is built on the windows divided by
    $s = \\sqrt{J(0)}$, the root of the zero controller's loss (`J(0)` of the data as
    given), so its data, the proximal
    weight and the Young weight are unit-free; scaling $x_0$, $y$ and $u$ by any $c > 0$
    gives the same iterates. `loss_history`, `final_loss`, `atol` and the callback's loss are
    in the user's units.

    **The margin and the unit of $P$.** Near the edge of the dissipative set, where the
    best controllers often sit, the certificates that reach it grow and become
    ill-conditioned. With only an absolute margin $\\varepsilon$ the iterates inflated $P$
    until $\\varepsilon$ sank below the float64 check's round-off allowance, which grows with
    $P$, and the check refused the step; and Clarabel stopped on `NumericalError` once $P$'s
    condition number passed about $5\\cdot10^4$. So the margin has a part
    $\\rho\\operatorname{tr}P$ in the decision variable $P$, with $\\rho$ 100 times the
    part of that allowance that grows with $P$ (the next iterate has it again at its own
    $P$), and the SDP solves for $X = \\tilde P^{-1/2}P\\tilde P^{-1/2}$, which stays near
    $I$ however ill-conditioned $\\tilde P$ is. On the zoo (`dj.experiments.zoo`) this
    ended every refused step of the defaults: before, 14 of 24 held-out runs and 8 of 12
    tuning runs without early stop ended `not_certified` or `solver_failed`.

    **Safeguards.** A small proximal term $\\frac{\\mu}{2}\\lVert\\delta\\theta\\rVert^2$ (`prox`)
    keeps the step unique when the data do not determine every parameter (few windows); it can only
    lower the objective at the optimum below $J(\\theta_i)$, so monotonicity is kept. After
    every solve the new iterate is re-evaluated in float64 (after rounding to the data's
    dtype): the step is accepted only if the true loss did not increase and the exact KYP
    check (paper Lemma 2) holds with the returned $P$. A step that lowers the loss but fails
    the check (near the edge, once $P$, $A$ and $B$ have grown, the check's round-off
    allowance can pass the step's margin) is halved, up to 8 times, towards the current
    iterate, with $P$ interpolated likewise: the SDP's feasible set is convex and holds
    $(\\delta\\theta, P) = (0, \\tilde P)$, so the shorter step keeps both guarantees in exact
    arithmetic, and it is accepted only if it passes both float64 checks. When no shorter
    step passes either, the run stops at its last certified iterate: `stalled` after
    accepted steps (not a failure: with float32 data, rounding a near-converged step can
    take it out of the set; one of eight runs of an order-8 problem stopped so within
    0.3 % of the others' losses), `not_certified` at the first step. A failed SDP is
    solved again by a new Clarabel solver (an updated one keeps the equilibration of the
    iterate it was built at, which goes stale as the data drift), then once more around the
    maximum-margin certificate of the iterate if that has more of the SDP's margin, then
    with $\\mu$ raised $10^2$ and $10^4$ times: a shorter step, still certified and
    monotone ($\\delta\\theta = 0$ stays feasible), that Clarabel solves where the
    certificates are ill-conditioned (`dissil_jax/_train/ico/step.py`).
    Otherwise the previous, certified iterate is kept and that run stops (`result` names
    the reason). A shortened step counts as a step in the stopping rule. A step that
    raises the loss is shortened likewise; if no shorter step lowers it, the step is not
    taken, and the run ends `converged` when the rise is below the stopping rule's
    tolerance or below $10^{-6}$ of the zero controller's loss (the SDP's own accuracy:
    at the loss's floor its step moves the loss by round-off), `loss_increased`
    otherwise.

    Stops after `max_steps` iterations or when $|\\Delta J| <$ `atol` $+$ `rtol` $|J_0|$.
    Initialisations are solved in parallel threads (one Clarabel solver each), see `DISSIL_JAX_THREADS`.

    **Arguments:**

    - `key`: PRNG key for the random initialisations.
    - `windows`: demonstration windows with horizon $h = 2$ (ValueError otherwise: the
      overbound is derived for the two-step loss; cut longer demonstrations into 2-step
      windows, or use `dj.fit_pgd`).
    - `qsr`: the controller's supply rate (any symmetric $Q$; an indefinite $Q$'s positive
      part is linearised at the current iterate, so every iterate stays certified).
    - `num_inits`: number of random initialisations.
    - `max_steps`: maximum number of ICO iterations (paper: 150).
    - `atol`, `rtol`: stop when $|\\Delta J| <$ `atol` $+$ `rtol` $|J_0|$; default `atol` = 0,
      `rtol` = 1e-6 as in [`fit_pgd`][dissil_jax.fit_pgd] (the paper's tol is `atol`, with
      `rtol` = 0: 1e-3 linear, 1e-5 nonlinear).
    - `init_scale`: standard deviation of the random initial entries, which are then
      projected as in paper Alg. 1 (default 0.1, measured on the zoo's tuning half: from the
      paper's N(0, 1) draws, which the reproduction passes, a median run ended up to 1.17x
      and the worst 464x above the best initial scale's loss; from N(0, 0.1^2) every
      median was within 0.1 %).
    - `eps`: margin of the dissipativity LMI (never more than the current iterate has).
    - `prox`: proximal weight $\\mu$ on the step.
    - `window_cone`: `"stacked"` (default), `"soc"` or `"psd"`, see above.
    - `callback`: optional `callback(init_index, step, K, P, loss)` called for the initial
      point (step 0) and every accepted iterate, from worker threads.
    - `progress`: as in [`fit_pgd`][dissil_jax.fit_pgd] (default True: a line on standard
      error every 10 s once training has taken 10 s).
    - `throw`: raise a `ValueError` when a run stopped early (an SDP failure or a refused
      step, see `FitResult.result`). With `throw=False` the result is returned; every
      run, including one that stopped early, carries its best (and last accepted) certified iterate.
    - `balance`: as in [`fit_pgd`][dissil_jax.fit_pgd] (default True): when the outputs'
      size is more than 5x above or below the inputs', solve on outputs rescaled by a
      power of two and the matching supply rate, and map the result back exactly. Without
      it, outputs 1000 times the inputs made every SDP fail after a few steps. A narrow
      cone far from zero is solved about its centre first (as in `fit_pgd`); without it
      ICO's SDP failed on every run for the cones $[10, 11]$ and $[10^3, 10^3 + 1]$.

    **Returns:** a [`FitResult`][dissil_jax.FitResult] with `P` and `certified` filled in.

    ```python
    res = dj.fit_ico(jr.PRNGKey(0), windows, dj.QSR.passive(1), num_inits=4)
    K = res.best()
    ```
    """
    if qsr is None:
        raise ValueError("`qsr` is None; use `dj.fit_ico_nc` for unconstrained ICO.")
    return _fit(key, windows, qsr, num_inits=num_inits, max_steps=max_steps, atol=atol,
                rtol=rtol, init_scale=init_scale, eps=eps, prox=prox,
                window_cone=window_cone, callback=callback, throw=throw, balance=balance,
                progress=progress)


def fit_ico_nc(
    key, windows: Windows, *, num_inits: int = 8, max_steps: int = 150, atol: float = 0.0,
    rtol: float = RTOL, init_scale: float = INIT_SCALE, prox: float = 1e-4,
    window_cone: str = "stacked",
    callback: Callable | None = None, throw: bool = True, balance: bool = True,
    progress: bool = True,
) -> FitResult:
    """ICO without the dissipativity constraint (the paper's ICO-NC baseline).

    The same overbound and iteration as [`fit_ico`][dissil_jax.fit_ico], with no LMI and no
    projection of the random initialisation (drawn from the paper's N(0, 1) by default; its
    initial scale was not re-measured); the result carries `P = None` and
    `certified = None` (no stability guarantee). `callback` receives `P = None`; `throw`,
    `balance` and `progress` as in `fit_ico`.
    """
    return _fit(key, windows, None, num_inits=num_inits, max_steps=max_steps, atol=atol,
                rtol=rtol,
                init_scale=init_scale, eps=1e-6, prox=prox, window_cone=window_cone,
                callback=callback, throw=throw, balance=balance, progress=progress)
