"""What a user moving between dtypes, transformations and storage formats meets: complex or
list storages, other controller types, strict dtype promotion, pickling, traced rates and
batched outcome names (found by an interoperability audit)."""

import pickle
import warnings

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import dissil_jax as dj


@pytest.fixture
def K():
    return dj.LTIController(jnp.array([[0.5]]), jnp.array([[1.0]]), jnp.array([[0.2]]),
                            jnp.array([[0.5]]))


@pytest.mark.parametrize("call", [
    lambda K, P: dj.certify(K, dj.QSR.passive(1), P=P),
    lambda K, P: dj.certify(K, dj.QSR.passive(1), hint=P),
    lambda K, P: dj.project(K, dj.QSR.passive(1), P_ref=P),
    lambda K, P: dj.kyp_matrix(K.A, K.B, K.C, K.D, dj.QSR.passive(1), P),
])
def test_a_complex_storage_is_refused_not_cast(K, call):
    # numpy would drop the imaginary part with only a ComplexWarning, and `certify` then
    # reported a certificate for a storage that is not one.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"`(P|hint|P_ref)` must be an array of real "
                                             r"numbers, got dtype complex128"):
            call(K, np.array([[0.1 + 5j]]))


def test_storages_given_as_lists_work_everywhere(K):
    q = dj.QSR.passive(1)
    P = dj.certify(K, q).P
    listed = np.asarray(P).tolist()
    assert dj.certify(K, q, P=listed).holds
    assert bool(dj.project(K, q, P_ref=listed).result == dj.Outcome.unchanged)


def test_host_checks_refuse_traced_arrays_by_name(K):
    q = dj.QSR.passive(1)
    with pytest.raises(ValueError, match="`A` is traced"):
        jax.jit(lambda A: dj.kyp_matrix(A, K.B, K.C, K.D, q, np.eye(1)))(K.A)


@pytest.mark.parametrize("fn", [dj.predict, dj.imitation_loss])
def test_predict_and_loss_refuse_other_controller_types(fn):
    import control

    W = dj.Windows(jnp.zeros((2, 1)), jnp.ones((2, 2, 1)), jnp.ones((2, 2, 1)))
    sys = control.ss([[0.5]], [[1.0]], [[1.0]], [[0.0]], True)
    with pytest.raises(ValueError, match="`K` must be a `dj.LTIController`, got StateSpace"):
        fn(sys, W)


def test_from_statespace_names_the_type_it_got(K):
    with pytest.raises(ValueError, match="`sys` must be a `control.StateSpace`.*got "
                                         "LTIController"):
        dj.LTIController.from_statespace(K)


@pytest.mark.parametrize("key", [0, None, np.ones(2)])
def test_random_controller_refuses_a_non_key(key):
    with pytest.raises(ValueError, match="`key` must be a JAX PRNG key"):
        dj.LTIController.random(key, 1, 1, 1)


def test_paper_step_rule_runs_under_strict_dtype_promotion(getkey):
    # The rule's step counter is int32; it is cast to the decay's dtype.
    y = jr.normal(getkey(), (6, 2, 1))
    W = dj.Windows(jr.normal(getkey(), (6, 1)), y, -0.3 * y)
    with jax.numpy_dtype_promotion("strict"):
        res = dj.fit_gd(getkey(), W, learning_rate=0.5, decay=0.99, num_inits=2,
                        max_steps=3)
    plain = dj.fit_gd(getkey(), W, learning_rate=0.5, decay=0.99, num_inits=2, max_steps=3)
    assert res.loss_history.shape == plain.loss_history.shape == (2, 4)
    assert np.all(np.isfinite(np.asarray(res.final_loss)))


def test_an_mlp_result_pickles(getkey):
    y = jr.normal(getkey(), (6, 2, 1))
    W = dj.Windows(jnp.zeros((6, 1)), y, -0.2 * y)
    res = dj.fit_mlp(getkey(), W, hidden=(4, 4), num_inits=2, max_steps=5)
    back = pickle.loads(pickle.dumps(res))
    x = jnp.linspace(-1.0, 1.0, 5)[:, None]
    f = lambda r: jax.vmap(lambda K: jax.vmap(K.mlp)(x))(r.controllers)
    np.testing.assert_array_equal(np.asarray(f(back)), np.asarray(f(res)))


def _leaky(v):
    """A slope-restricted activation defined at module level (picklable)."""
    return jnp.maximum(v, 0.5 * v)


def test_a_ren_with_a_named_activation_pickles_and_a_lambda_does_not():
    """The activation is a static field: pickled by reference, so a top-level function
    round-trips and a lambda cannot (as docs/ren.md says)."""
    K = dj.LTIController.random(jr.PRNGKey(0), 2, 1, 1, scale=0.3)
    R = dj.RENController.from_lti(K, width=2, activation=_leaky)
    back = pickle.loads(pickle.dumps(R))
    assert back.activation is _leaky
    x, u = jnp.ones(2), jnp.ones(1)
    np.testing.assert_array_equal(np.asarray(back(x, u)[1]), np.asarray(R(x, u)[1]))
    with pytest.raises((pickle.PicklingError, AttributeError)):
        pickle.dumps(dj.RENController.from_lti(K, width=2,
                                               activation=lambda v: jnp.maximum(v, 0.0)))


def test_a_traced_rate_gets_a_message_about_rates_not_about_reals():
    with pytest.raises(ValueError, match="`Q` is traced .* a `QSR` is static host data"):
        jax.vmap(lambda q: dj.QSR(q, 3.556, 0.601))(jnp.array([-29.867, -20.0]))


def test_batched_projection_and_certificate_decode_per_member(K):
    # Against a plain loop of single calls; the second member is far outside the set.
    q = dj.QSR.passive(1)
    members = [K, jax.tree.map(lambda a: -50.0 * a, K)]
    Ks = jax.tree.map(lambda *a: jnp.stack(a), *members)
    P = dj.certify(K, q).P  # certifies the first member: "unchanged"; the second "solved"
    names = dj.project(Ks, q, P_ref=P, throw=False).result_names()
    assert names == [dj.project(Ki, q, P_ref=P, throw=False).result_names()
                     for Ki in members]
    assert len(set(names)) == 2  # the members ended differently
    cert = dj.certify(Ks, q)
    assert cert.result_names() == [dj.certify(Ki, q).result_names() for Ki in members]
    assert [n == "solved" for n in cert.result_names()] == list(cert.holds)


@pytest.mark.parametrize("method", ["clarabel", "first_order"])
def test_differentiating_a_projection_names_it_and_the_way_out(K, method):
    q = dj.QSR.passive(1)

    def f(s, stop=False):
        target = jax.tree.map(lambda a: s * a, K)
        if stop:
            target = jax.lax.stop_gradient(target)
        return jnp.sum(dj.project(target, q, method=method).controller.D)

    with pytest.raises(ValueError, match="`dj.project` has no derivative.*stop_gradient"):
        jax.grad(f)(1.0)
    # values, jit and vmap are untouched; a stopped gradient passes
    assert float(jax.jit(f)(1.0)) == pytest.approx(float(f(1.0)), rel=1e-6)
    assert jax.vmap(f)(jnp.array([1.0, 2.0])).shape == (2,)
    assert float(jax.grad(lambda s: f(s, stop=True))(1.0)) == 0.0


def test_a_controller_of_mixed_dtypes_is_refused_by_name():
    with jax.enable_x64(True):
        A = jnp.array([[0.5]], jnp.float32)
        B = C = D = jnp.array([[1.0]], jnp.float64)
        with pytest.raises(ValueError, match="must share one dtype, got float32, float64"):
            dj.LTIController(A, B, C, D)


def test_a_traced_size_asks_for_a_static_argument(K):
    with pytest.raises(ValueError, match="`horizon` must be a positive integer known when "
                                         "tracing .* static argument"):
        jax.jit(lambda h: dj.observability_toeplitz(K, h))(3)


def test_to_statespace_under_jit_names_the_traced_matrix(K):
    with pytest.raises(ValueError, match="`A` is traced .* read on the host"):
        jax.jit(lambda A: dj.LTIController(A, K.B, K.C, K.D).to_statespace())(K.A)


def test_a_sweep_over_a_scalar_asks_for_an_axis_of_values():
    with pytest.raises(ValueError, match="the swept arguments are scalars: a sweep needs a "
                                         "leading axis"):
        dj.sweep(lambda lr: 2.0 * lr)(0.3)
