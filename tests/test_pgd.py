import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import independent_kyp_ok, index, random_windows

import dissil_jax as dj
from dissil_jax._train import pgd

QSR = dj.QSR(-29.867, 3.556, 0.601)


def _reference_pgd(K, P, windows, qsr, lr, decay, max_steps, tol):
    """Plain Python loop: one controller, grad step, project with the previous P, stop rule."""
    loss, grad = jax.jit(dj.imitation_loss), jax.jit(jax.grad(dj.imitation_loss))
    hist = [float(loss(K, windows))]
    for i in range(max_steps):
        g = grad(K, windows)
        K_tilde = jax.tree.map(lambda a, b: a - lr * decay**i * b, K, g)
        if qsr is not None:
            K, P = dj.project(K_tilde, qsr, P)
        else:
            K = K_tilde
        hist.append(float(loss(K, windows)))
        if abs(hist[-1] - hist[-2]) < tol:
            break
    return K, hist


@pytest.mark.parametrize("qsr", [QSR, None], ids=["pgd", "gd"])
def test_vmapped_training_equals_python_loop(getkey, qsr):
    w = random_windows(getkey(), N=12, gain=0.2)
    key = getkey()
    kw = dict(num_inits=3, max_steps=12, learning_rate=0.05, decay=0.95, tol=1e-4,
              init_scale=0.3)
    res = dj.fit_pgd(key, w, qsr, **kw) if qsr is not None else dj.fit_gd(key, w, **kw)
    K0 = pgd.init_controllers(key, 3, w, 0.3)
    P0 = None
    if qsr is not None:
        K0, P0 = dj.project(K0, qsr)
    for i in range(3):
        Ki, hist = _reference_pgd(index(K0, i), None if P0 is None else P0[i], w, qsr, 0.05,
                                  0.95, 12, 1e-4)
        n = len(hist)
        assert int(res.steps[i]) == n - 1
        np.testing.assert_allclose(res.loss_history[i, :n], hist, rtol=1e-9, atol=1e-12)
        assert np.all(np.isnan(res.loss_history[i, n:]))
        np.testing.assert_allclose(index(res.controllers, i).D, Ki.D, rtol=1e-9, atol=1e-12)


def test_pgd_controllers_certified_and_loss_decreases(getkey):
    w = random_windows(getkey(), N=20, gain=0.25)
    res = dj.fit_pgd(getkey(), w, QSR, num_inits=4, max_steps=60, learning_rate=0.05, tol=0.0)
    assert res.controllers.batch_shape == (4,) and res.P.shape == (4, 1, 1)
    assert bool(jnp.all(res.certified))
    for i in range(4):
        Ki = index(res.controllers, i)
        assert independent_kyp_ok(Ki, QSR, res.P[i])
        assert dj.certify(Ki, QSR).holds
    assert bool(jnp.all(res.final_loss < res.initial_loss))
    assert bool(jnp.all(res.steps == 60)) and not bool(jnp.any(res.converged))
    assert res.stop_reasons() == ["max_steps"] * 4
    assert res.loss_history.shape == (4, 61) and not bool(jnp.any(jnp.isnan(res.loss_history)))
    assert float(res.wall_time) > 0
    np.testing.assert_allclose(res.final_loss, res.loss_history[:, -1])


def test_no_retracing_across_calls(getkey):
    w1 = random_windows(getkey(), N=8)
    w2 = random_windows(getkey(), N=8, gain=0.1)
    dj.fit_pgd(getkey(), w1, QSR, num_inits=2, max_steps=5)
    before = pgd.TRACE_COUNT["pgd_loop"]
    dj.fit_pgd(getkey(), w2, QSR, num_inits=2, max_steps=5, learning_rate=0.01, decay=0.9)
    dj.fit_pgd(getkey(), w1, QSR, num_inits=2, max_steps=5)
    assert pgd.TRACE_COUNT["pgd_loop"] == before


def test_learning_rate_sweep_with_vmap_equals_loop(getkey):
    w = random_windows(getkey(), N=10, gain=0.2)
    key = getkey()
    lrs = jnp.array([0.01, 0.05, 0.1])
    run = lambda lr: dj.pgd_run(key, w, QSR, learning_rate=lr, num_inits=2, max_steps=8,
                                tol=1e-6, init_scale=0.3)
    swept = jax.jit(jax.vmap(run))(lrs)
    assert swept.loss_history.shape == (3, 2, 9)
    for j, lr in enumerate(lrs):
        single = jax.jit(run)(lr)
        np.testing.assert_allclose(swept.loss_history[j], single.loss_history, rtol=1e-9,
                                   atol=1e-8, equal_nan=True)
        np.testing.assert_array_equal(swept.steps[j], single.steps)
        np.testing.assert_array_equal(swept.stop_reason[j], single.stop_reason)
        for i in range(2):
            assert independent_kyp_ok(index(index(swept.controllers, j), i), QSR, swept.P[j, i])


def test_gd_has_no_certificate_and_fits_better(getkey):
    w = random_windows(getkey(), N=10, gain=0.8)  # gain 0.8 lies outside the controller cone
    kw = dict(num_inits=2, max_steps=80, learning_rate=0.05, tol=0.0)
    gd = dj.fit_gd(getkey(), w, **kw)
    pg = dj.fit_pgd(getkey(), w, QSR, **kw)
    assert gd.P is None and gd.certified is None
    assert float(gd.final_loss.min()) < float(pg.final_loss.min())


def test_stop_reasons(getkey):
    """Every stopping rule is reported: converged, max_steps and a diverging run."""
    w = random_windows(getkey(), N=10, gain=0.2)
    res = dj.fit_gd(getkey(), w, num_inits=2, max_steps=500, learning_rate=0.05, tol=1e-9)
    conv = dj.fit_gd(getkey(), w, num_inits=2, max_steps=500, learning_rate=0.05, tol=1e-3)
    assert conv.stop_reasons() == ["converged"] * 2 and bool(jnp.all(conv.converged))
    assert bool(jnp.all(conv.steps < 500))
    assert set(res.stop_reasons()) <= {"converged", "max_steps"}
    # Divergence: a huge learning rate on unconstrained GD drives the loss to inf/NaN.
    big = dj.fit_gd(getkey(), random_windows(getkey(), N=10, gain=2.0), num_inits=2,
                    max_steps=200, learning_rate=1e6, tol=0.0, init_scale=1.0)
    assert big.stop_reasons() == ["non_finite"] * 2
    assert not bool(jnp.any(big.converged))
    with pytest.raises(ValueError, match="stop_reason"):
        dj.FitResult(None, None, None, big.loss_history, big.final_loss, big.converged,
                     big.steps, big.wall_time).stop_reasons()


def test_trainer_bad_input(getkey):
    w = random_windows(getkey(), N=4)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.fit_pgd(getkey(), w, dj.QSR.passive(2))
    with pytest.raises(ValueError, match="`qsr.Q`"):
        dj.fit_pgd(getkey(), w, dj.QSR(1.0, 0.5, 0.0))
    with pytest.raises(ValueError, match="`learning_rate`"):
        dj.fit_pgd(getkey(), w, QSR, learning_rate=float("nan"))
    with pytest.raises(ValueError, match="`num_inits`"):
        dj.fit_gd(getkey(), w, num_inits=0)
    with pytest.raises(ValueError, match="`windows`"):
        dj.fit_gd(getkey(), (w.x0, w.y, w.u))
    with pytest.raises(ValueError, match="infeasible"):
        dj.fit_pgd(getkey(), w, dj.QSR(-1.0, 0.0, -1.0))
