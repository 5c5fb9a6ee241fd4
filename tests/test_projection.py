import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import independent_kyp_ok, index, tree_allclose
from hypothesis import given, settings, strategies as st

import dissil_jax as dj

CASES = [
    ("nonlinear-paper", dj.QSR(-29.867, 3.556, 0.601), 1),
    ("passive-6x3", dj.QSR.passive(3), 6),
    ("conic", dj.QSR.conic(-0.5, 2.0, 2), 3),
    ("bounded-gain-rect", dj.QSR.bounded_gain(0.7, 2, 3), 2),
    ("degenerate-conic", dj.QSR.degenerate_conic(-0.2, 2), 2),
]


def _random_targets(key, n, qsr, batch, scale=1.0):
    keys = jax.random.split(key, batch)
    return jax.vmap(lambda k: dj.LTIController.random(k, n, qsr.n_in, qsr.n_out, scale))(keys)


@pytest.mark.parametrize("name, qsr, n", CASES, ids=[c[0] for c in CASES])
def test_projection_certified_eager_jit_vmap(getkey, name, qsr, n):
    Ks = _random_targets(getkey(), n, qsr, 4)
    K0 = index(Ks, 0)
    eager = dj.project(K0, qsr)
    jitted = jax.jit(lambda K: dj.project(K, qsr))(K0)
    # Solvers are reused across calls and threads with in-place updates; results must not
    # depend on which solver object handled which target.
    assert tree_allclose(eager, jitted, rtol=1e-10, atol=1e-12)
    batch = jax.jit(jax.vmap(lambda K: dj.project(K, qsr)))(Ks)
    leading = dj.project(Ks, qsr)  # leading batch axes without an explicit vmap
    for i in range(4):
        Ki, Pi = index(batch, i)
        assert independent_kyp_ok(Ki, qsr, Pi)
        assert dj.certify(Ki, qsr).holds
        # the batched host path equals the one-at-a-time path
        assert tree_allclose(index(leading, i), (Ki, Pi), rtol=1e-10, atol=1e-12)
    assert tree_allclose(index(batch, 0), eager, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name, qsr, n", CASES[:3], ids=[c[0] for c in CASES[:3]])
def test_certified_controller_projects_onto_itself(getkey, name, qsr, n):
    K, P = dj.project(_random_targets(getkey(), n, qsr, 1), qsr)
    K, P = index(K, 0), P[0]
    K2, P2 = dj.project(K, qsr, P)
    assert tree_allclose(K2, K, rtol=0, atol=0) and np.array_equal(P2, P)
    # also under jit and with the status API: UNCHANGED, no solve
    _, _, status = jax.jit(lambda K, P: dj.project_with_status(K, qsr, P))(K, P)
    assert int(status) == dj.Status.UNCHANGED


def test_projection_is_no_further_than_a_known_feasible_point(getkey):
    # Any certified controller K_c is feasible for the set at P~ = its own P, so the projection
    # of a target with P_ref = P_c is at least as close to the target as K_c.
    qsr = dj.QSR.passive(2)
    Kc, Pc = dj.project(dj.LTIController.random(getkey(), 2, 2, 2, 1.0), qsr)
    target = jax.tree.map(lambda a: a + 0.3, Kc)
    Kp, _ = dj.project(target, qsr, Pc)
    dist = lambda K: sum(float(jnp.sum((a - b) ** 2)) for a, b in
                         zip(jax.tree.leaves(K), jax.tree.leaves(target)))
    assert dist(Kp) <= dist(Kc) + 1e-8
    assert dist(Kp) < dist(Kc)  # and it actually moved towards the target


def test_projection_in_float32_is_still_certified(getkey):
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    K = dj.LTIController.random(getkey(), 1, 1, 1, 3.0).astype(jnp.float32)
    Kp, P = dj.project(K, qsr)
    assert Kp.A.dtype == jnp.float32 and P.dtype == jnp.float32
    assert independent_kyp_ok(Kp, qsr, P)


def test_positive_q_rejected():
    qsr = dj.QSR(1.0, 0.5, 1.0)
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    with pytest.raises(ValueError, match="`qsr.Q`"):
        dj.project(K, qsr)


def test_shape_mismatch_rejected():
    K = dj.LTIController.random(jax.random.PRNGKey(0), 2, 2, 1)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.project(K, dj.QSR.passive(2))
    with pytest.raises(ValueError, match="`P_ref`"):
        dj.project(K, dj.QSR.bounded_gain(1.0, 1, 2), jnp.eye(3))


def test_infeasible_supply_rate_raises():
    # Q = -I, S = 0, R = -I: w = -|y|^2 - |u|^2 < 0, no system is dissipative.
    qsr = dj.QSR(-1.0, 0.0, -1.0)
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    with pytest.raises(ValueError, match="infeasible"):
        dj.project(K, qsr)
    _, _, status = dj.project_with_status(K, qsr)
    assert int(status) == dj.Status.INFEASIBLE
    with pytest.raises(Exception, match="infeasible"):
        jax.block_until_ready(jax.jit(lambda K: dj.project(K, qsr))(K))


def test_traced_qsr_rejected():
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    with pytest.raises(ValueError, match="close over"):
        jax.jit(lambda q: dj.project(K, q))(dj.QSR.passive(1))


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 3),
    p=st.integers(1, 2),
    scale=st.floats(0.05, 5.0),
    kind=st.sampled_from(["passive", "gain", "conic"]),
)
def test_property_every_projection_is_certified(seed, n, p, scale, kind):
    qsr = {"passive": dj.QSR.passive(p), "gain": dj.QSR.bounded_gain(1.5, p, p),
           "conic": dj.QSR.conic(0.1, 3.0, p)}[kind]
    K = dj.LTIController.random(jax.random.PRNGKey(seed), n, p, p, scale)
    Kp, P = dj.project(K, qsr)
    assert independent_kyp_ok(Kp, qsr, P)
    K2, P2 = dj.project(Kp, qsr, P)
    assert tree_allclose(K2, Kp, rtol=0, atol=0)
