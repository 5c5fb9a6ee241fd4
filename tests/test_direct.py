"""The direct parameterisation (`_direct_map.py`) and `dj.fit_direct`."""

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest
from helpers import as_float32, dissipation_ok, expert_windows, index

import dissil_jax as dj
import dissil_jax.internal as dji
from dissil_jax.experiments import realisable_windows
from dissil_jax.experiments.protocol import example_spec, fit, run_config, training_data
from dissil_jax.internal import certified, direct, direct_map as dm

I2, I3 = np.eye(2), np.eye(3)
#: Every kind of supply rate the library accepts (Q <= 0).
SUPPLY_RATES = {
    "strict_paper": dj.QSR(-29.867, 3.556, 0.601),  # Q < 0, the paper's nonlinear example
    "passive": dj.QSR.passive(2),  # Q = 0
    "q_minus_1e-4": dj.QSR(-1e-4 * I2, I2 / 2, 0 * I2),  # the issue's failure case
    "rank_deficient": dj.QSR(np.diag([-1.0, 0.0]), I2 / 2, 0 * I2),
    "degenerate_cone": dj.QSR.degenerate_conic(0.5, dim=2),  # Q = 0, R < 0
    "cone": dj.QSR.conic(-1.0, 3.0, dim=2),
    "gain_2x3": dj.QSR.bounded_gain(2.0, n_in=3, n_out=2),  # S = 0, non-square
    "input_only": dj.QSR(0 * I2, 0 * I2, I2),  # Q = S = 0: C and D are free
}


def _random_theta(key, num, n, qsr, scale):
    m, p = qsr.S.shape
    th = dm.init_params(key, num, n, p, m, scale, jnp.float64)
    X = th.X + 0.5 * jr.normal(jr.fold_in(key, 1), th.X.shape)
    return dm.DirectParams(X, th.W, th.V)


# -- the map ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SUPPLY_RATES))
def test_map_is_dissipative_with_its_margin_for_every_theta(getkey, name):
    """KYP(P) <= -eps diag(P, Phi0) and P >= eps I for any theta, checked in float64."""
    qsr, n = SUPPLY_RATES[name], 3
    _, Phi0 = dm.feedthrough_centre(qsr)
    for scale in (0.3, 1.0, 3.0):
        th = _random_theta(getkey(), 40, n, qsr, scale)
        K, P = jax.jit(jax.vmap(lambda t: dm.direct_map(t, qsr)))(th)
        assert bool(np.all(certified(K.A, K.B, K.C, K.D, qsr, P)))
        M = dj.kyp_matrix(*(np.asarray(a, np.float64) for a in (K.A, K.B, K.C, K.D)), qsr,
                          np.asarray(P, np.float64))
        bound = np.zeros_like(M)
        bound[:, :n, :n], bound[:, n:, n:] = np.asarray(P), Phi0
        size = np.abs(M).max(axis=(1, 2)) + np.abs(bound).max(axis=(1, 2))
        assert np.all(np.linalg.eigvalsh(M + dm.MARGIN * bound)[:, -1] <= 1e-10 * size)
        assert np.all(np.linalg.eigvalsh(np.asarray(P))[:, 0] >= dm.MARGIN * (1 - 1e-10))
    for i in range(3):  # independent of the library's KYP blocks
        assert dissipation_ok(index(K, i), qsr, P[i], python_control=False)


def test_map_is_well_conditioned_near_q_zero():
    """The constants and the map are continuous at Q = 0; no centre runs away like
    (-Q)^{-1} S = 5000 I at Q = -1e-4 I (the published maps' failure)."""
    passive = dj.QSR.passive(3)
    th = _random_theta(jr.PRNGKey(0), 8, 4, passive, 1.0)
    K0, P0 = jax.jit(jax.vmap(lambda t: dm.direct_map(t, passive)))(th)
    D0_passive = dm.feedthrough_centre(passive)[0]
    np.testing.assert_allclose(D0_passive, I3, rtol=0.2)
    for delta in (1e-4, 1e-8):
        qsr = dj.QSR(-delta * I3, I3 / 2, 0 * I3)
        D0, Phi0, G_phi, T_u, N = dm.map_constants(qsr, dm.MARGIN)
        assert np.linalg.norm(D0, 2) < 2.0 and np.linalg.cond(Phi0) < 10
        assert np.linalg.norm(D0 - D0_passive) < 100 * delta
        K, P = jax.jit(jax.vmap(lambda t: dm.direct_map(t, qsr)))(th)
        for a, b in zip(jax.tree.leaves((K, P)), jax.tree.leaves((K0, P0))):
            assert float(jnp.max(jnp.abs(a - b))) < 1e3 * delta * (1 + float(jnp.max(jnp.abs(b))))


def test_a_narrow_cone_far_from_zero_is_feasible():
    """[1e5, 1e5 + 1]: Phi has entries of 1e10 and one positive eigenvalue of 2.5e-11, below
    an eigen-decomposition's round-off, so the rate was refused as admitting "no controller
    of any order", while `certify` proves static and dynamic controllers for it. The count
    now also goes through the Schur complement R - S'Q^-1 S = (b - a)^2 / 4 when Q < 0.
    A rate with no positive direction is still refused."""
    qsr = dj.QSR.conic(1e5, 1e5 + 1, dim=1)
    dji.check_feasible(qsr)  # no ValueError
    K = dj.LTIController(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                         np.array([[1e5 + 0.5]]))
    assert dj.certify(K, qsr).holds  # the rate admits a controller indeed
    for bad in (dj.QSR(-1.0, 0.0, -1.0), dj.QSR(-1.0, 1e5, -1e10 - 1.0)):
        with pytest.raises(ValueError, match="`qsr` is infeasible"):
            dji.check_feasible(bad)


@pytest.mark.parametrize("e", [-24, -12, 12, 24])
def test_degenerate_cone_with_outputs_in_other_units_is_feasible(e):
    """A degenerate cone (Q = 0, R < 0) with its outputs in units 2^e (the rate the trainers
    solve after balancing outputs of that size): its static set is tiny against R (Phi's
    positive eigenvalue ~|S|^2/|R|), which the centre search and the feasibility count took
    for round-off at 2^-24. Both now balance S against R first; the centre's Phi0 is
    positive definite in exact float64 terms, and the map's controllers certify."""
    c = 2.0**e
    cone = dj.QSR.degenerate_conic(0.5, dim=2)
    qsr = dj.QSR(c * c * cone.Q, c * cone.S, cone.R)
    dji.check_feasible(qsr)  # no ValueError
    D0, Phi0 = dm.feedthrough_centre(qsr)
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    Phi = R + S.T @ D0 + D0.T @ S + D0.T @ Q @ D0
    np.testing.assert_allclose(Phi, Phi0, rtol=1e-12, atol=0)
    assert np.linalg.eigvalsh(Phi)[0] > 0
    th = _random_theta(jr.PRNGKey(3), 6, 2, qsr, 1.0)
    K, P = jax.jit(jax.vmap(lambda t: dm.direct_map(t, qsr)))(th)
    assert bool(np.all(certified(K.A, K.B, K.C, K.D, qsr, P)))


def test_grad_through_the_map():
    qsr = SUPPLY_RATES["rank_deficient"]
    w = expert_windows(0, 2, 2, 2)
    th = index(_random_theta(jr.PRNGKey(1), 1, 2, qsr, 1.0), 0)
    f = jax.jit(lambda t: dj.imitation_loss(dm.direct_map(t, qsr)[0], w))
    g = jax.jit(jax.grad(f))(th)
    d = jax.tree.map(lambda a: jr.normal(jr.PRNGKey(2), a.shape), th)
    shift = lambda h: jax.tree.map(lambda a, b: a + h * b, th, d)
    fd = (f(shift(1e-6)) - f(shift(-1e-6))) / 2e-6
    directional = sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(d)))
    np.testing.assert_allclose(directional, fd, rtol=1e-6)


# -- training -----------------------------------------------------------------------------


#: The four kinds (Q < 0, Q = 0, Q ~ 0, rank-deficient Q) in float64 and float32, two more
#: in float64 (all: map tests above). float32 rows run with the slow tests; float32 at the
#: linear example's sizes stays in the fast suite (`test_issue_failure_case_q_minus_1e4`).
_ISSUE = ("strict_paper", "passive", "q_minus_1e-4", "rank_deficient")
FIT_CASES = [(n, "float64") for n in _ISSUE] + [
    pytest.param(n, "float32", marks=pytest.mark.slow) for n in _ISSUE] + [
    ("degenerate_cone", "float64"), ("gain_2x3", "float64")]


@pytest.mark.parametrize(("name", "dtype"), FIT_CASES)
def test_fit_direct_is_certified(getkey, name, dtype):
    """Every returned controller passes the float64 checks (with its P, and dj.certify's
    own SDP), in float64 and in float32, without the fallback projection."""
    qsr = SUPPLY_RATES[name]
    m, p = qsr.S.shape
    w = expert_windows(3, 2, p, m, N=16)
    w = as_float32(w) if dtype == "float32" else w
    res = dj.fit_direct(getkey(), w, qsr, num_inits=4, max_steps=30, atol=0.0, rtol=0.0)
    K = res.controllers
    assert K.A.dtype == res.P.dtype == res.loss_history.dtype == jnp.dtype(dtype)
    assert bool(jnp.all(res.certified)) and not bool(jnp.any(res.projected))
    assert bool(np.all(dj.certify(K, qsr, P=res.P).holds))
    assert bool(np.all(dj.certify(K, qsr).holds))
    assert bool(jnp.all(res.final_loss < res.initial_loss))
    assert res.result_names() == ["max_steps"] * 4


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_issue_failure_case_q_minus_1e4(dtype):
    """The issue's test: Q = -1e-4 I at the linear example's sizes (n̂ = 6, m = p = 3, 25
    initial segments, 20 initialisations). The published maps' centre (-Q)^{-1}S = 5000 I
    blew the loss up to 1e6 and 2 of 20 controllers failed the float64 check; here training
    matches the passive supply rate and every controller is certified."""
    spec = example_spec("linear")
    w = training_data(spec, 0, 0, "initial", 25)[2]
    w = as_float32(w) if dtype == "float32" else w
    # the reproduction's settings: its step, and its data in one scale (`balance=False`)
    kw = dict(num_inits=20, learning_rate=spec.direct_learning_rate, max_steps=150, atol=0.0,
              rtol=0.0, balance=False)
    near = dj.fit_direct(jr.PRNGKey(0), w, dj.QSR(-1e-4 * I3, I3 / 2, 0 * I3), **kw)
    assert bool(jnp.all(near.certified)) and not bool(jnp.any(near.projected))
    med = float(jnp.median(near.final_loss))
    assert med < 1e-3 * float(jnp.median(near.initial_loss))
    if dtype == "float64":  # as good as passivity itself, the limit Q -> 0
        passive = dj.fit_direct(jr.PRNGKey(0), w, dj.QSR.passive(3), **kw)
        assert med < 2 * float(jnp.median(passive.final_loss))


def test_training_loss_within_2x_of_ico_small():
    """The linear-size criterion at a small size (n̂ = 2, m = p = 2, passive, noisy
    realisable windows), with the defaults: median training loss within 2x of ICO's."""
    qsr = SUPPLY_RATES["passive"]
    w, _ = realisable_windows(jr.PRNGKey(0), qsr, n_state=2, num_windows=25, noise=0.1)
    ico = dj.fit_ico(jr.PRNGKey(1), w, qsr, num_inits=4, atol=1e-3)
    res = dj.fit_direct(jr.PRNGKey(1), w, qsr, num_inits=4, max_steps=150, atol=0.0, rtol=0.0)
    assert float(jnp.median(res.final_loss)) <= 2 * float(jnp.median(ico.final_loss))


def _reference_adam(windows, qsr, lr, max_steps, tol):
    """A plain Python loop for one initialisation: Adam on J(K(theta)) / s^2. Returns
    `run(theta) -> (theta, losses)`; its loss, gradient and Adam step are compiled once
    for all initialisations (each step a separate call from Python)."""
    s2 = float(np.mean(np.sum(np.asarray(windows.y) ** 2, axis=(1, 2)))
               + np.mean(np.sum(np.asarray(windows.x0) ** 2, axis=1)))
    J = jax.jit(lambda t: dj.imitation_loss(dm.direct_map(t, qsr)[0], windows))
    grad = jax.jit(jax.grad(lambda t: J(t) / s2))
    opt = optax.adam(lr)

    @jax.jit
    def adam_step(theta, state):
        updates, state = opt.update(grad(theta), state, theta)
        return optax.apply_updates(theta, updates), state

    def run(theta):
        state, hist = opt.init(theta), [float(J(theta))]
        for _ in range(max_steps):
            theta, state = adam_step(theta, state)
            hist.append(float(J(theta)))
            if abs(hist[-1] - hist[-2]) < tol:
                break
        return theta, hist
    return run


def test_batched_training_equals_python_loop(getkey):
    qsr = SUPPLY_RATES["strict_paper"]
    w = expert_windows(1, 1, 1, 1, N=20)
    key = getkey()
    res = dj.fit_direct(key, w, qsr, num_inits=3, max_steps=40, atol=1e-3, learning_rate=0.05,
                        init_scale=0.7)
    th0 = dm.init_params(key, 3, 1, 1, 1, 0.7, jnp.float64)
    stopped_early = False
    reference = _reference_adam(w, qsr, 0.05, 40, 1e-3)
    for i in range(3):
        th, hist = reference(index(th0, i))
        n = len(hist)
        stopped_early |= n < 41
        assert int(res.steps[i]) == n - 1
        np.testing.assert_allclose(res.loss_history[i, :n], hist, rtol=1e-8)
        assert np.all(np.isnan(res.loss_history[i, n:]))
        K, P = dm.direct_map(th, qsr)
        for a, b in zip(jax.tree.leaves((index(res.controllers, i), res.P[i])),
                        jax.tree.leaves((K, P))):
            np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-10)
    assert stopped_early  # the stopping rule was exercised


def test_learning_rate_sweep_with_vmap_equals_loop(getkey):
    qsr = SUPPLY_RATES["passive"]
    w = expert_windows(2, 2, 2, 2)
    key, lrs = getkey(), [0.01, 0.05, 0.2]
    run = lambda lr: dj.direct_run(key, w, qsr, learning_rate=lr, num_inits=2, max_steps=15,
                                   atol=1e-6)
    swept = jax.jit(jax.vmap(run))(jnp.asarray(lrs))
    assert swept.loss_history.shape == (3, 2, 16) and swept.certified is None
    run_one = jax.jit(run)  # traced once: the rate is an argument, not a constant
    for j, lr in enumerate(lrs):
        one = run_one(lr)
        for a, b in zip(jax.tree.leaves(index(swept, j)), jax.tree.leaves(one)):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_the_run_is_pure_jax_and_differentiable(getkey):
    """No host callback anywhere in the run (`throw=False`: `throw=True` adds equinox's
    error callback after the loop); forward-mode derivatives through the loop."""
    qsr = SUPPLY_RATES["passive"]
    w = expert_windows(2, 2, 2, 2)
    key = getkey()
    final = jax.jit(lambda lr: jnp.mean(dj.direct_run(
        key, w, qsr, learning_rate=lr, num_inits=2, max_steps=10, atol=0.0, rtol=0.0,
        throw=False).final_loss))
    jaxpr = str(jax.make_jaxpr(final)(0.05))
    assert "callback" not in jaxpr and "while" in jaxpr
    d = jax.jit(jax.jacfwd(final))(0.05)
    h = 1e-6
    np.testing.assert_allclose(d, (final(0.05 + h) - final(0.05 - h)) / (2 * h), rtol=1e-5)


@pytest.mark.parametrize("c", [1e-3, 1e3])
def test_unit_free(c):
    qsr = SUPPLY_RATES["passive"]
    wk = lambda s: realisable_windows(jr.PRNGKey(4), qsr, n_state=2, num_windows=30,
                                      noise=0.1, scale=s)[0]
    ref = dj.fit_direct(jr.PRNGKey(0), wk(1.0), qsr, num_inits=3, max_steps=20, atol=0.0, rtol=0.0)
    res = dj.fit_direct(jr.PRNGKey(0), wk(c), qsr, num_inits=3, max_steps=20, atol=0.0, rtol=0.0)
    for a, b in zip(jax.tree.leaves(res.controllers), jax.tree.leaves(ref.controllers)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(res.loss_history, c**2 * ref.loss_history, rtol=1e-6)


def test_no_retracing_across_calls(getkey, monkeypatch):
    traced = eqx.debug.assert_max_traces(direct._run, max_traces=1)
    monkeypatch.setattr(direct, "_run_jit", eqx.filter_jit(traced))
    qsr = SUPPLY_RATES["strict_paper"]
    w1, w2 = expert_windows(5, 1, 1, 1), expert_windows(6, 1, 1, 1)
    dj.fit_direct(getkey(), w1, qsr, num_inits=2, max_steps=5)
    # the tolerances are traced: other values reuse the compiled run
    dj.fit_direct(getkey(), w1, qsr, num_inits=2, max_steps=5, atol=1e-9, rtol=1e-3)
    dj.fit_direct(getkey(), w2, dj.QSR(-29.867, 3.556, 0.601), num_inits=2, max_steps=5,
                  learning_rate=0.01, init_scale=0.5)
    with pytest.raises(RuntimeError, match="traced"):
        dj.fit_direct(getkey(), w1, qsr, num_inits=3, max_steps=5)


def test_rates_of_one_shape_share_one_compilation(getkey, monkeypatch):
    """The trainers pass the rate's values traced (`MapRate`): supply rates of one shape,
    out-of-band ones included (solved divided by a power of two), train under one
    compilation. (With the rate static, each compiled its own run, and ~100 rates in one
    process exhausted Linux's memory-map limit and aborted it.)"""
    traced = eqx.debug.assert_max_traces(direct._run, max_traces=1)
    monkeypatch.setattr(direct, "_run_jit", eqx.filter_jit(traced))
    w = expert_windows(5, 1, 1, 1)
    for gamma in (0.5, 2.0, 1e3):
        qsr = dj.QSR.bounded_gain(gamma, n_in=1, n_out=1)
        res = dj.fit_direct(getkey(), w, qsr, num_inits=2, max_steps=5)
        assert bool(np.all(certified(*(res.controllers.A, res.controllers.B,
                                       res.controllers.C, res.controllers.D), qsr, res.P)))


@pytest.mark.parametrize("name", ["strict_paper", "passive", "cone"])
def test_traced_rate_is_the_static_rate(getkey, name):
    """The map under a traced `MapRate` equals the map with the rate's constants baked in,
    up to the round-off of an XLA program compiled another way (a few ulps of float64)."""
    qsr = SUPPLY_RATES[name]
    th = _random_theta(getkey(), 8, 3, qsr, 1.0)
    static = jax.jit(jax.vmap(lambda t: dm.direct_map(t, qsr)))(th)
    traced = jax.jit(jax.vmap(lambda t, r: dm.direct_map(t, r), in_axes=(0, None)))(
        th, dm.map_rate(qsr, dm.MARGIN, jnp.float64))
    for a, b in zip(jax.tree.leaves(traced), jax.tree.leaves(static)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(np.abs(b).max()))


def test_defaults_follow_the_order(getkey):
    # The paper's sizes keep the values chosen there; wider controllers get a smaller step
    # and a smaller initial scale (rule: docs/concepts.md, "Initialisation and steps").
    assert direct.default_hyperparameters(6, 3) == (0.3, 0.5)
    lr, s = direct.default_hyperparameters(48, 2)
    assert np.isclose(lr, 0.3 * 9 / 50) and np.isclose(s, 0.5 * (9 / 50) ** 0.5)
    assert direct.default_hyperparameters(1, 1) == (0.3, 0.5)  # capped at the paper's values
    # The run uses them: identical to passing them explicitly, and not to the old fixed ones.
    n, p = 10, 2
    w = dj.Windows(jr.normal(getkey(), (6, n)), jr.normal(getkey(), (6, 3, p)),
                   jr.normal(getkey(), (6, 3, p)))
    # Jitted (the hyperparameters, Python floats, are static): one compilation for the
    # whole run instead of one per operation outside its loop.
    run = eqx.filter_jit(lambda **kw: dj.direct_run(
        jr.PRNGKey(0), w, dj.QSR.passive(p), num_inits=2, max_steps=3, atol=0.0, rtol=0.0,
        **kw).loss_history)
    lr, s = direct.default_hyperparameters(n, p)
    np.testing.assert_array_equal(run(), run(learning_rate=lr, init_scale=s))
    assert not np.array_equal(run(), run(learning_rate=0.3, init_scale=0.5))


def test_windows_at_rest_need_n_state(getkey):
    qsr = SUPPLY_RATES["passive"]
    w = expert_windows(7, 2, 2, 2)
    rest = dj.Windows(None, w.y, w.u)
    res = dj.fit_direct(getkey(), rest, qsr, n_state=3, num_inits=2, max_steps=10)
    assert res.controllers.A.shape == (2, 3, 3) and bool(jnp.all(res.certified))
    with pytest.raises(ValueError, match="`n_state`"):
        dj.fit_direct(getkey(), rest, qsr)


def test_failed_check_is_projected_and_flagged(getkey):
    """The fallback: a controller that fails the float64 check is projected and flagged."""
    qsr = SUPPLY_RATES["passive"]
    w = expert_windows(8, 2, 2, 2)
    res = eqx.filter_jit(dj.direct_run)(getkey(), w, qsr, num_inits=3, max_steps=10)
    broken = eqx.tree_at(lambda r: r.controllers.B, res, res.controllers.B.at[1].mul(50.0))
    with pytest.warns(UserWarning, match=r"1 of 3 trained controllers .* replaced by their "
                                         "projections"):
        out = direct.certify_or_project(broken, qsr, w, eps=1e-6)
    np.testing.assert_array_equal(out.projected, [False, True, False])
    assert bool(jnp.all(out.certified))
    assert bool(np.all(dj.certify(out.controllers, qsr, P=out.P).holds))
    np.testing.assert_allclose(out.final_loss[1], dj.imitation_loss(index(out.controllers, 1), w))
    np.testing.assert_array_equal(out.final_loss[::2], res.final_loss[::2])
    assert out.result_names() == res.result_names()


def test_bad_arguments(getkey):
    qsr = SUPPLY_RATES["passive"]
    w = expert_windows(9, 2, 2, 2)
    k = getkey()
    with pytest.raises(ValueError, match="`qsr` is required"):
        dj.fit_direct(k, w, None)
    for margin in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="`margin`"):
            dj.fit_direct(k, w, qsr, margin=margin)
    with pytest.raises(ValueError, match="not both"):
        dj.fit_direct(k, w, qsr, optimizer=optax.adam(0.1), learning_rate=0.1)
    with pytest.raises(ValueError, match="`learning_rate`"):
        dj.fit_direct(k, w, qsr, learning_rate=-1.0)
    with pytest.raises(ValueError, match="`qsr.Q`"):
        dj.fit_direct(k, w, dj.QSR(I2, I2 / 2, 0 * I2))
    with pytest.raises(ValueError, match="`qsr` is infeasible"):
        dj.fit_direct(k, w, dj.QSR(0 * I2, 0 * I2, -I2))


def test_sharded_sweep_equals_unsharded(tmp_path):
    """A learning-rate sweep sharded over 2 (forced host) devices equals the unsharded one
    (plain `jax.sharding`: a `NamedSharding` on the swept axis, automatic propagation)."""
    script = textwrap.dedent("""
        import json, sys
        import jax, jax.numpy as jnp, jax.random as jr, numpy as np
        from jax.sharding import AxisType, NamedSharding, PartitionSpec
        jax.config.update("jax_enable_x64", True)
        import dissil_jax as dj
        assert jax.device_count() == 2
        qsr = dj.QSR.passive(2)
        rng = np.random.default_rng(0)
        w = dj.Windows(rng.normal(size=(12, 2)), rng.normal(size=(12, 2, 2)),
                       rng.normal(size=(12, 2, 2)))
        run = jax.jit(jax.vmap(lambda lr: dj.direct_run(
            jr.PRNGKey(0), w, qsr, learning_rate=lr, num_inits=3, max_steps=30, atol=3e-2,
            throw=False)))
        lrs = jnp.array([0.01, 0.03, 0.1, 0.3])
        mesh = jax.make_mesh((2,), ("d",), axis_types=(AxisType.Auto,))
        sharded = run(jax.device_put(lrs, NamedSharding(mesh, PartitionSpec("d"))))
        plain = run(lrs)
        devices = len(sharded.final_loss.sharding.device_set)
        diff = max(float(np.nanmax(np.abs(np.asarray(a, float) - np.asarray(b, float))
                                   / (1 + np.abs(np.asarray(b, float)))))
                   for a, b in zip(jax.tree.leaves(sharded), jax.tree.leaves(plain)))
        same = all(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
                   for a, b in zip(jax.tree.leaves((sharded.steps, sharded.result)),
                                   jax.tree.leaves((plain.steps, plain.result))))
        steps = np.asarray(sharded.steps).tolist()
        print(json.dumps(dict(devices=devices, diff=diff, same=same, steps=steps)))
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    assert out["same"] and out["diff"] <= 1e-10  # same steps; values up to XLA's rounding
    assert len({s for row in out["steps"] for s in row}) > 1  # runs stop at different steps


def test_protocol_uses_the_specs_direct_settings(getkey):
    spec = dataclasses.replace(example_spec("nonlinear"), max_steps=6, direct_tol=1e-9,
                               direct_learning_rate=0.123, direct_init_scale=0.7)
    w, key = expert_windows(10, 1, 1, 1), getkey()
    res = fit("direct", key, w, spec, 2)
    ref = dj.fit_direct(key, w, spec.qsr, num_inits=2, max_steps=6, atol=1e-9, rtol=0.0,
                        learning_rate=0.123, init_scale=0.7)
    np.testing.assert_array_equal(res.loss_history, ref.loss_history)


# -- the issue's criteria at full size ------------------------------------------------------


@pytest.mark.slow
def test_nonlinear_example_criteria():
    """100 initialisations, 25 initial segments: all certified, median test MSE <= 0.02.
    (The time, well under a second once compiled, is measured in
    `benchmarks/bench_direct.py`, not asserted here.)"""
    rec = run_config("nonlinear", "initial", "direct", 25, inits=100)
    assert rec["certified"] is True and rec["percent_stable"] == 100.0
    assert rec["mse_median"] <= 0.02
    spec = example_spec("nonlinear")
    w = training_data(spec, 0, 0, "initial", 25)[2]
    kw = dict(num_inits=100, max_steps=150, atol=0.0, rtol=0.0, learning_rate=spec.direct_learning_rate)
    dj.fit_direct(jr.PRNGKey(0), w, spec.qsr, **kw)  # compile
    res = dj.fit_direct(jr.PRNGKey(0), w, spec.qsr, **kw)
    assert bool(jnp.all(res.steps == 150))
    assert bool(np.all(dj.certify(res.controllers, spec.qsr).holds))


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_linear_example_criteria(dtype):
    """n̂ = 6, m = p = 3, passive, 25 initial segments, 20 initialisations: all certified,
    median training loss within 2x of ICO's on the same data (the time, under a second, is
    measured in `benchmarks/bench_direct.py`)."""
    spec = example_spec("linear")
    w64 = training_data(spec, 0, 0, "initial", 25)[2]
    w = as_float32(w64) if dtype == "float32" else w64
    kw = dict(num_inits=20, learning_rate=spec.direct_learning_rate, atol=spec.direct_tol)
    res = dj.fit_direct(jr.PRNGKey(1), w, spec.qsr, **kw)
    assert bool(jnp.all(res.certified)) and not bool(jnp.any(res.projected))
    assert bool(np.all(dj.certify(res.controllers, spec.qsr).holds))
    ico = dj.fit_ico(jr.PRNGKey(1), w64, spec.qsr, num_inits=20, atol=spec.tol, throw=False)
    assert float(jnp.median(res.final_loss)) <= 2 * float(jnp.median(ico.final_loss))
