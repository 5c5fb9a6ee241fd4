"""`dj.LTIController`: one step, random draws, state-space round trips, shapes and batches."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import tree_allclose

import dissil_jax as dj


def test_call_is_one_step(getkey):
    K = dj.LTIController.random(getkey(), 3, 2, 1, scale=1.0)
    x, u = jnp.arange(3.0), jnp.array([1.0, -2.0])
    xn, y = K(x, u)
    np.testing.assert_allclose(xn, K.A @ x + K.B @ u)
    np.testing.assert_allclose(y, K.C @ x + K.D @ u)
    assert (K.n_state, K.n_in, K.n_out) == (3, 2, 1)


def test_random_scale_and_determinism(getkey):
    key = getkey()
    K1 = dj.LTIController.random(key, 20, 10, 10, scale=0.3)
    K2 = dj.LTIController.random(key, 20, 10, 10, scale=0.3)
    assert tree_allclose(K1, K2)
    assert 0.25 < float(jnp.std(K1.A)) < 0.35


def test_statespace_round_trip(getkey):
    K = dj.LTIController.random(getkey(), 2, 3, 2)
    sys = K.to_statespace(dt=0.1)
    assert isinstance(sys, control.StateSpace) and sys.dt == 0.1
    assert tree_allclose(dj.LTIController.from_statespace(sys), K)
    with pytest.raises(ValueError, match="`sys`"):
        dj.LTIController.from_statespace(control.ss([[-1.0]], [[1.0]], [[1.0]], [[0.0]]))


def test_statespace_conversions_refuse_other_inputs(getkey):
    """A transfer function used to fail with "'TransferFunction' object has no attribute
    'A'"; `dt` of a continuous or unspecified timebase gave no discrete-time system."""
    tf = control.tf([1.0, 0.5], [1.0, -0.5], 0.1)
    for sys in (tf, [tf], 3.0):
        with pytest.raises(ValueError, match=r"`sys` must be a `control.StateSpace`.*"
                                             r"control.ss\(sys\)"):
            dj.LTIController.from_statespace(sys)
    assert dj.LTIController.from_statespace(control.ss(tf)).n_state == 1  # the suggestion
    K = dj.LTIController.random(getkey(), 2, 1, 1)
    for dt in (0, 0.0, -0.1, None, False, np.nan, "0.1"):
        with pytest.raises(ValueError, match="`dt`"):
            K.to_statespace(dt)
    assert K.to_statespace(True).dt is True and K.to_statespace(1).dt == 1


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match="`B`"):
        dj.LTIController(np.eye(2), np.ones((3, 1)), np.ones((1, 2)), np.ones((1, 1)))
    with pytest.raises(ValueError, match="`D`"):
        dj.LTIController(np.eye(2), np.ones((2, 1)), np.ones((1, 2)), np.ones((2, 1)))
    with pytest.raises(ValueError, match="`A`"):
        dj.LTIController(np.full((2, 2), np.nan), np.ones((2, 1)), np.ones((1, 2)), np.ones((1, 1)))
    with pytest.raises(ValueError, match="`n_state`"):
        dj.LTIController.random(jax.random.PRNGKey(0), 1.5, 1, 1)


def test_batched_controllers_via_vmap(getkey):
    keys = jax.random.split(getkey(), 4)
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, 2, 1, 1))(keys)
    assert Ks.batch_shape == (4,)
    x = jnp.ones((4, 2))
    u = jnp.ones((4, 1))
    xn, y = jax.vmap(lambda K, x, u: K(x, u))(Ks, x, u)
    for i in range(4):
        Ki = jax.tree.map(lambda a: a[i], Ks)
        np.testing.assert_allclose(y[i], Ki(x[i], u[i])[1])


@pytest.mark.parametrize(
    "mats, name",
    [
        (([[True]], [[1.0]], [[1.0]], [[1.0]]), "`A`"),  # boolean dtype
        (([[1.0]], [[1.0]], np.array([[1j]]), [[1.0]]), "`C`"),  # complex dtype
        (([[1.0]], [[1.0]], [[1.0]], "one"), "`D`"),  # not numeric
        ((np.ones(1), [[1.0]], [[1.0]], [[1.0]]), "`A`"),  # 1-d
        (([[1.0]], 1.0, [[1.0]], [[1.0]]), "`B`"),  # scalar
        (([[1.0]], [[1.0]], [[np.nan]], [[1.0]]), "`C`"),
        (([[1.0]], [[1.0]], [[1.0]], [[-np.inf]]), "`D`"),
        ((np.ones((2, 1, 1)), np.ones((3, 1, 1)), np.ones((2, 1, 1)), np.ones((2, 1, 1))), "`B`"),
        ((np.ones((2, 1, 1)), np.ones((2, 1, 1)), np.ones((2, 1, 1)), np.ones((1, 1))), "`D`"),
    ],
)
def test_invalid_matrices_name_the_argument(mats, name):
    with pytest.raises(ValueError, match=name):
        dj.LTIController(*mats)


def test_integer_matrices_take_the_floats_dtype():
    """Integer entries are cast, as `Windows` and `QSR` cast them (they were refused): to
    the other matrices' float dtype, or to JAX's default float when all are integers."""
    K = dj.LTIController(np.eye(2, dtype=int), np.ones((2, 1), np.float32), [[1, 0]], [[0]])
    assert {M.dtype for M in (K.A, K.B, K.C, K.D)} == {np.dtype(np.float32)}
    np.testing.assert_array_equal(K.A, np.eye(2))
    K = dj.LTIController([[1]], [[2]], [[3]], [[0]])
    assert K.A.dtype == jnp.result_type(float) and float(K.B[0, 0]) == 2.0


def test_random_size_errors_name_the_argument(getkey):
    with pytest.raises(ValueError, match="`n_in`"):
        dj.LTIController.random(getkey(), 2, 1.5, 1)
    with pytest.raises(ValueError, match="`n_out`"):
        dj.LTIController.random(getkey(), 2, 1, -1)
    with pytest.raises(TypeError):
        dj.LTIController.random(2, 1, 1)  # `key` is required (first)
    with pytest.raises(TypeError):
        dj.LTIController.random(getkey(), 2, 1, 1, 0.5)  # `scale` is keyword-only


def test_random_signature_takes_the_key_first():
    import inspect

    sig = inspect.signature(dj.LTIController.random)
    assert list(sig.parameters) == ["key", "n_state", "n_in", "n_out", "scale", "dtype"]
    kinds = {name: p.kind for name, p in sig.parameters.items()}
    assert kinds["key"] is inspect.Parameter.POSITIONAL_OR_KEYWORD
    assert all(kinds[k] is inspect.Parameter.KEYWORD_ONLY for k in ("scale", "dtype"))


def _batch(getkey, shape, n=2, p=1, m=1):
    keys = jax.random.split(getkey(), int(np.prod(shape)))
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, n, p, m, scale=0.6))(keys)
    return jax.tree.map(lambda a: a.reshape(shape + a.shape[1:]), Ks)


@pytest.mark.parametrize("shape", [(3,), (2, 3)])
def test_batched_to_statespace_equals_loop(getkey, shape):
    Ks = _batch(getkey, shape, n=2, p=3, m=2)
    systems = Ks.to_statespace(dt=0.1)
    assert isinstance(systems, np.ndarray) and systems.dtype == object
    assert systems.shape == shape
    for idx in np.ndindex(*shape):
        ref = jax.tree.map(lambda a: a[idx], Ks).to_statespace(dt=0.1)
        sys = systems[idx]
        assert isinstance(sys, control.StateSpace) and sys.dt == 0.1
        for name in "ABCD":
            np.testing.assert_array_equal(getattr(sys, name), getattr(ref, name))
    # from_statespace inverts it, from the array and from a nested list
    assert tree_allclose(dj.LTIController.from_statespace(systems), Ks, rtol=0, atol=0)
    assert tree_allclose(dj.LTIController.from_statespace(systems.tolist()), Ks, rtol=0, atol=0)


def test_from_statespace_batch_errors(getkey):
    a = dj.LTIController.random(getkey(), 2, 1, 1).to_statespace()
    b = dj.LTIController.random(getkey(), 3, 1, 1).to_statespace()
    with pytest.raises(ValueError, match="`sys`"):
        dj.LTIController.from_statespace([a, b])  # different sizes
    with pytest.raises(ValueError, match="`sys`"):
        dj.LTIController.from_statespace([[a, a], [a]])  # ragged
    with pytest.raises(ValueError, match="`sys`"):
        dj.LTIController.from_statespace([])
    with pytest.raises(ValueError, match="`sys`"):
        dj.LTIController.from_statespace([a, control.ss([[-1.0]], [[1.0]], [[1.0]], [[0.0]])])


def test_dtype_is_kept_and_cast(getkey):
    K = dj.LTIController.random(getkey(), 2, 1, 1, dtype=jnp.float32)
    assert all(M.dtype == jnp.float32 for M in (K.A, K.B, K.C, K.D))
    K64 = K.astype(jnp.float64)
    assert all(M.dtype == jnp.float64 for M in (K64.A, K64.B, K64.C, K64.D))
    assert tree_allclose(K64, K, rtol=0, atol=0)  # float32 -> float64 is exact
    sys = K.to_statespace()
    assert sys.A.dtype == np.float64 and sys.dt is True


def test_random_static_controllers_and_bad_scales():
    K = dj.LTIController.random(jax.random.PRNGKey(0), 0, 2, 3, scale=0.5)
    assert (K.n_state, K.n_in, K.n_out) == (0, 2, 3) and K.D.shape == (3, 2)
    assert dj.certify(K, dj.QSR.bounded_gain(100.0, n_in=2, n_out=3)).holds  # static: Phi(D)
    for bad in (-1.0, float("nan"), float("inf"), np.ones(2)):
        with pytest.raises(ValueError, match="`scale`"):
            dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1, scale=bad)
    with pytest.raises(ValueError, match="`n_state`"):
        dj.LTIController.random(jax.random.PRNGKey(0), -1, 1, 1)
    # a traced scale (a sweep over initial scales) still draws
    draw = jax.vmap(lambda s: dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1, scale=s).A)
    np.testing.assert_allclose(draw(jnp.array([1.0, 2.0]))[1], 2 * draw(jnp.array([1.0, 2.0]))[0])
