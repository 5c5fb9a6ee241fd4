"""`dj.fit_pgd`, `dj.pgd_run` and `dj.fit_gd` (paper Alg. 2) against plain Python loops."""

import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import as_float32, dissipation_ok, index, loop_loss, random_windows, through_solves

import dissil_jax as dj
from dissil_jax.internal import (
    INIT_SCALE,
    init_controllers,
    outcome as _outcome,
    output_factor,
    pgd,
    pgd_steps,
    projection_fo as first_order,
)

QSR = dj.QSR(-29.867, 3.556, 0.601)


def _reference_pgd(K, P, windows, qsr, lr, decay, max_steps, tol):
    """Plain Python loop: one controller, grad step, project with the previous P, and stop
    when the paper's J (computed independently) changes by less than `tol`."""
    grad = jax.jit(jax.grad(dj.imitation_loss))
    hist = [loop_loss(K, windows)]
    # steps are taken on J / s^2, s^2 the power of the inputs and initial states
    s2 = (np.mean(np.sum(np.asarray(windows.y) ** 2, axis=(1, 2)))
          + np.mean(np.sum(np.asarray(windows.x0) ** 2, axis=1)))
    for i in range(max_steps):
        g = jax.tree.map(lambda a: a / s2, grad(K, windows))
        K_tilde = jax.tree.map(lambda a, b: a - lr * decay**i * b, K, g)
        if qsr is not None:
            K, P = dj.project(K_tilde, qsr, P)
        else:
            K = K_tilde
        hist.append(loop_loss(K, windows))
        if abs(hist[-1] - hist[-2]) < tol:
            break
    return K, P, hist


def _check_against_loop(res, K0, P0, w, qsr, lr, decay, max_steps, tol):
    # Projected runs pass through max_steps + 1 Clarabel solves (the initial projection and
    # one per step): the batched run and the loop agree to the solver's tolerance compounded
    # over them (helpers.through_solves); the trainers also draw K0 inside `jit`, where XLA
    # may round N(0,1)*scale differently in the last bit. Unconstrained runs differ by
    # round-off only.
    rtol = through_solves(max_steps + 1) if qsr is not None else 1e-9
    for i in range(K0.A.shape[0]):
        Ki, Pi, hist = _reference_pgd(index(K0, i), None if P0 is None else P0[i], w, qsr, lr,
                                      decay, max_steps, tol)
        n = len(hist)
        assert int(res.steps[i]) == n - 1
        np.testing.assert_allclose(res.loss_history[i, :n], hist, rtol=rtol, atol=1e-12)
        assert np.all(np.isnan(res.loss_history[i, n:]))
        for name in "ABCD":
            np.testing.assert_allclose(getattr(index(res.controllers, i), name),
                                       getattr(Ki, name), rtol=rtol, atol=rtol * 1e-3)
        if qsr is not None:
            # P is pinned only by the projection's proximal term (weight 1e-6), so two solves
            # agree on it only to ~sqrt(tol / 1e-6); what matters is that it certifies.
            assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])


@pytest.mark.numerics
@pytest.mark.parametrize("size", [1, 2], ids=["n1", "n2m2p2"])
@pytest.mark.parametrize("constrained", [True, False], ids=["pgd", "gd"])
def test_vmapped_training_equals_python_loop(getkey, constrained, size):
    w = random_windows(getkey(), N=12, n=size, p=size, m=size, gain=0.2)
    qsr = (QSR if size == 1 else dj.QSR.passive(2)) if constrained else None
    key = getkey()
    # the loop trains in one scale; the balancing of outputs is checked against the
    # balanced problem itself (test_output_units.py)
    kw = dict(num_inits=3, max_steps=12, learning_rate=0.05, decay=0.95, atol=1e-4,
              rtol=0.0, init_scale=0.3, balance=False)
    res = dj.fit_pgd(key, w, qsr, **kw) if qsr is not None else dj.fit_gd(key, w, **kw)
    K0 = init_controllers(key, 3, w, 0.3)
    P0 = None
    if qsr is not None:
        K0, P0 = dj.project(K0, qsr)
    _check_against_loop(res, K0, P0, w, qsr, 0.05, 0.95, 12, 1e-4)


def test_initial_draw_is_standard_normal(getkey):
    """Paper §4.1: every matrix element "from a normal distribution": N(0, 1) by default."""
    import scipy.stats

    w = random_windows(getkey(), N=4, n=3, p=2, m=2)
    K = init_controllers(getkey(), 400, w, INIT_SCALE)
    entries = np.concatenate([np.asarray(M).ravel() for M in (K.A, K.B, K.C, K.D)])
    assert entries.size == 400 * (9 + 6 + 6 + 4)
    assert scipy.stats.kstest(entries, "norm").pvalue > 1e-3
    assert abs(np.std(entries) - 1.0) < 0.03
    # Different initialisations are independent draws; scale multiplies every entry.
    assert not np.allclose(K.A[0], K.A[1])
    K2 = init_controllers(jax.random.PRNGKey(1), 2, w, 0.5)
    K1 = init_controllers(jax.random.PRNGKey(1), 2, w, 1.0)
    np.testing.assert_allclose(K2.B, 0.5 * K1.B, rtol=1e-15)


def test_pgd_controllers_certified_and_loss_decreases(getkey):
    w = random_windows(getkey(), N=20, gain=0.25)
    res = dj.fit_pgd(getkey(), w, QSR, num_inits=4, max_steps=60, learning_rate=0.05, atol=0.0, rtol=0.0)
    assert res.controllers.batch_shape == (4,) and res.P.shape == (4, 1, 1)
    assert bool(jnp.all(res.certified))
    for i in range(4):
        Ki = index(res.controllers, i)
        assert dissipation_ok(Ki, QSR, res.P[i])
        assert dj.certify(Ki, QSR).holds
    assert bool(jnp.all(res.final_loss < res.initial_loss))
    assert bool(jnp.all(res.steps == 60)) and not bool(jnp.any(res.converged))
    assert res.result_names() == ["max_steps"] * 4
    assert res.loss_history.shape == (4, 61) and not bool(jnp.any(jnp.isnan(res.loss_history)))
    assert float(res.wall_time) > 0
    np.testing.assert_allclose(res.final_loss, res.loss_history[:, -1])


def test_no_retracing_across_calls(getkey, monkeypatch):
    """New data, step sizes and an equal (not identical) supply rate reuse one compilation,
    with the default step (Adam) as with the paper's rule."""
    w1 = random_windows(getkey(), N=8)
    w2 = random_windows(getkey(), N=8, gain=0.4)
    # outputs balanced against the inputs as they are (another factor, another rate: the
    # same compilation too, `test_rates_of_one_shape_share_one_compilation`)
    assert output_factor(w1) == output_factor(w2) == 1.0

    def count_traces():
        traced = eqx.debug.assert_max_traces(pgd._run, max_traces=1)
        monkeypatch.setattr(pgd, "_run_jit", eqx.filter_jit(traced))

    count_traces()
    dj.fit_pgd(getkey(), w1, QSR, num_inits=2, max_steps=5)
    dj.fit_pgd(getkey(), w2, QSR, num_inits=2, max_steps=5)
    dj.fit_pgd(getkey(), w1, dj.QSR(-29.867, 3.556, 0.601), num_inits=2, max_steps=5,
               init_scale=0.5)
    with pytest.raises(RuntimeError, match="traced"):  # the check itself can fail
        dj.fit_pgd(getkey(), w1, QSR, num_inits=3, max_steps=5)
    count_traces()
    dj.fit_pgd(getkey(), w1, QSR, num_inits=2, max_steps=5, learning_rate=1.0, decay=0.99)
    dj.fit_pgd(getkey(), w2, QSR, num_inits=2, max_steps=5, learning_rate=0.01, decay=0.9)


@pytest.mark.parametrize("method", ["clarabel", "first_order"])
def test_rates_of_one_shape_share_one_compilation(getkey, monkeypatch, method):
    """`fit_pgd` passes its rate by reference (a traced token that the projection's host
    callback resolves, and for the first-order path the ADMM's constants as arrays): rates
    of one shape, an out-of-band one included, train under one compilation (a static rate
    compiled a run per rate, and a few hundred exhausted the process's memory maps). Each
    run equals `pgd_run`'s, whose rate is static: the same host solves and ADMM
    arithmetic, compiled in another program (round-off; the ADMM's iterations could then
    differ at the margin of its stopping test, but agree here)."""
    traced = eqx.debug.assert_max_traces(pgd._run, max_traces=1)
    monkeypatch.setattr(pgd, "_run_jit", eqx.filter_jit(traced))
    w, key = random_windows(getkey(), N=8), getkey()
    before = first_order.FALLBACKS["projections"]
    for gamma in (0.5, 2.0, 1e3):
        qsr = dj.QSR.bounded_gain(gamma, n_in=1, n_out=1)
        res = dj.fit_pgd(key, w, qsr, num_inits=2, max_steps=5, balance=False, method=method)
        ref = jax.jit(lambda k, q=qsr: dj.pgd_run(k, w, q, num_inits=2, max_steps=5,
                                                  method=method))(key)
        assert bool(np.all(res.certified))
        assert all(dissipation_ok(index(res.controllers, i), qsr, res.P[i]) for i in range(2))
        for a, b in zip(jax.tree.leaves((res.controllers, res.P, res.final_loss)),
                        jax.tree.leaves((ref.controllers, ref.P, ref.final_loss))):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    # the first-order path ran its ADMM (the counter counts its projections), Clarabel not
    assert (first_order.FALLBACKS["projections"] > before) == (method == "first_order")


def test_learning_rate_sweep_with_vmap_equals_loop(getkey):
    w = random_windows(getkey(), N=10, gain=0.2)
    key = getkey()
    lrs = [0.01, 0.05, 0.1]
    run = lambda lr: dj.pgd_run(key, w, QSR, learning_rate=lr, num_inits=2, max_steps=8,
                                atol=1e-6, rtol=0.0, init_scale=0.3)
    swept = jax.jit(jax.vmap(run))(jnp.asarray(lrs))
    assert swept.loss_history.shape == (3, 2, 9)
    K0, P0 = dj.project(init_controllers(key, 2, w, 0.3), QSR)
    for j, lr in enumerate(lrs):
        res_j = jax.tree.map(lambda a: a[j], swept)
        _check_against_loop(res_j, K0, P0, w, QSR, lr, 0.99, 8, 1e-6)


def test_gd_has_no_certificate_and_fits_better(getkey):
    w = random_windows(getkey(), N=10, gain=0.8)  # gain 0.8 lies outside the controller cone
    kw = dict(num_inits=2, max_steps=80, learning_rate=0.05, atol=0.0, rtol=0.0)
    gd = dj.fit_gd(getkey(), w, **kw)
    pg = dj.fit_pgd(getkey(), w, QSR, **kw)
    assert gd.P is None and gd.certified is None
    assert float(gd.final_loss.min()) < float(pg.final_loss.min())


def test_gd_default_step_follows_the_width(getkey):
    """Plain GD's default Adam step is 0.1 up to width n + p = 9 and 0.1 * 9 / (n + p)
    above (`gd_learning_rate`), through `fit_gd` and `pgd_run(qsr=None)` alike."""
    from dissil_jax.internal import gd_learning_rate
    assert gd_learning_rate(6, 3) == 0.1 and gd_learning_rate(1, 1) == 0.1
    assert gd_learning_rate(16, 2) == pytest.approx(0.05)
    # A width-14 controller (n = 13, p = 1): the default must be Adam at 0.1 * 9 / 14.
    w, key = random_windows(getkey(), N=6, n=13), getkey()
    kw = dict(num_inits=2, max_steps=4, atol=0.0, rtol=0.0)
    default = dj.fit_gd(key, w, balance=False, **kw)  # pgd_run does not balance outputs
    same = dj.fit_gd(key, w, optimizer=optax.adam(0.1 * 9 / 14), balance=False, **kw)
    run = eqx.filter_jit(lambda: dj.pgd_run(key, w, None, throw=False, **kw))()
    np.testing.assert_array_equal(default.controllers.A, same.controllers.A)
    # pgd_run compiled as another program: the same arithmetic, fused differently
    np.testing.assert_allclose(run.controllers.A, same.controllers.A, rtol=1e-10)


def test_gd_default_initial_scale_follows_the_order(getkey):
    """Plain GD's default initial scale is 0.3 up to order 9 and 0.3 * sqrt(9 / n) above
    (`gd_init_scale`), through `fit_gd` and `pgd_run(qsr=None)` alike; `fit_pgd` keeps 0.3."""
    from dissil_jax.internal import gd_init_scale
    assert gd_init_scale(9) == 0.3 and gd_init_scale(1) == 0.3
    assert gd_init_scale(36) == pytest.approx(0.15)
    kw = dict(num_inits=2, max_steps=0, balance=False)  # max_steps=0: the draw itself
    for n, sigma in ((4, 0.3), (13, 0.3 * (9 / 13) ** 0.5)):
        w, key = random_windows(getkey(), N=6, n=n), getkey()
        default = dj.fit_gd(key, w, **kw)
        given = dj.fit_gd(key, w, init_scale=sigma, **kw)
        np.testing.assert_array_equal(default.controllers.A, given.controllers.A)
        run = dj.pgd_run(key, w, None, num_inits=2, max_steps=0)
        # another compiled program: the data scale's round trip may differ in the last bit
        np.testing.assert_allclose(run.controllers.A, given.controllers.A, rtol=1e-14)
        # the draw itself: N(0, sigma^2) entries of the shared initialisation
        np.testing.assert_allclose(given.controllers.A, init_controllers(key, 2, w, sigma).A,
                                   rtol=1e-15)
    pgd = dj.fit_pgd(key, w, dj.QSR.passive(1), **kw)
    K0, _ = dj.project(init_controllers(key, 2, w, 0.3), dj.QSR.passive(1))
    np.testing.assert_allclose(pgd.controllers.A, K0.A, rtol=1e-6, atol=1e-9)


def test_stop_reasons(getkey):
    """Every stopping rule is reported: converged, max_steps and a diverging run."""
    w = random_windows(getkey(), N=10, gain=0.2)
    capped = dj.fit_gd(getkey(), w, num_inits=2, max_steps=5, learning_rate=0.05, atol=0.0, rtol=0.0)
    conv = dj.fit_gd(getkey(), w, num_inits=2, max_steps=500, learning_rate=0.05, atol=1e-3)
    assert conv.result_names() == ["converged"] * 2 and bool(jnp.all(conv.converged))
    assert bool(jnp.all(conv.steps < 500))
    assert capped.result_names() == ["max_steps"] * 2 and not bool(jnp.any(capped.converged))
    assert bool(jnp.all(capped.steps == 5))
    # Divergence: a huge learning rate on unconstrained GD drives the loss to inf/NaN.
    diverging = dict(num_inits=2, max_steps=200, learning_rate=1e6, atol=0.0, rtol=0.0, init_scale=1.0)
    wb = random_windows(getkey(), N=10, gain=2.0)
    big = dj.fit_gd(getkey(), wb, throw=False, **diverging)
    assert big.result_names() == ["non_finite"] * 2
    with pytest.raises(ValueError, match="non_finite"):
        dj.fit_gd(getkey(), wb, **diverging)
    assert not bool(jnp.any(big.converged))
    with pytest.raises(ValueError, match="stop_reason"):
        dj.FitResult(None, None, None, big.loss_history, big.final_loss, big.converged,
                     big.steps, big.wall_time).result_names()


def test_stopping_rule_uses_the_papers_loss(getkey):
    """The run stops at the first step where the paper's J (summed over the horizon, eq. 16)
    changes by less than tol; with the per-step average (J/h) it would stop elsewhere."""
    w = random_windows(getkey(), N=10, h=3, gain=0.2)
    res = dj.fit_gd(getkey(), w, num_inits=4, max_steps=300, learning_rate=0.02, atol=1e-3)
    hist = np.asarray(res.loss_history)
    for i in range(4):
        n = int(res.steps[i])
        K = index(res.controllers, i)
        assert hist[i, n] == pytest.approx(loop_loss(K, w), rel=1e-10)
        dJ = np.abs(np.diff(hist[i, : n + 1]))
        assert dJ[-1] < 1e-3 and np.all(dJ[:-1] >= 1e-3)
        # With J/h the stopping step would be earlier for at least one run.
    assert any(np.argmax(np.abs(np.diff(hist[i])) / 3 < 1e-3) + 1 < int(res.steps[i])
               for i in range(4))


def test_trainer_bad_input(getkey):
    w = random_windows(getkey(), N=4)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.fit_pgd(getkey(), w, dj.QSR.passive(2))
    # An indefinite Q is accepted (tests/test_indefinite_q.py), but not one that admits no
    # controller: with p = 2 inputs, Q = 1 and R = -I the supply form has 1 < p positive
    # eigenvalues.
    w2 = random_windows(getkey(), N=4, p=2)
    with pytest.raises(ValueError, match="`qsr` is infeasible"):
        dj.fit_pgd(getkey(), w2, dj.QSR(1.0, np.zeros((1, 2)), -np.eye(2)))
    with pytest.raises(ValueError, match="`learning_rate`"):
        dj.fit_pgd(getkey(), w, QSR, learning_rate=float("nan"))
    with pytest.raises(ValueError, match="`num_inits`"):
        dj.fit_gd(getkey(), w, num_inits=0)
    with pytest.raises(ValueError, match="`max_steps`"):
        dj.fit_gd(getkey(), w, max_steps=-1)
    with pytest.raises(ValueError, match="`init_scale`"):
        dj.fit_pgd(getkey(), w, QSR, init_scale=float("inf"))
    with pytest.raises(ValueError, match="`windows`"):
        dj.fit_gd(getkey(), (w.x0, w.y, w.u))
    with pytest.raises(ValueError, match="infeasible"):
        dj.fit_pgd(getkey(), w, dj.QSR(-1.0, 0.0, -1.0))


class _FailAfter:
    """Replaces the projection's single Clarabel solve: the first `ok` solves run, the rest
    report `solver_failed` (a solver failure injected on the host)."""

    def __init__(self, monkeypatch, ok):
        from dissil_jax.internal import projection_cache as _projection

        self.ok, self.calls, self._orig = ok, 0, _projection._ProjectionSolver.solve
        self.failed = _outcome.code("solver_failed")
        fail = self

        def solve(solver, *args):
            fail.calls += 1
            if fail.calls > fail.ok:
                return None, fail.failed, 0.0
            return fail._orig(solver, *args)

        monkeypatch.setattr(_projection._ProjectionSolver, "solve", solve)


def test_solver_failure_mid_run_keeps_the_last_certified_iterate(getkey, monkeypatch):
    w = random_windows(getkey(), N=12, gain=0.6)  # gain outside the cone: every step projects
    key = getkey()
    ref = dj.fit_pgd(key, w, QSR, num_inits=1, max_steps=6, learning_rate=0.05, atol=0.0, rtol=0.0)
    fail = _FailAfter(monkeypatch, ok=4)
    res = dj.fit_pgd(key, w, QSR, num_inits=1, max_steps=6, learning_rate=0.05, atol=0.0, rtol=0.0,
                     throw=False)
    assert fail.calls > 4
    with pytest.raises(ValueError, match="solver_failed"):
        dj.fit_pgd(key, w, QSR, num_inits=1, max_steps=6, learning_rate=0.05, atol=0.0, rtol=0.0)
    assert res.result_names() == ["solver_failed"] and not bool(res.converged[0])
    k = int(res.steps[0])
    assert 0 < k < 6
    # Step k failed: it is recorded with the kept iterate, which is the last accepted iterate
    # of the unperturbed run (step k - 1), and certified.
    np.testing.assert_allclose(res.loss_history[0, :k], ref.loss_history[0, :k], rtol=1e-12)
    assert float(res.loss_history[0, k]) == float(res.loss_history[0, k - 1])
    assert float(res.final_loss[0]) == pytest.approx(float(ref.loss_history[0, k - 1]),
                                                     rel=1e-12)
    assert bool(res.certified[0]) and int(res.kept_step[0]) == k - 1
    assert dissipation_ok(index(res.controllers, 0), QSR, res.P[0])


@pytest.mark.parametrize("trainer", ["pgd", "direct", "gd"])
def test_best_iterate_is_kept(getkey, trainer):
    """A step too long for the problem makes the loss go up and down. The certified
    trainers return their iterate of lowest loss and say which step it was; the
    unconstrained baseline returns its last iterate."""
    w = random_windows(getkey(), N=12, n=2, gain=0.6)
    kw = dict(num_inits=4, max_steps=12, atol=0.0, rtol=0.0, throw=False)
    if trainer == "pgd":  # the paper's rule without decay, far above its default step
        res = dj.fit_pgd(getkey(), w, QSR, learning_rate=8.0, decay=1.0, **kw)
    elif trainer == "direct":
        res = dj.fit_direct(getkey(), w, QSR, learning_rate=3.0, **kw)
    else:
        res = dj.fit_gd(getkey(), w, optimizer=optax.sgd(6.0), **kw)
    hist = np.asarray(res.loss_history)
    last = np.array([h[int(s)] for h, s in zip(hist, np.asarray(res.steps))])
    # the premise: some run ended above its best loss (else the test shows nothing)
    assert np.any(last > np.nanmin(hist, axis=1) * (1 + 1e-9))
    kept = np.asarray(res.kept_step)
    for i in range(4):
        K = index(res.controllers, i)
        if trainer == "gd":
            assert kept[i] == int(res.steps[i])
            assert float(res.final_loss[i]) == pytest.approx(last[i], rel=1e-12, nan_ok=True)
            continue
        assert kept[i] == int(np.nanargmin(hist[i]))
        assert float(res.final_loss[i]) == pytest.approx(np.nanmin(hist[i]), rel=1e-12)
        # the returned controller is the one that had that loss, and it is certified
        assert loop_loss(K, w) == pytest.approx(float(res.final_loss[i]), rel=1e-9)
        assert bool(res.certified[i]) and dissipation_ok(K, QSR, res.P[i])


def test_failed_initial_projection(getkey, monkeypatch):
    w = random_windows(getkey(), N=6)
    _FailAfter(monkeypatch, ok=0)
    with pytest.raises(ValueError, match="2 of 2 runs.*solver_failed"):
        dj.fit_pgd(getkey(), w, QSR, num_inits=2, max_steps=3)
    with pytest.raises(Exception, match="Clarabel failed"):  # traced: EquinoxRuntimeError
        jax.jit(lambda k: dj.pgd_run(k, w, QSR, num_inits=2, max_steps=3).final_loss)(getkey())
    res = eqx.filter_jit(dj.pgd_run)(getkey(), w, QSR, num_inits=2, max_steps=3, throw=False)
    assert res.result_names() == ["solver_failed"] * 2
    assert not bool(jnp.any(res.certified)) and bool(jnp.all(res.steps == 0))


def test_best_picks_among_certified_runs_only(getkey):
    """`best()` is the lowest final loss among the certified runs (a run whose first
    projection failed keeps its uncertified draw, possibly of lower loss); among finite
    runs for the baselines; and it refuses when nothing qualifies or for a sweep."""
    Ks = init_controllers(getkey(), 4, random_windows(getkey(), N=3), 1.0)
    loss = jnp.array([2.0, 1.0, 3.0, jnp.nan])
    res = dj.FitResult(Ks, None, jnp.array([True, False, True, False]), loss[:, None], loss,
                       jnp.zeros(4, bool), jnp.zeros(4, int), jnp.asarray(0.0))
    pick = lambda r: [i for i in range(4)
                      if bool(jnp.all(index(Ks, i).A == r.best().A))]
    assert pick(res) == [0]
    assert pick(eqx.tree_at(lambda r: r.certified, res, None,
                            is_leaf=lambda x: x is None)) == [1]  # unconstrained: lowest
    with pytest.raises(ValueError, match="none of the 4 runs is certified"):
        eqx.tree_at(lambda r: r.certified, res, jnp.zeros(4, bool)).best()
    with pytest.raises(ValueError, match="non-finite"):
        eqx.tree_at(lambda r: (r.certified, r.final_loss), res,
                    (None, jnp.full(4, jnp.nan)), is_leaf=lambda x: x is None).best()
    sweep = jax.tree.map(lambda a: jnp.stack([a, a]), res)
    with pytest.raises(ValueError, match="one initialisation axis"):
        sweep.best()


def test_non_finite_loss_under_a_constraint_keeps_the_last_finite_iterate(getkey, monkeypatch):
    """The loss is made NaN once it falls below a threshold between steps 2 and 3 of a
    reference run: the constrained run must keep its step-2 iterate, certified."""
    w = random_windows(getkey(), N=12, gain=0.6)
    key = getkey()
    kw = dict(num_inits=1, max_steps=6, learning_rate=0.05, atol=0.0, rtol=0.0)
    ref = dj.fit_pgd(key, w, QSR, **kw)
    hist = np.asarray(ref.loss_history[0])
    assert np.all(np.diff(hist) < 0)
    s2 = (np.mean(np.sum(np.asarray(w.y) ** 2, axis=(1, 2)))
          + np.mean(np.sum(np.asarray(w.x0) ** 2, axis=1)))
    threshold = (hist[2] + hist[3]) / 2 / s2  # the loop sees J / s^2
    true_loss = pgd_steps._batched_loss

    def nan_below(K, windows):
        loss, grad = true_loss(K, windows)
        return jnp.where(loss < threshold, jnp.nan, loss), grad

    monkeypatch.setattr(pgd_steps, "_batched_loss", nan_below)
    # a new function object, so that jit's cache cannot serve the unpatched trace
    monkeypatch.setattr(pgd, "_run_jit", eqx.filter_jit(lambda *a, **k: pgd._run(*a, **k)))
    res = dj.fit_pgd(key, w, QSR, throw=False, **kw)
    assert res.result_names() == ["non_finite"] and int(res.steps[0]) == 3
    assert float(res.final_loss[0]) == pytest.approx(hist[2], rel=1e-12)
    assert float(res.loss_history[0, 3]) == pytest.approx(hist[2], rel=1e-12)
    assert bool(res.certified[0]) and int(res.kept_step[0]) == 2
    assert dissipation_ok(index(res.controllers, 0), QSR, res.P[0])
    assert loop_loss(index(res.controllers, 0), w) == pytest.approx(hist[2], rel=1e-10)
    with pytest.raises(ValueError, match="non_finite"):
        dj.fit_pgd(key, w, QSR, **kw)


@pytest.mark.parametrize("constrained", [True, False], ids=["pgd", "gd"])
def test_float32_training(getkey, constrained):
    """float32 windows train float32 controllers; the certificate holds for the rounded
    float32 numbers (checked in float64 by the definition-based test)."""
    w = random_windows(getkey(), N=12, n=2, p=2, m=2, gain=0.3)
    w32 = as_float32(w)
    qsr = dj.QSR.passive(2)
    kw = dict(num_inits=3, max_steps=20, learning_rate=0.05, atol=0.0, rtol=0.0)
    res = dj.fit_pgd(getkey(), w32, qsr, **kw) if constrained else dj.fit_gd(getkey(), w32, **kw)
    assert res.controllers.A.dtype == jnp.float32 and res.loss_history.dtype == jnp.float32
    assert bool(jnp.all(res.final_loss < res.initial_loss))
    if constrained:
        assert bool(jnp.all(res.certified)) and res.P.dtype == jnp.float32
        for i in range(3):
            assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])


def test_kept_step_of_a_batch_equals_python_loop(getkey):
    """Each lane of a batch (the initialisations are vmapped) reports as `kept_step` the step
    of lowest loss that a plain Python loop, one run per initialisation, finds, and returns
    that step's loss. The step is far too long for the problem, so the loss goes up and down
    and the best step is not the last. Not so long that the runs turn chaotic: at a step of
    8 one lane amplified the batch's and the loop's round-off differences (other BLAS
    kernels: OPENBLAS_CORETYPE=SkylakeX, Sandybridge) to 2.7 times the solvers' allowance;
    at 6 the worst lane stays within 1/30 of it under Haswell, SkylakeX and Sandybridge."""
    w = random_windows(getkey(), N=12, n=2, gain=0.6)
    key = getkey()
    steps, lr = 8, 6.0
    res = dj.fit_pgd(key, w, QSR, learning_rate=lr, decay=1.0, num_inits=4, max_steps=steps,
                     atol=0.0, rtol=0.0, init_scale=0.3, throw=False)
    K0, P0 = dj.project(init_controllers(key, 4, w, 0.3), QSR)
    rtol = through_solves(steps + 1)  # as in `_check_against_loop`
    kept = np.asarray(res.kept_step)
    for i in range(4):
        _, _, hist = _reference_pgd(index(K0, i), P0[i], w, QSR, lr, 1.0, steps, tol=0.0)
        hist = np.asarray(hist)
        best = int(np.argmin(hist))
        # the premise: the best step is unambiguous at the runs' agreement (each history
        # within rtol of the other, so a gap over 2 rtol cannot change the argmin)
        assert np.all(np.delete(hist, best) > hist[best] * (1 + 3 * rtol))
        np.testing.assert_allclose(res.loss_history[i], hist, rtol=rtol, atol=1e-12)
        assert kept[i] == best
        assert float(res.final_loss[i]) == pytest.approx(hist[best], rel=rtol)
    assert np.any(kept < steps)  # some run's best iterate is not its last


def test_float64_enabled_on_one_thread_only_is_refused_by_name():
    """`with jax.enable_x64(True):` (x64 off for the process) made `fit_pgd` fail deep in
    its compiled loop ("Incorrect output dtype ... Expected: float64, Actual: float32"): the
    projections' host callbacks run on XLA's threads, which the thread-local setting does
    not reach. A clear error says so; a single `dj.project` call in the same context (its
    callback on the calling thread) and float32 data still work. In a fresh process,
    where x64 is not enabled globally as in this suite."""
    script = textwrap.dedent("""
        import jax, jax.numpy as jnp, numpy as np, dissil_jax as dj
        y = jnp.asarray(np.random.default_rng(0).standard_normal((6, 3, 1)))
        qsr = dj.QSR.passive(1)
        with jax.enable_x64(True):
            W = dj.Windows(jnp.asarray(y[:, 0]), jnp.asarray(y, jnp.float64),
                           -0.5 * jnp.asarray(y, jnp.float64))
            try:
                dj.fit_pgd(jax.random.PRNGKey(0), W, qsr, num_inits=1, max_steps=2)
                print("no error")
            except ValueError as e:
                print("refused:", "jax_enable_x64" in str(e) and "fit_pgd" in str(e))
            K = dj.LTIController(0.5 * jnp.eye(1), jnp.ones((1, 1)), jnp.ones((1, 1)),
                                 -3.0 * jnp.ones((1, 1)))
            print("project:", dj.project(K, qsr).controller.A.dtype)
        W32 = dj.Windows(y[:, 0], y, -0.5 * y)
        print("float32:", bool(dj.fit_pgd(jax.random.PRNGKey(0), W32, qsr, num_inits=1,
                                          max_steps=2).certified.all()))
    """)
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.splitlines()[-3:] == ["refused: True", "project: float64",
                                             "float32: True"], proc.stdout
