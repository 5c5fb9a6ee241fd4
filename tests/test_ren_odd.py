"""Odd REN controllers: `RENController.odd_part` against its definition, its certificate,
and `dj.fit_ren(odd=True)`."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import expert_windows, supply_from_definition
from test_ren import SUPPLY_RATES, _np_step, _random_ren

import dissil_jax as dj
from dissil_jax.internal import ren_map as rm


def _np_rollout(K, x0, u):
    ys, x = [], x0
    for uk in u:
        x, y, _, _ = _np_step(K, x, uk)
        ys.append(y)
    return np.array(ys)


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_odd_part_is_half_the_difference_of_two_copies(activation):
    """Reference: two plain-numpy runs of K, from x0 on u and from -x0 on -u."""
    rng = np.random.default_rng(0)
    K = _random_ren(rng, activation=activation, scale=0.8)
    K2 = K.odd_part()
    assert (K2.n_state, K2.width, K2.n_in, K2.n_out) == (4, 6, 2, 2)
    for _ in range(5):
        x0, u = 2 * rng.standard_normal(2), 2 * rng.standard_normal((6, 2))
        ref = 0.5 * (_np_rollout(K, x0, u) - _np_rollout(K, -x0, -u))
        got = np.asarray(dj.ren_rollout(K2, jnp.concatenate([x0, -x0]), u))
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
        # odd: the mirrored start and inputs give the mirrored outputs
        mirror = np.asarray(dj.ren_rollout(K2, jnp.concatenate([-x0, x0]), -u))
        np.testing.assert_allclose(mirror, -got, rtol=1e-12, atol=1e-12)


def test_odd_part_keeps_batch_axes():
    rng = np.random.default_rng(1)
    Ks = [_random_ren(rng) for _ in range(3)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *Ks)
    odd = batch.odd_part()
    for i, K in enumerate(Ks):
        for a, b in zip(jax.tree.map(lambda a: a[i], odd).matrices, K.odd_part().matrices):
            np.testing.assert_array_equal(a, b)


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", sorted(SUPPLY_RATES))
def test_odd_part_inherits_the_certificate(name):
    """(P, Lambda) of K gives (diag(P, P)/2, diag(Lambda, Lambda)/2) for its odd part, for
    every Q <= 0; a fresh SDP agrees, and the storage decreases along the odd REN."""
    qsr = SUPPLY_RATES[name]
    theta = jax.tree.map(lambda a: a[0], rm.init_ren_params(jr.PRNGKey(2), 1, 2, 3, 2, 2, 0.7,
                                                         jnp.float64))
    K, P, lam = rm.ren_map(theta, qsr, 3, "relu")
    assert dj.certify_ren(K, qsr, P=P, multiplier=lam).holds
    P2, lam2 = 0.5 * np.kron(np.eye(2), np.asarray(P)), 0.5 * np.tile(np.asarray(lam), 2)
    K2 = K.odd_part()
    assert dj.certify_ren(K2, qsr, P=P2, multiplier=lam2).holds
    assert dj.certify_ren(K2, qsr).holds
    rng = np.random.default_rng(3)
    for _ in range(100):
        x, u = 3 * rng.standard_normal(4), 3 * rng.standard_normal(2)
        xn, y, _, _ = _np_step(K2, x, u)
        s = supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None], y[None])[0]
        # round-off of float64 sums of terms of size ~|P| |x|^2
        assert xn @ P2 @ xn - x @ P2 @ x - s <= 1e-9 * (1 + x @ P2 @ x + u @ u)


@pytest.mark.parametrize("at_rest", [False, True])
def test_fit_ren_odd_returns_the_certified_odd_controller_it_trained(at_rest):
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    w = expert_windows(1, 1, 1, 1, N=10)
    if at_rest:
        w = dj.Windows(None, w.y, w.u)
    res = dj.fit_ren(jr.PRNGKey(4), w, qsr, width=3, num_inits=3, max_steps=25, odd=True,
                     n_state=None if not at_rest else 1)
    assert res.certified.all() and res.P.shape == (3, 2, 2) and res.multiplier.shape == (3, 6)
    assert (res.final_loss < res.initial_loss).all()
    x0 = None if at_rest else jnp.concatenate([w.x0, -w.x0], -1)
    doubled = dj.Windows(x0, w.y, w.u)
    for i in range(3):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        assert (K.n_state, K.width) == (2, 6)
        # the returned controller's loss from (x0, -x0) is the loss the trainer reports
        # (trained in normalised units and mapped back exactly: round-off only)
        np.testing.assert_allclose(dj.ren_imitation_loss(K, doubled), res.final_loss[i],
                                   rtol=1e-9)
        assert dj.certify_ren(K, qsr).holds  # independent of the trainer's pair


def test_odd_must_be_a_bool():
    w = expert_windows(1, 1, 1, 1, N=4)
    with pytest.raises(ValueError, match="`odd`"):
        dj.fit_ren(jr.PRNGKey(0), w, dj.QSR.passive(1), width=2, num_inits=2, max_steps=2,
                   odd="yes")


@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_odd_relu_ren_applies_a_linear_first_control(activation):
    """Started at the plant state, an odd ReLU REN's first control in the loop is linear in
    x0, even on the paper's nonlinear plant (y = x - 2u): the loop's algebraic equation
    u0 = -K(x0, x0 - 2 u0) is positively homogeneous and odd. tanh is not (the control)."""
    from dissil_jax.experiments import Noise, simulate_controllers
    from dissil_jax.systems import paper_nonlinear_plant

    plant = paper_nonlinear_plant()
    rng = np.random.default_rng(4)
    K = _random_ren(rng, n=1, q=4, p=1, m=1, activation=activation, scale=0.6).odd_part()
    Ks = jax.tree.map(lambda a: a[None], K)
    x0 = jnp.array([[1.0], [-3.0], [0.5], [2.0], [7.0]])
    zeros = lambda d: jnp.zeros((5, 1, d))
    traj = simulate_controllers(plant, Ks, x0, Noise(zeros(1), zeros(1)),
                                jnp.concatenate([x0, -x0], -1))
    u0 = np.asarray(traj.u)[0, :, 0, 0]
    gain = u0 / np.asarray(x0[:, 0])
    assert abs(gain[0]) > 1e-3  # the controller acts
    if activation == "relu":
        # one Newton solve of the loop per point (tolerance 1e-6, `simulate_controllers`)
        np.testing.assert_allclose(gain, gain[0], rtol=1e-6, atol=1e-9)
    else:
        assert np.ptp(gain) > 1e-3
