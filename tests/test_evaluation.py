"""Demonstrations, data regimes, closed-loop simulation and metrics (issue 3)."""

import control
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import dissil_jax as dj
from dissil_jax import experiments as ex
from dissil_jax.experts import lqr_expert
from dissil_jax.systems import mass_spring_chain, paper_nonlinear_plant


@pytest.fixture(scope="module")
def linear():
    ch = mass_spring_chain(jr.PRNGKey(0))
    return ch.plant, lqr_expert(ch.Ac, ch.Bc, ch.Cc)


def _hand_traj(N=3, T=12, n=2, p=1, m=1):
    base = np.arange(N)[:, None, None] * 1000.0
    x = base + np.arange(T + 1)[None, :, None] * 10 + np.arange(n)[None, None, :]
    y = base + np.arange(T)[None, :, None] * 10 + 0.5
    u = base + np.arange(T)[None, :, None] * 10 + 0.25
    return ex.Trajectories(jnp.asarray(x), jnp.asarray(y), jnp.asarray(u))


def test_windows_hand_built():
    traj = _hand_traj()
    W = ex.initial_segments(traj, 2, horizon=2)
    np.testing.assert_array_equal(W.x0, [[0, 1], [1000, 1001]])
    np.testing.assert_array_equal(W.y[..., 0], [[0.5, 10.5], [1000.5, 1010.5]])
    np.testing.assert_array_equal(W.target[..., 0], [[-0.25, -10.25], [-1000.25, -1010.25]])
    S = ex.sliding_windows(traj, 11, horizon=2, span=10)  # 9 windows per trajectory
    assert S.num_windows == 11 and S.horizon == 2
    starts = [0, 1, 2, 3, 4, 5, 6, 7, 8, 0, 1]
    trajs = [0] * 9 + [1] * 2
    np.testing.assert_array_equal(S.x0[:, 0], [1000 * i + 10 * s for i, s in zip(trajs, starts)])
    np.testing.assert_array_equal(S.y[:, 1, 0], [1000 * i + 10 * (s + 1) + 0.5
                                                 for i, s in zip(trajs, starts)])
    np.testing.assert_array_equal(S.u[:, 0, 0], [1000 * i + 10 * s + 0.25
                                                 for i, s in zip(trajs, starts)])


def test_windows_bad_sizes():
    traj = _hand_traj(N=3, T=12)
    with pytest.raises(ValueError, match="`num_windows`"):
        ex.initial_segments(traj, 4)
    with pytest.raises(ValueError, match="`num_windows`"):
        ex.sliding_windows(traj, 3 * 9 + 1)
    with pytest.raises(ValueError, match="`horizon`"):
        ex.initial_segments(traj, 2, horizon=13)
    with pytest.raises(ValueError, match="`span`"):
        ex.sliding_windows(_hand_traj(T=5), 2, span=10)
    with pytest.raises(ValueError, match="`horizon`"):
        ex.sliding_windows(traj, 2, horizon=11, span=10)


def test_noise_entry_points(linear, getkey):
    """u_k = -K x_k + e_k, y_k = C x_k + D u_k, x_{k+1} = A x_k + B u_k + w_k, exactly."""
    plant, expert = linear
    x0 = jr.normal(getkey(), (5, 6))
    noise = ex.sample_noise(getkey(), 5, 300, plant)
    assert noise.w.shape == (5, 300, 6) and noise.e.shape == (5, 300, 3)
    np.testing.assert_allclose(np.std(ex.sample_noise(getkey(), 200, 50, plant).w), 0.04, rtol=0.05)
    tr = ex.simulate_expert(plant, expert, x0, noise)
    A, B, C, D = plant.matrices()
    K = np.asarray(expert.K)
    x = np.asarray(x0)
    for k in range(7):
        u = -x @ K.T + np.asarray(noise.e[:, k])
        np.testing.assert_allclose(tr.u[:, k], u, atol=1e-12)
        np.testing.assert_allclose(tr.y[:, k], x @ C.T + u @ D.T, atol=1e-12)
        x = x @ A.T + u @ B.T + np.asarray(noise.w[:, k])
        np.testing.assert_allclose(tr.x[:, k + 1], x, atol=1e-12)


def test_demonstration_windows(linear):
    plant, expert = linear
    key = jr.PRNGKey(3)
    W = ex.demonstration_windows(key, plant, expert, 20, "sliding")
    assert (W.num_windows, W.horizon, W.n_state, W.n_in, W.n_out) == (20, 2, 6, 3, 3)
    traj = ex.demonstrations(key, plant, expert, 3, 10, 1.0)  # ceil(20 / 9) = 3 trajectories
    np.testing.assert_allclose(W.x0, ex.sliding_windows(traj, 20).x0)
    I = ex.demonstration_windows(key, plant, expert, 5, "initial", x0_std=5.0)
    assert I.num_windows == 5
    with pytest.raises(ValueError, match="`plant_noise`"):
        ex.demonstration_windows(key, plant, expert, 5, plant_noise=-0.1)
    with pytest.raises(ValueError, match="`control_noise`"):
        ex.sample_noise(key, 2, 3, plant, control_noise=-1.0)
    with pytest.raises(ValueError, match="`regime`"):
        ex.demonstration_windows(key, plant, expert, 5, "random")


def _random_ltis(seed, K, n, p, m, scale):
    """A batch of K random controllers (numpy draws: no per-shape JAX compilation)."""
    rng = np.random.default_rng(seed)
    return dj.LTIController(*(scale * rng.normal(size=(K, *s))
                              for s in ((n, n), (n, p), (m, n), (m, p))))


def test_closed_loop_matrix_vs_python_control(linear, getkey):
    plant, _ = linear
    Ks = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), _random_ltis(1, 3, 6, 3, 3, 0.1),
                      _random_ltis(2, 3, 6, 3, 3, 0.6))
    rho = ex.lti_spectral_radius(plant, Ks)
    G = plant.to_statespace(dt=0.1)
    for i in range(6):
        Ki = jax.tree.map(lambda l: l[i], Ks)
        loop = control.feedback(G, Ki.to_statespace(dt=0.1), sign=-1)
        np.testing.assert_allclose(rho[i], np.abs(loop.poles()).max(), rtol=1e-9)
    assert np.any(rho < 1) and np.any(rho > 1)


def test_simulation_matches_loop_and_verdict(linear, getkey):
    """Batched closed loop vs a hand-written loop with (I + Dc D)^-1; verdict vs simulation."""
    plant, expert = linear
    Ks = _random_ltis(3, 4, 6, 3, 3, 0.5)
    x0 = 3 * jr.normal(getkey(), (5, 6))
    noise = ex.sample_noise(getkey(), 5, 300, plant)
    tr = ex.simulate_controllers(plant, Ks, x0, noise)
    A, B, C, D = plant.matrices()
    for i in range(4):
        Ac, Bc, Cc, Dc = (np.asarray(M[i]) for M in (Ks.A, Ks.B, Ks.C, Ks.D))
        x, xh = np.asarray(x0), np.asarray(x0)
        for k in range(5):
            e = np.asarray(noise.e[:, k])
            u = np.linalg.solve(np.eye(3) + Dc @ D, (-xh @ Cc.T - x @ C.T @ Dc.T + e).T).T
            y = x @ C.T + u @ D.T
            np.testing.assert_allclose(tr.u[i, :, k], u, rtol=1e-9, atol=1e-9)
            x, xh = x @ A.T + u @ B.T + np.asarray(noise.w[:, k]), xh @ Ac.T + y @ Bc.T
            np.testing.assert_allclose(tr.x[i, :, k + 1], x, rtol=1e-9, atol=1e-9)
    rho = ex.lti_spectral_radius(plant, Ks)
    final = np.linalg.norm(np.asarray(tr.x[:, :, -1]), axis=-1).max(axis=1)
    assert np.all(final[rho > 1.01] > 1e3) and np.all(final[rho < 0.99] < 1e2)


def test_perfect_imitation_has_zero_mse(linear):
    """A dynamic controller that reproduces u = -Kx exactly (noise free): MSE 0, stable."""
    plant, expert = linear
    A, B, _, _ = plant.matrices()
    K = np.asarray(expert.K)
    good = dj.LTIController(A - B @ K, np.zeros((6, 3)), K, np.zeros((3, 3)))
    bad = dj.LTIController(np.eye(6) * 1.2, np.zeros((6, 3)), np.zeros((3, 6)), np.zeros((3, 3)))
    Ks = jax.tree.map(lambda a, b, c: jnp.concatenate([a[None], b[None], c]), good, bad,
                      _random_ltis(5, 2, 6, 3, 3, 0.05))
    x0 = 20 * jr.normal(jr.PRNGKey(0), (5, 6))
    ev = ex.evaluate(jr.PRNGKey(1), plant, expert, Ks, x0, 300, plant_noise=0.0,
                     control_noise=0.0)
    assert ev.exact and ev.stable.tolist()[:2] == [True, False]
    assert ev.mse[0] < 1e-20 and np.isinf(ev.mse[1])
    noisy = ex.evaluate(jr.PRNGKey(1), plant, expert, Ks, x0, 300)
    assert 0 < noisy.mse[0] < 1.0


class StaticGain(eqx.Module):
    """A memoryless nonlinear controller yhat = g tanh(uhat) (state passed through)."""

    g: jax.Array

    def __call__(self, xhat, uhat):
        return xhat, self.g * jnp.tanh(uhat)


def test_nonlinear_rule_and_memoryless_controllers():
    plant = paper_nonlinear_plant()
    expert = dj.experts.nmpc_expert(plant)
    d = jnp.array([0.1, 0.4, 0.2])
    Ks = dj.LTIController(jnp.zeros((3, 1, 1)), jnp.zeros((3, 1, 1)), jnp.zeros((3, 1, 1)),
                          d[:, None, None])
    x0 = 15 * jr.normal(jr.PRNGKey(0), (50, 1))
    ev = ex.evaluate(jr.PRNGKey(1), plant, expert, Ks, x0, 30)
    # d = 0.4: u = -2x, x+ = -1.5x + 0.4 sin x is unstable; d = 0.1, 0.2 are stable.
    assert not ev.exact and ev.stable.tolist() == [True, False, True]
    assert np.isfinite(ev.mse[[0, 2]]).all() and np.isinf(ev.mse[1])
    # A memoryless module with the loop solved by Newton: tanh(y) ~ y for small y, and the
    # loop y = x + 2 g tanh(y) - 2e is nonlinear; compare with a static LTI on small states.
    mem = StaticGain(jnp.array([0.1, 0.2]))
    noise = ex.sample_noise(jr.PRNGKey(2), 50, 30, plant)
    tr = ex.simulate_controllers(plant, mem, x0, noise)
    y, u = np.asarray(tr.y), np.asarray(tr.u)
    np.testing.assert_allclose(u, -np.array([0.1, 0.2])[:, None, None, None] * np.tanh(y)
                               + np.asarray(noise.e)[None], atol=1e-9)
    np.testing.assert_array_equal(tr.xhat, jnp.broadcast_to(x0[None, :, None], tr.xhat.shape))
    assert ex.rule_stable(tr).all()


def test_controller_dimension_mismatch(linear):
    plant, _ = linear
    x0 = jnp.zeros((2, 6))
    noise = ex.sample_noise(jr.PRNGKey(0), 2, 3, plant)
    wrong_io = _random_ltis(4, 2, 6, 2, 3, 0.1)
    with pytest.raises(ValueError, match="`controllers`"):
        ex.simulate_controllers(plant, wrong_io, x0, noise)
    wrong_state = _random_ltis(4, 2, 4, 3, 3, 0.1)
    with pytest.raises(ValueError, match="`controllers`"):
        ex.simulate_controllers(plant, wrong_state, x0, noise)
    with pytest.raises(ValueError, match="`controller`"):
        ex.lti_closed_loop_matrix(plant, jax.tree.map(lambda l: l[0], wrong_io))
    with pytest.raises(ValueError, match="`x0`"):
        ex.simulate_controllers(plant, _random_ltis(4, 2, 6, 3, 3, 0.1),
                                jnp.zeros((2, 5)), noise)


def test_summary_counts_unstable_as_inf():
    from dissil_jax import FitResult

    class Fake(eqx.Module):
        mse: np.ndarray
        stable: np.ndarray

    ev = Fake(np.array([1.0, 3.0, np.inf, 2.0]), np.array([True, True, False, True]))
    fit = FitResult(controllers=None, P=None, certified=None,
                    loss_history=jnp.array([[2.0, 1.0], [4.0, 1.0], [1.0, 1.0], [1.0, 0.5]]),
                    final_loss=jnp.array([1.0, 1.0, 1.0, 0.5]), converged=jnp.ones(4, bool),
                    steps=jnp.ones(4, int), wall_time=jnp.array(8.0))
    s = ex.summarize(ev, fit)
    assert s.percent_stable == 75.0
    assert s.mse_max == np.inf and s.mse_min == 1.0
    np.testing.assert_allclose([s.mse_q1, s.mse_median], [1.75, 2.5])
    assert s.mse_q3 == np.inf
    np.testing.assert_allclose(s.percent_change_cost, np.mean([-50, -75, 0, -50]))
    assert s.train_time_per_controller == 2.0


class _ZeroExpert(eqx.Module):
    """u = 0: the expert leaves the plant to itself (for a hand-checkable equilibrium time)."""

    def init(self, x0):
        return ()

    def __call__(self, x, carry):
        return jnp.zeros(1), carry


def test_equilibrium_horizon_by_hand():
    """x+ = 0.5 x + w: the noise floor is 0.04 / sqrt(1 - 0.25) ~ 0.046, and |x0| = 10 enters
    the band |x| <= 2 * floor ~ 0.092 after log2(10 / 0.092) ~ 6.8 steps, i.e. at k = 7."""
    plant = dj.LinearPlant([[0.5]], [[1.0]], [[1.0]], [[0.0]])
    x0 = jnp.array([[10.0], [-10.0], [1.0]])
    T = ex.equilibrium_horizon(jr.PRNGKey(0), plant, _ZeroExpert(), x0, max_steps=400,
                               control_noise=0.0)
    floor = 0.04 / np.sqrt(0.75)
    assert abs(T - np.log2(10 / (2 * floor))) < 1.5
    # Noise free, the band collapses to 0 and no finite horizon reaches it: refuse.
    with pytest.raises(ValueError, match="`max_steps`"):
        ex.equilibrium_horizon(jr.PRNGKey(0), plant, _ZeroExpert(), x0, max_steps=40,
                               plant_noise=0.0, control_noise=0.0)
    with pytest.raises(ValueError, match="`band`"):
        ex.equilibrium_horizon(jr.PRNGKey(0), plant, _ZeroExpert(), x0, max_steps=40, band=1.0)


def test_bounded_and_settled_verdicts_differ_on_an_oscillation():
    """A loop that oscillates without decaying is bounded but not settled."""
    n, T = 1, 30
    x0 = np.array([[[5.0]]])
    osc = np.concatenate([x0 * (-1.0) ** np.arange(T + 1)[None, :, None]], axis=0)  # [1, T+1, 1]
    grow = x0 * 1.5 ** np.arange(T + 1)[None, :, None]
    decay = x0 * 0.5 ** np.arange(T + 1)[None, :, None]
    x = jnp.asarray(np.stack([osc, grow, decay]))  # [K=3, N=1, T+1, 1]
    tr = ex.Trajectories(x, jnp.zeros((3, 1, T, n)), jnp.zeros((3, 1, T, n)))
    assert ex.rule_stable(tr).tolist() == [False, False, True]
    assert ex.rule_bounded(tr).tolist() == [True, False, True]
    nan = ex.Trajectories(x.at[2, 0, 3, 0].set(jnp.nan), tr.y, tr.u)
    assert ex.rule_bounded(nan).tolist() == [True, False, False]


def test_diverged_controller_counts_as_unstable(linear):
    plant, _ = linear
    Ks = _random_ltis(6, 2, 6, 3, 3, 0.05)
    Ks = eqx.tree_at(lambda K: K.A, Ks, Ks.A.at[1, 0, 0].set(jnp.nan))
    rho = ex.lti_spectral_radius(plant, Ks)
    assert np.isfinite(rho[0]) and rho[1] == np.inf


def test_controllers_started_at_rest(linear):
    """`xhat0="rest"` is x̂0 = 0 of the controllers' own order; the default stays x̂0 = x0."""
    plant, expert = linear
    x0 = 3 * jr.normal(jr.PRNGKey(0), (3, 6))
    noise = ex.sample_noise(jr.PRNGKey(1), 3, 20, plant)
    same = _random_ltis(5, 2, 6, 3, 3, 0.1)  # order 6 = the plant's: all three starts work
    rest = ex.simulate_controllers(plant, same, x0, noise, xhat0="rest")
    zeros = ex.simulate_controllers(plant, same, x0, noise, xhat0=jnp.zeros((3, 6)))
    default = ex.simulate_controllers(plant, same, x0, noise)
    np.testing.assert_array_equal(rest.x, zeros.x)
    np.testing.assert_array_equal(default.xhat[:, :, 0], np.broadcast_to(x0, (2, 3, 6)))
    assert np.abs(np.asarray(rest.x) - np.asarray(default.x)).max() > 1e-3
    lower = _random_ltis(6, 2, 4, 3, 3, 0.1)  # order 4: only at rest (or an explicit xhat0)
    with pytest.raises(ValueError, match="`controllers` have 4 states"):
        ex.simulate_controllers(plant, lower, x0, noise)
    tr = ex.simulate_controllers(plant, lower, x0, noise, xhat0="rest")
    assert tr.xhat.shape == (2, 3, 21, 4)
    ev = ex.evaluate(jr.PRNGKey(1), plant, expert, lower, x0, 20, xhat0="rest")
    assert ev.learned.xhat.shape == (2, 3, 21, 4) and np.all(ev.learned.xhat[:, :, 0] == 0)
