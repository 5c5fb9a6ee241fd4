"""The projection in a per-entry metric, and projected adaptive optimisers in their own metric."""

import pathlib
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optax
import pytest
from helpers import dissipation_ok, index

import dissil_jax as dj
from dissil_jax.internal import METRIC_FLOOR, optimizer_metric

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
from _reference import cvxpy_projection_problem, solve_reference  # noqa: E402

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

QSR = dj.QSR.passive(2)


def _case(key, batch=()):
    """Certified controllers, targets outside the set near them, and anisotropic weights."""
    k1, k2, k3 = jr.split(key, 3)
    draw = lambda k: dj.LTIController.random(k, 2, 2, 2, scale=1.0)
    K = jax.vmap(draw)(jr.split(k1, batch[0])) if batch else draw(k1)
    Kc, Pc = dj.project(K, QSR)
    def like(k, f):
        return dj.LTIController(*(f(jr.normal(ki, M.shape, M.dtype)) for ki, M in
                                  zip(jr.split(k, 4), jax.tree.leaves(Kc))))

    target = jax.tree.map(jnp.add, Kc, like(k2, lambda z: 0.6 * z))
    return target, Pc, like(k3, lambda z: jnp.exp(1.5 * z))


def _dist(K, target, W):
    return sum(float(jnp.sum(w * (a - b) ** 2)) for a, b, w in
               zip(jax.tree.leaves(K), jax.tree.leaves(target), jax.tree.leaves(W)))


def test_weighted_projection_matches_cvxpy(getkey):
    """The weighted projection equals the same SDP written in cvxpy, is certified, and is
    closer in its metric (and further in Frobenius) than the Frobenius projection."""
    target, Pc, W = _case(getkey())
    Kw, Pw = dj.project(target, QSR, Pc, metric=W)
    Kf, _ = dj.project(target, QSR, Pc)
    prob, params, variables = cvxpy_projection_problem(QSR, 2, weights=jax.tree.leaves(W))
    ref = solve_reference(prob, params, variables, jax.tree.leaves(target), Pc)
    # the controller to both solvers' tolerances (P, held only by the tiny `reg`, is looser)
    for got, want in zip(jax.tree.leaves(Kw), ref[:4]):
        np.testing.assert_allclose(got, want, atol=1e-4)
    K_ref = dj.LTIController(*ref[:4])
    assert _dist(Kw, target, W) == pytest.approx(_dist(K_ref, target, W), rel=1e-5)
    assert dissipation_ok(Kw, QSR, Pw)
    ones = jax.tree.map(jnp.ones_like, W)
    assert _dist(Kw, target, W) < _dist(Kf, target, W) * (1 - 1e-3)
    assert _dist(Kf, target, ones) < _dist(Kw, target, ones) * (1 - 1e-3)


def test_batched_metric_equals_a_loop(getkey):
    """Under vmap each controller is projected in its own metric (plain loop as reference)."""
    target, Pc, W = _case(getkey(), batch=(3,))
    Kb, Pb = jax.jit(jax.vmap(lambda K, P, W: dj.project(K, QSR, P, metric=W)))(target, Pc, W)
    for i in range(3):
        Ki, Pi = dj.project(index(target, i), QSR, Pc[i], metric=index(W, i))
        for a, b in zip((*jax.tree.leaves(index(Kb, i)), Pb[i]), (*jax.tree.leaves(Ki), Pi)):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
        assert dissipation_ok(Ki, QSR, Pi)


def test_metric_errors(getkey):
    target, Pc, W = _case(getkey())
    bad = [(dj.LTIController(-W.A, W.B, W.C, W.D), "`metric.A`"),
           (eqx.tree_at(lambda M: M.B, W, W.B.at[0, 0].set(jnp.nan)), "`metric.B`"),
           (dj.LTIController(W.A[:1, :1], W.B[:1], W.C[:, :1], W.D), "`metric.A`"),
           ((W.A, W.B, W.C, W.D), "`metric`")]
    for metric, name in bad:
        with pytest.raises(ValueError, match=name):
            dj.project(target, QSR, Pc, metric=metric)


def test_optimizer_metric_reads_the_second_moment(getkey):
    """sqrt(nu) of Adam-like states (also inside a chain), floored per controller; None for
    optimisers without a second moment."""
    K = jax.vmap(lambda k: dj.LTIController.random(k, 2, 2, 2))(jr.split(getkey(), 2))
    g = jax.tree.map(lambda a: a * jnp.arange(a.size, dtype=a.dtype).reshape(a.shape), K)
    for opt in (optax.adam(0.1), optax.rmsprop(0.1),
                optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1))):
        _, state = jax.vmap(opt.update)(g, jax.vmap(opt.init)(K), K)
        W = optimizer_metric(state, K)
        nu = optax.tree_utils.tree_get(state, "nu")
        top = jnp.max(jnp.stack([jnp.max(jnp.sqrt(v), axis=(1, 2)) for v in jax.tree.leaves(nu)]),
                      axis=0)
        for w, v in zip(jax.tree.leaves(W), jax.tree.leaves(nu)):
            want = jnp.maximum(jnp.sqrt(v), METRIC_FLOOR * top[:, None, None])
            np.testing.assert_allclose(w, want, rtol=1e-12)
        assert float(jnp.min(jnp.stack([jnp.min(w) for w in jax.tree.leaves(W)]))) > 0
    for opt in (optax.sgd(0.1), optax.sgd(0.1, momentum=0.9)):
        _, state = jax.vmap(opt.update)(g, jax.vmap(opt.init)(K), K)
        assert optimizer_metric(state, K) is None
