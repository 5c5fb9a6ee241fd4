"""Rollouts and the imitation loss (paper eq. 15-16) against plain loops and by hand."""

import jax
import jax.flatten_util  # noqa: F401
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import loop_outputs

import dissil_jax as dj
from dissil_jax.internal import rollout as _rollout

_loop_outputs = loop_outputs


@pytest.mark.parametrize("n, p, m, h", [(1, 1, 1, 2), (3, 2, 1, 5), (6, 3, 3, 7)])
def test_toeplitz_and_scan_equal_plain_loop(getkey, n, p, m, h):
    K = dj.LTIController.random(getkey(), n, p, m, scale=0.5)
    x0 = jax.random.normal(getkey(), (n,))
    u = jax.random.normal(getkey(), (h, p))
    ref = _loop_outputs(K, x0, u)
    np.testing.assert_allclose(dj.rollout(K, x0, u), ref, rtol=1e-12, atol=1e-12)
    O, T = dj.observability_toeplitz(K, h)
    assert O.shape == (h * m, n) and T.shape == (h * m, h * p)
    np.testing.assert_allclose((O @ x0 + T @ u.ravel()).reshape(h, m), ref, rtol=1e-12,
                               atol=1e-12)


def test_predict_both_paths_agree(getkey, monkeypatch):
    K = dj.LTIController.random(getkey(), 2, 2, 1, scale=0.5)
    w = dj.Windows(jax.random.normal(getkey(), (5, 2)), jax.random.normal(getkey(), (5, 4, 2)),
                   jax.random.normal(getkey(), (5, 4, 1)))
    a = dj.predict(K, w)
    monkeypatch.setattr(_rollout, "_TOEPLITZ_MAX_HORIZON", 0)
    b = dj.predict(K, w)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    for i in range(5):
        np.testing.assert_allclose(a[i], _loop_outputs(K, w.x0[i], w.y[i]), atol=1e-12)


def test_sign_convention_lqr_like_expert_is_passive_gain():
    # Expert u = -k y with k > 0 is imitated exactly by the static passive controller yhat = k y.
    k = 0.7
    y = jnp.linspace(-1, 1, 12).reshape(6, 2, 1)
    w = dj.Windows(jnp.zeros((6, 1)), y, -k * y)
    K = dj.LTIController([[0.0]], [[0.0]], [[0.0]], [[k]])
    assert float(dj.imitation_loss(K, w)) == pytest.approx(0.0, abs=1e-14)
    assert dj.certify(K, dj.QSR.passive(1)).holds
    K_wrong = dj.LTIController([[0.0]], [[0.0]], [[0.0]], [[-k]])
    assert float(dj.imitation_loss(K_wrong, w)) > 0.1


def test_loss_value_and_gradient_match_finite_differences(getkey):
    K = dj.LTIController.random(getkey(), 2, 2, 2, scale=0.5)
    w = dj.Windows(jax.random.normal(getkey(), (7, 2)), jax.random.normal(getkey(), (7, 3, 2)),
                   jax.random.normal(getkey(), (7, 3, 2)))
    # Paper eq. 16: squared norm of each window's stacked error, averaged over windows.
    ref = np.mean([np.sum((_loop_outputs(K, w.x0[i], w.y[i]) + np.asarray(w.u[i])) ** 2)
                   for i in range(7)])
    assert float(dj.imitation_loss(K, w)) == pytest.approx(ref, rel=1e-12)
    g = jax.grad(dj.imitation_loss)(K, w)
    flat, unravel = jax.flatten_util.ravel_pytree(K)
    gflat, _ = jax.flatten_util.ravel_pytree(g)
    f = lambda v: float(dj.imitation_loss(unravel(v), w))
    h = 1e-6
    fd = np.array([(f(flat.at[i].add(h)) - f(flat.at[i].add(-h))) / (2 * h)
                   for i in range(flat.size)])
    np.testing.assert_allclose(gflat, fd, rtol=1e-6, atol=1e-8)


def test_loss_is_the_papers_sum_over_the_horizon_by_hand():
    """J = (1/N) sum_i sum_k ||yhat_k + u_k||^2 (paper eq. 16), computed by hand.

    Static controller yhat = 2 uhat (D = 2, A = B = C = 0), N = 2 windows of h = 3 steps:
    window 1 errors (2*1 + 1, 2*0 - 1, 2*2 + 0) = (3, -1, 4): 9 + 1 + 16 = 26;
    window 2 errors (2*(-1) + 2, 2*1 + 0, 2*0 + 1) = (0, 2, 1): 0 + 4 + 1 = 5; J = 31 / 2.
    """
    K = dj.LTIController([[0.0]], [[0.0]], [[0.0]], [[2.0]])
    y = jnp.array([[[1.0], [0.0], [2.0]], [[-1.0], [1.0], [0.0]]])
    u = jnp.array([[[1.0], [-1.0], [0.0]], [[2.0], [0.0], [1.0]]])
    w = dj.Windows(jnp.zeros((2, 1)), y, u)
    assert float(dj.imitation_loss(K, w)) == pytest.approx(31 / 2, rel=1e-14)


def test_observability_toeplitz_needs_a_horizon():
    with pytest.raises(ValueError, match="`horizon`"):
        dj.observability_toeplitz(dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1), 0)


def test_float32_rollout_and_loss_match_float64(getkey):
    K = dj.LTIController.random(getkey(), 3, 2, 2, scale=0.4)
    x0, u = jax.random.normal(getkey(), (3,)), jax.random.normal(getkey(), (5, 2))
    f32 = lambda t: jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), t)
    y64, y32 = dj.rollout(K, x0, u), dj.rollout(f32(K), f32(x0), f32(u))
    assert y32.dtype == jnp.float32
    np.testing.assert_allclose(y32, y64, rtol=1e-5, atol=1e-5)
    w = dj.Windows(x0[None], u[None], u[None])
    w32 = dj.Windows(*(f32(a) for a in (w.x0, w.y, w.u)))
    J32 = dj.imitation_loss(f32(K), w32)
    assert J32.dtype == jnp.float32
    assert float(J32) == pytest.approx(float(dj.imitation_loss(K, w)), rel=1e-5)


@pytest.mark.parametrize("shape", [(3,), (2, 3)])
def test_batched_observability_toeplitz_equals_loop(getkey, shape):
    n, p, m, h = 3, 2, 2, 4
    keys = jax.random.split(getkey(), int(np.prod(shape)))
    Kb = jax.vmap(lambda k: dj.LTIController.random(k, n, p, m, scale=0.5))(keys)
    Kb = jax.tree.map(lambda a: a.reshape(shape + a.shape[1:]), Kb)
    O, T = dj.observability_toeplitz(Kb, h)
    assert O.shape == shape + (h * m, n) and T.shape == shape + (h * m, h * p)
    for idx in np.ndindex(*shape):
        Oi, Ti = dj.observability_toeplitz(jax.tree.map(lambda a: a[idx], Kb), h)
        np.testing.assert_allclose(O[idx], Oi, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(T[idx], Ti, rtol=1e-14, atol=1e-14)
    # also under jit
    Oj, Tj = jax.jit(dj.observability_toeplitz, static_argnums=1)(Kb, h)
    np.testing.assert_allclose(Oj, O, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(Tj, T, rtol=1e-14, atol=1e-14)


def test_batched_controller_is_refused_where_one_is_required(getkey):
    Kb = jax.vmap(lambda k: dj.LTIController.random(k, 2, 1, 1))(jax.random.split(getkey(), 3))
    w = dj.Windows(jnp.zeros((4, 2)), jnp.ones((4, 3, 1)), jnp.ones((4, 3, 1)))
    with pytest.raises(ValueError, match="`K`"):
        dj.predict(Kb, w)
    with pytest.raises(ValueError, match="`K`"):
        dj.observability_toeplitz("not a controller", 2)


def test_windows_at_rest_keep_the_dtype_and_vmap_over_controllers(getkey):
    """x̂0 = 0 (`Windows(None, ...)`): float32 stays float32, and a batch of controllers of
    order 3 (any order fits windows at rest) vmaps as in the trainers."""
    Kb = jax.vmap(lambda k: dj.LTIController.random(k, 3, 1, 1, scale=0.5))(
        jax.random.split(getkey(), 4))
    y, u = jax.random.normal(getkey(), (5, 3, 1)), jax.random.normal(getkey(), (5, 3, 1))
    w = dj.Windows(None, y, u)
    J = jax.vmap(dj.imitation_loss, in_axes=(0, None))(Kb, w)
    for i in range(4):
        Ki = jax.tree.map(lambda a: a[i], Kb)
        ref = np.mean([np.sum((_loop_outputs(Ki, np.zeros(3), y[j]) + np.asarray(u[j])) ** 2)
                       for j in range(5)])
        assert float(J[i]) == pytest.approx(ref, rel=1e-12)
    f32 = lambda t: jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), t)
    K0 = jax.tree.map(lambda a: a[0], Kb)
    w32 = dj.Windows(None, f32(y), f32(u))
    assert dj.predict(f32(K0), w32).dtype == jnp.float32
    assert dj.rollout(f32(K0), None, f32(y[0])).dtype == jnp.float32
    assert float(dj.imitation_loss(f32(K0), w32)) == pytest.approx(float(J[0]), rel=1e-5)
