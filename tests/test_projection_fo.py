"""The first-order projection (`_projection/first_order.py`, `dj.project(method="first_order")`)."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, index

import dissil_jax as dj
from dissil_jax.internal import ConvexifiedLMI, projection_fo as fo

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

RATES = {"passive": dj.QSR.passive(2),
         "strict": dj.QSR(-np.eye(2), 0.5 * np.eye(2), 0.5 * np.eye(2))}


def _batch(key, num, n=3):
    return jax.vmap(lambda k: dj.LTIController.random(k, n, 2, 2, scale=1.0))(
        jr.split(key, num))


def _dist(K, T):
    return sum(float(jnp.sum((a - b) ** 2)) for a, b in zip(jax.tree.leaves(K),
                                                              jax.tree.leaves(T)))


@pytest.mark.parametrize("name", RATES)
def test_lmi_matrix_is_the_convexified_lmi(getkey, name):
    # Built independently: the host class assembles M from its affine basis.
    qsr, n = RATES[name], 3
    K = dj.LTIController.random(getkey(), n, 2, 2, scale=1.0)
    X, Y = jr.normal(getkey(), (2, n, n))
    P, Pt = X @ X.T + jnp.eye(n), Y @ Y.T + jnp.eye(n)
    lmi = ConvexifiedLMI(n, 2, 2, qsr)
    x = lmi.layout.pack(*(np.asarray(M) for M in (K.A, K.B, K.C, K.D)), np.asarray(P))
    np.testing.assert_allclose(fo.lmi_matrix(K.A, K.B, K.C, K.D, P, Pt, qsr),
                               lmi.evaluate(x, np.asarray(Pt)), atol=1e-12)


def test_psd_part_matches_eigh(getkey):
    X = jr.normal(getkey(), (9, 9))
    X = X + X.T
    w, V = np.linalg.eigh(np.asarray(X))
    ref = (V * np.maximum(w, 0)) @ V.T
    # Newton-Schulz resolves eigenvalues above ~1.5^-40 |X|_F ~ 1e-7 |X|_F; these are O(1)
    # and well separated from 0, so the two agree to round-off after the quadratic phase.
    assert np.min(np.abs(w)) > 1e-3
    np.testing.assert_allclose(fo.psd_part(X), ref, atol=1e-10)


@pytest.mark.parametrize("name", RATES)
def test_first_order_agrees_with_clarabel_and_is_certified(getkey, name):
    qsr, K = RATES[name], _batch(getkey(), 3)
    P_ref = jnp.broadcast_to(jnp.eye(3), (3, 3, 3))
    fo.FALLBACKS["rows"] = 0
    a = dj.project(K, qsr, P_ref, method="first_order")
    b = dj.project(K, qsr, P_ref, method="clarabel")
    assert fo.FALLBACKS["rows"] == 0  # the first-order results passed the check themselves
    for i in range(3):
        Ka, Kb, Ki = index(a.controller, i), index(b.controller, i), index(K, i)
        assert dissipation_ok(Ka, qsr, a.P[i])
        # The first-order solve aims at the margin 1e-4 (Clarabel: eps = 1e-6) and stops
        # at residuals ~1e-6 |M|: the solutions differ by about that margin shift times
        # the constraint's sensitivity (O(1) here), so 1e-3 on entries and on the
        # distance relative to the distance moved.
        assert max(float(jnp.abs(x - y).max()) for x, y in
                   zip(jax.tree.leaves(Ka), jax.tree.leaves(Kb))) < 1e-3
        da, db = _dist(Ka, Ki), _dist(Kb, Ki)
        assert abs(da - db) <= 1e-3 * db + 1e-9


def test_vmapped_equals_a_python_loop(getkey):
    qsr, K = RATES["strict"], _batch(getkey(), 3)
    P_ref = jnp.broadcast_to(jnp.eye(3), (3, 3, 3))
    batched = dj.project(K, qsr, P_ref, method="first_order")
    for i in range(3):
        one = dj.project(index(K, i), qsr, jnp.eye(3), method="first_order")
        # A batched while_loop freezes converged rows, so each row runs the same
        # iterations as alone; only the summation order of batched products differs.
        for x, y in zip(jax.tree.leaves(index(batched.controller, i)),
                        jax.tree.leaves(one.controller)):
            np.testing.assert_allclose(x, y, atol=1e-9)


def test_fallback_to_clarabel_when_the_budget_is_too_small(getkey, monkeypatch):
    qsr, K = RATES["passive"], _batch(getkey(), 2)
    monkeypatch.setattr(fo, "MAX_ITER_FO", 1)  # one ADMM step: far from feasible
    fo.FALLBACKS["rows"] = 0
    a = dj.project(K, qsr, method="first_order")
    b = dj.project(K, qsr, method="clarabel")
    assert fo.FALLBACKS["rows"] == 2
    assert bool(np.all(a.result == b.result))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):  # Clarabel's own answer
        np.testing.assert_array_equal(x, y)
    for i in range(2):
        assert dissipation_ok(index(a.controller, i), qsr, a.P[i])


def test_method_argument(getkey):
    K = _batch(getkey(), 1)
    with pytest.raises(ValueError, match="`method`"):
        dj.project(K, RATES["passive"], method="admm")
    with pytest.raises(ValueError, match="`method='first_order'`"):
        dj.project(K, RATES["passive"], method="first_order",
                   metric=jax.tree.map(jnp.ones_like, K))
    assert not fo.use_first_order("auto", K, None, RATES["passive"])  # Clarabel by default
    assert fo.use_first_order("first_order", K, None, RATES["passive"])
    # an indefinite Q (here Q = 0.5 I > 0) needs the linearisation only Clarabel's path has
    indefinite = dj.QSR(0.5 * np.eye(2), 0.5 * np.eye(2), -2.0 * np.eye(2))
    assert not fo.use_first_order("auto", K, None, indefinite)
    with pytest.raises(ValueError, match="`qsr.Q` negative semidefinite"):
        dj.project(K, indefinite, method="first_order")


def test_pgd_with_the_first_order_projection(getkey):
    # Every PGD iterate goes through the exact check (the callback after ADMM).
    from helpers import expert_windows

    w = expert_windows(0, 2, 1, 1)
    qsr = dj.QSR.passive(1)
    res = dj.fit_pgd(getkey(), w, qsr, num_inits=3, max_steps=5, atol=0.0, rtol=0.0,
                     learning_rate=1.0, method="first_order")  # the paper's rule
    # the default step, projected Adam, needs its metric: refused up front, with the fix
    with pytest.raises(ValueError, match="`method='first_order'`.*paper's rule"):
        dj.fit_pgd(getkey(), w, qsr, num_inits=3, max_steps=5, method="first_order")
    assert bool(res.certified.all())
    for i in range(3):
        assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])
