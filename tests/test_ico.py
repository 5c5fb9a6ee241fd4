"""ICO / ICO-NC (paper Alg. 1): the overbound, monotone loss, certified iterates."""

import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import as_float32, dissipation_ok, expert_windows, index, tree_allclose
from ico_checks import cone_min, cone_spec, feasible_point, overbound

import dissil_jax as dj
from dissil_jax.internal import (
    ICOProblem,
    ICOSolver,
    Iterate,
    ico_sdp as _ico_sdp,
    outcome as _outcome,
    stacked_factor,
)

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

NONLINEAR_QSR = dj.QSR(-29.867, 3.556, 0.601)  # the paper's nonlinear-example controller


def _problem(windows, qsr, cone="stacked"):
    return ICOProblem(np.asarray(windows.x0), np.asarray(windows.y),
                      np.asarray(windows.target), qsr, window_cone=cone)


def _start(key, windows, qsr, scale=0.3):
    K = dj.LTIController.random(key, windows.n_state, windows.n_in, windows.n_out, scale=scale)
    P = None
    if qsr is not None:
        K, P = dj.project(K, qsr)
        P = np.asarray(P)
    return K, P


CASES = [
    (1, 1, 1, dj.QSR.passive(1)),
    (1, 1, 1, NONLINEAR_QSR),
    (2, 2, 2, dj.QSR.conic(-0.5, 2.0, dim=2)),
    (3, 2, 2, dj.QSR.passive(2)),
]


@pytest.mark.parametrize("cone", _ico_sdp.WINDOW_CONES)
@pytest.mark.parametrize("n,p,m,qsr", CASES + [(3, 2, 2, None)])
def test_overbound_exact_at_zero(getkey, n, p, m, qsr, cone):
    windows = expert_windows(n + p, n, p, m)
    pb = _problem(windows, qsr, cone)
    K, P = _start(getkey(), windows, qsr)
    theta = pb.theta(K.A, K.B, K.C, K.D)
    assert pb.loss(theta) == pytest.approx(float(dj.imitation_loss(K, windows)), rel=1e-12)
    w = 0.7
    eps = None if qsr is None else min(pb.eps, 0.5 * pb.kyp_margin(theta, P))
    x = feasible_point(pb, np.zeros(pb.ntheta), w, P, theta, w)
    value, s = overbound(pb, x, theta, P, w, eps)
    assert value == pytest.approx(pb.loss(theta), rel=1e-12, abs=1e-14)
    assert cone_min(pb, s) >= -1e-12  # delta = 0 is feasible, including the KYP LMI
    # The assembled A, b (CSC order, in-place values) reproduce the affine maps: moving
    # sigma_1 below its minimum must leave the cones.
    x_bad = x.copy()
    x_bad[pb.osig] -= 1e-3 + 0.5 * x[pb.osig]
    assert cone_min(pb, overbound(pb, x_bad, theta, P, w, eps)[1]) < 0


@pytest.mark.parametrize("cone", _ico_sdp.WINDOW_CONES)
@pytest.mark.parametrize("n,p,m", [(1, 1, 1), (3, 2, 2), (2, 3, 1)])
def test_overbound_bounds_true_loss(getkey, n, p, m, cone):
    windows = expert_windows(7 * n + m, n, p, m)
    pb = _problem(windows, None, cone)
    K, _ = _start(getkey(), windows, None)
    theta = pb.theta(K.A, K.B, K.C, K.D)
    rng = np.random.default_rng(n)
    checked = 0
    for scale in (1e-3, 0.05, 0.3):
        for _ in range(5):
            d = scale * rng.normal(size=pb.ntheta)
            w_tilde = rng.uniform(0.1, 3.0)
            w = w_tilde * rng.uniform(0.05, 1.95)
            try:
                x = feasible_point(pb, d, w, None, theta, w_tilde)
            except ValueError:  # the step is outside the SDP's domain (I - Y not > 0)
                continue
            checked += 1
            value, s = overbound(pb, x, theta, None, w_tilde)
            assert cone_min(pb, s) >= -1e-9 * max(1.0, np.abs(s).max())
            assert value >= pb.loss(theta + d) - 1e-12
    assert checked >= 8


def test_blocks_fill_their_patterns(getkey):
    """Every cone block gives one number per pattern entry and `rows` entries of b, inside its
    rows and cones; every problem has the same attributes whatever the cone and supply rate."""
    windows = expert_windows(5, 2, 2, 2, N=9)
    K, P = _start(getkey(), windows, dj.QSR.passive(2))
    attrs = set()
    for qsr in (dj.QSR.passive(2), None):
        for cone in _ico_sdp.WINDOW_CONES:
            pb = _problem(windows, qsr, cone)
            theta = pb.theta(K.A, K.B, K.C, K.D)
            P_tilde = None if qsr is None else P
            A0, B0, C0, D0 = pb.mats(theta)
            _, z, ebar = pb.residuals(A0, B0, C0, D0)
            it = Iterate(theta, A0, B0, C0, D0, P_tilde, 0.9, 1e-7, pb.p_scale(P_tilde), z, ebar)
            for blk in pb.blocks:
                rows, cols = blk.pattern()
                vals, b = blk.fill(it)
                assert vals.shape == rows.shape == cols.shape and b.shape == (blk.rows,)
                assert rows.min() >= 0 and rows.max() < blk.rows and cols.max() < pb.nx
                sizes = [d * (d + 1) // 2 if kind == "psd" else d for kind, d in cone_spec(blk)]
                assert sum(sizes) == blk.rows
            assert sum(blk.rows for blk in pb.blocks) == pb.nrows
            assert (pb.kyp is None) == (qsr is None)
            attrs.add(frozenset(vars(pb)))
    assert len(attrs) == 1


@pytest.mark.parametrize("qsr", [dj.QSR.passive(2), None])
def test_stacked_cone_equals_per_window_cones(getkey, qsr):
    """The QR-compressed stacked cone has the optimum of one SOC per window (same bound)."""
    windows = expert_windows(4, 3, 2, 2, N=40)  # N m = 80 > n_theta = 31: compressed
    K, P = _start(getkey(), windows, qsr)
    out = {}
    for cone in ("stacked", "soc"):
        pb = _problem(windows, qsr, cone)
        theta = pb.theta(K.A, K.B, K.C, K.D)
        solver = ICOSolver(pb)
        d, _, w, status, _ = solver.solve(theta, P, 0.8)
        assert status == _outcome.code("solved")
        out[cone] = (solver.obj_val, d, w, pb)
    (obj_s, d_s, w_s, pb_s), (obj_w, d_w, w_w, pb_w) = out["stacked"], out["soc"]
    assert pb_s.nrows < pb_w.nrows - 2 * 40  # the point of stacking
    assert obj_s == pytest.approx(obj_w, rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(d_s, d_w, atol=1e-4 * np.abs(d_w).max())
    assert w_s == pytest.approx(w_w, rel=1e-3)


def test_stacked_factor_chunks_agree(getkey):
    """The chunked QR (TSQR) of the stacked residual is that of one big factorisation."""
    windows = expert_windows(6, 2, 2, 2, N=30)
    pb = _problem(windows, None)
    K, _ = _start(getkey(), windows, None)
    A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
    z = pb.x0 @ A.T + pb.u0 @ B.T
    ebar = pb.t1 - z @ C.T - pb.u1 @ D.T
    R1, g1, c1 = stacked_factor(pb, C, z, ebar)
    R7, g7, c7 = stacked_factor(pb, C, z, ebar, chunk=7)

    def e_of(d):  # the affine part of the step-1 residual, written out directly
        dA, dB, dC, dD = pb.mats(d)
        dz = pb.x0 @ dA.T + pb.u0 @ dB.T
        return ebar - dz @ C.T - z @ dC.T - pb.u1 @ dD.T

    L = np.stack([ebar.ravel() - e_of(np.eye(pb.ntheta)[j]).ravel()
                  for j in range(pb.ntheta)], axis=1)  # ebar(delta) = ebar - L delta
    rng = np.random.default_rng(0)
    for R, g, c in ((R1, g1, c1), (R7, g7, c7)):
        np.testing.assert_allclose(R.T @ R, L.T @ L, rtol=1e-5, atol=1e-5 * np.abs(L).max()**2)
        np.testing.assert_allclose(R.T @ g, L.T @ ebar.ravel(), rtol=1e-5, atol=1e-6)
        # The identity the cone relies on, ||ebar(delta)||^2 = ||g - R delta||^2 + c^2 (c
        # itself is not unique when L is rank deficient, e.g. zero controller states).
        for d in [np.zeros(pb.ntheta)] + [rng.normal(size=pb.ntheta) for _ in range(3)]:
            exact = np.sum(e_of(d) ** 2)
            assert np.sum((g - R @ d) ** 2) + c**2 == pytest.approx(exact, rel=1e-10)


def test_inplace_update_matches_fresh_solver(getkey):
    """Clarabel's in-place update (fixed sparsity) gives the same step as a fresh build."""
    windows = expert_windows(3, 3, 2, 2, N=15)
    qsr = dj.QSR.passive(2)
    pb = _problem(windows, qsr)
    K, P = _start(getkey(), windows, qsr)
    theta = pb.theta(K.A, K.B, K.C, K.D)
    reused = ICOSolver(pb)
    d, P1, w1, status, _ = reused.solve(theta, P, 1.0)
    assert status == _outcome.code("solved")
    theta2 = theta + d
    d_upd, P_upd, w_upd, _, _ = reused.solve(theta2, P1, 0.5)
    fresh = ICOSolver(pb)
    d_new, P_new, w_new, _, _ = fresh.solve(theta2, P1, 0.5)
    # Same optimum up to solver tolerance (a mis-ordered A would change it completely).
    assert reused.obj_val == pytest.approx(fresh.obj_val, rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(d_upd, d_new, atol=1e-3 * np.abs(d_new).max())
    # The reused solver keeps its first equilibration, so the minimisers agree only to solver
    # accuracy along flat directions; the true loss of the two steps agrees to ~1e-6.
    assert pb.loss(theta2 + d_upd) == pytest.approx(pb.loss(theta2 + d_new), rel=1e-5)


@pytest.mark.parametrize("n,p,m,qsr", CASES)
def test_fit_ico_monotone_and_every_iterate_certified(getkey, n, p, m, qsr):
    windows = expert_windows(n + 2 * m, n, p, m)
    iterates, lock = [], threading.Lock()

    def callback(i, step, K, P, loss):
        with lock:
            iterates.append((i, step, K, P, loss))

    res = dj.fit_ico(getkey(), windows, qsr, num_inits=3, max_steps=12, atol=1e-6, rtol=0.0,
                     init_scale=0.5, callback=callback)
    hist = np.asarray(res.loss_history)
    assert hist.shape == (3, 13)
    steps = np.asarray(res.steps)
    for i in range(3):
        h = hist[i, : steps[i] + 1]
        assert np.all(np.isfinite(h)) and np.all(np.isnan(hist[i, steps[i] + 1:]))
        assert np.all(np.diff(h) <= 0.0), h  # exact monotonicity of the true loss
        assert h[-1] == pytest.approx(float(res.final_loss[i]))
        assert h[-1] < h[0] - 1e-3  # it actually learns
    assert len(iterates) == int(steps.sum()) + 3  # initial points + accepted steps
    for i, step, K, P, loss in iterates:
        assert loss == pytest.approx(float(dj.imitation_loss(K, windows)), rel=1e-10)
        assert loss == pytest.approx(hist[i, step], rel=1e-12)
        assert dj.certify(K, qsr, P=P).holds
        assert dissipation_ok(K, qsr, P)
    assert bool(jnp.all(res.certified))
    for i in range(3):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        assert dj.certify(K, qsr, P=res.P[i]).holds
        assert dj.certify(K, qsr).holds  # a fresh, independent KYP SDP


def test_ico_nc_reaches_lower_loss_than_ico(getkey):
    windows = expert_windows(11, 2, 2, 2, N=20)
    key = getkey()
    res = dj.fit_ico(key, windows, dj.QSR.passive(2), num_inits=2, max_steps=40, atol=1e-5)
    res_nc = dj.fit_ico_nc(key, windows, num_inits=2, max_steps=40, atol=1e-5)
    assert res_nc.P is None and res_nc.certified is None
    assert res_nc.loss_history.shape == (2, 41)
    assert float(jnp.min(res_nc.final_loss)) <= float(jnp.min(res.final_loss)) + 1e-9
    # The expert is not passive: the unconstrained fit is much better here.
    assert float(jnp.min(res_nc.final_loss)) < 0.5 * float(jnp.min(res.final_loss))
    # ICO-NC converges to a stationary point of the true loss.
    K = jax.tree.map(lambda a: a[int(jnp.argmin(res_nc.final_loss))], res_nc.controllers)
    grads = jax.grad(dj.imitation_loss)(K, windows)
    gnorm = max(float(jnp.abs(g).max()) for g in jax.tree.leaves(grads))
    assert gnorm < 1e-2


def test_rejected_step_keeps_certified_iterate(getkey, monkeypatch):
    """Solver inaccuracy guard: a step that raises the true loss is refused and the run stops."""
    windows = expert_windows(5, 1, 1, 1)
    qsr = dj.QSR.passive(1)
    original = ICOSolver.solve
    calls = []

    def bad_solve(self, *args, **kwargs):
        d, P, w, status, t = original(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 2:  # second step: pretend the solver returned a bad point
            d = d - 5.0 * np.sign(d + 1e-3)
        return d, P, w, status, t

    monkeypatch.setattr(ICOSolver, "solve", bad_solve)
    key = getkey()
    with pytest.raises(ValueError, match="loss_increased|not_certified"):
        dj.fit_ico(key, windows, qsr, num_inits=1, max_steps=10, atol=0.0, rtol=0.0)
    calls.clear()
    res = dj.fit_ico(key, windows, qsr, num_inits=1, max_steps=10, atol=0.0, rtol=0.0, throw=False)
    assert int(res.steps[0]) == 1 and not bool(res.converged[0])
    assert res.result_names()[0] in ("loss_increased", "not_certified")
    assert bool(res.certified[0])
    hist = np.asarray(res.loss_history[0])
    assert np.isfinite(hist[1]) and np.all(np.isnan(hist[2:]))
    assert float(res.final_loss[0]) == pytest.approx(hist[1])


def test_bad_input(getkey):
    windows3 = dj.Windows(np.zeros((4, 1)), np.ones((4, 3, 1)), np.ones((4, 3, 1)))
    with pytest.raises(ValueError, match="`windows`.*h = 2"):
        dj.fit_ico(getkey(), windows3, dj.QSR.passive(1))
    with pytest.raises(ValueError, match="`windows`"):
        dj.fit_ico_nc(getkey(), windows3)
    windows = expert_windows(0, 1, 1, 1)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.fit_ico(getkey(), windows, dj.QSR.passive(2))
    # An indefinite Q is accepted (tests/test_indefinite_q.py), but not one that admits no
    # controller: with p = 2 inputs, Q = 1 and R = -I the supply form has 1 < p positive
    # eigenvalues.
    with pytest.raises(ValueError, match="`qsr` is infeasible"):
        dj.fit_ico(getkey(), dj.Windows(windows.x0, jnp.concatenate([windows.y] * 2, -1),
                                        windows.u), dj.QSR(1.0, np.zeros((1, 2)), -np.eye(2)))
    with pytest.raises(ValueError, match="fit_ico_nc"):
        dj.fit_ico(getkey(), windows, None)


def _assert_stopping_rule(res, tol, max_steps):
    """`converged` means exactly: the last accepted step changed the loss by less than `tol`
    (and no earlier one did); otherwise the run used all `max_steps`."""
    hist, steps = np.asarray(res.loss_history), np.asarray(res.steps)
    for i, reason in enumerate(res.result_names()):
        s = int(steps[i])
        h = hist[i, : s + 1]
        assert np.all(np.isfinite(h)) and np.all(np.isnan(hist[i, s + 1:]))
        assert h[-1] == pytest.approx(float(res.final_loss[i]), rel=1e-12)
        dJ = np.abs(np.diff(h))
        assert np.all(dJ[:-1] >= tol)  # it did not stop late
        assert bool(res.converged[i]) is (reason == "converged")
        if reason == "converged":
            assert 1 <= s < max_steps and dJ[-1] < tol
        else:
            assert reason == "max_steps" and s == max_steps and dJ[-1] >= tol


def test_converged_flag_and_no_warning(getkey):
    windows = expert_windows(2, 1, 1, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # the absolute rule alone (rtol=0), which `_assert_stopping_rule` checks exactly
        res = dj.fit_ico_nc(getkey(), windows, num_inits=2, max_steps=50, atol=1e-4, rtol=0.0)
        short = dj.fit_ico_nc(getkey(), windows, num_inits=2, max_steps=3, atol=1e-4,
                              rtol=0.0)
        ico = dj.fit_ico(getkey(), windows, dj.QSR.passive(1), num_inits=2, max_steps=40,
                         atol=1e-3, rtol=0.0, init_scale=0.5)
    assert bool(jnp.all(res.converged)) and res.result_names() == ["converged"] * 2
    assert np.all(np.asarray(res.steps) < 50)
    assert res.wall_time.shape == () and float(res.wall_time) > 0
    _assert_stopping_rule(res, 1e-4, 50)
    assert not bool(jnp.any(short.converged)) and short.result_names() == ["max_steps"] * 2
    _assert_stopping_rule(short, 1e-4, 3)
    assert ico.result_names() == ["converged"] * 2 and bool(jnp.all(ico.certified))
    _assert_stopping_rule(ico, 1e-3, 40)
    for i in range(2):
        assert dissipation_ok(index(ico.controllers, i), dj.QSR.passive(1), ico.P[i])


@pytest.mark.parametrize("cone", ["soc", "psd"])
def test_fit_ico_with_per_window_cones(getkey, cone):
    """The reference window cones run end to end: monotone, every iterate certified."""
    windows = expert_windows(3, 2, 1, 1, N=8)
    qsr = dj.QSR.passive(1)
    iterates, lock = [], threading.Lock()

    def callback(i, step, K, P, loss):
        with lock:
            iterates.append((i, step, K, P, loss))

    key = getkey()
    res = dj.fit_ico(key, windows, qsr, num_inits=2, max_steps=4, atol=0.0, rtol=0.0, window_cone=cone,
                     callback=callback)
    ref = dj.fit_ico(key, windows, qsr, num_inits=2, max_steps=4, atol=0.0, rtol=0.0)  # "stacked"
    assert res.result_names() == ["max_steps"] * 2 and bool(jnp.all(res.certified))
    assert len(iterates) == 2 * 5
    for i, step, K, P, loss in iterates:
        assert dissipation_ok(K, qsr, P)
        assert loss == pytest.approx(float(dj.imitation_loss(K, windows)), rel=1e-10)
    hist = np.asarray(res.loss_history)
    assert np.all(np.diff(hist, axis=1) <= 0) and np.all(hist[:, -1] < hist[:, 0] - 1e-3)
    for i in range(2):
        assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])
    # Same overbound as the default ("psd" with a full Y is at least as tight for m = 1).
    np.testing.assert_allclose(hist[:, 1], np.asarray(ref.loss_history)[:, 1], rtol=1e-3)


def test_fit_ico_rejects_unknown_window_cone(getkey):
    windows = expert_windows(3, 1, 1, 1, N=4)
    with pytest.raises(ValueError, match="`window_cone`"):
        dj.fit_ico(getkey(), windows, dj.QSR.passive(1), num_inits=1, max_steps=1,
                   window_cone="sdp")
    with pytest.raises(ValueError, match="`window_cone`"):
        dj.fit_ico_nc(getkey(), windows, num_inits=1, max_steps=1, window_cone=None)


def test_fit_ico_float32_controllers_are_certified_as_returned(getkey):
    """float32 windows: every accepted iterate is checked exactly as it is returned, i.e. after
    rounding to float32, and the returned float32 controllers and P pass the exact check."""
    windows = expert_windows(3, 2, 1, 1, N=8)
    w32 = as_float32(windows)
    qsr = NONLINEAR_QSR
    last, lock = {}, threading.Lock()

    def callback(i, step, K, P, loss):
        with lock:
            last[i] = (step, K, P)

    res = dj.fit_ico(getkey(), w32, qsr, num_inits=2, max_steps=6, atol=0.0, rtol=0.0, callback=callback)
    assert res.controllers.A.dtype == jnp.float32 and res.P.dtype == jnp.float32
    assert np.all(np.asarray(res.steps) >= 1) and bool(jnp.all(res.certified))
    f32 = lambda M: np.asarray(M, np.float64).astype(np.float32).astype(np.float64)
    for i in range(2):
        K, P = index(res.controllers, i), res.P[i]
        step, K_cb, P_cb = last[i]
        assert step == int(res.steps[i])
        for M in (*jax.tree.leaves(K_cb), P_cb):  # the iterate the guards checked ...
            np.testing.assert_array_equal(np.asarray(M, np.float64), f32(M))
        assert tree_allclose(K_cb, K.astype(jnp.float64), rtol=0, atol=0)  # ... is returned
        np.testing.assert_array_equal(np.asarray(P, np.float64), np.asarray(P_cb, np.float64))
        assert dissipation_ok(K, qsr, P)
        assert dj.certify(K, qsr, P=P).holds


def test_long_runs_near_the_edge_are_not_refused():
    """A small problem whose best controllers sit on the edge of the dissipative set, from the
    paper's N(0, 1) draws, with the default stopping rule. When the SDP solved for $P$
    itself with only an absolute margin, all four runs were refused before they converged:
    three `not_certified` (the iterates inflated $P$ until the margin sank below the float64
    check's round-off allowance, which grows with $P$) and one `solver_failed` (Clarabel's
    `NumericalError` on an ill-conditioned $P$), after 15 to 28 steps. Every run now
    converges or takes all its steps, and returns a controller that the independent KYP
    check accepts with the returned $P$."""
    windows = expert_windows(0, 2, 1, 1)
    qsr = dj.QSR.passive(1)
    res = dj.fit_ico(jax.random.PRNGKey(0), windows, qsr, num_inits=4, max_steps=40,
                     init_scale=1.0, throw=False)
    assert set(res.result_names()) <= {"converged", "max_steps"}, res.result_names()
    for i in range(4):
        hist = np.asarray(res.loss_history[i, : int(res.steps[i]) + 1])
        assert np.all(np.diff(hist) <= 0)  # every accepted step lowered the loss
        assert dissipation_ok(index(res.controllers, i), qsr, np.asarray(res.P[i]))
