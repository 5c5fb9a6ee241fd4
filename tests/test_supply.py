"""`dj.QSR`, the closed-loop theorem (`closed_loop_certificate`) and `stabilising_qsr`."""

import numpy as np
import pytest

import dissil_jax as dj

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)


def test_special_cases_match_their_definitions():
    rng = np.random.default_rng(0)
    u, y = rng.normal(size=(50, 2)), rng.normal(size=(50, 2))
    np.testing.assert_allclose(dj.QSR.passive(2).supply(u, y), np.sum(u * y, -1))
    a, b = -0.5, 2.0
    w = dj.QSR.conic(a, b, dim=2).supply(u, y)
    np.testing.assert_allclose(w, -np.sum((y - a * u) * (y - b * u), -1))
    g = 1.7
    np.testing.assert_allclose(dj.QSR.bounded_gain(g, n_in=2, n_out=2).supply(u, y),
                               g**2 * np.sum(u * u, -1) - np.sum(y * y, -1))
    d = -0.3
    np.testing.assert_allclose(dj.QSR.degenerate_conic(d, dim=2).supply(u, y),
                               np.sum(y * u, -1) - d * np.sum(u * u, -1))


def test_rectangular_bounded_gain_shapes():
    q = dj.QSR.bounded_gain(2.0, n_out=3, n_in=2)
    assert q.Q.shape == (3, 3) and q.S.shape == (3, 2) and q.R.shape == (2, 2)
    assert q.n_out == 3 and q.n_in == 2
    rng = np.random.default_rng(1)
    u, y = rng.normal(size=(50, 2)), rng.normal(size=(50, 3))
    np.testing.assert_allclose(q.supply(u, y), 4.0 * np.sum(u * u, -1) - np.sum(y * y, -1),
                               rtol=1e-12)
    # a general rectangular supply rate against its definition, one pair at a time
    Q, S, R = -np.eye(3) + 0.1, rng.normal(size=(3, 2)), np.array([[1.0, 0.3], [0.3, 2.0]])
    g = dj.QSR(Q, S, R)
    for k in range(5):
        expect = y[k] @ Q @ y[k] + 2 * y[k] @ S @ u[k] + u[k] @ R @ u[k]
        assert g.supply(u[k], y[k]) == pytest.approx(expect, rel=1e-12)


@pytest.mark.parametrize(
    "args, name",
    [
        ((np.eye(2), np.zeros((2, 3)), np.eye(2)), "R"),
        ((np.eye(3), np.zeros((2, 3)), np.eye(3)), "Q"),
        (([[0, 1], [0, 0]], np.zeros((2, 2)), np.eye(2)), "Q"),
        ((np.zeros((2, 2)), np.zeros((2, 2)), [[1, np.nan], [np.nan, 1]]), "R"),
        ((1j, 0.5, 0.0), "Q"),
        ((0.0, "half", 0.0), "S"),
        ((0.0, 0.5, np.ones((1, 1, 1))), "R"),
        ((0.0, np.array([[0.5 + 1j]]), 0.0), "S"),
    ],
)
def test_qsr_validation_names_argument(args, name):
    with pytest.raises(ValueError, match=f"`{name}`"):
        dj.QSR(*args)


def test_constructor_validation():
    with pytest.raises(ValueError, match="`a`"):
        dj.QSR.conic(2.0, 1.0, dim=1)
    with pytest.raises(ValueError, match="`gamma`"):
        dj.QSR.bounded_gain(-1.0, n_in=1, n_out=1)
    # a square beyond float64 (a raw OverflowError before)
    with pytest.raises(ValueError, match="`gamma` = 1e\\+200 is too large"):
        dj.QSR.bounded_gain(1e200, n_in=1, n_out=1)
    with pytest.raises(ValueError, match="`a` = .* and `b` = .* are too large"):
        dj.QSR.conic(1e160, 1e170, dim=1)
    with pytest.raises(ValueError, match="`dim`"):
        dj.QSR.passive(0)
    # arrays, strings and complex numbers are named, not left to numpy's own errors
    for bad in (np.array([1.0, 2.0]), "1", 1 + 1j, np.nan):
        with pytest.raises(ValueError, match="`gamma`"):
            dj.QSR.bounded_gain(bad, n_in=1, n_out=1)
        with pytest.raises(ValueError, match="`a`"):
            dj.QSR.conic(bad, 2.0, dim=1)
        with pytest.raises(ValueError, match="`b`"):
            dj.QSR.conic(0.0, bad, dim=1)
        with pytest.raises(ValueError, match="`d`"):
            dj.QSR.degenerate_conic(bad, dim=1)
    assert dj.QSR.bounded_gain(np.float32(2.0), n_in=1, n_out=1).R[0, 0] == 4.0


def test_neg_q_factor():
    q = dj.QSR(np.diag([-4.0, 0.0]), np.eye(2), np.eye(2))
    L = q.neg_q_factor()
    assert L.shape == (2, 1)
    np.testing.assert_allclose(-L @ L.T, q.Q, atol=1e-12)
    assert dj.QSR.passive(3).neg_q_factor().shape == (3, 0)
    with pytest.raises(ValueError, match="positive eigenvalue"):
        dj.QSR(np.diag([1.0, -1.0]), np.eye(2), np.eye(2)).neg_q_factor()


def _theorem1(plant, ctrl, alpha):
    """Paper Theorem 1's matrix, written out here (not the library's)."""
    top = np.hstack([plant.Q + alpha * ctrl.R, -plant.S + alpha * ctrl.S.T])
    bot = np.hstack([(-plant.S + alpha * ctrl.S.T).T, plant.R + alpha * ctrl.Q])
    return np.vstack([top, bot])


def test_paper_controller_supply_rate_and_certificate():
    """Paper numbers: plant (-1, 3.556, 29.333), alpha = 1, M = (0.399, 0.534)."""
    plant = dj.QSR(-1.0, 3.556, 29.333)
    ctrl = dj.stabilising_qsr(plant, alpha=1.0, margins=(0.399, 0.534))
    np.testing.assert_allclose([ctrl.Q[0, 0], ctrl.S[0, 0], ctrl.R[0, 0]],
                               [-29.867, 3.556, 0.601], rtol=1e-12)
    np.testing.assert_allclose(_theorem1(plant, ctrl, 1.0), np.diag([-0.399, -0.534]),
                               atol=1e-12)
    holds, alpha = cert = dj.closed_loop_certificate(plant, ctrl)
    assert holds and cert.message.startswith("Theorem 1 holds")
    # the returned multiplier really certifies, and is at least as good as alpha = 1
    lam = np.linalg.eigvalsh(_theorem1(plant, ctrl, alpha))[-1]
    assert lam <= -0.399 + 1e-9
    # the recipe scales with alpha: alpha = 2 halves every entry
    ctrl2 = dj.stabilising_qsr(plant, alpha=2.0, margins=(0.399, 0.534))
    np.testing.assert_allclose([ctrl2.Q[0, 0], ctrl2.S[0, 0], ctrl2.R[0, 0]],
                               [-29.867 / 2, 3.556 / 2, 0.601 / 2], rtol=1e-12)


def test_closed_loop_certificate_rejects_impossible_pair():
    # Two gains whose product exceeds one: the small-gain condition must fail for every alpha.
    cert = dj.closed_loop_certificate(dj.QSR.bounded_gain(2.0, n_in=1, n_out=1),
                                      dj.QSR.bounded_gain(0.6, n_in=1, n_out=1))
    holds, _ = cert
    assert not holds
    assert cert.message.startswith("no multiplier found")  # Theorem 1's words, not the
    # projection's ("solved and verified ...")
    holds, _ = dj.closed_loop_certificate(dj.QSR.bounded_gain(2.0, n_in=1, n_out=1),
                                          dj.QSR.bounded_gain(0.4, n_in=1, n_out=1))
    assert holds
    # At the edge: gain bounds 2 and 0.5 - 1e-9 leave alpha in (4, 4 + 1.6e-8), narrower
    # than Brent's tolerance in log(alpha); the search in alpha itself finds it, and the
    # multiplier returned certifies (M(alpha) = diag(-1 + alpha g^2, 4 - alpha))
    g = 0.5 - 1e-9
    cert = dj.closed_loop_certificate(dj.QSR.bounded_gain(2.0, n_in=1, n_out=1),
                                      dj.QSR.bounded_gain(g, n_in=1, n_out=1))
    assert cert.holds and max(-1 + cert.alpha * g**2, 4 - cert.alpha) < -1e-9
    # Passive + passive is not strictly enough (zero margin), strictly passive pair works.
    assert not dj.closed_loop_certificate(dj.QSR.passive(1), dj.QSR.passive(1)).holds
    assert dj.closed_loop_certificate(dj.QSR(-0.1, 0.5, -0.1), dj.QSR.passive(1)).holds


def test_stabilising_qsr_always_certifies():
    """The recipe's identities hold at the requested alpha, where M(alpha) = diag(-M1, -M2)."""
    rng = np.random.default_rng(1)
    for trial in range(6):
        S = rng.normal(size=(2, 3))
        Q1, R1 = rng.normal(size=(2, 2)), rng.normal(size=(3, 3))
        plant = dj.QSR(-Q1 @ Q1.T, S, R1 + R1.T)
        alpha = float(rng.uniform(0.2, 5))
        if trial % 2:  # scalar margins
            M1, M2 = float(rng.uniform(0.05, 1)), float(rng.uniform(0.05, 1))
            ctrl = dj.stabilising_qsr(plant, alpha=alpha, margins=(M1, M2))
            M1, M2 = M1 * np.eye(2), M2 * np.eye(3)
        else:  # matrix margins
            G1, G2 = rng.normal(size=(2, 2)), rng.normal(size=(3, 3))
            M1, M2 = G1 @ G1.T + 0.1 * np.eye(2), G2 @ G2.T + 0.1 * np.eye(3)
            ctrl = dj.stabilising_qsr(plant, alpha=alpha, margins=(M1, M2))
        assert ctrl.S.shape == (3, 2) and ctrl.Q.shape == (3, 3) and ctrl.R.shape == (2, 2)
        np.testing.assert_allclose(ctrl.S, plant.S.T / alpha, rtol=1e-12)
        np.testing.assert_allclose(ctrl.R, -(plant.Q + M1) / alpha, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(ctrl.Q, -(plant.R + M2) / alpha, rtol=1e-12, atol=1e-14)
        M = _theorem1(plant, ctrl, alpha)
        np.testing.assert_allclose(M, np.block([[-M1, np.zeros((2, 3))],
                                                [np.zeros((3, 2)), -M2]]), atol=1e-12)
        np.testing.assert_allclose(np.linalg.eigvalsh(M),
                                   np.sort(np.concatenate([np.linalg.eigvalsh(-M1),
                                                           np.linalg.eigvalsh(-M2)])),
                                   atol=1e-12)
        assert dj.closed_loop_certificate(plant, ctrl).holds


def test_stabilising_qsr_argument_errors():
    plant = dj.QSR.bounded_gain(1.0, n_in=3, n_out=2)  # S is 2x3: M1 is 2x2, M2 is 3x3
    good = (np.eye(2), np.eye(3))
    dj.stabilising_qsr(plant, margins=good)
    for margins, match in [
        (0.1, "`margins`"), ((0.1, 0.2, 0.3), "`margins`"),
        ((np.eye(3), np.eye(3)), r"`margins\[0\]`"), ((np.eye(2), np.eye(2)), r"`margins\[1\]`"),
        # not symmetric, with positive eigenvalues: the message said "must be positive
        # (definite), got eigenvalues [0.5 1.5]"
        ((np.array([[1.0, 1.0], [0.0, 1.0]]), np.eye(3)), r"`margins\[0\]` must be symmetric"),
        ((-np.eye(2), np.eye(3)), r"`margins\[0\]`"), ((np.eye(2), 0.0), r"`margins\[1\]`"),
        ((np.nan, 1.0), r"`margins\[0\]`"), ((np.ones((1, 2, 2)), np.eye(3)), r"`margins\[0\]`"),
        ((np.diag([1.0, 0.0]), np.eye(3)), r"`margins\[0\]`"),
        (("a", 1.0), r"`margins\[0\]`"), ((np.eye(2), 1j), r"`margins\[1\]`"),
    ]:
        with pytest.raises(ValueError, match=match):
            dj.stabilising_qsr(plant, margins=margins)
    for alpha in (0.0, -1.0, np.nan, np.inf, "1", np.array([1.0, 2.0]), 1j):
        with pytest.raises(ValueError, match="`alpha`"):
            dj.stabilising_qsr(plant, alpha=alpha, margins=good)
    with pytest.raises(ValueError, match="`plant_qsr`"):
        dj.stabilising_qsr((0.0, 0.5, 0.0))


def test_interconnection_shape_errors():
    gain = dj.QSR.bounded_gain(1.0, n_in=3, n_out=2)
    with pytest.raises(ValueError, match="`controller_qsr`"):
        dj.closed_loop_certificate(gain, gain)
    with pytest.raises(ValueError, match="margins"):
        dj.stabilising_qsr(dj.QSR.passive(1), margins=(0.1, -1.0))
    with pytest.raises(ValueError, match="`alpha`"):
        dj.stabilising_qsr(dj.QSR.passive(1), alpha=0.0)


# -- a supply rate is a static, hashable value -------------------------------------------


def test_qsr_hash_and_equality_by_value():
    a, b = dj.QSR.passive(2), dj.QSR.passive(2)
    assert a is not b
    assert hash(a) == hash(b)
    assert (a == b) is True and (a != b) is False
    assert dj.QSR(-1.0, 3.556, 29.333) == dj.QSR(-1.0, 3.556, 29.333)
    others = [dj.QSR.passive(3), dj.QSR.conic(0.0, 1.0, dim=2), dj.QSR.degenerate_conic(0.1, dim=2),
              dj.QSR.bounded_gain(1.0, n_in=2, n_out=2), dj.QSR.bounded_gain(1.0, n_in=3, n_out=2)]
    for other in others:
        assert (a == other) is False and (a != other) is True
    assert a != "passive" and a != (a.Q, a.S, a.R)
    # usable as dict keys / in sets; equal values collapse
    assert len({a, b, *others}) == 1 + len(others)
    assert {a: 1}[b] == 1
    # -0.0 and 0.0 are the same supply rate (hash consistent with ==)
    z = dj.QSR(np.zeros((1, 1)), 0.5, -0.0 * np.ones((1, 1)))
    assert z == dj.QSR.passive(1) and hash(z) == hash(dj.QSR.passive(1))
    # equal after a pickle round trip, and the arrays stay read-only
    import pickle

    c = pickle.loads(pickle.dumps(dj.QSR.conic(-0.5, 2.0, dim=2)))
    assert c == dj.QSR.conic(-0.5, 2.0, dim=2) and not c.Q.flags.writeable


def test_qsr_has_no_array_leaves_and_read_only_float64_arrays():
    import equinox as eqx
    import jax

    q = dj.QSR(-np.eye(2), np.ones((2, 3)), np.eye(3))
    assert jax.tree.leaves(q) == []
    assert eqx.filter(q, eqx.is_array) == q
    for M, shape in ((q.Q, (2, 2)), (q.S, (2, 3)), (q.R, (3, 3))):
        assert isinstance(M, np.ndarray) and M.dtype == np.float64 and M.shape == shape
        assert not M.flags.writeable
        with pytest.raises(ValueError):
            M[0, 0] = 1.0
    assert q.Q is q.Q  # cheap: no copy per access
    # the caller's input is copied, so later edits of it do not change the supply rate
    S = np.ones((2, 3))
    q2 = dj.QSR(-np.eye(2), S, np.eye(3))
    S[0, 0] = 5.0
    assert q2.S[0, 0] == 1.0 and q2 == q


def test_qsr_as_static_argument_of_jit_and_filter_jit():
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    traces = []

    def f(x, qsr):
        traces.append(qsr)
        return x @ jnp.asarray(qsr.S) @ jnp.asarray(qsr.R)

    x = jnp.ones((3, 2))
    ref = np.ones((3, 2)) @ dj.QSR.conic(-1.0, 2.0, dim=2).S @ dj.QSR.conic(-1.0, 2.0, dim=2).R
    static = jax.jit(f, static_argnums=1)
    np.testing.assert_allclose(static(x, dj.QSR.conic(-1.0, 2.0, dim=2)), ref)
    np.testing.assert_allclose(static(x, dj.QSR.conic(-1.0, 2.0, dim=2)), ref)
    assert len(traces) == 1  # an equal supply rate hits the compilation cache
    static(x, dj.QSR.conic(-1.0, 3.0, dim=2))
    assert len(traces) == 2  # a different one retraces
    # as an ordinary (pytree) argument of jax.jit and eqx.filter_jit: no leaves, so static
    for wrap in (jax.jit, eqx.filter_jit):
        traces.clear()
        g = wrap(f)
        np.testing.assert_allclose(g(x, dj.QSR.conic(-1.0, 2.0, dim=2)), ref)
        g(x, dj.QSR.conic(-1.0, 2.0, dim=2))
        assert len(traces) == 1
        assert isinstance(traces[0], dj.QSR) and isinstance(traces[0].S, np.ndarray)
    # and through jax.vmap (nothing to map over in the supply rate)
    out = jax.vmap(f, in_axes=(0, None))(jnp.ones((4, 3, 2)), dj.QSR.conic(-1.0, 2.0, dim=2))
    np.testing.assert_allclose(out, np.broadcast_to(ref, (4, 3, 2)))


def test_closed_loop_certificate_does_not_depend_on_the_rates_scales():
    """Multiplying a rate by kappa > 0 admits the same systems, so the verdict must not
    change: the multiplier scan is centred on the ratio of the rates' sizes (with a fixed
    scan over [1e-8, 1e8], a controller rate of size 1e11 from `stabilising_qsr`, built to
    satisfy the theorem at alpha = 1e-11, got no multiplier)."""
    plant = dj.QSR(-1.0, 3.556, 29.333)
    pairs = [(plant, dj.QSR(-29.867, 3.556, 0.601), True),
             (dj.QSR.bounded_gain(2.0, n_in=1, n_out=1),
              dj.QSR.bounded_gain(0.6, n_in=1, n_out=1), False)]
    gain = dj.QSR.bounded_gain(1e-5, n_in=1, n_out=1)
    pairs.append((gain, dj.stabilising_qsr(gain, alpha=1e-11, margins=(0.5, 1e-11)), True))
    for p, c, expected in pairs:
        for kappa in (1e-12, 1.0, 1e12):
            scaled = dj.QSR(kappa * c.Q, kappa * c.S, kappa * c.R)
            assert dj.closed_loop_certificate(p, scaled).holds is expected, (kappa, expected)
