"""`fit_ren(init=...)`: the REN map backwards, and runs that start at given controllers."""

import warnings

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import REN_RATES, expert_windows, random_ren_params

import dissil_jax as dj
from dissil_jax.internal import ren_init, ren_inverse, ren_map as rm, units as units_mod

RATES = REN_RATES


def _random_theta(key, n, q, scale=0.4):
    return jax.tree.map(lambda a: a[0], random_ren_params(key, 1, n, q, 2, 2, scale))


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", list(RATES))
@pytest.mark.parametrize("width, direct_input", [(0, False), (3, False), (3, True)])
def test_map_backwards_returns_the_parameters_of_a_value(name, width, direct_input):
    """Any value of the map is mapped back to parameters whose value it is. The inverse is
    exact algebra once the SDP has found a certificate with room (any such certificate
    gives the same REN), so the only error is the float64 round-off of its solves and of
    Γ's square root: 1e-9 of the matrices' size is far above it and far below a wrong
    block (of the size of the matrices)."""
    qsr = RATES[name]
    theta = _random_theta(jr.PRNGKey(width + 10 * direct_input), 3, width)
    K, _, _ = rm.ren_map(theta, qsr, width, "tanh", rm.MARGIN, direct_input)
    mats = tuple(np.asarray(M) for M in K.matrices)
    back, delta = ren_inverse.ren_params_of(mats, qsr, rm.MARGIN, direct_input)
    assert delta >= 0.0  # a value of the map is in its image with room
    K2, P2, lam2 = rm.ren_map(jax.tree.map(jnp.asarray, back), qsr, width, "tanh", rm.MARGIN,
                              direct_input)
    size = max(np.abs(M).max(initial=0.0) for M in mats)
    for M, M2 in zip(mats, K2.matrices):
        np.testing.assert_allclose(M2, M, atol=1e-9 * size, rtol=0)
    assert dj.certify_ren(K2, qsr, P=P2, multiplier=lam2).holds


def test_feedthrough_inverse_is_exact_and_refuses_what_the_map_cannot_reach():
    qsr = RATES["strict"]
    W = np.array([[0.3, -1.2], [0.7, 0.1]])
    _, D, _ = rm.output_map(jnp.asarray(W), jnp.zeros((0, 0)), qsr, rm.MARGIN)
    np.testing.assert_allclose(ren_inverse.feedthrough_params(np.asarray(D), qsr, rm.MARGIN),
                               W, atol=1e-12)
    # a feedthrough with Phi(D) < 0: no REN with it is dissipative
    assert ren_inverse.feedthrough_params(10 * np.eye(2), qsr, rm.MARGIN) is None


def _direct(windows, qsr, **kw):
    return dj.fit_direct(jr.PRNGKey(0), windows, qsr, num_inits=4, max_steps=60,
                         progress=False, **kw)


def _loss(K, windows):
    return np.asarray(jax.vmap(lambda k: dj.imitation_loss(k, windows))(K))


@pytest.mark.filterwarnings("ignore:.*runs returned their start")
@pytest.mark.parametrize("odd", [False, True])
def test_runs_start_at_the_given_lti_controllers_and_never_end_worse(odd):
    """Each run's first loss is that of its start (up to float64 round-off of the two
    rollouts and of the map's solves), the returned controller is never worse than it
    (`keep="best"` keeps the start), every result is certified, and the neurons moved."""
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    w = expert_windows(1, 2, 1, 1, N=10)
    d = _direct(w, qsr)
    res = dj.fit_ren(jr.PRNGKey(1), w, qsr, width=3, num_inits=4, max_steps=40, init=d,
                     activation="relu", odd=odd, progress=False)
    start = _loss(d.controllers, w)
    np.testing.assert_allclose(np.asarray(res.loss_history)[:, 0], start, rtol=1e-8)
    assert np.all(np.asarray(res.final_loss) <= start * (1 + 1e-12))
    assert res.certified.all() and res.margin in ren_init.INIT_MARGINS
    for i in range(4):
        K = jax.tree.map(lambda a: a[i], res.controllers)
        assert dj.certify_ren(K, qsr).holds  # an independent SDP
    assert np.abs(np.asarray(res.controllers.D21)).max() > 0  # the neurons were trained


def test_a_single_controller_starts_every_run_with_its_own_neurons():
    qsr = dj.QSR.passive(1)
    w = expert_windows(2, 2, 1, 1, N=10)
    d = _direct(w, qsr)
    K = jax.tree.map(lambda a: a[0], d.controllers)
    res = dj.fit_ren(jr.PRNGKey(1), w, qsr, width=2, num_inits=3, max_steps=0, init=K,
                     progress=False)
    np.testing.assert_allclose(np.asarray(res.loss_history)[:, 0],
                               float(dj.imitation_loss(K, w)), rtol=1e-8)
    C1 = np.asarray(res.controllers.C1)
    assert not np.allclose(C1[0], C1[1])  # drawn per run
    assert np.all(np.asarray(res.controllers.D21) == 0)  # not yet acting on the output


def test_a_trained_ren_resumes_where_it_stopped():
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    w = expert_windows(1, 2, 1, 1, N=10)
    first = dj.fit_ren(jr.PRNGKey(2), w, qsr, width=3, num_inits=2, max_steps=30,
                       progress=False)
    more = dj.fit_ren(jr.PRNGKey(3), w, qsr, width=3, num_inits=2, max_steps=30, init=first,
                      progress=False)
    np.testing.assert_allclose(np.asarray(more.loss_history)[:, 0], first.final_loss,
                               rtol=1e-8)
    assert np.all(np.asarray(more.final_loss) <= np.asarray(first.final_loss) * (1 + 1e-12))


def test_starts_survive_every_change_of_units():
    """The outputs' centre and units and the states' units of `balance` (here all three:
    a narrow cone far from zero, outputs far larger than inputs, states far smaller than
    outputs), then the data scale: the runs still start exactly at `init`."""
    qsr = dj.QSR.conic(10.0, 11.0, dim=1)
    w = expert_windows(3, 2, 1, 1, N=10)
    w = dj.Windows(w.x0 / 30, w.y, 10.5 * w.y + 0.3 * w.u)
    units = units_mod.balancing_units(w, True, qsr)
    assert units.centre is not None and units.c != 1.0 and units.d is not None
    d = _direct(w, qsr)
    res = dj.fit_ren(jr.PRNGKey(1), w, qsr, width=2, num_inits=4, max_steps=5, init=d,
                     progress=False)
    np.testing.assert_allclose(np.asarray(res.loss_history)[:, 0], _loss(d.controllers, w),
                               rtol=1e-7)
    assert res.certified.all()


@pytest.mark.filterwarnings("ignore:`windows` start at rest")
def test_windows_at_rest_take_the_order_of_init():
    qsr = dj.QSR.passive(1)
    w = expert_windows(2, 2, 1, 1, N=10)
    rest = dj.Windows(None, w.y, w.u)
    d = _direct(rest, qsr, n_state=3)
    res = dj.fit_ren(jr.PRNGKey(1), rest, qsr, width=2, num_inits=4, max_steps=3, init=d,
                     progress=False)
    assert res.controllers.n_state == 3


def test_the_default_margin_falls_back_until_every_start_is_reached():
    """A REN the map reaches at margin 1e-3 but not at 1e-2 (its Γ has eigenvalues near
    zero at 1e-3) is started at 1e-3 by default, and refused by name at an explicit 1e-2."""
    qsr = RATES["strict"]
    theta = _random_theta(jr.PRNGKey(5), 2, 2)
    theta = theta.__class__(1e-3 * theta.X, *jax.tree.leaves(theta)[1:])
    K, _, _ = rm.ren_map(theta, qsr, 2, "tanh", 1e-3)
    mats = tuple(np.asarray(M) for M in K.matrices)
    assert ren_inverse.ren_params_of(mats, qsr, 1e-2, False)[1] < 0
    Kb = jax.tree.map(lambda a: a[None], K)
    common = dict(num_inits=1, n_state=2, width=2, n_in=2, n_out=2, init_scale=0.1,
                  direct_input=False, odd=False, activation="tanh", dtype=jnp.float64)
    theta0, margin = ren_init.initial_params(Kb, jr.PRNGKey(0), qsr, units_mod.Units(), 1.0,
                                             margins=ren_init.INIT_MARGINS, **common)
    assert margin == 1e-3
    K0, _, _ = rm.ren_map(jax.tree.map(lambda a: a[0], theta0), qsr, 2, "tanh", margin)
    for M, M0 in zip(mats, K0.matrices):
        np.testing.assert_allclose(M0, M, atol=1e-7 * max(np.abs(m).max() for m in mats))
    with pytest.raises(ValueError, match=r"`init\[0\]` is not in the set .* `margin` 0.01"):
        ren_init.initial_params(Kb, jr.PRNGKey(0), qsr, units_mod.Units(), 1.0,
                                margins=(1e-2,), **common)


def test_a_start_reached_only_approximately_tries_smaller_margins_then_warns(monkeypatch):
    """The map's value at a start is measured against the start (`_deviation`, checked
    here against a perturbed parameter); a start off by more than round-off is tried at
    the smaller margins, and when none reaches it exactly the closest is used with a
    warning that names the deviation (a new user's gain bound of 1e-5 started 37 % above
    the given controllers' loss, silently)."""
    qsr = RATES["strict"]
    theta = _random_theta(jr.PRNGKey(5), 2, 2)
    K, _, _ = rm.ren_map(theta, qsr, 2, "tanh", 1e-2)
    mats = [np.asarray(M) for M in K.matrices]
    dev = lambda th: ren_init._deviation(th, mats, qsr, 1e-2, False, jnp.float64)
    assert dev(theta) < 1e-9
    bumped = theta.__class__(theta.X + 1e-3 * jnp.eye(theta.X.shape[0]),
                             *jax.tree.leaves(theta)[1:])
    assert dev(bumped) > ren_init._EXACT
    Kb = jax.tree.map(lambda a: a[None], K)
    common = dict(num_inits=1, n_state=2, width=2, n_in=2, n_out=2, init_scale=0.1,
                  direct_input=False, odd=False, activation="tanh", dtype=jnp.float64)
    run = lambda: ren_init.initial_params(Kb, jr.PRNGKey(0), qsr, units_mod.Units(), 1.0,
                                          margins=ren_init.INIT_MARGINS, **common)[1]
    offs = {1e-2: 0.5, 1e-3: 0.0, 1e-4: 0.2}
    monkeypatch.setattr(ren_init, "_deviation", lambda th, Ki, rate, margin, *a: offs[margin])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert run() == 1e-3  # exact there: no warning
    offs.update({1e-3: 0.3})
    with pytest.warns(UserWarning, match=r"only approximately \(at `margin` 0.0001, the "
                                         r"closest of 3\).* 2.0e-01"):
        assert run() == 1e-4


def test_bad_init_is_refused_by_name():
    qsr = dj.QSR.passive(1)
    w = expert_windows(2, 2, 1, 1, N=10)
    d = _direct(w, qsr)
    fit = lambda init, **kw: dj.fit_ren(jr.PRNGKey(0), w, qsr, num_inits=kw.pop("num_inits", 4),
                                        max_steps=2, init=init, progress=False, **kw)
    with pytest.raises(ValueError, match="`init` must be a `dj.LTIController`"):
        fit(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="`init` has batch shape"):
        fit(d, num_inits=3)
    with pytest.raises(ValueError, match="`init` has n_state 3"):
        fit(dj.LTIController.random(jr.PRNGKey(0), 3, 1, 1))
    ren = dj.fit_ren(jr.PRNGKey(1), w, qsr, width=2, num_inits=4, max_steps=2,
                     progress=False)
    with pytest.raises(ValueError, match="`init` has width 2"):
        fit(ren, width=3)
    with pytest.raises(ValueError, match="activation 'tanh', but the runs use 'relu'"):
        fit(ren, width=2, activation="relu")
    with pytest.raises(ValueError, match="`init` cannot be a REN with `odd=True`"):
        fit(ren, width=2, odd=True)
    with_d12 = ren.controllers.__class__(*ren.controllers.matrices[:5],
                                         ren.controllers.D12 + 0.1,
                                         *ren.controllers.matrices[6:],
                                         activation=ren.controllers.activation)
    with pytest.raises(ValueError, match="nonzero `D12`"):
        fit(with_d12, width=2)
    # D = 0 under passivity: Phi(D) = R = 0, on the edge of the set
    edge = dj.LTIController(np.zeros((2, 2)), np.zeros((2, 1)), np.zeros((1, 2)),
                            np.zeros((1, 1)))
    with pytest.raises(ValueError, match=r"`init` is not in the set `fit_ren` trains in"):
        fit(edge)


def test_mapping_the_starts_back_says_so_while_it_runs(monkeypatch, capsys):
    """The SDPs run before the training loop, one per start (minutes for many starts at a
    high order): past the heartbeat's delay a line on standard error says what they do."""
    from dissil_jax.internal import progress

    monkeypatch.setattr(progress, "DELAY", 0.0)
    monkeypatch.setattr(progress, "INTERVAL", 0.01)
    monkeypatch.setattr(progress, "_BEAT", 0.005)
    qsr = dj.QSR.passive(1)
    w = expert_windows(2, 2, 1, 1, N=10)
    d = _direct(w, qsr)
    dj.fit_ren(jr.PRNGKey(1), w, qsr, width=2, num_inits=4, max_steps=0, init=d)
    err = capsys.readouterr().err
    assert "fit_ren: mapping 4 starts back through the REN map at margin" in err


def test_a_start_that_no_step_improves_is_named_as_the_start():
    """A run that returns its start unchanged is reported as such, naming `init` (the
    start may be a minimum already), not as a random draw the step was too large for."""
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    w = expert_windows(1, 2, 1, 1, N=10)
    d = _direct(w, qsr)
    with pytest.warns(UserWarning, match=r"returned their start \(`init`\) unchanged"):
        res = dj.fit_ren(jr.PRNGKey(1), w, qsr, width=2, num_inits=4, max_steps=5, init=d,
                         learning_rate=10.0, progress=False)
    assert np.all(np.asarray(res.kept_step) == 0)
