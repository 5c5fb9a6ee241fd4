"""Deprecated call forms: each still works, gives the new form's result, and warns.

One test per deprecated form. Remove a test together with its form (planned for 0.3.0).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import tree_allclose

import dissil_jax as dj


def _same(a, b) -> bool:
    return tree_allclose(a, b, rtol=0, atol=0)


# -- LTIController.random(key, n, n_in, n_out, scale, dtype) -> (n_state, n_in, n_out, *, ..., key)


@pytest.mark.parametrize("make_key", [jax.random.PRNGKey, jax.random.key], ids=["raw", "typed"])
def test_random_key_first_positional(make_key):
    key = make_key(0)
    with pytest.warns(DeprecationWarning, match=r"LTIController\.random"):
        old = dj.LTIController.random(key, 3, 2, 1)
    assert _same(old, dj.LTIController.random(3, 2, 1, key=key))


def test_random_key_first_positional_scale_and_dtype():
    key = jax.random.PRNGKey(1)
    with pytest.warns(DeprecationWarning, match=r"LTIController\.random"):
        old = dj.LTIController.random(key, 2, 1, 2, 0.7, jnp.float32)
    new = dj.LTIController.random(2, 1, 2, scale=0.7, dtype=jnp.float32, key=key)
    assert old.A.dtype == jnp.float32 and _same(old, new)


def test_random_key_first_with_keyword_scale():
    key = jax.random.PRNGKey(2)
    with pytest.warns(DeprecationWarning, match=r"LTIController\.random"):
        old = dj.LTIController.random(key, 2, 2, 2, scale=0.3)
    assert _same(old, dj.LTIController.random(2, 2, 2, scale=0.3, key=key))


def test_random_old_keyword_n():
    key = jax.random.PRNGKey(3)
    with pytest.warns(DeprecationWarning, match=r"LTIController\.random"):
        old = dj.LTIController.random(key=key, n=2, n_in=1, n_out=1, scale=0.5)
    assert _same(old, dj.LTIController.random(2, 1, 1, scale=0.5, key=key))


def test_random_key_first_under_vmap():
    """The trainers' form: `jax.vmap(lambda k: LTIController.random(k, n, p, m, s, dtype))`."""
    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    with pytest.warns(DeprecationWarning, match=r"LTIController\.random"):
        old = jax.vmap(lambda k: dj.LTIController.random(k, 2, 1, 1, 1.0, None))(keys)
    new = jax.vmap(lambda k: dj.LTIController.random(2, 1, 1, scale=1.0, key=k))(keys)
    assert old.batch_shape == (4,) and _same(old, new)


def test_random_new_form_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dj.LTIController.random(2, 1, 1, scale=0.5, key=jax.random.PRNGKey(0))
        dj.LTIController.random(n_state=2, n_in=1, n_out=1, key=jax.random.PRNGKey(0))


def test_random_old_form_keeps_its_errors():
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="`n_state`"):
        dj.LTIController.random(jax.random.PRNGKey(0), 0, 1, 1)
    with pytest.raises(TypeError):
        dj.LTIController.random(jax.random.PRNGKey(0), 2, 1)  # missing n_out


# -- QSR.bounded_gain(gamma, n_out, n_in) -> bounded_gain(gamma, *, n_in, n_out) -------------


def test_bounded_gain_positional_sizes():
    with pytest.warns(DeprecationWarning, match=r"bounded_gain"):
        old = dj.QSR.bounded_gain(1.5, 3, 2)  # old meaning: n_out=3, n_in=2
    new = dj.QSR.bounded_gain(1.5, n_in=2, n_out=3)
    assert old == new and old.S.shape == (3, 2)
    np.testing.assert_array_equal(old.R, 2.25 * np.eye(2))


def test_bounded_gain_positional_n_out_keyword_n_in():
    with pytest.warns(DeprecationWarning, match=r"bounded_gain"):
        old = dj.QSR.bounded_gain(0.5, 4, n_in=1)
    assert old == dj.QSR.bounded_gain(0.5, n_in=1, n_out=4)


def test_bounded_gain_keyword_form_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q = dj.QSR.bounded_gain(2.0, n_out=3, n_in=2)  # keywords in either order
    assert q.S.shape == (3, 2)


def test_bounded_gain_old_form_keeps_its_errors():
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match="`gamma`"):
        dj.QSR.bounded_gain(-1.0, 1, 1)
    with pytest.raises(TypeError):
        dj.QSR.bounded_gain(1.0, 1, 1, 1)
    with pytest.raises(TypeError):
        dj.QSR.bounded_gain(1.0, 2, n_out=2)  # n_out twice


# -- stabilising_qsr(plant_qsr, alpha, margins) -> stabilising_qsr(plant_qsr, *, alpha, margins)


def test_stabilising_qsr_positional_alpha_and_margins():
    plant = dj.QSR(-1.0, 3.556, 29.333)
    with pytest.warns(DeprecationWarning, match="stabilising_qsr"):
        old = dj.stabilising_qsr(plant, 2.0, (0.399, 0.534))
    assert old == dj.stabilising_qsr(plant, alpha=2.0, margins=(0.399, 0.534))


def test_stabilising_qsr_positional_alpha():
    plant = dj.QSR(-1.0, 3.556, 29.333)
    with pytest.warns(DeprecationWarning, match="stabilising_qsr"):
        old = dj.stabilising_qsr(plant, 0.5, margins=(0.1, 0.2))
    assert old == dj.stabilising_qsr(plant, alpha=0.5, margins=(0.1, 0.2))


def test_stabilising_qsr_keyword_form_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dj.stabilising_qsr(dj.QSR.passive(1), alpha=1.0, margins=(0.1, 0.1))
        dj.stabilising_qsr(plant_qsr=dj.QSR.passive(1))
    with pytest.raises(TypeError):
        dj.stabilising_qsr(dj.QSR.passive(1), 1.0, alpha=1.0)  # alpha twice


# -- the projection's status API of 0.1 -----------------------------------------------------


def test_project_with_status_matches_project_and_warns():
    qsr = dj.QSR.passive(1)
    K = dj.LTIController.random(2, 1, 1, scale=1.0, key=jax.random.PRNGKey(3))
    Kp, P = dj.project(K, qsr)
    with pytest.warns(DeprecationWarning, match="project_with_status"):
        Kw, Pw, status = dj.project_with_status(K, qsr)
    assert tree_allclose((Kw, Pw), (Kp, P), rtol=0, atol=0)
    with pytest.warns(DeprecationWarning, match="Status"):
        Status = dj.Status
    assert int(status) == Status.SOLVED
    with pytest.warns(DeprecationWarning):
        _, _, again = dj.project_with_status(Kp, qsr, P)  # certified by P: no solve
    assert int(again) == Status.UNCHANGED
    with pytest.warns(DeprecationWarning):
        _, _, bad = dj.project_with_status(K, dj.QSR(-1.0, 0.0, -1.0))  # never raises
    assert int(bad) == Status.INFEASIBLE


def test_unknown_module_attribute_still_raises():
    with pytest.raises(AttributeError, match="no_such_name"):
        dj.no_such_name  # noqa: B018
