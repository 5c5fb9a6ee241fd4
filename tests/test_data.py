"""`dj.Windows`, the demonstrations: shapes, validation, the feedback sign, pytree use."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import loop_loss, random_windows

import dissil_jax as dj

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)


@pytest.mark.parametrize("n", [None, 3])
def test_sizes_and_the_sign_convention(getkey, n):
    """The properties read the documented axes; the target is -u (negative feedback)."""
    w = random_windows(getkey(), 5, 4, n=n, p=2, m=3, gain=None)
    assert (w.num_windows, w.horizon, w.n_in, w.n_out, w.n_state) == (5, 4, 2, 3, n)
    assert (w.x0 is None) == (n is None)
    np.testing.assert_array_equal(w.target, -np.asarray(w.u))


def test_the_negative_feedback_sign_by_hand():
    """An LQR-like expert u = -k y is imitated by the static controller yhat = k y, whose
    loss is then zero; the opposite sign is charged (2k)^2 |y|^2 per step."""
    k, y = 0.7, jnp.array([[[1.0], [2.0]], [[-1.0], [0.5]]])
    w = dj.Windows(jnp.zeros((2, 1)), y, -k * y)
    same = dj.LTIController(jnp.zeros((1, 1)), jnp.zeros((1, 1)), jnp.zeros((1, 1)),
                            jnp.full((1, 1), k))
    assert float(dj.imitation_loss(same, w)) == 0.0
    flipped = dj.LTIController(same.A, same.B, same.C, -same.D)
    expected = (2 * k) ** 2 * float(jnp.sum(y**2)) / 2
    assert float(dj.imitation_loss(flipped, w)) == pytest.approx(expected, rel=1e-14)
    assert loop_loss(flipped, w) == pytest.approx(expected, rel=1e-14)


def test_at_rest_goes_through_jit_and_tree_maps(getkey):
    """A pytree like any other: it goes through jit and tree maps with x0 still None."""
    w = random_windows(getkey(), 5, 3, n=None, p=2, m=1, gain=None)
    w2 = jax.jit(lambda v: jax.tree.map(lambda a: 2 * a, v))(w)
    assert w2.x0 is None
    np.testing.assert_allclose(w2.y, 2 * np.asarray(w.y))


def test_vmap_over_stacked_windows(getkey):
    """A stack of window sets maps like any pytree: each slice is that set's loss."""
    K = dj.LTIController.random(getkey(), 2, 1, 1, scale=0.5)
    sets = [random_windows(getkey(), 4, 3, n=2, p=1, m=1, gain=None) for _ in range(3)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *sets)
    losses = jax.vmap(lambda w: dj.imitation_loss(K, w))(stacked)
    np.testing.assert_allclose(losses, [loop_loss(K, w) for w in sets], rtol=1e-12)


def test_inputs_are_converted_and_keep_their_dtype():
    w = dj.Windows(np.zeros((2, 1), np.float32), [[[1.0]], [[2.0]]], np.ones((2, 1, 1), np.float32))
    assert all(isinstance(a, jax.Array) for a in (w.x0, w.y, w.u))
    assert w.x0.dtype == jnp.float32 and w.u.dtype == jnp.float32


def test_validation_names_the_argument():
    z = lambda *s: jnp.zeros(s)
    with pytest.raises(ValueError, match="`x0` must have shape"):
        dj.Windows(z(3), z(3, 2, 1), z(3, 2, 1))
    for x0 in (None, z(3, 1)):
        with pytest.raises(ValueError, match="`y`"):
            dj.Windows(x0, z(3, 2), z(3, 2, 1))
        with pytest.raises(ValueError, match="`u`"):
            dj.Windows(x0, z(3, 2, 1), z(3, 2))
        with pytest.raises(ValueError, match="horizon"):
            dj.Windows(x0, z(3, 2, 1), z(3, 4, 1))
        with pytest.raises(ValueError, match="`y` contains NaN"):
            dj.Windows(x0, jnp.full((3, 2, 1), jnp.nan), z(3, 2, 1))
        with pytest.raises(ValueError, match="`u` contains NaN"):
            dj.Windows(x0, z(3, 2, 1), jnp.full((3, 2, 1), jnp.inf))
    with pytest.raises(ValueError, match="`x0`, `y` and `u` must share the window axis"):
        dj.Windows(z(3, 1), z(4, 2, 1), z(3, 2, 1))
    with pytest.raises(ValueError, match="`y` and `u` must share the window axis"):
        dj.Windows(None, z(4, 2, 1), z(3, 2, 1))
    with pytest.raises(ValueError, match="`x0` contains NaN"):
        dj.Windows(jnp.full((3, 1), jnp.nan), z(3, 2, 1), z(3, 2, 1))
    with pytest.raises(ValueError, match="at least one window"):
        dj.Windows(None, z(0, 2, 1), z(0, 2, 1))


@pytest.mark.parametrize("gamma", [1e-3, 1e-4])
def test_realisable_windows_for_tight_gain_bounds(gamma):
    """The expert's projection used the default margin 1e-6, which a gain bound of 1e-3 has
    no room for (its room is gamma^2): the margin is now a thousandth of the room there.
    The expert is certified (`dj.certify`'s float64 check) and fits its windows exactly
    (noise 0: the loss is float64 round-off of outputs of size gamma)."""
    from dissil_jax.experiments.data import realisable_windows

    qsr = dj.QSR.bounded_gain(gamma, n_in=1, n_out=2)
    w, K = realisable_windows(jr.PRNGKey(0), qsr, n_state=2, num_windows=5, horizon=3)
    assert bool(dj.certify(K, qsr).holds)
    assert float(dj.imitation_loss(K, w)) <= 1e-28
