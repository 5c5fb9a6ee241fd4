"""The NN + GD baseline: a static ReLU MLP controller."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import random_windows, tree_allclose

import dissil_jax as dj
from dissil_jax._train.mlp import _pairs, _train_one


def test_mlp_controller_is_memoryless(getkey):
    K = dj.MLPController(2, 3, (8, 8), key=getkey())
    x, u = jnp.arange(4.0), jnp.array([0.3, -1.0])
    x_next, y = K(x, u)
    assert jnp.array_equal(x_next, x)
    # Independent forward pass through the layers.
    h = u
    for layer in K.mlp.layers[:-1]:
        h = jax.nn.relu(layer.weight @ h + layer.bias)
    ref = K.mlp.layers[-1].weight @ h + K.mlp.layers[-1].bias
    np.testing.assert_allclose(y, ref, rtol=1e-12)
    assert (K.n_in, K.n_out, K.batch_shape) == (2, 3, ())
    with pytest.raises(ValueError, match="`hidden`"):
        dj.MLPController(2, 3, (8, 4), key=getkey())


def test_fit_mlp_lowers_loss(getkey):
    windows = random_windows(getkey(), N=20, h=2, n=2, p=2, m=2)
    res = dj.fit_mlp(getkey(), windows, hidden=(16, 16), num_inits=3, max_steps=300,
                     learning_rate=1e-2, tol=0.0)
    hist = np.asarray(res.loss_history)
    assert hist.shape == (3, 301)
    assert np.all(np.isfinite(hist))
    assert np.all(hist[:, -1] < 0.1 * hist[:, 0])
    np.testing.assert_allclose(res.final_loss, hist[:, -1])
    assert res.P is None and res.certified is None
    assert res.controllers.batch_shape == (3,)
    # final_loss is the loss of the returned controllers, computed independently.
    X, T = np.asarray(windows.y).reshape(-1, 2), -np.asarray(windows.u).reshape(-1, 2)
    for i in range(3):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        pred = np.stack([np.asarray(K(jnp.zeros(2), x)[1]) for x in X])
        assert np.mean(np.sum((pred - T) ** 2, -1)) == pytest.approx(float(res.final_loss[i]),
                                                                      rel=1e-10)
    best = res.best()
    assert isinstance(best, dj.MLPController) and best.batch_shape == ()


def test_vmapped_training_equals_loop(getkey):
    windows = random_windows(getkey(), N=10, h=2, n=1, p=2, m=1)
    key = getkey()
    kwargs = dict(hidden=(8, 8, 8), max_steps=60, learning_rate=5e-3, tol=1e-4)
    res = dj.fit_mlp(key, windows, num_inits=4, **kwargs)
    X, T = _pairs(windows)
    one = eqx.filter_jit(lambda k: _train_one(k, X, T, **kwargs))
    for i, k in enumerate(jr.split(key, 4)):
        model, hist, J, converged, steps, reason = one(k)
        assert tree_allclose(model, jax.tree.map(lambda a: a[i], res.controllers),
                             rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(hist, res.loss_history[i], rtol=1e-9, equal_nan=True)
        assert float(J) == pytest.approx(float(res.final_loss[i]), rel=1e-9)
        assert bool(converged) == bool(res.converged[i])
        assert int(steps) == int(res.steps[i])
        assert int(reason) == int(res.stop_reason[i])


def test_stopping_rule(getkey):
    windows = random_windows(getkey(), N=10, h=2)
    res = dj.fit_mlp(getkey(), windows, hidden=(4,), num_inits=2, max_steps=200,
                     learning_rate=1e-3, tol=1e-2)
    assert bool(jnp.all(res.converged)) and res.stop_reasons() == ["converged"] * 2
    steps = np.asarray(res.steps)
    hist = np.asarray(res.loss_history)
    for i in range(2):
        assert steps[i] < 200
        assert np.all(np.isfinite(hist[i, : steps[i] + 1]))
        assert np.all(np.isnan(hist[i, steps[i] + 1:]))
        assert abs(hist[i, steps[i]] - hist[i, steps[i] - 1]) < 1e-2
    with pytest.raises(ValueError, match="`num_inits`"):
        dj.fit_mlp(getkey(), windows, num_inits=0)
