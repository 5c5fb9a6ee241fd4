import numpy as np
import pytest

import dissil_jax as dj


def test_special_cases_match_their_definitions():
    rng = np.random.default_rng(0)
    u, y = rng.normal(size=(50, 2)), rng.normal(size=(50, 2))
    np.testing.assert_allclose(dj.QSR.passive(2).supply(u, y), np.sum(u * y, -1))
    a, b = -0.5, 2.0
    w = dj.QSR.conic(a, b, 2).supply(u, y)
    np.testing.assert_allclose(w, -np.sum((y - a * u) * (y - b * u), -1))
    g = 1.7
    np.testing.assert_allclose(dj.QSR.bounded_gain(g, 2, 2).supply(u, y),
                               g**2 * np.sum(u * u, -1) - np.sum(y * y, -1))
    d = -0.3
    np.testing.assert_allclose(dj.QSR.degenerate_conic(d, 2).supply(u, y),
                               np.sum(y * u, -1) - d * np.sum(u * u, -1))


def test_rectangular_bounded_gain_shapes():
    q = dj.QSR.bounded_gain(2.0, n_out=3, n_in=2)
    assert q.Q.shape == (3, 3) and q.S.shape == (3, 2) and q.R.shape == (2, 2)
    assert q.n_out == 3 and q.n_in == 2


@pytest.mark.parametrize(
    "args, name",
    [
        ((np.eye(2), np.zeros((2, 3)), np.eye(2)), "R"),
        ((np.eye(3), np.zeros((2, 3)), np.eye(3)), "Q"),
        (([[0, 1], [0, 0]], np.zeros((2, 2)), np.eye(2)), "Q"),
        ((np.zeros((2, 2)), np.zeros((2, 2)), [[1, np.nan], [np.nan, 1]]), "R"),
    ],
)
def test_qsr_validation_names_argument(args, name):
    with pytest.raises(ValueError, match=f"`{name}`"):
        dj.QSR(*args)


def test_constructor_validation():
    with pytest.raises(ValueError, match="`a`"):
        dj.QSR.conic(2.0, 1.0, 1)
    with pytest.raises(ValueError, match="`gamma`"):
        dj.QSR.bounded_gain(-1.0, 1, 1)
    with pytest.raises(ValueError, match="`dim`"):
        dj.QSR.passive(0)


def test_neg_q_factor():
    q = dj.QSR(np.diag([-4.0, 0.0]), np.eye(2), np.eye(2))
    L = q.neg_q_factor()
    assert L.shape == (2, 1)
    np.testing.assert_allclose(-L @ L.T, q.Q, atol=1e-12)
    assert dj.QSR.passive(3).neg_q_factor().shape == (3, 0)
    with pytest.raises(ValueError, match="positive eigenvalue"):
        dj.QSR(np.diag([1.0, -1.0]), np.eye(2), np.eye(2)).neg_q_factor()


def test_paper_controller_supply_rate_and_certificate():
    plant = dj.QSR(-1.0, 32 / 9, 88 / 3)
    ctrl = dj.stabilising_qsr(plant, alpha=1.0, margins=(0.399, 0.534))
    np.testing.assert_allclose([ctrl.Q[0, 0], ctrl.S[0, 0], ctrl.R[0, 0]],
                               [-29.867, 3.556, 0.601], atol=5e-4)
    holds, alpha = dj.closed_loop_certificate(plant, ctrl)
    assert holds and alpha > 0
    # The paper's rounded pair also passes, with alpha = 1 feasible.
    holds, _ = dj.closed_loop_certificate(dj.QSR(-1, 3.556, 29.333), dj.QSR(-29.867, 3.556, 0.601))
    assert holds


def test_closed_loop_certificate_rejects_impossible_pair():
    # Two gains whose product exceeds one: the small-gain condition must fail for every alpha.
    holds, _ = dj.closed_loop_certificate(dj.QSR.bounded_gain(2.0, 1, 1),
                                          dj.QSR.bounded_gain(0.6, 1, 1))
    assert not holds
    holds, _ = dj.closed_loop_certificate(dj.QSR.bounded_gain(2.0, 1, 1),
                                          dj.QSR.bounded_gain(0.4, 1, 1))
    assert holds
    # Passive + passive is not strictly enough (zero margin), strictly passive pair works.
    assert not dj.closed_loop_certificate(dj.QSR.passive(1), dj.QSR.passive(1)).holds
    assert dj.closed_loop_certificate(dj.QSR(-0.1, 0.5, -0.1), dj.QSR.passive(1)).holds


def test_stabilising_qsr_always_certifies():
    rng = np.random.default_rng(1)
    for _ in range(5):
        S = rng.normal(size=(2, 3))
        plant = dj.QSR(-np.eye(2), S, np.eye(3) * 3)
        alpha = float(rng.uniform(0.2, 5))
        ctrl = dj.stabilising_qsr(plant, alpha=alpha, margins=(0.1, 0.2))
        assert ctrl.S.shape == (3, 2)
        assert dj.closed_loop_certificate(plant, ctrl).holds


def test_interconnection_shape_errors():
    with pytest.raises(ValueError, match="`controller_qsr`"):
        dj.closed_loop_certificate(dj.QSR.bounded_gain(1.0, 2, 3), dj.QSR.bounded_gain(1.0, 2, 3))
    with pytest.raises(ValueError, match="margins"):
        dj.stabilising_qsr(dj.QSR.passive(1), margins=(0.1, -1.0))
    with pytest.raises(ValueError, match="`alpha`"):
        dj.stabilising_qsr(dj.QSR.passive(1), alpha=0.0)
