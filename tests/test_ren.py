"""REN controllers: the model, its certificate (against the definition), the direct map and
`dj.fit_ren`."""

import math
import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest
from helpers import REN_RATES, expert_windows, random_ren_params, supply_from_definition

import dissil_jax as dj
import dissil_jax.internal as dji
from dissil_jax.internal import (
    MapDescent,
    direct_map as dm,
    iterate,
    map_loss,
    ren_certify,
    ren_controller,
    ren_map as rm,
    ren_train,
    ren_units,
)

I2 = np.eye(2)
SUPPLY_RATES = REN_RATES  # Q <= 0 of every kind (m = p = 2)
ACT = {"relu": lambda v: np.maximum(v, 0.0), "tanh": np.tanh}


def _random_ren(rng, n=2, q=3, p=2, m=2, scale=0.4, activation="tanh"):
    shapes = [(n, n), (n, q), (n, p), (q, n), (q, q), (q, p), (m, n), (m, q), (m, p)]
    mats = [scale * rng.standard_normal(s) for s in shapes]
    mats[4] = np.tril(mats[4], -1)
    return dj.RENController(*mats, activation=activation)


# -- the model, from its definition (plain numpy, neuron by neuron) -----------------------

def _np_step(K, x, u):
    """One REN step with the layer solved row by row: v_i sees w_j for j < i only."""
    A, B1, B2, C1, D11, D12, C2, D21, D22 = (np.asarray(M, np.float64) for M in K.matrices)
    sigma = (ACT[K.activation] if isinstance(K.activation, str)
             else lambda v: float(K.activation(v)))
    w = np.zeros(D11.shape[0])
    v = np.zeros_like(w)
    for i in range(len(w)):
        v[i] = C1[i] @ x + D11[i, :i] @ w[:i] + D12[i] @ u
        w[i] = sigma(v[i])
    return A @ x + B1 @ w + B2 @ u, C2 @ x + D21 @ w + D22 @ u, v, w


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_step_and_rollout_match_the_definition(activation):
    rng = np.random.default_rng(0)
    K = _random_ren(rng, activation=activation, scale=0.8)
    x0, u = rng.standard_normal(2), rng.standard_normal((5, 2))
    ys, x = [], x0
    for k in range(5):
        x, y, _, _ = _np_step(K, x, u[k])
        ys.append(y)
    # float64 evaluations of the same sums in another order: round-off only
    np.testing.assert_allclose(dj.ren_rollout(K, x0, u), np.array(ys), rtol=1e-12, atol=1e-12)


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_predict_and_loss_vmapped_equal_python_loops():
    rng = np.random.default_rng(1)
    Ks = [_random_ren(rng) for _ in range(3)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *Ks)
    w = expert_windows(0, 2, 2, 2, N=7)
    loss = jax.jit(jax.vmap(dj.ren_imitation_loss, in_axes=(0, None)))(batch, w)
    for i, K in enumerate(Ks):
        err = [np.concatenate([_rollout_np(K, w.x0[j], w.y[j]) - w.target[j]]) for j in range(7)]
        ref = np.mean([np.sum(e**2) for e in err])
        np.testing.assert_allclose(loss[i], ref, rtol=1e-12)


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_layer_matches_the_definition(activation):
    """The explicit layer against the numpy row-by-row definition, at small and large
    widths."""
    rng = np.random.default_rng(7)
    for q in (5, 35):
        K = _random_ren(rng, q=q, activation=activation, scale=0.8 / np.sqrt(q))
        x, u = rng.standard_normal(2), rng.standard_normal(2)
        _, _, _, w_ref = _np_step(K, x, u)
        # q-term sums in another order: round-off only
        np.testing.assert_allclose(K.layer(jnp.asarray(x), jnp.asarray(u)), w_ref,
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("activation", ["relu", "tanh"])
def test_layer_derivatives_match_differentiating_the_definition(activation):
    """The layer's own derivative rule (a pass over the tangents) against JAX
    differentiating a plain row-by-row layer written here, in reverse and forward mode."""
    sigma = {"relu": jax.nn.relu, "tanh": jnp.tanh}[activation]

    def plain(C1, D11, D12, x, u):
        w = []
        for i in range(C1.shape[0]):
            v = C1[i] @ x + D12[i] @ u + sum((D11[i, j] * w[j] for j in range(i)), 0.0)
            w.append(sigma(v))
        return jnp.stack(w)

    rng = np.random.default_rng(8)
    for q in (6, 20):
        K = _random_ren(rng, q=q, activation=activation, scale=0.8 / np.sqrt(q))
        args = (K.C1, K.D11, K.D12, jnp.asarray(rng.standard_normal(2)),
                jnp.asarray(rng.standard_normal(2)))
        weights = jnp.asarray(rng.standard_normal(q))

        def lib(C1, D11, D12, x, u):
            return eqx.tree_at(lambda k: (k.C1, k.D11, k.D12), K, (C1, D11, D12)).layer(x, u)

        scalar = lambda f: lambda *a: weights @ jnp.sin(f(*a))
        g_lib = jax.jit(jax.grad(scalar(lib), argnums=range(5)))(*args)
        g_ref = jax.grad(scalar(plain), argnums=range(5))(*args)
        tangents = tuple(jnp.asarray(rng.standard_normal(a.shape)) for a in args)
        t_lib = jax.jit(lambda a, t: jax.jvp(lib, a, t)[1])(args, tangents)
        t_ref = jax.jvp(plain, args, tangents)[1]
        # the same products summed in another order: round-off only
        for a, b in zip(g_lib, g_ref):
            np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(t_lib, t_ref, rtol=1e-11, atol=1e-12)


def _rollout_np(K, x, u):
    out = []
    for k in range(u.shape[0]):
        x, y, _, _ = _np_step(K, np.asarray(x), np.asarray(u[k]))
        out.append(y)
    return np.array(out)


def test_width_zero_and_idle_neurons_are_the_lti_controller(getkey):
    K = dj.LTIController.random(getkey(), 2, 1, 1, scale=0.5)
    u = jr.normal(getkey(), (6, 1))
    x0 = jnp.array([0.3, -1.0])
    for q in (0, 4):
        R = dj.RENController.from_lti(K, width=q)
        np.testing.assert_allclose(dj.ren_rollout(R, x0, u), dj.rollout(K, x0, u), rtol=1e-13)
    back = dj.RENController.from_lti(K).to_lti()
    assert all(np.array_equal(a, b) for a, b in zip((back.A, back.B, back.C, back.D),
                                                    (K.A, K.B, K.C, K.D)))
    with pytest.raises(ValueError, match="width 4"):
        dj.RENController.from_lti(K, width=4).to_lti()
    # certify_ren at width 0 is the KYP certificate of the LTI controller
    qsr = dj.QSR(-1.0, 0.0, 4.0)
    assert dj.certify_ren(dj.RENController.from_lti(K), qsr).holds == dj.certify(K, qsr).holds


def test_bad_input_names_the_argument():
    rng = np.random.default_rng(2)
    K = _random_ren(rng)
    mats = list(K.matrices)
    bad = list(mats)
    bad[4] = np.ones((3, 3))
    with pytest.raises(ValueError, match="`D11` must be strictly lower"):
        dj.RENController(*bad)
    bad = list(mats)
    bad[1] = np.ones((2, 4))
    with pytest.raises(ValueError, match="`B1` has shape"):
        dj.RENController(*bad)
    for act in ("sigmoid", lambda v: 2 * v, lambda v: v + 1.0, lambda v: -jnp.tanh(v)):
        with pytest.raises(ValueError, match="`activation`"):
            dj.RENController(*mats, activation=act)
    # NumPy's and math's functions cannot run on traced arrays: said so, by name
    for act in (np.tanh, math.tanh):
        with pytest.raises(ValueError, match="`activation` must be a JAX function.*np.tanh"):
            dj.RENController(*mats, activation=act)
    with pytest.raises(ValueError, match="`activation` must take one array"):
        dj.RENController(*mats, activation=lambda a, b: a)
    # a traceable callable closing over a traced value cannot be screened inside `jit`
    with pytest.raises(ValueError, match="closes over traced values"):
        jax.jit(lambda c: dj.RENController(*mats, activation=lambda v: c * jnp.tanh(v)).A)(0.5)
    # a callable that passes the screen is kept (leaky ReLU: slopes 0.1 and 1)
    dj.RENController(*mats, activation=lambda v: jnp.where(v > 0, v, 0.1 * v))
    w = expert_windows(0, 2, 2, 2, N=4)
    with pytest.raises(ValueError, match="`qsr.Q` has a positive eigenvalue"):
        dj.fit_ren(jr.PRNGKey(0), w, dj.QSR(I2, I2, I2), max_steps=1)
    with pytest.raises(ValueError, match="`width`"):
        dj.fit_ren(jr.PRNGKey(0), w, SUPPLY_RATES["passive"], width=-1)
    with pytest.raises(ValueError, match="`S`|`qsr`"):
        dj.fit_ren(jr.PRNGKey(0), w, dj.QSR.passive(3), max_steps=1)
    for bad in (0.5, "yes", None):  # the old `input_share` was a number
        with pytest.raises(ValueError, match="`direct_input` must be True or False"):
            dj.fit_ren(jr.PRNGKey(0), w, SUPPLY_RATES["passive"], direct_input=bad)
    with pytest.raises(ValueError, match="`multiplier`"):
        dj.certify_ren(K, SUPPLY_RATES["gain"], P=np.eye(2), multiplier=np.ones(2))


# -- the certificate against the definition -------------------------------------------------

@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_lmi_is_the_s_procedure_form_of_the_definition():
    """xi' M xi = V(x+) - V(x) - s(u, y) + 2 w'L(v - w) for free (x, w, u), evaluated by
    running the linear part one step (no library code in the reference)."""
    rng = np.random.default_rng(3)
    K = _random_ren(rng)
    qsr = SUPPLY_RATES["strict"]
    P, lam = np.array([[2.0, 0.3], [0.3, 1.0]]), np.array([0.5, 1.5, 2.0])
    M = ren_certify.ren_lmi(K, qsr, P, lam)
    A, B1, B2, C1, D11, D12, C2, D21, D22 = (np.asarray(X) for X in K.matrices)
    for _ in range(20):
        x, w, u = rng.standard_normal(2), rng.standard_normal(3), rng.standard_normal(2)
        xn, v, y = A @ x + B1 @ w + B2 @ u, C1 @ x + D11 @ w + D12 @ u, C2 @ x + D21 @ w + D22 @ u
        ref = (xn @ P @ xn - x @ P @ x - supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None],
                                                                y[None])[0]
               + 2 * w @ (lam * (v - w)))
        xi = np.concatenate([x, w, u])
        np.testing.assert_allclose(xi @ M @ xi, ref, rtol=1e-11, atol=1e-11)


def _worst_dissipation(K, qsr, P, horizon=6, steps=300, seed=0):
    """max over unit-norm (x0, u_0..u_{T-1}) of V(x_T) - V(x_0) - sum_k s(u_k, y_k), run on
    the nonlinear REN itself, by Adam ascent from 16 random starts (pure JAX simulation; the
    ReLU network is positively homogeneous, so the unit sphere loses nothing)."""
    Q, S, R = (jnp.asarray(M) for M in (qsr.Q, qsr.S, qsr.R))
    P = jnp.asarray(P)
    n, p = K.n_state, K.n_in

    def gap(z):
        z = z / jnp.linalg.norm(z)
        x0, u = z[:n], z[n:].reshape(horizon, p)

        def f(x, uk):
            xn, y = K(x, uk)
            return xn, y @ Q @ y + 2 * y @ S @ uk + uk @ R @ uk

        xT, s = jax.lax.scan(f, x0, u)
        return xT @ P @ xT - x0 @ P @ x0 - jnp.sum(s)

    opt = optax.adam(0.05)
    z = jr.normal(jr.PRNGKey(seed), (16, n + horizon * p))
    state = opt.init(z)
    grad = jax.jit(jax.vmap(jax.value_and_grad(lambda z: -gap(z))))
    best = -np.inf
    for _ in range(steps):
        val, g = grad(z)
        best = max(best, float(-val.min()))
        upd, state = opt.update(g, state)
        z = optax.apply_updates(z, upd)
    return best


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", ["strict", "passive", "gain"])
def test_certificate_holds_along_random_and_worst_case_inputs(name):
    qsr = SUPPLY_RATES[name]
    theta = jax.tree.map(lambda a: a[0], rm.init_ren_params(jr.PRNGKey(1), 1, 2, 3, 2, 2, 0.7,
                                                         jnp.float64))
    K, _, _ = rm.ren_map(theta, qsr, 3, "relu")
    cert = dj.certify_ren(K, qsr)
    assert cert.holds and cert.status == "optimal"
    # random sequences: the storage decrease at every step of the nonlinear system
    rng = np.random.default_rng(4)
    P = cert.P
    for _ in range(50):
        x = 3 * rng.standard_normal(2)
        for _ in range(8):
            u = 3 * rng.standard_normal(2)
            xn, y, _, _ = _np_step(K, x, u)
            s = supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None], y[None])[0]
            # round-off of float64 sums of terms of size ~|P| |x|^2
            assert xn @ P @ xn - x @ P @ x - s <= 1e-9 * (1 + x @ P @ x + u @ u)
            x = xn
    # worst case found by optimisation: still no storage increase beyond round-off
    assert _worst_dissipation(K, qsr, P) <= 1e-9


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("gamma", [1e-5, 1e-6])
def test_certify_ren_solves_tight_gain_bounds_in_balanced_units(gamma):
    """A gain bound of 1e-5 has R = 1e-10 beside Q = -1: the SDP's best margin fell below
    Clarabel's tolerance and `certify_ren` was undecided on RENs whose trainer's pair
    passed the check (an audit's case; width 0 went through `dj.certify`, which balanced
    the blocks). It now solves in the units that balance Q and R, like `dj.certify`; the
    pair, mapped back exactly, passes an exact rational-arithmetic check of the S-procedure
    matrix (`test_lmi_is_the_s_procedure_form_of_the_definition` ties it to the
    definition)."""
    from helpers import exactly_dissipative

    qsr = dj.QSR.bounded_gain(gamma, n_in=1, n_out=1)
    k1, k2, k3 = jr.split(jr.PRNGKey(1), 3)
    y = jr.normal(k2, (20, 5, 1))
    w = dj.Windows(jr.normal(k1, (20, 1)), y, -0.5 * gamma * y + 0.01 * jr.normal(k3, y.shape))
    res = dj.fit_ren(jr.PRNGKey(1), w, qsr, width=1, num_inits=1, max_steps=200,
                     progress=False)
    K = jax.tree.map(lambda a: a[0], res.controllers)
    cert = dj.certify_ren(K, qsr, progress=False)
    assert cert.holds, cert.message
    assert np.all(np.asarray(cert.multiplier) > 0)
    assert exactly_dissipative(ren_certify.augmented_lti(K),
                               ren_certify.augmented_qsr(qsr, cert.multiplier), cert.P)


def test_a_non_dissipative_ren_is_rejected():
    """A REN with a large feedthrough and an active network violates a small gain bound; the
    SDP finds no certificate, and optimised inputs show the violation on the system."""
    rng = np.random.default_rng(5)
    K = _random_ren(rng, scale=1.0, activation="relu")
    qsr = dj.QSR.bounded_gain(0.1, n_in=2, n_out=2)
    cert = dj.certify_ren(K, qsr)
    assert not cert.holds and cert.margin < 0
    assert _worst_dissipation(K, qsr, np.eye(2)) > 0.1
    # a given (P, Lambda) that does not certify is refused by the eigenvalue check
    given = dj.certify_ren(K, qsr, P=np.eye(2), multiplier=np.ones(3))
    assert not given.holds
    # the messages say which verdict was reached, one per controller when batched
    assert given.message.startswith("the given (P, multiplier) does not prove")
    assert cert.message.startswith(("no storage", "undecided"))
    assert str(cert.status) in cert.message
    # an SDP solved to optimality below zero disproves the certificate and says so (it
    # said "undecided"): an unstable linear part fails it for every activation
    unstable = dj.RENController.from_lti(dj.LTIController(
        np.array([[1.5]]), np.array([[1.0]]), np.array([[1.0]]), np.array([[0.0]])), width=2)
    bad = dj.certify_ren(unstable, dj.QSR.bounded_gain(100.0, n_in=1, n_out=1))
    assert not bad.holds and str(bad.status).startswith("infeasible")
    assert bad.message.startswith("no storage")
    theta = jax.tree.map(lambda a: a[0], rm.init_ren_params(jr.PRNGKey(0), 1, 2, 3, 2, 2, 0.5,
                                                             jnp.float64))
    good = rm.ren_map(theta, dj.QSR.passive(2), 3, "relu")[0]
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), good, K)
    batch = dj.certify_ren(both, dj.QSR.passive(2))
    assert list(batch.holds) == [True, False]
    assert batch.message[0].startswith("certified") and not batch.message[1].startswith("cert")


# -- the direct map ------------------------------------------------------------------------

@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", list(SUPPLY_RATES))
def test_map_values_are_certified_for_every_q(name):
    """Every value of the map holds its certificate with the margin the map promises,
    M(P, Lam) <= -eps diag(P, 2 Lam, Phi0 / 2), checked in float64 on the REN's own
    dissipation matrix (`ren_lmi`, built from the definition's blocks)."""
    qsr = SUPPLY_RATES[name]
    theta = random_ren_params(jr.PRNGKey(2), 6, 2, 4, 2, 2, 0.5)
    K, P, lam = jax.jit(jax.vmap(lambda t: rm.ren_map(t, qsr, 4, "tanh",
                                                      direct_input=True)))(theta)
    cert = dj.certify_ren(K, qsr, P=P, multiplier=lam)
    assert cert.holds.all() and (np.asarray(lam) > 0).all()
    assert np.abs(np.asarray(K.D12)).min() > 0  # the neurons' direct input is in use
    assert (np.asarray(K.D11)[:, np.triu_indices(4)[0], np.triu_indices(4)[1]] == 0).all()
    Phi0 = dm.feedthrough_centre(qsr)[1]
    for i in range(6):
        Pi, li = np.asarray(P[i]), np.asarray(lam[i])
        M = ren_certify.ren_lmi(jax.tree.map(lambda a: a[i], K), qsr, Pi, li)
        bound = dm.MARGIN * np.block([
            [Pi, np.zeros((2, 6))],
            [np.zeros((4, 2)), np.diag(2 * li), np.zeros((4, 2))],
            [np.zeros((2, 6)), Phi0 / 2]])
        # round-off of the float64 products, relative to the matrix's largest entry
        assert np.linalg.eigvalsh(M + bound)[-1] <= 1e-10 * np.abs(M).max()


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_width_zero_is_a_certified_lti_controller():
    """At width 0 the REN map is a direct map of LTI controllers: its storage is a KYP
    certificate of `K.to_lti()` (`dj.certify`'s float64 check, the LTI tools' own)."""
    for name, qsr in SUPPLY_RATES.items():
        theta = random_ren_params(jr.PRNGKey(3), 4, 3, 0, 2, 2, 0.5)
        K, P, lam = jax.jit(jax.vmap(lambda t: rm.ren_map(t, qsr, 0)))(theta)
        assert lam.shape == (4, 0), name
        cert = dj.certify(K.to_lti(), qsr, P=P)
        assert np.all(cert.holds), name


# -- training --------------------------------------------------------------------------------

#: Single-input single-output rates for the training tests (small sizes compile faster).
SISO = {"strict": dj.QSR(-29.867, 3.556, 0.601), "passive": dj.QSR.passive(1)}


def _softsign(v):
    return v / (1 + jnp.abs(v))  # slope in (0, 1], sigma(0) = 0: a user's callable


@pytest.mark.parametrize("name, activation", [(name, "tanh") for name in SISO]
                         + [("passive", _softsign)])
def test_fit_ren_is_certified_independently(name, activation):
    """Trained RENs (with a named activation, and with a user's callable, which the
    trainer screens once eagerly and then builds inside its compiled loop) hold the
    certificate of a fresh SDP and decrease their storage on the nonlinear system."""
    qsr = SISO[name]
    w = expert_windows(1, 2, 1, 1, N=10)
    res = dj.fit_ren(jr.PRNGKey(4), w, qsr, width=3, num_inits=3, max_steps=25,
                     activation=activation)
    assert res.certified.all()
    assert (res.final_loss < res.initial_loss).all()
    # independent: the SDP's own certificate, and the storage decrease on the system
    for i in range(3):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        assert dj.certify_ren(K, qsr).holds
        P = np.asarray(res.P[i])
        rng = np.random.default_rng(i)
        for _ in range(200):
            x, u = 3 * rng.standard_normal(2), 3 * rng.standard_normal(1)
            xn, y, _, _ = _np_step(K, x, u)
            s = supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None], y[None])[0]
            assert xn @ P @ xn - x @ P @ x - s <= 1e-9 * (1 + x @ P @ x + u @ u)


def test_batched_training_equals_python_loop():
    qsr = SISO["strict"]
    w = expert_windows(2, 1, 1, 1, N=8)
    theta0 = rm.init_ren_params(jr.PRNGKey(5), 3, 1, 3, 1, 1, 0.5, jnp.float64)
    opt = optax.adam(0.05)
    loss_fn = map_loss(lambda th: rm.ren_map(th, qsr, 3, "tanh", dm.MARGIN),
                       dj.ren_imitation_loss)

    def run(theta):
        state, hist, *_ = iterate(MapDescent(theta, w, opt, loss_fn), max_steps=15, atol=0.0,
                                  rtol=0.0)
        return hist, state[2][1]

    hist, P = jax.jit(run)(theta0)
    for i in range(3):
        h_i, P_i = jax.jit(run)(jax.tree.map(lambda a: a[i:i + 1], theta0))
        # the same float64 operations per initialisation, batched or not: round-off only
        np.testing.assert_allclose(hist[i], h_i[0], rtol=1e-9)
        np.testing.assert_allclose(P[i], P_i[0], rtol=1e-9, atol=1e-12)


def test_failed_end_check_gets_an_sdp_certificate(monkeypatch):
    """Force the eigenvalue check of the map's pairs to fail: the SDP fallback certifies the
    controller (its pair checked by the real check)."""
    qsr = SISO["passive"]
    w = expert_windows(3, 1, 1, 1, N=6)
    real, calls = ren_train.certified_batch, []

    def certified_batch(K, q, P, lam):
        calls.append(1)
        return np.zeros(2, bool) if len(calls) == 1 else real(K, q, P, lam)

    monkeypatch.setattr(ren_train, "certified_batch", certified_batch)
    res = dj.fit_ren(jr.PRNGKey(6), w, qsr, width=2, num_inits=2, max_steps=3)
    assert res.certified.all()
    assert dj.certify_ren(res.controllers, qsr, P=res.P, multiplier=res.multiplier).holds.all()


def test_without_direct_input_d12_is_zero():
    theta = random_ren_params(jr.PRNGKey(7), 2, 1, 3, 2, 2, 0.5)
    K, P, lam = jax.jit(jax.vmap(lambda t: rm.ren_map(t, SUPPLY_RATES["passive"], 3)))(theta)
    assert not np.asarray(K.D12).any()
    assert dj.certify_ren(K, SUPPLY_RATES["passive"], P=P, multiplier=lam).holds.all()


def test_experiments_protocol_records_ren_as_certified():
    import dataclasses

    from dissil_jax.experiments.protocol import METHOD_LABELS, example_spec, run_config

    spec = dataclasses.replace(example_spec("nonlinear", quick=True), ren_width=2,
                               max_steps=5, num_test=8)
    rec = run_config("nonlinear", "initial", "ren", 3, inits=2, spec=spec)
    assert rec["certified"] is True and rec["controllers"] == 2
    assert METHOD_LABELS["ren"] == "REN (ours)"


def test_batched_check_equals_a_loop_over_controllers():
    """`certify_ren` checks a batch of given pairs in one vectorised pass; a loop over the
    members gives the same verdicts and margins, for certified members, members whose pair
    fails and a member certified only in the unit-multiplier form (large data)."""
    qsr = SUPPLY_RATES["strict"]
    theta = random_ren_params(jr.PRNGKey(11), 4, 2, 3, 2, 2, 0.5)
    K, P, lam = jax.jit(jax.vmap(lambda t: rm.ren_map(t, qsr, 3)))(theta)
    K = jax.tree.map(np.array, K)
    P, lam = np.array(P), np.array(lam)
    K.D22[1] += 3.0  # breaks the gain bound: refused
    P[2] *= 0.5  # the pair no longer certifies
    # member 3 in large units (as `to_user_units` returns a REN trained on data of size s):
    # Lambda ~ s^2 P, where the plain form's allowance (0.1 here) swamps its margin (~0.16)
    # and only the unit-multiplier form certifies it
    s = 1e4
    K.B1[3] *= s
    K.D21[3] *= s
    K.C1[3] /= s
    K.D12[3] /= s
    lam[3] *= s**2
    batch = dj.certify_ren(K, qsr, P=P, multiplier=lam)
    assert list(batch.holds) == [True, False, False, True]
    for i in range(4):
        one = dj.certify_ren(jax.tree.map(lambda a: a[i], K), qsr, P=P[i], multiplier=lam[i])
        assert one.holds == batch.holds[i]
        np.testing.assert_array_equal(one.margin, batch.margin[i])


def test_controllers_in_traces_and_batches():
    """A REN built inside `jit` from constant matrices (its D11 check used to call `bool` on
    a tracer); a batch of RENs called or rolled out says to vmap, naming the REN's own
    rollout."""
    rng = np.random.default_rng(12)
    K = _random_ren(rng, n=2, q=3)
    u = jnp.ones((4, 2))
    f = jax.jit(lambda A: dj.ren_rollout(eqx.tree_at(lambda k: k.A, K, A), None, u))
    g = jax.jit(lambda A: dj.ren_rollout(dj.RENController(A, *K.matrices[1:],
                                                          activation="tanh"), None, u))
    np.testing.assert_array_equal(f(K.A), g(K.A))
    Ks = jax.tree.map(lambda a: jnp.stack([a, a]), K)
    with pytest.raises(ValueError, match=r"`K` must be a single controller.*vmap"):
        Ks(jnp.zeros(2), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"jax.vmap\(dj.ren_rollout"):
        dj.ren_rollout(Ks, None, u)


def test_fit_ren_screens_a_callable_again_on_every_call():
    """A callable that passed the screen once and was changed since is refused: it is
    static in the compiled trainer, and the certificate assumes its slope restriction."""
    class Act:
        slope = 1.0

        def __call__(self, v):
            return self.slope * jnp.tanh(v)

    act = Act()
    w = expert_windows(2, 1, 1, 1, N=6)
    dj.fit_ren(jr.PRNGKey(0), w, SISO["passive"], width=2, num_inits=2, max_steps=2,
               activation=act)
    act.slope = 3.0
    with pytest.raises(ValueError, match="`activation` is not slope-restricted"):
        dj.fit_ren(jr.PRNGKey(0), w, SISO["passive"], width=2, num_inits=2, max_steps=2,
                   activation=act)
    with pytest.raises(ValueError, match="`width` must be a non-negative integer"):
        dj.fit_ren(jr.PRNGKey(0), w, SISO["passive"], width=None)


def test_an_unhashable_activation_and_a_traced_certificate_are_refused_by_name():
    """A callable activation is a static field, which JAX hashes: one defining `__eq__`
    without `__hash__` passed every check and then broke `fit_ren` inside JAX. And
    `certify_ren` under a transformation raised JAX's conversion error."""
    class Half:
        def __call__(self, v):
            return 0.5 * jnp.tanh(v)

        def __eq__(self, other):  # leaves __hash__ None
            return isinstance(other, Half)

    w = expert_windows(2, 1, 1, 1, N=6)
    with pytest.raises(ValueError, match="`activation` must be hashable"):
        dj.fit_ren(jr.PRNGKey(0), w, SISO["passive"], width=2, num_inits=2, max_steps=2,
                   activation=Half())
    K = dj.RENController.from_lti(dj.LTIController(0.5 * jnp.eye(1), jnp.ones((1, 1)),
                                                   jnp.ones((1, 1)), jnp.zeros((1, 1))), 2)
    qsr = dj.QSR.bounded_gain(4.0, n_in=1, n_out=1)
    with pytest.raises(ValueError, match="`certify_ren` cannot run under `jax.jit`"):
        jax.jit(lambda k: dj.certify_ren(k, qsr).margin)(K)


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_unbalanced_ren_realisations_are_decided_by_componentwise_bounds():
    """A certified REN with its states in very different units (x = T z, T = diag(1, 1e-3,
    1e-6): the same system and a congruent inequality): the relative tests of both forms
    refuse it, the componentwise round-off bound proves it, and a REN pushed beyond its
    gain bound in the same units stays refused (found by a new-user audit: `fit_ren` raised
    on a trained controller whose storage had eigenvalues 44 and 5e7)."""
    qsr = SUPPLY_RATES["gain"]
    theta = random_ren_params(jr.PRNGKey(13), 1, 3, 4, 2, 2, 0.3)
    K, P, lam = jax.tree.map(lambda a: np.asarray(a[0]),
                             jax.jit(jax.vmap(lambda t: rm.ren_map(t, qsr, 4)))(theta))
    T = np.diag([1.0, 1e-3, 1e-6])
    Ti = np.diag([1.0, 1e3, 1e6])

    def transformed(K):
        return eqx.tree_at(lambda k: (k.A, k.B1, k.B2, k.C1, k.C2), K,
                           (Ti @ K.A @ T, Ti @ K.B1, Ti @ K.B2, K.C1 @ T, K.C2 @ T))

    Kt, Pt = transformed(K), T.T @ P @ T
    G = ren_certify.augmented_lti(Kt)
    mats = (G.A, G.B, G.C, G.D)
    for form, q in ((mats, ren_certify.augmented_qsr(qsr, lam)),
                    ((lambda u: (u.A, u.B, u.C, u.D))(ren_units.unit_multiplier(G, lam)),
                     ren_certify.augmented_qsr(qsr, np.ones(4)))):
        # the premise: neither relative test proves it
        assert dji.kyp_margin(*form, q, Pt) < dji.lmi.VERIFY_RTOL * dji.kyp_scale(*form, q, Pt)
    assert dj.certify_ren(Kt, qsr, P=Pt, multiplier=lam).holds
    # the SDP finds a certificate of its own too: it is solved in balanced states and neurons
    assert dj.certify_ren(Kt, qsr).holds
    bad = transformed(eqx.tree_at(lambda k: k.D22, K, K.D22 + 2.0))  # beyond the gain 1.5
    assert not dj.certify_ren(bad, qsr, P=Pt, multiplier=lam).holds


def test_batched_augmented_rates_equal_one_at_a_time():
    """The batched check builds every member's augmented rate and its `rate_factor` at once;
    against `augmented_qsr` and `rate_factor` per member (multipliers inside and far
    outside the rate band)."""
    qsr = SUPPLY_RATES["strict"]
    lam = np.array([[0.1, 0.2, 0.3], [30.0, 40.0, 1.0], [1e5, 2e7, 3.0], [1e-4, 1e-5, 1e-6]])
    Q, S, R, factor = ren_certify._augmented_arrays(qsr, lam)
    for i in range(len(lam)):
        aug = ren_certify.augmented_qsr(qsr, lam[i])
        for a, b in ((Q[i], aug.Q), (S[i], aug.S), (R[i], aug.R)):
            np.testing.assert_array_equal(a, b)
        assert factor[i] == dji.rate_scale.rate_factor(aug)


def test_certify_ren_checks_the_given_pair():
    """A wrong `P` shape is reported as `P`'s, a wrong multiplier as the multiplier's, and
    a non-symmetric `P` is refused as by `dj.certify`."""
    K = _random_ren(np.random.default_rng(0), n=2, q=4)
    qsr = SUPPLY_RATES["strict"]
    with pytest.raises(ValueError, match=r"`P` must be 2x2"):
        dj.certify_ren(K, qsr, P=np.eye(3), multiplier=np.ones(4))
    with pytest.raises(ValueError, match=r"`multiplier` must be \(4,\)"):
        dj.certify_ren(K, qsr, P=np.eye(2), multiplier=np.ones(3))
    with pytest.raises(ValueError, match=r"`P` must be symmetric"):
        dj.certify_ren(K, qsr, P=np.array([[1.0, 0.5], [0.0, 1.0]]), multiplier=np.ones(4))


def test_fit_ren_on_large_data_is_certified_and_dissipative():
    """Data in large units: the returned REN's neurons stay in the normalised units, so its
    multiplier is about s^2 (here ~1e6) times the storage's size. The float64 check accepts
    the congruent form with a unit multiplier, where the round-off allowance of the
    original form (it grows with the largest term) would swamp the margin; the storage
    still decreases along the nonlinear system's own trajectories."""
    qsr = dj.QSR(-np.eye(1), np.zeros((1, 1)), 0.9 * np.eye(1))  # a gain bound
    w = expert_windows(1, 2, 1, 1, N=10)
    big = dj.Windows(1e3 * w.x0, 1e3 * w.y, 1e3 * w.u)
    res = dj.fit_ren(jr.PRNGKey(5), big, qsr, width=3, num_inits=3, max_steps=25)
    assert res.certified.all()
    lam, P = np.asarray(res.multiplier), np.asarray(res.P)
    assert lam.min() > 1e3 * np.abs(P).max()  # the premise: very different units
    for i in range(3):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        rng = np.random.default_rng(i)
        for _ in range(200):
            x, u = 3e3 * rng.standard_normal(2), 3e3 * rng.standard_normal(1)
            xn, y, _, _ = _np_step(K, x, u)
            s = supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None], y[None])[0]
            assert xn @ P[i] @ xn - x @ P[i] @ x - s <= 1e-9 * (1 + x @ P[i] @ x + u @ u)
    # and a REN that is not dissipative stays refused in either form
    K = jax.tree.map(lambda a: a[0], res.controllers)
    K_bad = eqx.tree_at(lambda k: k.D22, K, K.D22 + 2.0)  # feedthrough beyond the gain bound
    assert not dj.certify_ren(K_bad, qsr, P=P[0], multiplier=lam[0]).holds
    # A fresh SDP certifies it too: it is solved in balanced neuron units (before, Clarabel
    # failed from data of size 1e3 on), and the multiplier it returns is of the trainer's size.
    cert = dj.certify_ren(K, qsr)
    assert cert.holds and cert.multiplier.min() > 1e3 * np.abs(cert.P).max()


def test_certify_ren_balances_states_and_neurons_together():
    """States in units 2^100 and 2^300 away from the neurons' (x = 2^e z): the neuron
    balancing ran first, in the unbalanced states, and Clarabel failed (`solver_error`); the
    two balancings now alternate, states first. The storage, mapped back to unit
    coordinates, decreases along the REN's own steps. At 2^600 no storage fits float64 in
    the given coordinates: refused, with a warning that says why (the raw scipy/cvxpy
    errors it raised before said nothing of the cause)."""
    rng = np.random.default_rng(0)
    qsr = SUPPLY_RATES["strict"]
    K = _random_ren(rng, n=2, q=3, scale=0.3, activation="relu")
    assert dj.certify_ren(K, qsr).holds  # the premise
    for e in (100, 300):
        d = 2.0**e
        Kd = eqx.tree_at(lambda k: (k.B1, k.B2, k.C1, k.C2), K,
                         (K.B1 * d, K.B2 * d, K.C1 / d, K.C2 / d))
        cert = dj.certify_ren(Kd, qsr)
        assert cert.holds, cert.status
        P = np.asarray(cert.P) * d**2  # V(x) = (d x)' P_d (d x): exact in powers of two
        for _ in range(200):
            x, u = rng.standard_normal(2), rng.standard_normal(2)
            xn, y, _, _ = _np_step(K, x, u)
            s = supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None], y[None])[0]
            assert xn @ P @ xn - x @ P @ x - s <= 1e-9 * (1 + x @ P @ x + u @ u)
    d = 2.0**600
    Kd = eqx.tree_at(lambda k: (k.B1, k.B2, k.C1, k.C2), K,
                     (K.B1 * d, K.B2 * d, K.C1 / d, K.C2 / d))
    with pytest.warns(UserWarning, match="beyond float64's range"):
        assert not dj.certify_ren(Kd, qsr).holds


def test_certify_ren_tries_its_second_coordinates_when_the_first_pair_fails(monkeypatch):
    """`certify_ren` solves in `ren_units.COORDINATES` in turn until a pair passes the check
    (on RENs trained for |Q| ~ 1e6 R each order certified runs the other did not). A first
    pair that fails the check is replaced by the second's; one that passes is kept, and
    the second SDP is not solved."""
    K = _random_ren(np.random.default_rng(0), n=2, q=3, scale=0.3, activation="relu")
    d = 2.0**20  # states in other units than the neurons: the two coordinates differ
    K = eqx.tree_at(lambda k: (k.B1, k.B2, k.C1, k.C2), K, (K.B1 * d, K.B2 * d, K.C1 / d,
                                                            K.C2 / d))
    qsr = SUPPLY_RATES["strict"]
    real, calls = ren_certify._solve, []

    def first_fails(G, qsr, q, d, ts):
        calls.append(d)
        P, lam, status = real(G, qsr, q, d, ts)
        return (-P, lam, "spoiled") if len(calls) == 1 else (P, lam, status)

    monkeypatch.setattr(ren_certify, "_solve", first_fails)
    cert = dj.certify_ren(K, qsr)
    assert cert.holds and cert.status == "optimal" and len(calls) == 2
    monkeypatch.setattr(ren_certify, "_solve", lambda *a: (calls.append(a[3]), real(*a))[1])
    calls.clear()
    assert dj.certify_ren(K, qsr).holds and len(calls) == 1


def test_certify_ren_refuses_what_the_layer_does_not_run():
    """A D11 with entries on the diagonal (set by `tree_at`, or built under `jit` where the
    constructor cannot check it) is refused: the layer runs only tril(D11, -1), so a
    certificate of the whole matrix would be of another system. Here the full D11 = -10
    would 'certify' a gain of 2.25 against the bound 1."""
    one, z = np.ones((1, 1)), np.zeros((1, 1))
    K = dj.RENController(z, z, z, z, z, 1.5 * one, z, 1.5 * one, z)  # y = 1.5 relu(1.5 u)
    qsr = dj.QSR.bounded_gain(1.0, n_in=1, n_out=1)
    assert not dj.certify_ren(K, qsr).holds
    bad = eqx.tree_at(lambda k: k.D11, K, jnp.asarray(-10.0 * one))
    with pytest.raises(ValueError, match="`K.D11` must be strictly lower"):
        dj.certify_ren(bad, qsr)
    with pytest.raises(ValueError, match="`K.D11`"):
        dj.certify_ren(jax.jit(lambda d: eqx.tree_at(lambda k: k.D11, K, d))(-10.0 * one), qsr)
    for tol in (-1.0, np.nan, "a"):
        with pytest.raises(ValueError, match="`tol` must be a finite non-negative"):
            dj.certify_ren(K, qsr, P=one, multiplier=np.ones(1), tol=tol)
    for lam, msg in (([np.nan], "NaN or inf"), ("a", "real numbers"), ([1 + 1j], "real")):
        with pytest.raises(ValueError, match=f"`multiplier`.*{msg}|`multiplier` contains {msg}"):
            dj.certify_ren(K, qsr, P=one, multiplier=lam)


def test_activation_screen_has_the_evaluations_precision():
    """Without x64 the screen evaluates in float32; a slope of 1 + 1e-4 is refused there as
    in float64 (the allowance is a few ulps per quotient, not a fixed 1e-2), while the
    usual slope-restricted functions pass. An activation holding JAX arrays is refused
    with the reason (it is a compile-time constant of the controller)."""
    code = """
import jax, jax.numpy as jnp
from dissil_jax.internal import ren_controller
check_activation = ren_controller.check_activation
assert not jax.config.jax_enable_x64
for f in (jnp.tanh, jax.nn.relu, jax.nn.hard_tanh, jax.nn.soft_sign, jax.nn.elu,
          lambda v: 0.5 * (jnp.tanh(v) + jax.nn.relu(v))):
    check_activation(f)
for f in (lambda v: 1.0001 * v, lambda v: 1.011 * jnp.tanh(v), lambda v: 1.001 * jax.nn.relu(v)):
    try:
        check_activation(f)
    except ValueError:
        continue
    raise SystemExit("accepted a slope above 1")
print("OK")
"""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, env=env)
    assert out.stdout.strip().endswith("OK"), out.stderr[-2000:]
    # a narrow bump in the data's range, and a slope of 1.5 beyond 1e3, passed the earlier
    # 123-point grid in [-1e3, 1e3] (a new-user audit)
    bump = lambda v: jax.nn.relu(v) + 5.0 * jax.nn.relu(1.0 - jnp.abs(v - 1.12) / 0.02)
    steep = lambda v: jax.nn.relu(v) + 0.5 * jax.nn.relu(v - 1001.0)
    for f in (lambda v: 1.0001 * v, lambda v: 1.00001 * jnp.tanh(v), bump, steep):
        with pytest.raises(ValueError, match="not slope-restricted"):
            ren_controller.check_activation(f)

    class Scaled(eqx.Module):
        a: jax.Array

        def __call__(self, v):
            return self.a * jnp.tanh(v)

    with pytest.raises(ValueError, match="holding JAX arrays"):
        ren_controller.check_activation(Scaled(jnp.asarray(0.5)))


def _tight_gain_problem(gamma):
    """Windows that start at a state, an expert of gain ~0.5 and a gain bound `gamma`."""
    key = jr.PRNGKey(0)
    y = jr.normal(key, (25, 2, 1))
    u = -0.5 * y + 0.1 * jr.normal(jr.fold_in(key, 1), (25, 2, 1))
    W = dj.Windows(jr.normal(jr.fold_in(key, 2), (25, 2)), y, u)
    return key, W, dj.QSR.bounded_gain(gamma, n_out=1, n_in=1)


def test_rates_of_one_shape_share_one_compilation(monkeypatch):
    """`fit_ren` passes the rate's values and the map's input units traced: gain bounds
    from 1e-6 to 1e3 (units and rate factor both vary) train under one compilation, each
    certified by the float64 end check."""
    traced = eqx.debug.assert_max_traces(ren_train._run, max_traces=1)
    monkeypatch.setattr(ren_train, "_run_jit", eqx.filter_jit(traced))
    for gamma in (1e-6, 1e-3, 1.0, 1e3):
        key, W, qsr = _tight_gain_problem(gamma)
        res = dj.fit_ren(key, W, qsr, width=2, num_inits=2, max_steps=5)
        assert bool(np.all(res.certified))


@pytest.mark.parametrize("name", list(SUPPLY_RATES))
def test_traced_rate_is_the_static_rate(name):
    """The REN map under a traced `ren_rate` equals the map with the rate baked in, up to
    the round-off of an XLA program compiled another way (a few ulps of float64)."""
    qsr = SUPPLY_RATES[name]
    theta = random_ren_params(jr.PRNGKey(12), 4, 2, 3, 2, 2, 0.5)
    static = jax.jit(jax.vmap(lambda t: rm.ren_map(t, qsr, 3, direct_input=True)))(theta)
    traced = jax.jit(jax.vmap(lambda t, r: rm.ren_map(t, r, 3, direct_input=True),
                              in_axes=(0, None)))(theta, rm.ren_rate(qsr, dtype=jnp.float64))
    for a, b in zip(jax.tree.leaves(traced), jax.tree.leaves(static)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(np.abs(b).max()))


@pytest.mark.parametrize("gamma", [1e-3, 1e-6])
@pytest.mark.parametrize("hyper", [{}, dict(learning_rate=0.3, init_scale=0.5)])
def test_tight_gain_bounds_train_well_conditioned_certified_rens(gamma, hyper):
    """With `B` in units of the inputs' certified size ($\\sqrt R = \\gamma$), the storages
    stay of moderate condition (measured at most 2.9e3; 1.6e12 without the units at 1e-6
    and the step (0.3, 0.5), as in the test below), every run passes the end check, and the
    storage decreases along the REN's own steps."""
    key, W, qsr = _tight_gain_problem(gamma)
    assert rm.input_units(qsr)[0] == 2.0 ** np.round(np.log2(gamma))
    res = dj.fit_ren(key, W, qsr, width=4, num_inits=2, **hyper)
    assert res.certified.all()
    for i in range(2):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        P = np.asarray(res.P[i], np.float64)
        assert np.linalg.cond(P) < 1e6
        rng = np.random.default_rng(i)
        for _ in range(200):
            x, u = rng.standard_normal(2), rng.standard_normal(1)
            xn, yk, _, _ = _np_step(K, x, u)
            s = supply_from_definition(qsr.Q, qsr.S, qsr.R, u[None], yk[None])[0]
            # round-off of float64 sums of terms of size ~|P| (|x|^2 + |x+|^2)
            assert xn @ P @ xn - x @ P @ x - s <= 1e-9 * (1 + x @ P @ x + xn @ P @ xn)


def test_ill_conditioned_storages_are_named_when_the_end_check_fails(monkeypatch):
    """Without the inputs' units (the map as it was), a gain bound of 1e-6 lets the runs buy
    imitation with storage (condition numbers ~1e12): the end check cannot verify them, and
    the error says why; with `throw=False` they are returned flagged, never as certified."""
    key, W, qsr = _tight_gain_problem(1e-6)
    monkeypatch.setattr(rm, "input_units", lambda qsr, margin=None: np.ones(qsr.R.shape[0]))
    # and the fallback SDP in the given units only: in balanced input and output units it
    # now certifies these controllers with storages of its own, so nothing would fail
    monkeypatch.setattr(ren_certify, "_io_units", lambda G, qsr, q: iter([(G, qsr)]))
    # width 3: static arguments of its own, so the patched map is traced afresh rather than
    # taken from the compiled loop of the test above
    # the step and scale of that measurement (`fit_ren`'s defaults then)
    hyper = dict(learning_rate=0.3, init_scale=0.5)
    res = dj.fit_ren(key, W, qsr, width=3, num_inits=2, throw=False, **hyper)
    bad = ~np.asarray(res.certified)
    assert bad.any()
    assert all(r == "not_certified" for r, b in zip(res.result_names(), bad) if b)
    assert max(np.linalg.cond(np.asarray(P)) for P in np.asarray(res.P)[bad]) > 1e8
    with pytest.raises(ValueError, match="condition number .* beyond what float64"):
        dj.fit_ren(key, W, qsr, width=3, num_inits=2, **hyper)
    # float32 runs are told that float64 may pass; these float64 ones are not
    assert "float32" not in ren_train._uncertified_message(res, 2)
    single = eqx.tree_at(lambda r: r.final_loss, res, res.final_loss.astype(jnp.float32))
    assert "jax_enable_x64" in ren_train._uncertified_message(single, 2)


def test_default_step_and_scale_are_the_capped_rule():
    """`fit_ren`'s defaults: `fit_direct`'s rule at order n, each capped at 0.1; a call with
    them spelled out trains the same controllers."""
    from dissil_jax.internal import direct

    assert ren_train.default_ren_hyperparameters(1, 1) == (0.1, 0.1)
    lr, scale = ren_train.default_ren_hyperparameters(48, 6)  # width 54: the rule's step
    assert lr == direct.default_hyperparameters(48, 6)[0] < 0.1 and scale == 0.1
    w = expert_windows(2, 1, 1, 1, N=6)
    qsr = SISO["passive"]
    a = dj.fit_ren(jr.PRNGKey(8), w, qsr, width=2, num_inits=2, max_steps=5)
    b = dj.fit_ren(jr.PRNGKey(8), w, qsr, width=2, num_inits=2, max_steps=5,
                   learning_rate=0.1, init_scale=0.1)
    c = dj.fit_ren(jr.PRNGKey(8), w, qsr, width=2, num_inits=2, max_steps=5,
                   learning_rate=0.3, init_scale=0.5)
    np.testing.assert_array_equal(a.final_loss, b.final_loss)
    assert not np.array_equal(a.final_loss, c.final_loss)


def test_sdp_fallback_is_checked_as_rounded_to_the_result_dtype(monkeypatch):
    """In float32 the end check's SDP pair is rounded before it is checked again: the pair
    checked is the pair returned, and a pair that fails once rounded is not certified."""
    qsr = SISO["passive"]
    w = expert_windows(3, 2, 1, 1, N=6)
    w = dj.Windows(*(jnp.asarray(a, jnp.float32) for a in (w.x0, w.y, w.u)))
    seen = []

    def check(verdict_after_rounding):
        def certified_batch(K, q, P, lam):
            seen.append(np.array(P))
            if len(seen) == 1:  # the map's own pairs: force the SDP fallback
                return np.zeros(np.shape(P)[0], bool)
            return np.full(np.shape(P)[0], verdict_after_rounding)
        return certified_batch

    monkeypatch.setattr(ren_train, "certified_batch", check(True))
    res = dj.fit_ren(jr.PRNGKey(6), w, qsr, width=2, num_inits=2, max_steps=3)
    assert res.P.dtype == jnp.float32 and res.certified.all()
    for i, P_checked in enumerate(seen[1:]):
        np.testing.assert_array_equal(P_checked[0], np.asarray(res.P[i], np.float64))
    # the real SDP pair, rounded, is also proved by the library's check
    assert dj.certify_ren(res.controllers, qsr, P=res.P, multiplier=res.multiplier).holds.all()
    seen.clear()
    monkeypatch.setattr(ren_train, "certified_batch", check(False))
    res = dj.fit_ren(jr.PRNGKey(6), w, qsr, width=2, num_inits=2, max_steps=3, throw=False)
    assert not res.certified.any()
    assert res.result_names() == ["not_certified"] * 2


def test_runs_without_a_finite_iterate_are_flagged_not_raised():
    """Draws so large that the map overflows in float32 leave runs with no finite iterate:
    with `throw=False` they come back flagged `non_finite` (no certificate is attempted on
    NaN), and `throw=True` raises a `ValueError` that says so."""
    rng = np.random.default_rng(0)
    y = rng.standard_normal((10, 4, 1)).astype(np.float32)
    W = dj.Windows(rng.standard_normal((10, 2)).astype(np.float32), y, -0.5 * y)
    qsr = dj.QSR.bounded_gain(2.0, n_in=1, n_out=1)
    kw = dict(width=2, num_inits=2, init_scale=1e4, max_steps=5)
    res = dj.fit_ren(jr.PRNGKey(0), W, qsr, throw=False, **kw)
    names = res.result_names()
    assert "non_finite" in names
    assert not any(c for c, r in zip(np.asarray(res.certified), names) if r == "non_finite")
    with pytest.raises(ValueError, match="never had a finite iterate"):
        dj.fit_ren(jr.PRNGKey(0), W, qsr, **kw)
