"""The trainers balance the units of the controller's output against its input's.

When the outputs are far larger or smaller than the inputs, `fit_direct`, `fit_pgd`,
`fit_gd`, `fit_ico`, `fit_ico_nc` and `fit_ren` train on the outputs divided by a power of two c, with the supply
rate (c²Q, cS, R), and scale the result back. Powers of two make every step exact, so a
run on such data must equal, bit for bit, the run on the balanced problem mapped back.
"""

import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, in_storage_units, index

import dissil_jax as dj
from dissil_jax.experiments import realisable_windows
from dissil_jax.internal import output_factor, output_ratio, rate_scale, units

QSR = dj.QSR(-0.2 * np.eye(2), 0.5 * np.eye(2), 0.3 * np.eye(2))  # a cone: Q, S, R all act
SCALE = 64.0  # the user's outputs are 64x the base problem's (a change of units)


def _base():
    w, _ = realisable_windows(jr.PRNGKey(2), QSR, n_state=2, num_windows=20, noise=0.1)
    return w


def _rate(q: dj.QSR, a: float) -> dj.QSR:
    """The rate of the outputs scaled by a: w(u, a y) = y'(a²Q)y + 2y'(aS)u + u'Ru, so the
    same controllers in the new units satisfy (Q/a², S/a, R)."""
    return dj.QSR(q.Q / a**2, q.S / a, q.R)


def test_output_factor():
    y = np.ones((4, 2, 1))
    for r, c in ((1.0, 1.0), (0.21, 1.0), (4.9, 1.0), (50.0, 64.0), (1 / 20, 1 / 16),
                 (3e5, 2.0**18)):
        w = dj.Windows(None, y, r * np.ones((4, 2, 1)))
        assert output_ratio(w) == pytest.approx(r)
        assert output_factor(w) == c
    # the initial states count as inputs; all-zero outputs or inputs leave the data alone
    w = dj.Windows(np.full((4, 2), 10.0), y, np.ones((4, 2, 1)))
    assert output_ratio(w) == pytest.approx(np.sqrt(2 / (2 + 200)))
    assert output_factor(w) == 0.125
    assert output_factor(dj.Windows(None, y, np.zeros((4, 2, 1)))) == 1.0
    assert output_factor(dj.Windows(None, 0 * y, np.ones((4, 2, 1)))) == 1.0


FITS = {
    "direct": lambda w, q, **kw: dj.fit_direct(jr.PRNGKey(0), w, q, num_inits=3, max_steps=60,
                                               **kw),
    "pgd": lambda w, q, **kw: dj.fit_pgd(jr.PRNGKey(0), w, q, num_inits=3, max_steps=10, **kw),
    "gd": lambda w, q, **kw: dj.fit_gd(jr.PRNGKey(0), w, num_inits=3, max_steps=30, **kw),
    "ren": lambda w, q, **kw: dj.fit_ren(jr.PRNGKey(0), w, q, width=3, num_inits=3,
                                         max_steps=40, **kw),
    "ico": lambda w, q, **kw: dj.fit_ico(jr.PRNGKey(0), w, q, num_inits=3, max_steps=4, **kw),
    "ico_nc": lambda w, q, **kw: dj.fit_ico_nc(jr.PRNGKey(0), w, num_inits=3, max_steps=4,
                                               **kw),
}


@pytest.mark.parametrize("name", list(FITS))
def test_unbalanced_outputs_train_as_the_balanced_problem(name):
    base = _base()
    user = dj.Windows(base.x0, base.y, SCALE * base.u)
    q_user = _rate(QSR, SCALE)
    c = output_factor(user)
    assert c > 8.0  # the user's data are out of balance
    # the problem the trainer should solve: outputs divided by c (exactly: powers of two)
    balanced = dj.Windows(base.x0, base.y, (SCALE / c) * base.u)
    assert output_factor(balanced) == 1.0
    q_bal = _rate(QSR, SCALE / c)
    atol = 1e-6  # in the user's units; the balanced run's is atol / c²
    res = FITS[name](user, q_user, atol=atol)
    ref = FITS[name](balanced, q_bal, atol=atol / c**2)
    out = ("C2", "D21", "D22") if name == "ren" else ("C", "D")
    for field in vars(ref.controllers):
        a, b = getattr(res.controllers, field), getattr(ref.controllers, field)
        if isinstance(b, str) or callable(b):
            continue
        np.testing.assert_array_equal(a, c * np.asarray(b) if field in out else b)
    np.testing.assert_array_equal(res.loss_history, c**2 * np.asarray(ref.loss_history))
    np.testing.assert_array_equal(res.final_loss, c**2 * np.asarray(ref.final_loss))
    np.testing.assert_array_equal(res.steps, ref.steps)
    _check_storages(name, res, ref.P, getattr(ref, "multiplier", None), q_user)


def _check_storages(name, res, P, multiplier, qsr, coordinates=lambda K, P: (K, P)):
    """The storages (and a REN's multipliers) are the expected ones, and every controller
    passes an independent check in the user's units (a fresh SDP for a REN; from the
    definition, in `coordinates`, for the LTI controllers)."""
    if name in ("gd", "ico_nc"):
        assert res.P is None
        return
    np.testing.assert_array_equal(res.P, P)
    assert bool(np.all(res.certified))
    if name == "ren":
        np.testing.assert_array_equal(res.multiplier, multiplier)
        for i in range(3):
            assert dj.certify_ren(index(res.controllers, i), qsr).holds
        return
    for i in range(3):
        K_i, P_i = coordinates(index(res.controllers, i), res.P[i])
        assert dissipation_ok(K_i, qsr, P_i)


STATE_SCALE = np.array([1 / 64, 1 / 32])  # the user's states: 1/64 and 1/32 the base's


@pytest.mark.parametrize("name", list(FITS))
def test_states_in_units_of_their_own_train_as_the_balanced_problem(name):
    """Initial states far smaller than the outputs (x0 -> d x0 per state, the same
    controllers in the coordinates x = D x_b) train as the base problem: the run
    equals the base run mapped back bit for bit ((DAD^-1, DB, CD^-1, D), storage
    D^-1 P D^-1; a REN's multiplier unchanged), and every controller passes an independent
    check in the user's units. Without the states' balancing the runs learned next to
    nothing on such data (a new user's trial)."""
    base = _base()
    assert units.state_factors(base) is None  # the base problem is in balance
    user = dj.Windows(base.x0 * STATE_SCALE, base.y, base.u)
    d = units.state_factors(user)
    assert d is not None and np.all(np.log2(d) % 1 == 0)  # powers of two: exact
    # the problem the trainer should solve: the states divided by d
    balanced = dj.Windows(user.x0 / d, base.y, base.u)
    assert units.state_factors(balanced) is None
    res = FITS[name](user, QSR, atol=1e-6)
    ref = FITS[name](balanced, QSR, atol=1e-6)
    n = ref.controllers.A.shape[-1]
    dd = np.tile(d, n // d.size)  # an odd REN would carry two copies of the state
    left = {"A": dd[:, None] / dd[None, :], "B": dd[:, None], "C": 1 / dd[None, :],
                   "B1": dd[:, None], "B2": dd[:, None], "C1": 1 / dd[None, :],
                   "C2": 1 / dd[None, :]}
    for field in vars(ref.controllers):
        b = getattr(ref.controllers, field)
        if isinstance(b, str) or callable(b):
            continue
        np.testing.assert_array_equal(getattr(res.controllers, field),
                                      np.asarray(b) * left.get(field, 1.0))
    np.testing.assert_array_equal(res.loss_history, ref.loss_history)
    np.testing.assert_array_equal(res.steps, ref.steps)
    # the user's states differ in size by 2^6: checked where the storage's diagonal is one
    _check_storages(name, res, None if ref.P is None else
                    np.asarray(ref.P) / (dd[:, None] * dd[None, :]), getattr(ref, "multiplier", None), QSR,
                    in_storage_units)


def test_state_factors():
    """Per state: 1 unless it is more than 5x smaller than the outputs (or always zero),
    else the power of two nearest the ratio of its rms to the outputs' rms; states far
    larger are left as they are (`_units.py` says why); None when every state is in
    balance or the windows start at rest."""
    y = np.ones((4, 2, 1))
    x0 = np.array([[1.0, 100.0, 0.0, 0.19, 0.003], [-1.0, -100.0, 0.0, -0.19, -0.003]] * 2)
    w = dj.Windows(x0, y, y)
    np.testing.assert_allclose(units.state_ratios(w)[[0, 1, 3, 4]], [1.0, 100.0, 0.19, 0.003])
    assert np.isnan(units.state_ratios(w)[2])
    np.testing.assert_array_equal(units.state_factors(w), [1.0, 1.0, 1.0, 0.25, 2.0**-8])
    assert units.state_factors(dj.Windows(x0[:, :3], y, y)) is None
    assert units.state_factors(dj.Windows(None, y, y)) is None
    assert units.state_factors(dj.Windows(x0, 0 * y, y)) is None  # outputs all zero
    lo, hi = units.STATE_BAND
    assert hi == float("inf")
    assert units.state_factors(dj.Windows(np.full((4, 1), 1.01 * lo), y, y)) is None
    assert units.state_factors(dj.Windows(np.full((4, 1), 0.99 * lo), y, y)) is not None


def test_large_states_with_a_failed_fit_are_named():
    """States far larger than the outputs are left as they are; when the runs also ended
    above a tenth of the zero controller's loss the trainers warn, naming the power of two
    to divide x0 by. The thresholds on a stand-in result, then one real fit each way."""
    import types
    import warnings

    hint = "initial states are up to"
    rho_top, ratio_top = units.LARGE_STATES
    u = units.Units(hint=(2 * rho_top, 4.0))
    with pytest.warns(UserWarning, match=f"{hint} {2 * rho_top:.3g} times.*x0 / 32"):
        units.large_states_hint(types.SimpleNamespace(final_loss=np.full(3, 4.0 * 1.01 * ratio_top)), u)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        units.large_states_hint(types.SimpleNamespace(final_loss=np.full(3, 4.0 * 0.99 * ratio_top)), u)
        units.large_states_hint(types.SimpleNamespace(final_loss=np.full(3, 4.0)), units.Units())
    passive = dj.QSR.passive(2)
    base = realisable_windows(jr.PRNGKey(0), passive, n_state=4, num_windows=20, horizon=5)[0]
    assert units.balancing_units(base, True, passive).hint is None  # states in balance
    small_units = dj.Windows(base.x0 * 64, base.y, base.u)
    with pytest.warns(UserWarning, match=f"{hint} .*x0 / 64"):
        res = dj.fit_direct(jr.PRNGKey(1), small_units, passive, num_inits=2, progress=False)
    zero = np.mean(np.sum(np.asarray(base.u) ** 2, axis=(1, 2)))
    assert np.median(np.asarray(res.final_loss)) > ratio_top * zero
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = dj.fit_direct(jr.PRNGKey(1), base, passive, num_inits=2, progress=False)
    assert not [w for w in caught if hint in str(w.message)]
    assert np.median(np.asarray(res.final_loss)) < ratio_top * zero


# A supply rate and its multiple 2^20 admit the same controllers, with storages P and
# 2^20 P. The trainers and `project` divide a rate far from unit size by the power of two
# nearest its largest entry, so the two runs must agree bit for bit.
RATE_FITS = {
    "direct": lambda w, q: dj.fit_direct(jr.PRNGKey(0), w, q, num_inits=2, max_steps=40),
    "pgd": lambda w, q: dj.fit_pgd(jr.PRNGKey(0), w, q, num_inits=2, max_steps=8),
    "ico": lambda w, q: dj.fit_ico(jr.PRNGKey(0), w, q, num_inits=2, max_steps=3),
    "ren": lambda w, q: dj.fit_ren(jr.PRNGKey(0), w, q, width=2, num_inits=2, max_steps=30),
}


@pytest.mark.parametrize("name", list(RATE_FITS))
@pytest.mark.parametrize("power", [20, -20])
def test_a_scaled_supply_rate_trains_the_same_controllers(name, power):
    w, a = _base(), 2.0**power
    unit = dj.QSR(2 * QSR.Q, 2 * QSR.S, 2 * QSR.R)  # largest entry 1: used as it is
    big = dj.QSR(a * unit.Q, a * unit.S, a * unit.R)
    res, ref = RATE_FITS[name](w, big), RATE_FITS[name](w, unit)
    for field in vars(ref.controllers):
        b = getattr(ref.controllers, field)
        if not (isinstance(b, str) or callable(b)):
            np.testing.assert_array_equal(getattr(res.controllers, field), b)
    np.testing.assert_array_equal(res.final_loss, ref.final_loss)
    np.testing.assert_array_equal(res.P, a * np.asarray(ref.P))
    assert bool(np.all(res.certified))
    if name == "ren":
        np.testing.assert_array_equal(res.multiplier, a * np.asarray(ref.multiplier))
        return
    for i in range(2):  # the independent float64 check, at the user's scale
        assert dissipation_ok(index(res.controllers, i), big, res.P[i])


def test_project_solves_a_scaled_rate_as_the_unit_one():
    """A target inside a gain bound of 1e4 (rate entries up to 1e8) used to fail in
    Clarabel; the rate divided by 2^27 is projected as a gain bound of ~1."""
    K = dj.LTIController.random(jr.PRNGKey(3), 3, 2, 2, scale=0.5)
    a = 2.0**27
    unit = dj.QSR(-np.eye(2) / a, np.zeros((2, 2)), 1e8 / a * np.eye(2))
    big = dj.QSR.bounded_gain(1e4, n_in=2, n_out=2)
    (K1, P1), (K2, P2) = dj.project(K, big), dj.project(K, unit)
    for f in "ABCD":
        np.testing.assert_array_equal(getattr(K1, f), getattr(K2, f))
    np.testing.assert_array_equal(P1, a * np.asarray(P2))
    assert dissipation_ok(K1, big, P1)


def test_rate_factor():
    """1 for rates of ordinary size (the paper's, the zoo's); otherwise the power of two
    nearest the rate's size: its largest entry, or its room when Q < 0 and that is smaller."""
    f = rate_scale.rate_factor
    assert f(dj.QSR(-29.867, 3.556, 0.601)) == 1.0  # the paper's nonlinear example
    assert f(dj.QSR.passive(3)) == 1.0
    assert f(dj.QSR(0.0, 0.5e6, 0.0)) == 2.0**19  # passivity times 1e6
    assert f(dj.QSR.bounded_gain(1e3, n_in=1, n_out=1)) == 2.0**20  # R = 1e6, room 1e6
    assert f(dj.QSR.bounded_gain(1e-4, n_in=1, n_out=1)) == 1.0  # largest entry |Q| = 1
    # the cone [100, 101]: entries up to 1.01e4 but room 0.25, so the margin stays small
    assert f(dj.QSR.conic(100.0, 101.0, dim=1)) == 0.25


def test_a_storage_that_overflows_in_the_users_units_says_so():
    """float32 states 1e30 times smaller than the outputs: the balanced run is certified, but
    its storage D^-1 P D^-1 overflows float32 in the user's units. The runs are
    `not_certified` (never returned as certified), and `throw` names the cause (it gave the
    solver's generic advice)."""
    base = _base()
    w = dj.Windows(np.asarray(base.x0, np.float32) * np.float32([1e-30, 1.0]),
                   np.asarray(base.y, np.float32), np.asarray(base.u, np.float32))
    res = dj.fit_direct(jr.PRNGKey(0), w, QSR, num_inits=2, max_steps=20, throw=False)
    assert not np.any(np.asarray(res.certified))
    with pytest.raises(ValueError, match="storages that overflow float32 in your units"):
        dj.fit_direct(jr.PRNGKey(0), w, QSR, num_inits=2, max_steps=20)
