"""`dj.certify`: the KYP certificate against python-control, frequency responses and the definition."""

import warnings

import control
import cvxpy as cp
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    dissipation_matrix,
    dissipation_ok,
    freq_response,
    frequency_supply_min,
    min_hermitian_part,
)

import dissil_jax as dj
import dissil_jax.internal as dji
from dissil_jax.internal import certify_fast, certify_sdp

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)


def _first_order(a, b, c, d):
    return dj.LTIController([[a]], [[b]], [[c]], [[d]])


@pytest.mark.parametrize("delta, expected", [(1e-7, True), (-1e-7, False), (1e-4, True),
                                             (-1e-4, False)])
def test_nearly_lossless_first_order(delta, expected):
    # G(z) = d + 1/(z - 0.5) is passive iff d >= 1/1.5 (worst case at z = -1).
    K = _first_order(0.5, 1.0, 1.0, 1 / 1.5 + delta)
    cert = dj.certify(K, dj.QSR.passive(1))
    assert cert.holds is expected
    assert (cert.margin > 0) is expected
    if expected:
        assert dissipation_ok(K, dj.QSR.passive(1), cert.P)
    elif np.all(np.isfinite(cert.P)):
        assert not dissipation_ok(K, dj.QSR.passive(1), cert.P, rel_margin=0.0)


def _random_stable(rng, n, m):
    A = rng.normal(size=(n, n))
    A *= rng.uniform(0.3, 0.95) / max(abs(np.linalg.eigvals(A)))
    return A, rng.normal(size=(n, m)), rng.normal(size=(m, n)), rng.normal(size=(m, m))


def test_agrees_with_python_control_passivity():
    """Passive and non-passive systems by construction; python-control and certify agree.

    Shifting D by c I shifts the Hermitian part of G(e^jw) by exactly c, so
    D -> D - (h_min - delta) I is passive (delta > 0) or not (delta < 0) with a clear margin.
    """
    rng = np.random.default_rng(0)
    verdicts = []
    for trial in range(12):
        A, B, C, D = _random_stable(rng, 2, 2)
        expected = trial % 2 == 0
        delta = rng.uniform(0.05, 0.5) * (1 if expected else -1)
        D = D - (min_hermitian_part(A, B, C, D) - delta) * np.eye(2)
        assert bool(min_hermitian_part(A, B, C, D) > 0) is expected
        ref = bool(control.ispassive(control.ss(A, B, C, D, True)))
        K = dj.LTIController(A, B, C, D)
        cert = dj.certify(K, dj.QSR.passive(2))
        assert ref is expected and cert.holds is expected
        if expected:
            assert dissipation_ok(K, dj.QSR.passive(2), cert.P)
        verdicts.append(cert.holds)
    assert sum(verdicts) == 6 and len(verdicts) - sum(verdicts) == 6


def test_input_feedforward_index_matches_python_control():
    sys = control.ss([[0.5, 0.1], [0.0, -0.3]], [[1.0], [0.5]], [[1.0, 0.2]], [[1.2]], True)
    nu = control.get_input_ff_index(sys)
    K = dj.LTIController.from_statespace(sys)
    assert dj.certify(K, dj.QSR.degenerate_conic(nu - 1e-4, dim=1)).holds
    assert not dj.certify(K, dj.QSR.degenerate_conic(nu + 1e-4, dim=1)).holds


def test_bounded_gain_matches_hinf_norm():
    rng = np.random.default_rng(3)
    A, B, C, D = _random_stable(rng, 3, 2)
    sys = control.ss(A, B, C, D, True)
    w = np.linspace(0, np.pi, 4001)
    gain = max(np.linalg.svd(sys(np.exp(1j * wi)), compute_uv=False)[0] for wi in w)
    K = dj.LTIController(A, B, C, D)
    qsr = dj.QSR.bounded_gain(gain * 1.001, n_in=2, n_out=2)
    cert = dj.certify(K, qsr)
    assert cert.holds and dissipation_ok(K, qsr, cert.P)
    assert not dj.certify(K, dj.QSR.bounded_gain(gain * 0.999, n_in=2, n_out=2)).holds


def _random_qsr(rng, p, m):
    """A general supply rate: indefinite Q and R, non-symmetric rectangular S."""
    Q, R = rng.normal(size=(m, m)), rng.normal(size=(p, p))
    return dj.QSR(Q + Q.T, rng.normal(size=(m, p)), R + R.T)


@pytest.mark.parametrize("n, p, m", [(1, 1, 1), (3, 2, 1), (2, 1, 3)])
def test_kyp_matrix_is_the_dissipation_form(n, p, m):
    """dj.kyp_matrix equals the matrix of V(Ax+Bu) - V(x) - w(u, Cx+Du) (by polarisation)."""
    rng = np.random.default_rng(n + 10 * p + 100 * m)
    qsr = _random_qsr(rng, p, m)
    mats = [rng.normal(size=s) for s in ((n, n), (n, p), (m, n), (m, p))]
    G = rng.normal(size=(n, n))
    P = G @ G.T + np.eye(n)
    K = dj.LTIController(*mats)
    H = dissipation_matrix(K, qsr, P)
    np.testing.assert_allclose(dj.kyp_matrix(*mats, qsr, P), H, rtol=1e-12,
                               atol=1e-12 * np.abs(H).max())
    # batched: a stack of controllers gives the stack of matrices
    stack = [np.stack([M, 2 * M, -M]) for M in mats]
    Ps = np.stack([P, 2 * P, P + np.eye(n)])
    batched = dj.kyp_matrix(*stack, qsr, Ps)
    for i in range(3):
        Ki = dj.LTIController(*(M[i] for M in stack))
        np.testing.assert_allclose(batched[i], dissipation_matrix(Ki, qsr, Ps[i]), rtol=1e-12,
                                   atol=1e-12 * np.abs(batched[i]).max())


def test_certificate_margin_is_min_of_the_two_eigenvalues():
    qsr = dj.QSR.passive(2)
    rng = np.random.default_rng(5)
    A, B, C, D = _random_stable(rng, 2, 2)
    D = D - (min_hermitian_part(A, B, C, D) - 0.2) * np.eye(2)
    K = dj.LTIController(A, B, C, D)
    cert = dj.certify(K, qsr, max_margin=True)
    assert cert.holds and cert.status == "optimal"
    for P in (cert.P, 3.0 * cert.P, cert.P + 0.5 * np.eye(2), -cert.P):
        given = dj.certify(K, qsr, P=P)
        expect = min(-np.linalg.eigvalsh(dissipation_matrix(K, qsr, P))[-1],
                     np.linalg.eigvalsh(P)[0])
        assert given.margin == pytest.approx(expect, rel=1e-9, abs=1e-12)
        assert given.holds is bool(expect > 0) is dissipation_ok(K, qsr, P, rel_margin=0.0)
        np.testing.assert_array_equal(given.P, P)
    # the SDP's margin is the best one: no worse than any of the storages tried above
    assert cert.margin >= dj.certify(K, qsr, P=3.0 * cert.P).margin - 1e-9
    assert dj.certify(K, qsr, P=-cert.P).margin < 0
    # a non-passive system: negative margin
    bad = dj.certify(dj.LTIController(A, B, C, D - 0.5 * np.eye(2)), qsr)
    assert not bad.holds and bad.margin < 0


def test_tol_is_the_relative_round_off_allowance():
    K = _first_order(0.5, 1.0, 1.0, 1 / 1.5 + 1e-7)
    qsr = dj.QSR.passive(1)
    cert = dj.certify(K, qsr)
    assert cert.holds and 0 < cert.margin < 1e-6
    assert dj.certify(K, qsr, P=cert.P, rtol=0.0).holds
    assert not dj.certify(K, qsr, P=cert.P, rtol=1e-3).holds  # margin < tol * scale
    assert not dj.certify(K, qsr, rtol=1e-3).holds  # also after the SDP
    # A comfortable system keeps its certificate under a loose tolerance.
    K2 = _first_order(0.5, 1.0, 1.0, 2.0)
    assert dj.certify(K2, qsr, rtol=1e-3).holds
    for tol in (-1e-3, np.nan, np.inf):
        with pytest.raises(ValueError, match="`rtol`"):
            dj.certify(K, qsr, rtol=tol)


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_unbalanced_realisations_are_decided_by_componentwise_bounds():
    """A certified controller in badly scaled state coordinates, x = T z with cond(T) = 1e4:
    the same system and the same inequality (KYP(T'PT) is a congruence of KYP(P)), but the
    terms' size swamps the margin of the relative test. The componentwise round-off bound
    proves it; a controller that is not dissipative, in the same coordinates, stays refused
    by both."""
    rng = np.random.default_rng(3)
    qsr = dj.QSR.passive(2)
    C = rng.standard_normal((2, 3))
    # G(z) = D + C C'/(z - 0.5): passive when D >= C C'/1.5 (z = -1); twice that, plus I
    K = dj.LTIController(0.5 * np.eye(3), C.T, C, 2 * C @ C.T / 1.5 + np.eye(2))
    P = dj.certify(K, qsr).P
    U, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    V, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    T = U @ np.diag([1.0, 1e-2, 1e-4]) @ V
    Ti = np.linalg.inv(T)

    def transformed(K):
        return dj.LTIController(Ti @ np.asarray(K.A) @ T, Ti @ np.asarray(K.B),
                                np.asarray(K.C) @ T, np.asarray(K.D))

    Kt, Pt = transformed(K), T.T @ P @ T
    assert dj.certify(K, qsr, P=P).holds
    A, B, C, D = (np.asarray(M) for M in (Kt.A, Kt.B, Kt.C, Kt.D))
    # the premise: the relative test alone refuses it
    assert dji.kyp_margin(A, B, C, D, qsr, Pt) < dji.lmi.VERIFY_RTOL * dji.kyp_scale(A, B, C, D,
                                                                                 qsr, Pt)
    assert dj.certify(Kt, qsr, P=Pt).holds
    assert dji.kyp_certified(A, B, C, D, qsr, Pt)
    assert not dj.certify(Kt, qsr, P=Pt, rtol=1e-9).holds  # a larger rtol: relative only
    # not dissipative: D with a negative eigenvalue (Phi(D) = D + D' is not > 0)
    bad = transformed(dj.LTIController(K.A, K.B, K.C, np.diag([3.0, -0.01])))
    assert not dj.certify(bad, qsr, P=Pt).holds
    assert not dji.kyp_bound_holds(*(np.asarray(M) for M in (bad.A, bad.B, bad.C, bad.D)),
                                   qsr.Q, qsr.S, qsr.R, Pt)


def test_the_storage_search_balances_the_states():
    """States in very different units (a similarity by diag(s, 1, 1/s), or B = 1e6 with
    C = 1e-6): the Riccati storages and the SDP used to fail (`insufficient_progress`,
    `numerical_error`); the search runs in balanced units and maps P back. Checked with
    the independent dissipation check; a non-dissipative controller in the same units stays
    refused."""
    rng = np.random.default_rng(3)
    qsr = dj.QSR.passive(2)
    C = rng.standard_normal((2, 3))
    A = 0.5 * np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    for D, dissipative in ((2 * C @ C.T / 1.5 + np.eye(2), True), (np.diag([3.0, -0.01]),
                                                                   False)):
        for s in (1e-3, 1e-6):
            T, Ti = np.diag([s, 1.0, 1 / s]), np.diag([1 / s, 1.0, s])
            K = dj.LTIController(Ti @ A @ T, Ti @ C.T, C @ T, D)
            cert = dj.certify(K, qsr)
            assert cert.holds is dissipative
            if dissipative:  # checked in the balanced units z = T x: storage T^-1 P T^-1
                assert dissipation_ok(dj.LTIController(A, C.T, C, D), qsr, Ti @ cert.P @ Ti)
    K1 = dj.LTIController([[0.5]], [[1e6]], [[1e-6]], [[1.0]])
    cert = dj.certify(K1, dj.QSR.passive(1))
    assert cert.holds and dissipation_ok(dj.LTIController([[0.5]], [[1.0]], [[1.0]], [[1.0]]),
                                         dj.QSR.passive(1), 1e12 * cert.P)
    # a realisation already in balance is left as it is (the usual case: nothing changes)
    np.testing.assert_array_equal(dji.certify_state_scale(np.diag([0.5, 0.5]), np.ones((2, 1)),
                                                          np.ones((1, 2))), [1.0, 1.0])


def test_states_beyond_float64s_range_are_refused_with_the_reason():
    """B = 2^e, C = 2^-e: certified up to e = 498 (the storage, of size 2^-2e, still fits
    float64); at e = 600 it cannot, and `certify` said only that the check failed, amid
    numpy overflow warnings."""
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    for e in (200, 498):
        d = 2.0**e
        cert = dj.certify(dj.LTIController([[0.5]], [[0.1 * d]], [[0.1 / d]], [[0.05]]), qsr)
        assert cert.holds
        assert dissipation_ok(dj.LTIController([[0.5]], [[0.1]], [[0.1]], [[0.05]]), qsr,
                              cert.P * d**2, python_control=False)
    d = 2.0**600
    with pytest.warns(UserWarning, match="beyond float64's range"), \
            np.errstate(over="ignore", invalid="ignore"):
        assert not dj.certify(dj.LTIController([[0.5]], [[0.1 * d]], [[0.1 / d]], [[0.05]]),
                              qsr).holds


def _kyp_eigenvalues(K, qsr, P):
    """lambda_max of the KYP matrix and lambda_min of P, written out here (no library code)."""
    A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    M11 = A.T @ P @ A - P - C.T @ Q @ C
    M12 = A.T @ P @ B - C.T @ (S + Q @ D)
    M22 = B.T @ P @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R
    M = np.block([[M11, M12], [M12.T, M22]])
    return np.linalg.eigvalsh((M + M.T) / 2)[-1], np.linalg.eigvalsh((P + P.T) / 2)[0]


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("n, seed, spread", [(4, 2, 1.4), (4, 3, 1.5), (6, 8, 1.5)])
def test_the_sdp_is_resolved_in_states_balanced_by_a_storage(n, seed, spread):
    """A controller against a gain bound 1 % above its gain, in states x = Tz with
    T = U diag(10^-s .. 10^s) V (rotations: no diagonal scaling undoes it). A storage exists
    that passes the float64 check in these states (the original's, carried over), yet the
    Riccati storages and the SDP found none (`optimal_inaccurate` with an indefinite P; a
    fit_direct controller with Q = -3.4e4 I, R = 0.99 I was refused so, against the
    trainer's certificate). Solved again in states balanced by an approximate storage, the
    storage passes an independent check; 1 % below the gain, it stays refused."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    B, C, D = rng.normal(size=(n, 2)), rng.normal(size=(2, n)), 0.1 * rng.normal(size=(2, 2))
    gain = np.linalg.svd(freq_response(A, B, C, D, np.linspace(0, np.pi, 4001)),
                         compute_uv=False).max()
    qsr = dj.QSR.bounded_gain(1.01 * gain, n_in=2, n_out=2)
    U, _ = np.linalg.qr(rng.normal(size=(n, n)))
    V, _ = np.linalg.qr(rng.normal(size=(n, n)))
    T = U @ np.diag(np.logspace(-spread, spread, n)) @ V
    Ti = np.linalg.inv(T)
    K = dj.LTIController(Ti @ A @ T, Ti @ B, C @ T, D)
    # the premise: a certificate exists in these states
    P0 = dj.certify(dj.LTIController(A, B, C, D), qsr, max_margin=True).P
    assert dji.kyp_certified(*(np.asarray(M) for M in (K.A, K.B, K.C, K.D)), qsr, T.T @ P0 @ T)
    for max_margin in (False, True):
        cert = dj.certify(K, qsr, max_margin=max_margin)
        assert cert.holds, (cert.source, cert.margin)
        lam_kyp, lam_P = _kyp_eigenvalues(K, qsr, cert.P)
        assert lam_kyp < 0 < lam_P
        assert dj.certify(K, qsr, P=cert.P).holds
    bad = dj.QSR.bounded_gain(0.99 * gain, n_in=2, n_out=2)
    assert frequency_supply_min(A, B, C, D, bad) < 0  # independent: the gain exceeds it
    assert not dj.certify(K, bad).holds and not dj.certify(K, bad, max_margin=True).holds


def test_an_inaccurate_solver_is_reported_as_undecided():
    """A storage the SDP solver returned `optimal_inaccurate` that fails the check proves
    nothing either way: the message must not call the controller marginal."""
    cert = dj.Certificate(dj.Outcome.not_certified, np.eye(1), -1.0, "optimal_inaccurate")
    assert "undecided" in cert.message and "`P`" in cert.message
    assert "marginally" not in cert.message
    assert "marginally" in dj.Certificate(dj.Outcome.not_certified, np.eye(1), -1e-12,
                                          "optimal").message


def test_given_P_is_checked_not_solved():
    K = _first_order(0.5, 1.0, 1.0, 1.0)
    cert = dj.certify(K, dj.QSR.passive(1))
    again = dj.certify(K, dj.QSR.passive(1), P=cert.P)
    assert again.holds and again.status == "given"
    assert not dj.certify(K, dj.QSR.passive(1), P=-cert.P).holds
    with pytest.raises(ValueError, match="`P`"):
        dj.certify(K, dj.QSR.passive(1), P=np.eye(2))


def test_certify_float32_controller():
    """float32 input is certified as given (float64 arithmetic on the float32 values)."""
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    K = dj.project(dj.LTIController.random(jax.random.PRNGKey(3), 2, 1, 1, scale=2.0), qsr)[0]
    K32 = K.astype(jnp.float32)
    cert = dj.certify(K32, qsr)
    assert K32.A.dtype == jnp.float32 and cert.P.dtype == np.float64
    assert cert.holds and dissipation_ok(K32, qsr, cert.P)
    # the float32 values are certified exactly as their float64 embedding is
    ref = dj.certify(K32.astype(jnp.float64), qsr)
    np.testing.assert_allclose(cert.P, ref.P, rtol=1e-9)
    assert cert.margin == pytest.approx(ref.margin, rel=1e-9)
    P32 = cert.P.astype(np.float32)
    assert dj.certify(K32, qsr, P=P32).holds is dissipation_ok(K32, qsr, P32) is True
    # a float32 controller that is not dissipative is refused
    bad = jax.tree.map(lambda a: a * 10, K32)
    assert not dj.certify(bad, qsr).holds


def test_certify_bad_input():
    K = _first_order(0.5, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.certify(K, dj.QSR.passive(2))
    with pytest.raises(ValueError, match="`qsr`"):
        dj.certify(K, "passive")
    with pytest.raises(ValueError, match="`K`"):
        dj.certify("not a controller", dj.QSR.passive(1))
    batched = dj.LTIController(np.zeros((2, 1, 1)), np.ones((2, 1, 1)), np.ones((2, 1, 1)),
                               np.ones((2, 1, 1)))
    with pytest.raises(ValueError, match="`P`"):
        dj.certify(batched, dj.QSR.passive(1), P=np.ones((3, 1, 1)))  # wrong batch
    with pytest.raises(ValueError, match="`P`"):
        dj.certify(K, dj.QSR.passive(1), P=np.array([[np.nan]]))
    with pytest.raises(ValueError, match="`P`"):
        dj.certify(K, dj.QSR.passive(1), P=np.ones((1, 1, 1)))


# -- controllers with leading batch axes ----------------------------------------------------


def _stack(members, shape):
    """An LTIController with batch `shape` from a flat list of unbatched ones."""
    return jax.tree.map(lambda *a: jnp.stack(a).reshape(shape + a[0].shape), *members)


@pytest.mark.parametrize("shape", [(3,), (2, 2)])
def test_batched_certify_equals_loop(shape):
    rng = np.random.default_rng(7)
    qsr = dj.QSR.passive(2)
    members = []
    for i in range(int(np.prod(shape))):
        A, B, C, D = _random_stable(rng, 2, 2)
        if i % 2 == 0:  # make every other member strictly passive
            D = D @ D.T + 20.0 * np.eye(2)
        members.append(dj.LTIController(A, B, C, D))
    Ks = _stack(members, shape)
    cert = dj.certify(Ks, qsr)
    assert isinstance(cert.holds, np.ndarray) and cert.holds.dtype == bool
    assert cert.holds.shape == cert.margin.shape == cert.status.shape == shape
    assert cert.P.shape == shape + (2, 2)
    assert cert.holds.any() and not cert.holds.all()
    for i, idx in enumerate(np.ndindex(*shape)):
        ref = dj.certify(members[i], qsr)
        assert cert.holds[idx] == ref.holds and cert.status[idx] == ref.status
        np.testing.assert_allclose(cert.margin[idx], ref.margin, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cert.P[idx], ref.P, rtol=1e-9, atol=1e-12)
    # with P given the check is vectorised, and equals the loop too (members the search
    # disproved have no storage, NaN: give them the identity)
    found = np.where(np.isfinite(cert.P), cert.P, np.eye(2))
    given = dj.certify(Ks, qsr, P=found)
    assert given.status.shape == shape and set(given.status.ravel()) == {"given"}
    np.testing.assert_array_equal(given.holds, cert.holds)
    one_P = dj.certify(Ks, qsr, P=np.eye(2))  # one P for every member
    assert one_P.P.shape == shape + (2, 2)
    for i, idx in enumerate(np.ndindex(*shape)):
        ref = dj.certify(members[i], qsr, P=np.eye(2))
        assert one_P.holds[idx] == ref.holds
        assert one_P.margin[idx] == pytest.approx(ref.margin, rel=1e-12, abs=1e-15)
        ref = dj.certify(members[i], qsr, P=found[idx])
        assert given.holds[idx] == ref.holds
        assert given.margin[idx] == pytest.approx(ref.margin, rel=1e-12, abs=1e-15)


def test_empty_batch():
    Ks = dj.LTIController(*(np.zeros((0,) + s) for s in ((2, 2), (2, 1), (1, 2), (1, 1))))
    for cert in (dj.certify(Ks, dj.QSR.passive(1)), dj.certify(Ks, dj.QSR.passive(1), P=np.eye(2))):
        assert cert.holds.shape == cert.margin.shape == cert.status.shape == (0,)
        assert cert.P.shape == (0, 2, 2)


def test_unbatched_certificate_keeps_scalars():
    cert = dj.certify(_first_order(0.5, 1.0, 1.0, 1.0), dj.QSR.passive(1))
    assert type(cert.holds) is bool and type(cert.margin) is float
    assert type(cert.status) is str and cert.P.shape == (1, 1)


# -- the cheap storages tried before the SDP --------------------------------------------------


@pytest.mark.parametrize("qsr", [dj.QSR.passive(2), dj.QSR.bounded_gain(1.5, n_in=2, n_out=2),
                                 dj.QSR.conic(-0.5, 2.0, dim=2)], ids=["passive", "gain", "conic"])
def test_fast_path_and_sdp_agree(qsr):
    """Random controllers of both verdicts: the fast path and the SDP decide alike, and a
    storage either path returns passes the definition-based check."""
    rng = np.random.default_rng(11)
    verdicts, statuses = [], set()
    for trial in range(10):
        A, B, C, D = _random_stable(rng, 3, 2)
        B, C = B[:, :qsr.n_in], C[:qsr.n_out]
        # D = 0.5 I is inside all three supply rates' cones, D = -3 I outside; |G - D| is
        # small or of order one (B, C scaled), so some of each verdict and some near the edge
        D = (0.5 if trial % 2 else -3.0) * np.eye(2) + 0.05 * rng.normal(size=(2, 2))
        K = dj.LTIController(A, (0.1 + 0.2 * (trial % 3)) * B, C, D[:qsr.n_out, :qsr.n_in])
        fast, sdp = dj.certify(K, qsr), dj.certify(K, qsr, max_margin=True)
        assert fast.holds == sdp.holds
        verdicts.append(fast.holds)
        statuses.add(str(fast.status))
        for cert in (fast, sdp):
            if cert.holds:
                assert dissipation_ok(K, qsr, cert.P)
                assert cert.margin <= sdp.margin * (1 + 1e-6) + 1e-12  # the SDP's is the best
    assert any(verdicts) and not all(verdicts)
    assert "riccati" in statuses  # the Riccati storage proved some of them


def test_projected_controller_is_certified_from_the_cache(getkey):
    qsr = dj.QSR.passive(2)
    Kp, P = dj.project(dj.LTIController.random(getkey(), 4, 2, 2, scale=2.0), qsr)
    cert = dj.certify(Kp, qsr)
    assert cert.holds and cert.status == "cached"
    np.testing.assert_array_equal(cert.P, np.asarray(P, np.float64))
    assert dissipation_ok(Kp, qsr, cert.P)
    # another controller's numbers do not hit the cache
    other = jax.tree.map(lambda a: a * (1 - 1e-3), Kp)
    assert dj.certify(other, qsr).status != "cached"


def test_hint_is_tried_first():
    K = _first_order(0.5, 1.0, 1.0, 1.0)
    qsr = dj.QSR.passive(1)
    best = dj.certify(K, qsr, max_margin=True)
    cert = dj.certify(K, qsr, hint=best.P)
    assert cert.holds and cert.status == "hint"
    np.testing.assert_array_equal(cert.P, best.P)
    # a hint that proves nothing is passed over
    assert dj.certify(K, qsr, hint=-best.P).status != "hint"
    assert dj.certify(K, qsr, hint=-best.P).holds
    with pytest.raises(ValueError, match="`hint`"):
        dj.certify(K, qsr, hint=np.eye(2))


def test_fast_path_at_order_48():
    """A Riccati storage at n = 48 (the SDP would take minutes there)."""
    rng = np.random.default_rng(3)
    A, B, C, _ = _random_stable(rng, 48, 2)
    K = dj.LTIController(A, 0.1 * B, 0.1 * C, 5.0 * np.eye(2))
    cert = dj.certify(K, dj.QSR.passive(2))
    assert cert.holds and cert.status == "riccati"
    assert dissipation_ok(K, dj.QSR.passive(2), cert.P, python_control=False)


# -- the cheap disproof tried before the SDP ------------------------------------------------


def _cvxpy_max_margin(A, B, C, D, qsr) -> float:
    """max t s.t. KYP(P) <= -t I, P >= t I, t <= 1, written here with cvxpy (no library code)."""
    n, p = B.shape
    P, t = cp.Variable((n, n), symmetric=True), cp.Variable()
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    M11 = A.T @ P @ A - P - C.T @ Q @ C
    M12 = A.T @ P @ B - C.T @ (S + Q @ D)
    M22 = B.T @ P @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R
    M = cp.bmat([[M11, M12], [M12.T, M22]])
    cons = [(M + M.T) / 2 << -t * np.eye(n + p), P >> t * np.eye(n), t <= 1]
    with warnings.catch_warnings():  # "may be inaccurate": the asserted clearance is 1e-6
        warnings.simplefilter("ignore")
        cp.Problem(cp.Maximize(t), cons).solve(solver=cp.CLARABEL)
    return float(t.value)


@pytest.mark.parametrize("qsr", [dj.QSR.passive(2), dj.QSR.bounded_gain(1.5, n_in=2, n_out=2),
                                 dj.QSR.conic(-0.5, 2.0, dim=2),
                                 dj.QSR(np.diag([1.0, -2.0]), np.eye(2), np.eye(2))],
                         ids=["passive", "gain", "conic", "indefinite"])
def test_disproof_agrees_with_an_independent_sdp(qsr):
    """Random controllers, stable and not, inside and outside the rate: whenever the cheap
    disproof fires, an independent cvxpy SDP finds no storage; it never fires on a
    controller `certify` proves."""
    rng = np.random.default_rng(5)
    reasons = []
    for trial in range(16):
        A, B, C, D = _random_stable(rng, 3, 2)
        if trial % 4 == 3:
            A = A * 1.3 / max(abs(np.linalg.eigvals(A)))  # unstable
        D = (0.5 if trial % 2 else -3.0) * np.eye(2) + 0.05 * rng.normal(size=(2, 2))
        B = (0.1 + 0.3 * (trial % 3)) * B
        reason = certify_fast.disproof(A, B, C, D, qsr)
        cert = dj.certify(dj.LTIController(A, B, C, D), qsr)
        if reason is None:
            continue
        reasons.append(reason)
        assert not cert.holds and str(cert.source) == reason
        assert cert.result == dj.Outcome.infeasible and cert.margin == -np.inf
        # Clarabel's tolerances are ~1e-8; an infeasible problem's best t is clearly < 0.
        assert _cvxpy_max_margin(A, B, C, D, qsr) < 1e-6, reason
    for trial in range(8):  # certified controllers are never disproved
        K = dj.project(dj.LTIController.random(jax.random.PRNGKey(trial), 3, 2, 2, scale=2.0),
                       qsr).controller
        mats = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
        assert certify_fast.disproof(*mats, qsr) is None
    assert reasons, "no controller was disproved: the test has no teeth"
    if np.linalg.eigvalsh(qsr.Q)[-1] <= 0:
        assert any("unstable" in r for r in reasons), reasons


def test_disproof_skips_the_sdp_at_order_48(monkeypatch):
    """At n = 48 the SDP of a non-dissipative controller takes minutes; an unstable one and
    one whose feedthrough breaks the rate are refused without it."""
    def no_sdp(*args, **kwargs):
        raise AssertionError("the SDP was called")

    monkeypatch.setattr(certify_sdp, "solve", no_sdp)
    rng = np.random.default_rng(3)
    A, B, C, _ = _random_stable(rng, 48, 2)
    qsr = dj.QSR.passive(2)
    unstable = dj.LTIController(1.5 * A / max(abs(np.linalg.eigvals(A))), B, C, np.eye(2))
    cert = dj.certify(unstable, qsr)
    assert cert.result == dj.Outcome.infeasible and str(cert.source).startswith("disproved: unstable")
    active = dj.LTIController(A, 0.1 * B, 0.1 * C, -np.eye(2))  # He D < 0: not passive
    cert = dj.certify(active, qsr, max_margin=True)
    assert cert.result == dj.Outcome.infeasible and "feedthrough" in str(cert.source)
    # the message says so (it was the projection's "pass a different P_ref"); P is NaN
    assert np.isnan(cert.P).all() and "SDP was skipped" in cert.message, cert.message
    pair = dj.certify(jax.tree.map(lambda M: jnp.stack([M, M]), active), qsr)
    assert "P_ref" not in cert.message and pair.message == [cert.message] * 2
    assert min_hermitian_part(A, 0.1 * B, 0.1 * C, -np.eye(2)) < 0  # independent: He G < 0


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("s", [1e5, 1e6, 1e7])
def test_high_gain_controllers_against_their_gain_bound(s):
    """G(z) = s (1/(z - 0.5) + 1/(z - 0.9) + 0.5) has H-infinity norm 12.5 s (at z = 1: all
    three terms positive there, and no larger anywhere on the circle). Against a bound 1 %
    above it, Q = -1 and R ~ 1.6e12 s^2 made the KYP terms swamp the margin, and the
    dissipative controller was refused; 1 % below it, it must stay refused."""
    A, B, C, D = np.diag([0.5, 0.9]), s * np.ones((2, 1)), np.ones((1, 2)), np.array([[0.5 * s]])
    z = np.exp(1j * np.linspace(0, np.pi, 2001))
    gains = np.abs(C @ np.linalg.solve(z[:, None, None] * np.eye(2) - A, B)[..., 0].T + D)
    assert gains.max() == pytest.approx(12.5 * s, rel=1e-12)  # the reference, on a grid
    K = dj.LTIController(A, B, C, D)
    assert dj.certify(K, dj.QSR.bounded_gain(1.01 * 12.5 * s, n_in=1, n_out=1)).holds
    assert not dj.certify(K, dj.QSR.bounded_gain(0.99 * 12.5 * s, n_in=1, n_out=1)).holds


def test_certify_under_a_trace_says_why():
    K = dj.LTIController(0.5 * np.eye(1), np.ones((1, 1)), np.ones((1, 1)), np.ones((1, 1)))
    with pytest.raises(ValueError, match="`certify` cannot run under `jax.jit`"):
        jax.jit(lambda k: dj.certify(k, dj.QSR.passive(1)).margin)(K)
