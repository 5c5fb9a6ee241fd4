"""Supply rates with an indefinite Q (a positive eigenvalue): the linearised inner
approximation, the projection, PGD, ICO, the certificates and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dissipation_matrix, dissipation_ok, index, random_windows

import dissil_jax as dj
from dissil_jax.internal import ConvexifiedLMI, static_point

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)


def _random_rate(rng, m):
    """A feasible rate whose Q has both signs (m >= 2) or is positive (m = 1).

    R is chosen so that a random static gain D0 is strictly dissipative
    (D0'QD0 + D0'S + S'D0 + R = 0.1 I + G G'), so the set of controllers is not empty."""
    p = m
    V = np.linalg.qr(rng.standard_normal((m, m)))[0]
    lam = rng.uniform(0.2, 1.5, m) * (1 if m == 1 else np.where(np.arange(m) % 2, -1, 1))
    Q = V @ np.diag(lam) @ V.T
    S = rng.standard_normal((m, p)) * 0.5
    D0 = rng.standard_normal((m, p)) * 0.5
    G = rng.standard_normal((p, p)) * 0.3
    R = -(D0.T @ Q @ D0 + D0.T @ S + S.T @ D0) + 0.1 * np.eye(p) + G @ G.T
    return dj.QSR(Q, S, (R + R.T) / 2)


def _cases(count=50):
    """`count` (rate, n_state, key) triples over m = p in {1, 2, 3} and n in {1, 3, 6}."""
    rng = np.random.default_rng(2025)
    return [(_random_rate(rng, m), n, jax.random.PRNGKey(i))
            for i, (m, n) in enumerate((m, n) for _ in range(6) for m in (1, 2, 3)
                                       for n in (1, 3, 6))][:count]


def _assert_certified(K, qsr, P):
    # The float64 eigenvalue check of the exact KYP matrix at the returned P ...
    assert dj.certify(K, qsr, P=P).holds
    # ... and the definition-based storage test (one simulated step, no library code).
    assert dissipation_ok(K, qsr, P, python_control=False)


def test_linearisation_is_an_inner_approximation_exact_at_h0():
    """At H0 = H the convexified matrix's Schur complement is the KYP matrix of the
    definition; elsewhere it exceeds it by (H - H0)'Q+(H - H0) >= 0 (an inner bound)."""
    rng = np.random.default_rng(0)
    for m, n in ((1, 1), (2, 3), (3, 2)):
        qsr = _random_rate(rng, m)
        lmi = ConvexifiedLMI(n, m, m, qsr)
        A, B = 0.3 * rng.standard_normal((n, n)), rng.standard_normal((n, m))
        C, D = rng.standard_normal((m, n)), rng.standard_normal((m, m))
        P = np.eye(n) + 0.1 * np.ones((n, n))
        K = dj.LTIController(A, B, C, D)
        exact = dissipation_matrix(K, qsr, P)  # the KYP matrix, from the definition
        x = lmi.layout.pack(A, B, C, D, P)
        T = np.eye(lmi.N)
        T[-n:, -n:] = np.linalg.inv(P)  # undo the congruence by diag(I, I, I, P~) at P~ = P
        k = n + m

        def schur(H0):
            M = T @ lmi.evaluate(x, P, H0) @ T
            return M[:k, :k] - M[:k, k:] @ np.linalg.solve(M[k:, k:], M[:k, k:].T)

        scale = 1 + np.abs(exact).max()
        # round-off of a few products of O(1) matrices and one small solve
        assert np.allclose(schur((C, D)), exact, atol=1e-10 * scale)
        C0, D0 = C + rng.standard_normal(C.shape), D + rng.standard_normal(D.shape)
        H, H0 = np.hstack([C, D]), np.hstack([C0, D0])
        Qp = np.clip(np.linalg.eigvalsh(qsr.Q), 0, None)
        V = np.linalg.eigh(qsr.Q)[1]
        gap = (H - H0).T @ (V * Qp) @ V.T @ (H - H0)
        assert np.allclose(schur((C0, D0)) - exact, gap, atol=1e-9 * scale)


def test_projection_of_50_random_indefinite_rates():
    """Every projection is certified (two independent checks); projecting the certified
    controller with its own P returns it exactly."""
    for qsr, n, key in _cases(50):
        m = qsr.n_out
        K = dj.LTIController.random(key, n, m, m)
        K_proj, P = dj.project(K, qsr)
        _assert_certified(K_proj, qsr, P)
        again = dj.project(K_proj, qsr, P)
        assert bool(again.result == dj.Outcome.unchanged)
        for name in "ABCD":
            assert np.array_equal(getattr(again[0], name), getattr(K_proj, name))


def test_projection_keeps_an_already_certified_target():
    """A controller certified under an indefinite Q (found by `certify`) projects onto itself."""
    rng = np.random.default_rng(1)
    for m in (1, 2, 3):
        qsr = _random_rate(rng, m)
        K = dj.project(dj.LTIController.random(jax.random.PRNGKey(m), 2, m, m), qsr)[0]
        cert = dj.certify(K, qsr)
        assert cert.holds
        proj = dj.project(K, qsr, cert.P)
        assert bool(proj.result == dj.Outcome.unchanged)
        assert all(np.array_equal(getattr(proj[0], s), getattr(K, s)) for s in "ABCD")


def test_far_target_falls_back_and_is_certified():
    """A target far from the set (its own linearisation can leave the set empty) still
    gets a certified projection, via the static fallback point if needed; `K_ref` works."""
    qsr = dj.QSR(np.diag([1.0, -0.5]), 0.5 * np.eye(2), -0.2 * np.eye(2))
    K = dj.LTIController.random(jax.random.PRNGKey(3), 3, 2, 2)
    K = jax.tree.map(lambda M: 20.0 * M, K)
    K_proj, P = dj.project(K, qsr)
    _assert_certified(K_proj, qsr, P)
    K_ref, P_ref = K_proj, P
    K2 = jax.tree.map(lambda M: M + 0.05, K_ref)
    K2_proj, P2 = dj.project(K2, qsr, P_ref, K_ref=K_ref)
    _assert_certified(K2_proj, qsr, P2)


@pytest.mark.parametrize("D", [0.0, 0.1, -0.1])
def test_targets_inside_the_forbidden_gain_gap_are_projected(D):
    """$w = \\hat y^2 - 0.1\\hat u^2$: the dissipative static gains are $|D|\\ge0.32$,
    two components, and the depth of a static point grows with $|D|$ without bound. A
    target with $|D|$ in the gap gets a certified projection in the component nearest
    it, from a static fallback point of moderate size (the deepest one, $|D|\\approx10^8$,
    left no projection certifiable)."""
    qsr = dj.QSR(1.0, 0.0, -0.1)
    for A in (0.5, 1.2):
        K = dj.LTIController(np.array([[A]]), np.ones((1, 1)), np.ones((1, 1)),
                             np.array([[D]]))
        K_proj, P = dj.project(K, qsr)
        _assert_certified(K_proj, qsr, P)
        if D:
            assert np.sign(float(K_proj.D[0, 0])) == np.sign(D)


def test_static_fallback_point_is_deep_and_near_its_target():
    qsr = dj.QSR(1.0, 0.0, -0.1)
    for near, sign in ((None, None), (np.array([[0.2]]), 1.0), (np.array([[-0.2]]), -1.0)):
        D0 = static_point(qsr, near=near)
        d = float(D0[0, 0])
        assert (d**2 - 0.1) / (1 + d**2) > 0.45  # at least half the supremum 1, ...
        assert abs(d) < 10.0  # ... and no farther out than needed
        if sign is not None:
            assert np.sign(float(D0[0, 0])) == sign


def test_batched_projection_matches_a_python_loop():
    qsr = _random_rate(np.random.default_rng(4), 2)
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, 3, 2, 2))(
        jax.random.split(jax.random.PRNGKey(5), 4))
    Kb, Pb = dj.project(Ks, qsr)
    for i in range(4):
        Ki, Pi = dj.project(index(Ks, i), qsr)
        # the host solves each row with the same numbers (no BLAS reduction across rows)
        for name in "ABCD":
            np.testing.assert_array_equal(getattr(Kb, name)[i], getattr(Ki, name))
        np.testing.assert_array_equal(Pb[i], Pi)


def test_pgd_and_ico_under_indefinite_rates(getkey):
    """A few random rates, trained a handful of steps: every controller certified, ICO's
    loss never increases."""
    for qsr, n, _ in _cases(50)[::12]:
        m = qsr.n_out
        w = random_windows(getkey(), N=8, n=n, p=m, m=m)
        for fit in (dj.fit_pgd, dj.fit_ico):
            res = fit(getkey(), w, qsr, num_inits=2, max_steps=3, throw=False)
            assert bool(jnp.all(res.certified)), res.result_names()
            for i in range(2):
                _assert_certified(index(res.controllers, i), qsr, res.P[i])
            if fit is dj.fit_ico:
                h = np.asarray(res.loss_history)
                d = np.diff(h, axis=1)
                assert np.all(d[np.isfinite(d)] <= 0.0)


def test_certify_and_theorem1_with_indefinite_q():
    # A static gain D: the KYP matrix is diag(A'PA - P, B'PB - w(D)); w(D) = D'QD + 2SD + R.
    qsr = dj.QSR(0.5, 0.5, -0.1)  # w(D) = 0.5 D^2 + D - 0.1
    static = lambda d: dj.LTIController(0.5 * np.eye(1), 0.1 * np.ones((1, 1)), np.zeros((1, 1)),
                                        [[d]])
    assert dj.certify(static(0.5), qsr).holds  # w = 0.525 > 0
    assert not dj.certify(static(0.05), qsr).holds  # w = -0.049 < 0
    assert dj.certify(static(-3.0), qsr).holds  # w = 1.4 > 0: only an indefinite rate allows it
    # stabilising_qsr of an input-strictly-passive plant asks for Q2 > 0 ...
    plant = dj.QSR(0.0, 0.5, -0.6)
    ctrl = dj.stabilising_qsr(plant, alpha=2.0, margins=(0.1, 0.2))
    np.testing.assert_allclose(ctrl.Q, [[0.2]])
    np.testing.assert_allclose(ctrl.R, [[-0.05]])
    cert = dj.closed_loop_certificate(plant, ctrl)
    assert cert.holds
    # ... and Theorem 1 fails when the controller's Q2 exceeds the plant's input excess.
    assert not dj.closed_loop_certificate(plant, dj.QSR(0.7, 0.5, -0.05)).holds


def test_linear_example_plant_is_stabilised():
    """Plant 0 of the paper's linear example, its own indefinite-Q controller rate, ICO."""
    from dissil_jax.experiments import lti_spectral_radius, protocol

    spec = protocol.example_spec("linear")
    plant, _, windows, (key, _, _) = protocol.training_data(spec, 0, 0, "initial", 25)
    plant_qsr = dj.passivity_indices(plant)
    rho, nu = -plant_qsr.Q[0, 0], -plant_qsr.R[0, 0]
    qsr = dj.stabilising_qsr(plant_qsr, alpha=1.0, margins=(0.1 * rho, 0.1 * nu))
    assert np.linalg.eigvalsh(qsr.Q)[-1] > 0
    assert dj.closed_loop_certificate(plant_qsr, qsr).holds
    res = dj.fit_ico(key, windows, qsr, num_inits=2, max_steps=3, throw=False)
    assert bool(jnp.all(res.certified))
    for i in range(2):
        assert dj.certify(index(res.controllers, i), qsr, P=res.P[i]).holds
    assert np.all(lti_spectral_radius(plant, res.controllers) < 1)


def test_bad_input():
    # Phi = [[Q, S], [S', R]] has one positive eigenvalue but p = 2: no controller exists.
    bad = dj.QSR(np.diag([1.0, -1.0]), np.zeros((2, 2)), -np.eye(2))
    K = dj.LTIController.random(jax.random.PRNGKey(0), 2, 2, 2)
    with pytest.raises(ValueError, match="`qsr` is infeasible"):
        dj.project(K, bad)
    w = random_windows(jax.random.PRNGKey(1), N=4, n=2, p=2, m=2)
    for fit in (dj.fit_pgd, dj.fit_ico):
        with pytest.raises(ValueError, match="`qsr` is infeasible"):
            fit(jax.random.PRNGKey(0), w, bad)
    with pytest.raises(ValueError, match="`Q` must be symmetric"):
        dj.QSR([[1.0, 0.3], [0.0, -1.0]], np.eye(2), np.eye(2))
    good = dj.QSR(np.diag([1.0, -1.0]), 0.5 * np.eye(2), -0.1 * np.eye(2))
    with pytest.raises(ValueError, match="`qsr.Q`.*fit_pgd"):
        dj.fit_direct(jax.random.PRNGKey(0), w, good)
    with pytest.raises(ValueError, match="`K_ref.A`"):
        dj.project(K, good, K_ref=dj.LTIController.random(jax.random.PRNGKey(0), 1, 2, 2))


@pytest.mark.parametrize("gamma", [1e-6, 1e-8])
def test_small_gain_bounds_are_feasible(gamma):
    """Phi = diag(-1, gamma^2): one positive eigenvalue, far below Q's size. The count is
    taken after balancing the blocks by a congruence (which keeps the inertia); compared
    with the largest eigenvalue, gamma^2 looked like round-off and the rate was refused."""
    qsr = dj.QSR.bounded_gain(gamma, n_in=1, n_out=1)
    w = random_windows(jax.random.PRNGKey(1), N=6, n=2, p=1, m=1)
    res = dj.fit_direct(jax.random.PRNGKey(0), w, qsr, num_inits=2, max_steps=3)
    for i in range(2):  # independently of the trainer's storage
        assert dj.certify(index(res.controllers, i), qsr).holds
    # PGD's margin eps is absolute: the rate's room (gamma^2) is named, not "infeasible"
    with pytest.raises(ValueError, match="`eps` = 1e-06 is not below the supply rate's room"):
        dj.fit_pgd(jax.random.PRNGKey(0), w, qsr, num_inits=2, max_steps=3)
    # a tiny negative R is still infeasible (inertia (0, 2)), whatever its size
    with pytest.raises(ValueError, match="`qsr` is infeasible"):
        dj.fit_direct(jax.random.PRNGKey(0), w, dj.QSR(-1.0, 0.0, -gamma**2))
