"""Plants and the mass-spring benchmark: dynamics, discretisation, passivity (issue 3)."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
import scipy.linalg
from helpers import min_hermitian_part

import dissil_jax as dj
from dissil_jax.systems import chain_matrices, mass_spring_chain, paper_nonlinear_plant

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)


def test_linear_plant_step_output_and_vmap(getkey):
    A, B = jr.normal(getkey(), (3, 3)), jr.normal(getkey(), (3, 2))
    C, D = jr.normal(getkey(), (4, 3)), jr.normal(getkey(), (4, 2))
    plant = dj.LinearPlant(A, B, C, D)
    assert (plant.n_state, plant.n_in, plant.n_out) == (3, 2, 4)
    x, u = jr.normal(getkey(), (5, 3)), jr.normal(getkey(), (5, 2))
    xn = jax.vmap(plant.step)(x, u)
    y = jax.vmap(plant.output)(x, u)
    np.testing.assert_allclose(xn, x @ A.T + u @ B.T, rtol=1e-12)
    np.testing.assert_allclose(y, x @ C.T + u @ D.T, rtol=1e-12)


def test_sector_plant_matches_formula():
    plant = paper_nonlinear_plant()
    x, u = jnp.array([1.3]), jnp.array([-0.7])
    np.testing.assert_allclose(plant.step(x, u), 0.5 * 1.3 + 0.4 * np.sin(1.3) - 0.7, rtol=1e-14)
    np.testing.assert_allclose(plant.output(x, u), 1.3 + 1.4, rtol=1e-14)
    vec = dj.SectorPlant(np.diag([0.1, 0.2]), np.eye(2), np.eye(2), np.zeros((2, 2)), 0.3)
    x2 = jnp.array([0.5, -2.0])
    np.testing.assert_allclose(vec.step(x2, jnp.zeros(2)),
                               np.array([0.05, -0.4]) + 0.3 * np.sin(np.array([0.5, -2.0])))


@pytest.mark.parametrize("bad", ["B", "C", "D"])
def test_plant_shape_mismatch_names_argument(bad):
    mats = dict(A=np.eye(2), B=np.ones((2, 1)), C=np.ones((1, 2)), D=np.zeros((1, 1)))
    mats[bad] = np.ones((3, 3))
    with pytest.raises(ValueError, match=f"`{bad}`"):
        dj.LinearPlant(**mats)
    with pytest.raises(ValueError, match=f"`{bad}`"):
        dj.SectorPlant(**mats, alpha=0.1)


def test_plant_rejects_nan_and_vector_alpha():
    with pytest.raises(ValueError, match="`A`"):
        dj.LinearPlant(np.nan, 1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="`alpha`"):
        dj.SectorPlant(1.0, 1.0, 1.0, 0.0, [0.1, 0.2])


def test_chain_matrices_hand_built():
    A, B, C, D = chain_matrices([1.0, 2.0, 3.0], [4.0, 5.0, 6.0], 0.5)
    K = np.array([[3.0, -2.0, 0.0], [-2.0, 5.0, -3.0], [0.0, -3.0, 3.0]])
    Cd = np.array([[9.0, -5.0, 0.0], [-5.0, 11.0, -6.0], [0.0, -6.0, 6.0]])
    np.testing.assert_array_equal(A[:3, :3], 0)
    np.testing.assert_array_equal(A[:3, 3:], np.eye(3))
    np.testing.assert_array_equal(A[3:, :3], -K)
    np.testing.assert_array_equal(A[3:, 3:], -Cd)
    np.testing.assert_array_equal(B, np.vstack([np.zeros((3, 3)), np.eye(3)]))
    np.testing.assert_array_equal(C, np.hstack([np.zeros((3, 3)), np.eye(3)]))
    np.testing.assert_array_equal(D, 0.5 * np.eye(3))


def test_mass_spring_chain_sampling_and_zoh():
    ch = mass_spring_chain(jr.PRNGKey(3))
    assert np.all((1 <= ch.k) & (ch.k <= 5)) and np.all((1 <= ch.c) & (ch.c <= 10))
    assert 0.05 <= ch.phi <= 1 and ch.dt == 0.1
    assert (ch.plant.n_state, ch.plant.n_in, ch.plant.n_out) == (6, 3, 3)
    # Zero-order hold by hand: [[Ad, Bd], [0, I]] = expm([[A, B], [0, 0]] dt); D = phi I kept.
    M = np.zeros((9, 9))
    M[:6, :6], M[:6, 6:] = ch.Ac, ch.Bc
    E = scipy.linalg.expm(M * ch.dt)
    np.testing.assert_allclose(ch.plant.A, E[:6, :6], atol=1e-12)
    np.testing.assert_allclose(ch.plant.B, E[:6, 6:], atol=1e-12)
    np.testing.assert_allclose(ch.plant.C, ch.Cc, atol=0)
    np.testing.assert_allclose(ch.plant.D, ch.phi * np.eye(3), atol=0)
    # Reproducible from the key; an integer seed is refused with the fix.
    np.testing.assert_array_equal(mass_spring_chain(jr.PRNGKey(3)).plant.A, ch.plant.A)
    assert not np.allclose(mass_spring_chain(jr.PRNGKey(4)).plant.A, ch.plant.A)
    with pytest.raises(ValueError, match=r"`key`.*PRNGKey\(3\)"):
        mass_spring_chain(3)


def test_tustin_option_adds_half_cb_to_the_feedthrough():
    ch = mass_spring_chain(jr.PRNGKey(3), method="bilinear")
    Mi = np.eye(6) - ch.Ac * ch.dt / 2
    Ad = np.linalg.solve(Mi, np.eye(6) + ch.Ac * ch.dt / 2)
    np.testing.assert_allclose(ch.plant.A, Ad, atol=1e-12)
    Bd = np.linalg.solve(Mi, ch.Bc * ch.dt)
    assert not np.allclose(ch.plant.D, ch.phi * np.eye(3))
    np.testing.assert_allclose(ch.plant.D, ch.phi * np.eye(3) + ch.Cc @ Bd / 2, atol=1e-12)


def test_zoh_chains_are_passive_with_margin():
    """100 seeded draws of the paper's chain: every ZOH plant is certified passive (exact
    KYP SDP) with a positive margin, and its frequency response agrees (He G >= 0)."""
    margins = []
    for seed in range(100):
        ch = mass_spring_chain(jr.PRNGKey(seed), check_passive=False)
        cert = dj.certify(dj.LTIController(*ch.plant.matrices()), dj.QSR.passive(3))
        assert cert.holds, (seed, ch.phi, cert.margin)
        margins.append(cert.margin)
        if seed < 10:
            assert min_hermitian_part(*ch.plant.matrices()) > 0
    assert min(margins) > 1e-4


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tustin_chain_is_passive_frequency_domain(seed):
    """Independent passivity check: He G(e^{jw}) >= 0, with infimum phi at w = pi (Tustin)."""
    ch = mass_spring_chain(jr.PRNGKey(seed), method="bilinear")
    mats = ch.plant.matrices()
    assert dj.certify(dj.LTIController(*mats), dj.QSR.passive(3)).holds
    lam = min_hermitian_part(*mats)
    assert lam >= ch.phi - 1e-9
    np.testing.assert_allclose(lam, ch.phi, rtol=1e-6)  # attained at z = -1 (s = infinity)


def test_zoh_with_tiny_feedthrough_is_rejected():
    """ZOH needs phi above about dt/2: the generator must refuse phi = 0.01 (truly not passive)."""
    kwargs = dict(phi_range=(0.01, 0.01), dt=0.1, method="zoh")
    with pytest.raises(ValueError, match="not certified passive"):
        mass_spring_chain(jr.PRNGKey(0), **kwargs)
    ch = mass_spring_chain(jr.PRNGKey(0), check_passive=False, **kwargs)
    assert min_hermitian_part(*ch.plant.matrices()) < 0


@pytest.mark.parametrize("kwargs, name", [(dict(n_masses=0), "n_masses"), (dict(dt=-0.1), "dt"),
                                          (dict(k_range=(5.0, 1.0)), "k_range")])
def test_chain_bad_arguments(kwargs, name):
    with pytest.raises(ValueError, match=f"`{name}`"):
        mass_spring_chain(jr.PRNGKey(0), **kwargs)
