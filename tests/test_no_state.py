"""Training and evaluation from input-output logs alone: `dj.Windows(None, y, u)`.

Every reference below is a plain numpy loop started at rest (x̂0 = 0); none uses the
library's (O, T) matrices or its simulators.
"""

import jax
import jax.flatten_util  # noqa: F401
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import loop_loss, loop_outputs, random_windows

import dissil_jax as dj
from dissil_jax import experiments as ex
from dissil_jax.experts import lqr_expert
from dissil_jax.internal import check_n_state, init_controllers, rollout as _rollout
from dissil_jax.systems import mass_spring_chain, paper_nonlinear_plant

# -- loss, predict and rollout from rest ----------------------------------------------------


@pytest.mark.parametrize("n_hat", [1, 2, 3])
@pytest.mark.parametrize("h", [2, 5, 40])  # 40 > the Toeplitz cut-off: the scan path
def test_loss_at_rest_equals_plain_loop(getkey, n_hat, h):
    p, m, N = 2, 2, 6
    K = dj.LTIController.random(getkey(), n_hat, p, m, scale=0.4)
    w = random_windows(getkey(), N, h, n=None, p=p, m=m, gain=None)
    ref = np.stack([loop_outputs(K, None, w.y[i]) for i in range(N)])
    np.testing.assert_allclose(dj.predict(K, w), ref, rtol=1e-11, atol=1e-11)
    assert float(dj.imitation_loss(K, w)) == pytest.approx(loop_loss(K, w),
                                                           rel=1e-11)
    assert float(jax.jit(dj.imitation_loss)(K, w)) == pytest.approx(
        loop_loss(K, w), rel=1e-11)
    np.testing.assert_allclose(dj.rollout(K, None, w.y[0]), ref[0], rtol=1e-11, atol=1e-11)


def test_both_predict_paths_agree_at_rest(getkey, monkeypatch):
    K = dj.LTIController.random(getkey(), 3, 1, 2, scale=0.5)
    w = random_windows(getkey(), 4, 6, n=None, p=1, m=2, gain=None)
    a = dj.predict(K, w)
    monkeypatch.setattr(_rollout, "_TOEPLITZ_MAX_HORIZON", 0)
    b = dj.predict(K, w)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b[2], loop_outputs(K, None, w.y[2]), atol=1e-12)


def test_loss_at_rest_differs_from_loss_at_a_state(getkey):
    """With x0 given the same controller sees O x0 on top: the two losses differ."""
    K = dj.LTIController.random(getkey(), 2, 1, 1, scale=0.5)
    rest = random_windows(getkey(), 5, 4, n=None, p=1, m=1, gain=None)
    at_x0 = dj.Windows(jnp.ones((5, 2)), rest.y, rest.u)
    at_zero = dj.Windows(jnp.zeros((5, 2)), rest.y, rest.u)
    assert float(dj.imitation_loss(K, rest)) == pytest.approx(
        float(dj.imitation_loss(K, at_zero)), rel=1e-12)
    assert abs(float(dj.imitation_loss(K, rest)) - float(dj.imitation_loss(K, at_x0))) > 1e-3


def test_gradient_at_rest_matches_finite_differences(getkey):
    K = dj.LTIController.random(getkey(), 2, 1, 1, scale=0.5)
    w = random_windows(getkey(), 5, 4, n=None, p=1, m=1, gain=None)
    g = jax.grad(dj.imitation_loss)(K, w)
    flat, unravel = jax.flatten_util.ravel_pytree(K)
    gflat, _ = jax.flatten_util.ravel_pytree(g)
    f = lambda v: loop_loss(unravel(v), w)
    eps = 1e-6
    fd = np.array([(f(flat.at[i].add(eps)) - f(flat.at[i].add(-eps))) / (2 * eps)
                   for i in range(flat.size)])
    np.testing.assert_allclose(gflat, fd, rtol=1e-6, atol=1e-8)


def test_state_width_must_match_controller_order(getkey):
    K = dj.LTIController.random(getkey(), 2, 1, 1)
    w = random_windows(getkey(), 3, 2, n=None, p=1, m=1, gain=None, x0=jnp.ones((3, 1)))
    for fn in (dj.predict, dj.imitation_loss):
        with pytest.raises(ValueError, match="`windows.x0` has width 1 but `K` has 2 states"):
            fn(K, w)
    with pytest.raises(ValueError, match=r"`x0` must have shape \(2,\)"):
        dj.rollout(K, jnp.ones(1), w.y[0])


# -- check_n_state and init_controllers -----------------------------------------------------


def test_check_n_state(getkey):
    rest = random_windows(getkey(), 3, 2, n=None, p=1, m=1, gain=None)
    logged = random_windows(getkey(), 3, 2, n=None, p=1, m=1, gain=None, x0=jnp.ones((3, 2)))
    with pytest.raises(ValueError, match="`n_state` is required when `windows.x0` is None"):
        check_n_state(rest, None)
    with pytest.raises(ValueError, match="got 0: the trainers fit dynamic controllers"):
        check_n_state(rest, 0)
    for bad in (-1, 1.5, True, "2", np.ones(2), False):
        with pytest.raises(ValueError, match="`n_state` must be a positive integer"):
            check_n_state(rest, bad)
    assert check_n_state(rest, 3, warn=False) == 3
    assert type(check_n_state(rest, np.int64(1), warn=False)) is int
    assert check_n_state(logged, None) == 2 and check_n_state(logged, 2) == 2
    with pytest.raises(ValueError, match="`n_state` = 3 but `windows.x0` has width 2"):
        check_n_state(logged, 3)


@pytest.mark.parametrize("n_hat, p, m, need", [(1, 1, 1, 3), (3, 1, 1, 7), (6, 2, 2, 7),
                                                (5, 3, 1, 8), (4, 1, 4, 6)])
def test_short_windows_from_rest_warn(getkey, n_hat, p, m, need):
    # From rest an h-step window fixes D and h - 1 Markov parameters; a generic order-n̂
    # controller with p inputs and m outputs needs ceil(n̂/m) + ceil(n̂/p) of them.
    import warnings

    for h in (need - 1, need):
        rest = random_windows(getkey(), 3, h, n=None, p=p, m=m, gain=None)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert check_n_state(rest, n_hat) == n_hat
        texts = [str(w.message) for w in caught]
        if h < need:
            assert len(texts) == 1 and f"needs h >= {need}" in texts[0], texts
        else:
            assert texts == []
    # Windows with a recorded state never warn: the state fixes the rest.
    logged = random_windows(getkey(), 3, 1, n=n_hat, p=p, m=m, gain=None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_n_state(logged, n_hat)


def test_fit_warns_once_at_the_callers_line_for_short_windows_from_rest(getkey):
    rest = random_windows(getkey(), 4, 2, n=None, p=1, m=1, gain=0.5)
    with pytest.warns(UserWarning, match="needs h >= 5") as caught:
        dj.fit_gd(getkey(), rest, n_state=2, num_inits=1, max_steps=2)
    assert [w.filename for w in caught] == [__file__]


@pytest.mark.parametrize("n_hat", [1, 3])
def test_init_controllers_with_n_state(getkey, n_hat):
    w = random_windows(getkey(), 3, 2, n=None, p=2, m=1, gain=None)
    key = getkey()
    K = init_controllers(key, 4, w, 0.5, n_state=n_hat)
    assert K.batch_shape == (4,) and (K.n_state, K.n_in, K.n_out) == (n_hat, 2, 1)
    for i, k in enumerate(jr.split(key, 4)):  # initialisation i is the draw of key i
        ref = dj.LTIController.random(k, n_hat, 2, 1, scale=1.0, dtype=w.y.dtype)
        for M, R in zip((K.A, K.B, K.C, K.D), (ref.A, ref.B, ref.C, ref.D)):
            np.testing.assert_allclose(M[i], 0.5 * np.asarray(R), rtol=1e-14)
    with pytest.raises(ValueError, match="`n_state` is required"):
        init_controllers(key, 4, w, 0.5)
    logged = random_windows(getkey(), 3, 2, n=None, p=2, m=1, gain=None, x0=jnp.ones((3, 2)))
    assert init_controllers(key, 2, logged, 1.0).n_state == 2  # default: x0's width


def test_mlp_pairs_ignore_x0(getkey):
    from dissil_jax.internal import demonstration_pairs as _pairs

    w = random_windows(getkey(), 3, 2, n=None, p=1, m=1, gain=None)
    X, T = _pairs(w)
    np.testing.assert_array_equal(X, w.y)
    np.testing.assert_array_equal(T, -np.asarray(w.u))


# -- closed loop from rest ------------------------------------------------------------------


def _loop_from_rest(plant_mats, step, Ks_np, x0, w, e):
    """Closed loop of each controller with x̂_0 = 0 (numpy); returns x [K, N, T+1, n].

    Linear output y = Cx + Du, so u = (I + Dc D)^{-1}(-Cc x̂ - Dc C x + e) exactly.
    """
    _, _, C, D = plant_mats
    out = []
    for Ac, Bc, Cc, Dc in Ks_np:
        x, xh = np.asarray(x0, np.float64), np.zeros((x0.shape[0], Ac.shape[0]))
        xs = [x]
        for k in range(w.shape[1]):
            u = np.linalg.solve(np.eye(Dc.shape[0]) + Dc @ D,
                                (-xh @ Cc.T - x @ C.T @ Dc.T + e[:, k]).T).T
            y = x @ C.T + u @ D.T
            x, xh = step(x, u) + w[:, k], xh @ Ac.T + y @ Bc.T
            xs.append(x)
        out.append(np.stack(xs, axis=1))
    return np.stack(out)


def _np_ltis(Ks):
    return [tuple(np.asarray(M[i], np.float64) for M in (Ks.A, Ks.B, Ks.C, Ks.D))
            for i in range(Ks.A.shape[0])]


def test_simulate_nonlinear_plant_at_rest_with_a_second_order_controller(getkey):
    """n̂ = 2 on the 1-state nonlinear plant: only possible at rest."""
    plant = paper_nonlinear_plant()
    rng = np.random.default_rng(0)
    Ks = dj.LTIController(*(0.2 * rng.normal(size=(3, *s))
                            for s in ((2, 2), (2, 1), (1, 2), (1, 1))))
    x0 = 3 * jr.normal(getkey(), (4, 1))
    noise = ex.sample_noise(getkey(), 4, 12, plant)
    with pytest.raises(ValueError, match='`xhat0="rest"`'):
        ex.simulate_controllers(plant, Ks, x0, noise)
    tr = ex.simulate_controllers(plant, Ks, x0, noise, xhat0="rest")
    assert tr.xhat.shape == (3, 4, 13, 2)
    np.testing.assert_array_equal(tr.xhat[:, :, 0], 0.0)
    A, B, C, D = plant.matrices()
    alpha = float(plant.alpha)
    step = lambda x, u: x @ A.T + alpha * np.sin(x) + u @ B.T
    ref = _loop_from_rest((A, B, C, D), step, _np_ltis(Ks), x0, np.asarray(noise.w),
                          np.asarray(noise.e))
    np.testing.assert_allclose(tr.x, ref, rtol=1e-9, atol=1e-9)
    # An explicit zero xhat0 is the same thing.
    tr0 = ex.simulate_controllers(plant, Ks, x0, noise, xhat0=jnp.zeros((4, 2)))
    np.testing.assert_allclose(tr0.x, tr.x, rtol=1e-12, atol=1e-12)


def test_simulate_rest_argument_errors_and_memoryless(getkey):
    plant = paper_nonlinear_plant()
    Ks = dj.LTIController(*(jnp.zeros((2, *s)) for s in ((1, 1), (1, 1), (1, 1), (1, 1))))
    x0 = jnp.ones((3, 1))
    noise = ex.sample_noise(getkey(), 3, 4, plant)
    with pytest.raises(ValueError, match="`xhat0` must be None, \"rest\""):
        ex.simulate_controllers(plant, Ks, x0, noise, xhat0="zero")
    with pytest.raises(ValueError, match="`xhat0` contains NaN"):
        ex.simulate_controllers(plant, Ks, x0, noise, xhat0=jnp.full((3, 1), jnp.nan))
    mlp = jax.vmap(lambda k: dj.MLPController(k, 1, 1, (4, 4)))(jr.split(getkey(), 2))
    tr = ex.simulate_controllers(plant, mlp, x0, noise, xhat0="rest")
    np.testing.assert_array_equal(tr.xhat, 0.0)  # carried unchanged, zeros of plant size
    assert tr.xhat.shape == (2, 3, 5, 1)


def test_evaluate_at_rest_against_plain_loops(getkey):
    """Order-2 controllers on the 6-state chain, started at rest, vs numpy loops."""
    ch = mass_spring_chain(jr.PRNGKey(0))
    plant, expert = ch.plant, lqr_expert(ch.Ac, ch.Bc, ch.Cc)
    rng = np.random.default_rng(1)
    Ks = dj.LTIController(*(0.05 * rng.normal(size=(3, *s))
                            for s in ((2, 2), (2, 3), (3, 2), (3, 3))))
    x0 = 5 * jr.normal(getkey(), (4, 6))
    key, steps = getkey(), 40
    ev = ex.evaluate(key, plant, expert, Ks, x0, steps, xhat0="rest")
    noise = ex.sample_noise(key, 4, steps, plant, dtype=x0.dtype)  # evaluate's draw
    w, e = np.asarray(noise.w), np.asarray(noise.e)
    A, B, C, D = plant.matrices()
    Kx = np.asarray(expert.K)
    xe, xs = np.asarray(x0, np.float64), [np.asarray(x0, np.float64)]
    for k in range(steps):  # expert: u = -K x + e
        xe = xe @ A.T + (-xe @ Kx.T + e[:, k]) @ B.T + w[:, k]
        xs.append(xe)
    x_exp = np.stack(xs, axis=1)
    x_ctl = _loop_from_rest((A, B, C, D), lambda x, u: x @ A.T + u @ B.T, _np_ltis(Ks),
                            x0, w, e)
    np.testing.assert_allclose(ev.expert.x, x_exp, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ev.learned.x, x_ctl, rtol=1e-9, atol=1e-9)
    assert ev.exact and ev.stable.all()
    ref_mse = np.sum((x_ctl[:, :, 1:] - x_exp[None, :, 1:]) ** 2, axis=-1).mean(axis=(1, 2))
    np.testing.assert_allclose(ev.mse, ref_mse, rtol=1e-9)
    # Defaults unchanged: x̂0 = x0 needs order 6, so these order-2 controllers are refused.
    with pytest.raises(ValueError, match="`controllers` have 2 states"):
        ex.evaluate(key, plant, expert, Ks, x0, steps)


# -- the acceptance test: training from input-output logs alone --------------------


def test_fit_pgd_learns_a_passive_expert_from_rest():
    """A certified passive order-3 expert, run from x = 0 on random inputs, is learned back.

    Every window is the beginning of an expert trajectory from rest, so with x̂0 = 0 the
    order-3 expert fits the data exactly; PGD must bring every run to <= 5 % of its
    initial loss and return certified controllers.
    """
    p = m = 2
    qsr = dj.QSR.passive(m)
    K_star, _ = dj.project(dj.LTIController.random(jr.PRNGKey(0), 3, p, m, scale=1.0), qsr)
    assert dj.certify(K_star, qsr).holds
    y = jr.normal(jr.PRNGKey(1), (32, 8, p))
    u = -np.stack([loop_outputs(K_star, None, yi) for yi in y])  # u = -ŷ (negative feedback)
    windows = dj.Windows(None, y, u)
    assert float(dj.imitation_loss(K_star, windows)) < 1e-20
    with pytest.raises(ValueError, match="`n_state` is required"):
        dj.fit_pgd(jr.PRNGKey(2), windows, qsr, num_inits=2, max_steps=1)
    res = dj.fit_pgd(jr.PRNGKey(2), windows, qsr, n_state=3, num_inits=8, learning_rate=0.3,
                     decay=0.99, max_steps=150, atol=0.0, rtol=0.0)
    assert res.controllers.n_state == 3
    ratio = np.asarray(res.final_loss) / np.asarray(res.initial_loss)
    assert np.all(ratio <= 0.05), ratio
    assert np.all(np.asarray(res.certified))
    for i in range(res.num_inits):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        assert dj.certify(K, qsr).holds
        # The reported loss is the loss from rest of the returned controller.
        assert float(res.final_loss[i]) == pytest.approx(loop_loss(K, windows), rel=1e-8)
