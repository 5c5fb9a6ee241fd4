"""ICO near the edges: started from the paper's N(0, 1) draws no run may end early on the
solver; with defaults near the edge of the dissipative set no run may end on a refused step
that float64 could have certified; every returned controller is certified."""

from collections import Counter

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, expert_windows, freq_response, index

import dissil_jax as dj
from dissil_jax.experiments.data import realisable_windows
from dissil_jax.experiments.protocol import example_spec, training_data
from dissil_jax.internal import ICOProblem, ICOSolver, ico, ico_run, ico_step, outcome as _outcome


def test_large_initial_draws_do_not_stop_ico_early():
    """The nonlinear example at N = 25 with 100 N(0, 1) draws: before the SDP solved for
    P / lambda_max(P~), 4 of these runs stopped at their first SDP (InsufficientProgress)."""
    spec = example_spec("nonlinear")
    _, _, windows, (k_fit, _, _) = training_data(spec, 0, 0, "initial", 25)
    res = dj.fit_ico(k_fit, windows, spec.qsr, num_inits=100, max_steps=150, atol=spec.tol,
                     init_scale=1.0)
    reasons = Counter(res.result_names())
    assert set(reasons) <= {"converged", "max_steps"}, reasons
    assert bool(jnp.all(res.certified)) and bool(jnp.all(res.steps > 0))


def test_p_scale_is_the_square_root_of_p():
    rng = np.random.default_rng(0)
    G = rng.standard_normal((3, 3))
    P = G @ G.T + 1e-3 * np.eye(3)
    Ph = ICOProblem.p_scale(P)
    np.testing.assert_allclose(Ph, Ph.T, rtol=0, atol=1e-15)
    np.testing.assert_allclose(Ph @ Ph, P, rtol=1e-12, atol=1e-12)  # a few eigh round-offs
    assert ICOProblem.p_scale(None) == 1.0


@pytest.mark.parametrize("fail_every_time", [False, True])
def test_failed_solve_recentres_on_the_certificate_once(monkeypatch, fail_every_time):
    """When the updated solver and a new one both fail, the run re-centres once."""
    windows = expert_windows(0, 1, 1, 1, N=10)
    qsr = dj.QSR.passive(1)
    calls = {"solve": 0, "certify": 0}
    solve, certify = ICOSolver.solve, ico_step.certify

    def flaky(self, *args, **kwargs):
        calls["solve"] += 1
        if fail_every_time or calls["solve"] <= 2:  # the updated solver, then a new one
            return None, None, None, _outcome.code("solver_failed"), 0.0
        return solve(self, *args, **kwargs)

    def counted(*args, **kwargs):
        calls["certify"] += 1
        return certify(*args, **kwargs)

    monkeypatch.setattr(ICOSolver, "solve", flaky)
    monkeypatch.setattr(ico_step, "certify", counted)
    res = dj.fit_ico(jr.PRNGKey(3), windows, qsr, num_inits=1, max_steps=5, atol=0.0, rtol=0.0,
                     throw=False)
    assert calls["certify"] == 1  # one re-centring, at the first failure only
    assert bool(res.certified[0])
    if fail_every_time:
        assert res.result_names() == ["solver_failed"] and int(res.steps[0]) == 0
    else:
        assert res.result_names() == ["max_steps"] and int(res.steps[0]) == 5



def _realisable_windows(seed=1, n=3, p=2, m=2, N=20):
    """2-step windows of an LTI target the trainer can represent (`A` near 0.5 I)."""
    r = np.random.default_rng(seed)
    mats = (0.5 * np.eye(n) + 0.1 * r.normal(size=(n, n)), r.normal(size=(n, p)),
            r.normal(size=(m, n)), r.normal(size=(m, p)))
    K = dj.LTIController(*(jnp.asarray(M) for M in mats))
    x0, y = r.normal(size=(N, n)), r.normal(size=(N, 6, p))
    yh = jax.vmap(dj.rollout, in_axes=(None, 0, 0))(K, jnp.asarray(x0), jnp.asarray(y))
    return dj.Windows(jnp.asarray(x0), jnp.asarray(y[:, :2]), -yh[:, :2])


def _assert_certified_and_monotone(res, qsr):
    hist, steps = np.asarray(res.loss_history), np.asarray(res.steps)
    assert bool(jnp.all(res.certified))
    for i in range(hist.shape[0]):
        h = hist[i, : steps[i] + 1]
        assert np.all(np.diff(h) <= 0.0), h
        K = index(res.controllers, i)
        assert dissipation_ok(K, qsr, res.P[i])  # the exact float64 check, from the definition
        assert dj.certify(K, qsr, P=res.P[i]).holds


def test_defaults_on_a_realisable_passive_target_do_not_raise():
    """Before: 3 of these 8 runs ended `not_certified` (2) or `solver_failed` (1) near the
    optimum, so the default call (`throw=True`) raised."""
    windows, qsr = _realisable_windows(), dj.QSR.passive(2)
    res = dj.fit_ico(jr.PRNGKey(0), windows, qsr)  # all defaults: raises on a failed run
    assert set(res.result_names()) <= {"converged", "max_steps"}, Counter(res.result_names())
    _assert_certified_and_monotone(res, qsr)


def _drss_lqr_problem(seed, n, p, m, rate, N=25):
    """A random stable plant (python-control `drss` from numpy's global seed `seed`), an
    LQR expert with input and process noise on 50 trajectories, the first two steps of
    `N` of them, and the controller rate `stabilising_qsr` of the plant's gain bound 1.01
    times its H-infinity norm (`rate="gain"`) or of its cone (`"cone"`)."""
    import control
    import scipy.linalg as sla

    state = np.random.get_state()
    np.random.seed(seed)
    plant = control.drss(n, p, m)
    np.random.set_state(state)
    A, B, C = (np.asarray(M, np.float64) for M in (plant.A, plant.B, plant.C))
    D = np.zeros((p, m))
    X = sla.solve_discrete_are(A, B, C.T @ C + 1e-2 * np.eye(n), 0.1 * np.eye(m))
    K = np.linalg.solve(0.1 * np.eye(m) + B.T @ X @ B, B.T @ X @ A)
    rng = np.random.default_rng(seed)
    x = [rng.standard_normal((50, n))]
    u = []
    for _ in range(2):
        u.append(-x[-1] @ K.T + 0.02 * rng.standard_normal((50, m)))
        x.append(x[-1] @ A.T + u[-1] @ B.T + 0.04 * rng.standard_normal((50, n)))
    y = np.stack([x[0] @ C.T, x[1] @ C.T], 1)
    windows = dj.Windows(jnp.asarray(x[0][:N]), jnp.asarray(y[:N]),
                         jnp.asarray(np.stack(u, 1)[:N]))
    if rate == "gain":
        G = freq_response(A, B, C, D, np.linspace(0.0, np.pi, 4000))
        gain = np.linalg.svd(G, compute_uv=False).max()
        plant_qsr = dj.QSR.bounded_gain(1.01 * gain, n_in=m, n_out=p)
    else:
        plant_qsr = dj.lti_cone_qsr(dj.LinearPlant(A, B, C, D))
    return windows, dj.stabilising_qsr(plant_qsr)


@pytest.mark.parametrize("seed, n, p, m, rate", [(0, 3, 1, 1, "gain"), (22, 3, 2, 2, "cone")])
def test_defaults_on_a_drss_plant_with_an_lqr_expert_do_not_raise(seed, n, p, m, rate):
    """Before, one of the 8 default runs ended `solver_failed` (so `throw=True` raised):

    - SISO, gain bound: a run whose D met the gain bound with B far from 0 crept along that
      edge, where every certificate has P ~ 0 along B; at cond(P~) ~ 3e8 Clarabel stopped
      on `NumericalError` (now: a shorter step, `ico_step._SHORT_PROX`);
    - 2x2, cone: a run froze A and B and its Young weight fell to 6e-5, whose 1/w~^2 in the
      Young LMI stopped Clarabel at its first iteration (now balanced, `YoungLMI`)."""
    windows, qsr = _drss_lqr_problem(seed, n, p, m, rate)
    res = dj.fit_ico(jr.PRNGKey(seed), windows, qsr)  # all defaults: raises on a failed run
    assert set(res.result_names()) <= {"converged", "max_steps"}, Counter(res.result_names())
    _assert_certified_and_monotone(res, qsr)


def test_uncertifiable_step_is_shortened_not_refused(monkeypatch):
    """A step whose P fails the float64 check (here: P shifted off positive definiteness) is
    shortened towards the certified iterate instead of ending the run."""
    windows, qsr = _realisable_windows(seed=2, n=2, p=1, m=1), dj.QSR.passive(1)
    solve, calls = ICOSolver.solve, []

    def bad_P(self, *args, **kwargs):
        d, P, w, status, t = solve(self, *args, **kwargs)
        calls.append(1)
        if len(calls) == 2 and P is not None:
            P = P - 1.5 * np.linalg.eigvalsh(P)[0] * np.eye(len(P))  # lambda_min(P) < 0
        return d, P, w, status, t

    monkeypatch.setattr(ICOSolver, "solve", bad_P)
    res = dj.fit_ico(jr.PRNGKey(1), windows, qsr, num_inits=1, max_steps=6, atol=0.0,
                     rtol=0.0)
    assert res.result_names() == ["max_steps"] and int(res.steps[0]) == 6
    _assert_certified_and_monotone(res, qsr)


def test_failed_solve_is_retried_with_a_new_solver(monkeypatch):
    """An updated solver keeps its first equilibration; when it fails, the same SDP is
    solved by a new solver before the linearisation point is re-centred."""
    windows, qsr = _realisable_windows(seed=3, n=2, p=1, m=1), dj.QSR.passive(1)
    calls = {"fail": 0, "certify": 0}
    solve, certify = ICOSolver.solve, ico_step.certify

    def fails_once_updated(self, *args, **kwargs):
        if self.solver is not None and calls["fail"] == 0:  # an updated solver, once
            calls["fail"] += 1
            return None, None, None, _outcome.code("solver_failed"), 0.0
        return solve(self, *args, **kwargs)

    def counted(*args, **kwargs):
        calls["certify"] += 1
        return certify(*args, **kwargs)

    monkeypatch.setattr(ICOSolver, "solve", fails_once_updated)
    monkeypatch.setattr(ico_step, "certify", counted)
    res = dj.fit_ico(jr.PRNGKey(2), windows, qsr, num_inits=1, max_steps=4, atol=0.0,
                     rtol=0.0)
    assert calls == {"fail": 1, "certify": 0}
    assert res.result_names() == ["max_steps"] and int(res.steps[0]) == 4
    _assert_certified_and_monotone(res, qsr)


@pytest.mark.parametrize("P_c_margin", ["smaller", "larger"])
def test_recentring_only_on_a_larger_margin(monkeypatch, P_c_margin):
    """The fallback re-centres on the maximum-margin certificate only if that P has more
    of the SDP's margin than the iterate's (near the optimum it had 1e4 times less); the
    shorter steps come last, around the iterate's own P."""
    windows, qsr = _realisable_windows(seed=3, n=2, p=1, m=1), dj.QSR.passive(1)
    seen, short = [], []
    margin = ico.ICOProblem.kyp_margin

    def fail(self, theta0, P_tilde, w_tilde, eps=None, rel=0.0, prox=None):
        if prox is None:
            seen.append(np.asarray(P_tilde))
        else:
            short.append((np.asarray(P_tilde), prox))
        return None, None, None, _outcome.code("solver_failed"), 0.0

    def fake_margin(self, theta, P):  # rescale the margin of the re-centred P only
        m = margin(self, theta, P)
        if not seen or np.array_equal(np.asarray(P), seen[0]):
            return m
        return m * (1e-3 if P_c_margin == "smaller" else 1e3)

    monkeypatch.setattr(ICOSolver, "solve", fail)
    monkeypatch.setattr(ico.ICOProblem, "kyp_margin", fake_margin)
    res = dj.fit_ico(jr.PRNGKey(2), windows, qsr, num_inits=1, max_steps=4, throw=False)
    assert res.result_names() == ["solver_failed"] and int(res.steps[0]) == 0
    assert len(seen) == (2 if P_c_margin == "smaller" else 3)  # update, new solver, re-centred
    pb_prox = 1e-4  # fit_ico's default `prox`
    assert [mu for _, mu in short] == [f * pb_prox for f in ico_step._SHORT_PROX]
    assert all(np.array_equal(P, seen[0]) for P, _ in short)
    assert res.certified is not None and bool(res.certified[0])


def test_a_rise_below_the_tolerance_at_the_floor_is_convergence():
    """A static expert learned at order 3 (exactly realisable): the runs reach ~1e-10 of
    their initial loss, where the SDP's next step can raise the loss by round-off. That is
    convergence (the rise is far below rtol * J0), not a failure: with defaults fit_ico
    used to raise `loss_increased`."""
    rng = np.random.default_rng(0)
    m, p, N = 2, 3, 40
    D = rng.standard_normal((m, p))
    D *= 0.5 / np.linalg.norm(D, 2)  # gain 0.5, inside the gain bound 1
    y = rng.standard_normal((N, 2, p))
    windows = dj.Windows(rng.standard_normal((N, 3)), y, -np.einsum("mp,nhp->nhm", D, y))
    qsr = dj.QSR.bounded_gain(1.0, n_in=p, n_out=m)
    res = dj.fit_ico(jr.PRNGKey(0), windows, qsr, num_inits=4)  # throw=True: must not raise
    assert res.result_names() == ["converged"] * 4
    assert bool(np.all(np.asarray(res.final_loss) < 1e-6 * np.asarray(res.loss_history)[:, 0]))
    _assert_certified_and_monotone(res, qsr)


def test_a_rise_at_the_solvers_accuracy_is_convergence():
    """An audit's wide cone [10, 1000] (realisable windows): one of eight runs reached a
    loss of 1e-6 of the zero controller's, where the next SDP step raised it by 5e-8, more
    than rtol * J0 (7e-9) but within the SDP's accuracy (Clarabel's gap tolerance 1e-8 of
    the zero controller's loss, 1 in the SDP's units). With defaults `fit_ico` raised
    `loss_increased` although every run was certified and that run had the lowest loss."""
    qsr = dj.QSR.conic(10.0, 1000.0, dim=2)
    w, _ = realisable_windows(jr.PRNGKey(0), qsr, n_state=2, num_windows=50, noise=0.01)
    res = dj.fit_ico(jr.PRNGKey(1), w, qsr, progress=False)  # throw=True: must not raise
    assert set(res.result_names()) <= {"converged", "max_steps"}
    _assert_certified_and_monotone(res, qsr)


def test_a_run_without_a_certified_step_stalls_at_its_last_iterate(monkeypatch):
    """After accepted steps, a step that fails the float64 check even shortened stops the
    run `stalled` at its last certified iterate: not a failure, so `throw=True` returns
    (a float32 run of an order-8 problem raised `not_certified` for one of eight runs,
    within 0.3 % of the others' losses). At the first step it stays `not_certified`."""
    windows, qsr = _realisable_windows(seed=2, n=2, p=1, m=1), dj.QSR.passive(1)
    solve, calls = ICOSolver.solve, []

    def bad_P_from(k):
        def bad_P(self, *args, **kwargs):
            d, P, w, status, t = solve(self, *args, **kwargs)
            calls.append(1)
            if len(calls) >= k and P is not None:
                P = P - 1.5 * np.linalg.eigvalsh(P)[0] * np.eye(len(P))  # lambda_min(P) < 0
            return d, P, w, status, t
        return bad_P

    monkeypatch.setattr(ico_run, "shortened", lambda *args, **kwargs: None)
    monkeypatch.setattr(ICOSolver, "solve", bad_P_from(3))
    res = dj.fit_ico(jr.PRNGKey(1), windows, qsr, num_inits=1, max_steps=6, atol=0.0,
                     rtol=0.0)  # throw=True: no error
    assert res.result_names() == ["stalled"] and int(res.steps[0]) == 2
    _assert_certified_and_monotone(res, qsr)
    calls.clear()
    monkeypatch.setattr(ICOSolver, "solve", bad_P_from(1))
    with pytest.raises(ValueError, match="not_certified"):
        dj.fit_ico(jr.PRNGKey(1), windows, qsr, num_inits=1, max_steps=6, atol=0.0, rtol=0.0)


def test_a_failed_ico_sdp_gets_icos_own_advice():
    """Plant outputs of zero (a dead sensor) leave ICO's SDP degenerate and Clarabel fails;
    the error gave the projection's advice ("entries of 1e5 and more ... pass a smaller
    `init_scale`"), which names an argument ICO does not have. PGD trains on the same
    windows."""
    rng = np.random.default_rng(0)
    W = dj.Windows(rng.standard_normal((12, 2)), np.zeros((12, 2, 1)),
                   rng.standard_normal((12, 2, 1)))
    with pytest.raises(ValueError, match="solver_failed") as err:
        dj.fit_ico(jr.PRNGKey(0), W, dj.QSR.passive(1), num_inits=2, max_steps=5)
    assert "ICO's SDP" in str(err.value) and "dead sensor" in str(err.value)
    assert "init_scale" not in str(err.value)
    assert dj.fit_pgd(jr.PRNGKey(0), W, dj.QSR.passive(1), num_inits=2, max_steps=5).certified.all()
