"""The NN + GD baseline: a static ReLU MLP controller."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import as_float32, random_windows, tree_allclose

import dissil_jax as dj


def test_mlp_controller_is_memoryless(getkey):
    K = dj.MLPController(getkey(), 2, 3, (8, 8))
    x, u = jnp.arange(4.0), jnp.array([0.3, -1.0])
    x_next, y = K(x, u)
    assert jnp.array_equal(x_next, x)
    # Independent forward pass through the layers.
    h = u
    for layer in K.mlp.layers[:-1]:
        h = jax.nn.relu(layer.weight @ h + layer.bias)
    ref = K.mlp.layers[-1].weight @ h + K.mlp.layers[-1].bias
    np.testing.assert_allclose(y, ref, rtol=1e-12)
    assert (K.n_in, K.n_out, K.batch_shape, K.hidden) == (2, 3, (), (8, 8))
    assert dj.MLPController(getkey(), 2, 3, ()).hidden == ()
    # A batch prints as one line, also inside a FitResult's pretty-printed repr.
    Ks = jax.vmap(lambda k: dj.MLPController(k, 2, 3, (8, 8)))(jr.split(getkey(), 4))
    line = "MLPController(n_in=2, n_out=3, hidden=(8, 8), batch_shape=(4,), dtype=float"
    assert repr(Ks).startswith(line) and line in eqx.tree_pformat({"controllers": Ks})
    with pytest.raises(ValueError, match="`hidden`"):
        dj.MLPController(getkey(), 2, 3, (8, 4))


def test_fit_mlp_lowers_loss(getkey):
    windows = random_windows(getkey(), N=20, h=2, n=2, p=2, m=2)
    res = dj.fit_mlp(getkey(), windows, hidden=(16, 16), num_inits=3, max_steps=300,
                     learning_rate=1e-2, atol=0.0, rtol=0.0)
    hist = np.asarray(res.loss_history)
    assert hist.shape == (3, 301)
    assert np.all(np.isfinite(hist))
    assert np.all(hist[:, -1] < 0.1 * hist[:, 0])
    np.testing.assert_allclose(res.final_loss, hist[:, -1])
    assert res.P is None and res.certified is None
    assert res.controllers.batch_shape == (3,)
    # final_loss is the paper's loss (eq. 16) of the returned controllers, computed here:
    # squared error summed over the horizon, averaged over the windows.
    Y, T = np.asarray(windows.y), -np.asarray(windows.u)
    for i in range(3):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        pred = np.stack([[np.asarray(K(jnp.zeros(2), y)[1]) for y in win] for win in Y])
        assert np.mean(np.sum((pred - T) ** 2, axis=(1, 2))) == pytest.approx(
            float(res.final_loss[i]), rel=1e-10)
    # best() is the controller with the lowest final loss.
    i_best = int(np.argmin(np.asarray(res.final_loss)))
    best, ref = res.best(), jax.tree.map(lambda a: a[i_best], res.controllers)
    assert best.batch_shape == ()
    assert tree_allclose(best, ref, rtol=0, atol=0)
    assert not tree_allclose(best, jax.tree.map(lambda a: a[(i_best + 1) % 3], res.controllers))


def test_paper_network_has_three_weight_matrices(getkey):
    """Paper §5: "a three layer network" with weights (W1, W2, W3): two hidden layers."""
    from dissil_jax.experiments.protocol import example_spec

    for example, width in (("linear", 150), ("nonlinear", 25)):
        hidden = example_spec(example).hidden
        K = dj.MLPController(getkey(), 3, 3, hidden)
        weights = [layer.weight.shape for layer in K.mlp.layers]
        assert weights == [(width, 3), (width, width), (3, width)]


def _plain_adam_loop(key, windows, hidden, max_steps, learning_rate, atol, rtol):
    """One network trained by a plain Python loop: full-batch Adam on the paper's loss,
    stop when |J_k - J_(k-1)| < atol + rtol |J_0| (the loss of the final parameters is
    recorded)."""
    import optax

    model = dj.MLPController(key, windows.n_in, windows.n_out, hidden, dtype=jnp.float64)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    Y, T = windows.y, -windows.u

    def loss(q):
        f = eqx.combine(q, static).mlp
        pred = jax.vmap(jax.vmap(f))(Y)
        return jnp.mean(jnp.sum((pred - T) ** 2, axis=(1, 2)))

    vg = jax.jit(jax.value_and_grad(loss))
    opt = optax.adam(learning_rate)
    state = opt.init(params)
    hist, prev = [], np.inf
    for _ in range(max_steps + 1):
        J, g = vg(params)
        hist.append(float(J))
        if abs(float(J) - prev) < atol + rtol * hist[0] or len(hist) == max_steps + 1:
            break
        prev = float(J)
        updates, state = opt.update(g, state, params)
        params = optax.apply_updates(params, updates)
    return eqx.combine(params, static), hist


def test_vmapped_training_equals_loop(getkey):
    windows = random_windows(getkey(), N=10, h=2, n=1, p=2, m=1)
    key = getkey()
    kwargs = dict(hidden=(8, 8), max_steps=60, learning_rate=5e-3, atol=1e-4, rtol=0.0)
    res = dj.fit_mlp(key, windows, num_inits=4, balance=False, **kwargs)
    assert len(set(res.result_names())) >= 1
    for i, k in enumerate(jr.split(key, 4)):
        model, hist = _plain_adam_loop(k, windows, **kwargs)
        assert tree_allclose(model, jax.tree.map(lambda a: a[i], res.controllers),
                             rtol=1e-9, atol=1e-12)
        n = len(hist)
        np.testing.assert_allclose(res.loss_history[i, :n], hist, rtol=1e-9)
        assert np.all(np.isnan(np.asarray(res.loss_history[i, n:])))
        assert float(res.final_loss[i]) == pytest.approx(hist[-1], rel=1e-9)
        assert int(res.steps[i]) == n - 1
        assert bool(res.converged[i]) == (n - 1 < kwargs["max_steps"])


def test_balanced_training_equals_loop_in_balanced_units(getkey):
    """`balance=True` against a plain loop: the loop trains on (y/a, -u/c) with the powers
    of two a (per input channel) and c nearest the data's RMS, computed here by hand, and
    its network is mapped back by hand (first weights / a, last layer * c); the losses are
    the loop's times c² and `atol` is in the user's units."""
    base = random_windows(getkey(), N=10, h=2, n=1, p=2, m=1)
    y = np.asarray(base.y) * np.array([300.0, 0.02])  # channels in units far apart
    u = np.asarray(base.u) * 1e-3
    windows = dj.Windows(base.x0, jnp.asarray(y), jnp.asarray(u))
    a = 2.0 ** np.round(np.log2(np.sqrt(np.mean(y.reshape(-1, 2) ** 2, axis=0))))
    c = float(2.0 ** np.round(np.log2(np.sqrt(np.mean(u**2)))))
    assert np.all(a != 1.0) and c != 1.0
    key = getkey()
    kwargs = dict(hidden=(8, 8), max_steps=60, learning_rate=5e-3, rtol=0.0)
    atol = 1e-4
    res = dj.fit_mlp(key, windows, num_inits=3, atol=atol * c**2, **kwargs)
    scaled = dj.Windows(base.x0, jnp.asarray(y / a), jnp.asarray(u / c))
    for i, k in enumerate(jr.split(key, 3)):
        model, hist = _plain_adam_loop(k, scaled, atol=atol, **kwargs)
        first, last = model.params.layers[0], model.params.layers[-1]
        model = eqx.tree_at(lambda m: (m.params.layers[0].weight, m.params.layers[-1].weight,
                                       m.params.layers[-1].bias), model,
                            (first.weight / a, last.weight * c, last.bias * c))
        assert tree_allclose(model, jax.tree.map(lambda v: v[i], res.controllers),
                             rtol=1e-9, atol=1e-12 * c)
        n = len(hist)
        np.testing.assert_allclose(res.loss_history[i, :n], np.asarray(hist) * c**2, rtol=1e-9)
        assert int(res.steps[i]) == n - 1


def test_stopping_rule(getkey):
    windows = random_windows(getkey(), N=10, h=2)
    res = dj.fit_mlp(getkey(), windows, hidden=(4,), num_inits=2, max_steps=200,
                     learning_rate=1e-3, atol=1e-2)
    assert bool(jnp.all(res.converged)) and res.result_names() == ["converged"] * 2
    steps = np.asarray(res.steps)
    hist = np.asarray(res.loss_history)
    for i in range(2):
        assert steps[i] < 200
        assert np.all(np.isfinite(hist[i, : steps[i] + 1]))
        assert np.all(np.isnan(hist[i, steps[i] + 1:]))
        assert abs(hist[i, steps[i]] - hist[i, steps[i] - 1]) < 1e-2
    with pytest.raises(ValueError, match="`num_inits`"):
        dj.fit_mlp(getkey(), windows, num_inits=0)


def test_float32_training(getkey):
    w = random_windows(getkey(), N=12, h=2, n=1, p=2, m=2)
    w32 = as_float32(w)
    res = dj.fit_mlp(getkey(), w32, hidden=(8, 8), num_inits=2, max_steps=100,
                     learning_rate=1e-2, atol=0.0, rtol=0.0)
    assert res.loss_history.dtype == jnp.float32
    assert res.controllers.params.layers[0].weight.dtype == jnp.float32
    assert bool(jnp.all(res.final_loss < 0.5 * res.initial_loss))


def _units_windows(getkey, a, b):
    """Random windows with y in units `a` (per channel) and u in units `b`."""
    w = random_windows(getkey(), N=12, h=2, n=1, p=2, m=2)
    return w, dj.Windows(w.x0, w.y * jnp.asarray(a), w.u * b)


def test_balance_trains_the_same_network_in_any_units(getkey):
    """With `balance`, inputs in units 2^10 and 2^-7 (per channel) and targets in 2^-10
    give bit for bit the same training, the network mapped to the new units."""
    a, b = np.array([2.0**10, 2.0**-7]), 2.0**-10
    w, w2 = _units_windows(getkey, a, b)
    key, kw = getkey(), dict(hidden=(8, 8), num_inits=2, max_steps=40)
    r1, r2 = dj.fit_mlp(key, w, **kw), dj.fit_mlp(key, w2, **kw)
    np.testing.assert_array_equal(r2.loss_history, r1.loss_history * b**2)
    np.testing.assert_array_equal(r2.steps, r1.steps)
    y = w.y[:3]
    pred1 = jax.vmap(lambda K: jax.vmap(jax.vmap(K.mlp))(y))(r1.controllers)
    pred2 = jax.vmap(lambda K: jax.vmap(jax.vmap(K.mlp))(y * a))(r2.controllers)
    np.testing.assert_array_equal(pred2, pred1 * b)


def test_balance_returns_the_network_in_the_users_units(getkey):
    """The returned network, evaluated on the user's data by a plain loop, has the loss
    the result reports; without `balance` the same data train far worse."""
    a, b = np.array([1e3, 1e3]), 1e-3
    _, w = _units_windows(getkey, a, b)
    kw = dict(hidden=(16, 16), num_inits=2, max_steps=300)
    res = dj.fit_mlp(getkey(), w, **kw)
    raw = dj.fit_mlp(getkey(), w, balance=False, **kw)
    Y, T = np.asarray(w.y), -np.asarray(w.u)
    zero = np.mean(np.sum(T**2, axis=(1, 2)))
    for i in range(2):
        K = jax.tree.map(lambda x: x[i], res.controllers)
        pred = np.stack([[np.asarray(K(jnp.zeros(1), y)[1]) for y in win] for win in Y])
        assert np.mean(np.sum((pred - T) ** 2, axis=(1, 2))) == pytest.approx(
            float(res.final_loss[i]), rel=1e-9)
    # the data's units: the default step moves weights that should be ~1e-6 by 1e-3
    assert np.all(np.asarray(res.final_loss) < 0.5 * zero)
    assert np.all(np.asarray(raw.final_loss) > 10 * np.asarray(res.final_loss))


def test_balance_needs_concrete_windows(getkey):
    w = random_windows(getkey(), N=6, h=2, n=1, p=1, m=1)
    run = lambda bal: jax.jit(lambda y: dj.fit_mlp(
        jr.PRNGKey(0), dj.Windows(w.x0, y, w.u), hidden=(4,), num_inits=2, max_steps=3,
        balance=bal).final_loss)(w.y)
    with pytest.raises(ValueError, match="`balance=True`.*pass `balance=False`"):
        run(True)
    np.testing.assert_allclose(run(False), dj.fit_mlp(
        jr.PRNGKey(0), w, hidden=(4,), num_inits=2, max_steps=3, balance=False).final_loss,
        rtol=1e-12)
    with pytest.raises(ValueError, match="`balance`"):
        dj.fit_mlp(jr.PRNGKey(0), w, balance="yes")
