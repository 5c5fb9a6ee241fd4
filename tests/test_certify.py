import control
import numpy as np
import pytest
from helpers import independent_kyp_ok

import dissil_jax as dj


def _first_order(a, b, c, d):
    return dj.LTIController([[a]], [[b]], [[c]], [[d]])


@pytest.mark.parametrize("delta, expected", [(1e-7, True), (-1e-7, False), (1e-4, True),
                                             (-1e-4, False)])
def test_nearly_lossless_first_order(delta, expected):
    # G(z) = d + 1/(z - 0.5) is passive iff d >= 1/1.5 (worst case at z = -1).
    K = _first_order(0.5, 1.0, 1.0, 1 / 1.5 + delta)
    cert = dj.certify(K, dj.QSR.passive(1))
    assert cert.holds is expected
    if expected:
        assert independent_kyp_ok(K, dj.QSR.passive(1), cert.P)


def _random_stable(rng, n, m):
    A = rng.normal(size=(n, n))
    A *= rng.uniform(0.3, 0.95) / max(abs(np.linalg.eigvals(A)))
    return A, rng.normal(size=(n, m)), rng.normal(size=(m, n)), rng.normal(size=(m, m))


def test_agrees_with_python_control_passivity():
    rng = np.random.default_rng(0)
    agree = 0
    for trial in range(12):
        A, B, C, D = _random_stable(rng, 2, 2)
        D = D @ D.T * rng.uniform(0.0, 3.0)  # vary how passive the feedthrough makes it
        sys = control.ss(A, B, C, D, True)
        ref = control.ispassive(sys)
        ours = dj.certify(dj.LTIController(A, B, C, D), dj.QSR.passive(2)).holds
        agree += ref == ours
    assert agree == 12


def test_input_feedforward_index_matches_python_control():
    sys = control.ss([[0.5, 0.1], [0.0, -0.3]], [[1.0], [0.5]], [[1.0, 0.2]], [[1.2]], True)
    nu = control.get_input_ff_index(sys)
    K = dj.LTIController.from_statespace(sys)
    assert dj.certify(K, dj.QSR.degenerate_conic(nu - 1e-4, 1)).holds
    assert not dj.certify(K, dj.QSR.degenerate_conic(nu + 1e-4, 1)).holds


def test_bounded_gain_matches_hinf_norm():
    rng = np.random.default_rng(3)
    A, B, C, D = _random_stable(rng, 3, 2)
    sys = control.ss(A, B, C, D, True)
    w = np.linspace(0, np.pi, 4001)
    gain = max(np.linalg.svd(sys(np.exp(1j * wi)), compute_uv=False)[0] for wi in w)
    K = dj.LTIController(A, B, C, D)
    assert dj.certify(K, dj.QSR.bounded_gain(gain * 1.001, 2, 2)).holds
    assert not dj.certify(K, dj.QSR.bounded_gain(gain * 0.999, 2, 2)).holds


def test_given_P_is_checked_not_solved():
    K = _first_order(0.5, 1.0, 1.0, 1.0)
    cert = dj.certify(K, dj.QSR.passive(1))
    again = dj.certify(K, dj.QSR.passive(1), P=cert.P)
    assert again.holds and again.status == "given"
    assert not dj.certify(K, dj.QSR.passive(1), P=-cert.P).holds
    with pytest.raises(ValueError, match="`P`"):
        dj.certify(K, dj.QSR.passive(1), P=np.eye(2))


def test_certify_bad_input():
    K = _first_order(0.5, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.certify(K, dj.QSR.passive(2))
    with pytest.raises(ValueError, match="`K`"):
        dj.certify("not a controller", dj.QSR.passive(1))
