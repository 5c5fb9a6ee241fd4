"""Narrow cones far from zero: the interior cone [a, a + 1] with a = 1000 has entries of
1e6 (R = -a(a + 1)) but room (R - S'Q^-1 S) of 1/4, and its dissipative feedthroughs sit
near a + 1/2. Clarabel reported the projection infeasible, ADMM spent its whole budget,
ICO's SDP failed, and `fit_direct` fitted 2000x worse than PGD. Both the projection and
the trainers now solve such a rate about its centre (`rate_scale.centring`), an exact
change of variables D' = D + Q^-1 S; every result is checked in the rate as given.

The independent check is `exactly_dissipative`: Sylvester's criterion on P and -KYP(P) in
exact rational arithmetic on the float64 entries (a float64 eigenvalue test of a 1e-6
margin computed from terms of 1e6 is at the edge of round-off).
"""

import jax
import jax.random as jr
import numpy as np
import pytest
from helpers import exactly_dissipative

import dissil_jax as dj
from dissil_jax import internal as dji
from dissil_jax.experiments.data import realisable_windows

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

A_FAR = 1e3
FAR = dj.QSR.conic(A_FAR, A_FAR + 1.0, dim=1)
# the same rate about its centre D = a + 1/2: (Q, 0, R - S'Q^-1 S) = (-1, 0, 1/4)
CENTRED = dj.QSR(-1.0, 0.0, 0.25)
NOISE = 0.01
# one cone per channel, [-1, 1] and [0, 100]: a centre term of 2500 along the second
# channel, with a room of 2500 there too (an audit's rate, which the first criterion,
# the largest term against the smallest room, centred, and `fit_direct` then ended 200
# times above the zero controller's loss)
PER_CHANNEL = dj.QSR(-np.eye(2), np.diag([0.0, 50.0]), np.diag([1.0, 0.0]))


def _dist(K, L) -> float:
    return float(np.sqrt(sum(np.sum((np.asarray(getattr(K, f), np.float64)
                                     - np.asarray(getattr(L, f), np.float64)) ** 2)
                             for f in "ABCD")))


def test_centring_is_the_exact_change_of_variables():
    """`centring`: M = Q^-1 S and (Q, 0, R - S'Q^-1 S) for a far cone; None for the cone
    [1, 2] (its centre's term S'Q^-1 S = 2.25 against its room 0.25), for a wide cone in
    small units ([0.5, 1.5] * 1e-3: entries of 1 against a room of 2.5e-7, but a ratio of
    4, which the trainers' balancing of units handles), for rates whose large centre term
    comes with as much room along it (one cone per channel, [-1, 1] and [0, 100]; a Q
    with one tiny eigenvalue), for Q not negative definite and for S = 0."""
    found = dji.rate_scale.centring(FAR)
    assert found is not None
    M, rate = found
    np.testing.assert_allclose(M, [[-(A_FAR + 0.5)]], rtol=1e-15)
    np.testing.assert_allclose(rate.R, CENTRED.R, rtol=1e-9)  # R - S'Q^-1S cancels 1e6
    assert not np.any(rate.S) and np.array_equal(rate.Q, FAR.Q)
    for other in (dj.QSR.conic(1.0, 2.0, dim=1), dj.QSR.conic(0.5e-3, 1.5e-3, dim=1),
                  PER_CHANNEL, dj.QSR(-np.diag([1.0, 1e-3]), 0.5 * np.eye(2), 0.1 * np.eye(2)),
                  dj.QSR.passive(2),
                  dj.QSR.bounded_gain(1e3, n_in=1, n_out=1)):
        assert dji.rate_scale.centring(other) is None


@pytest.mark.parametrize("method", ["clarabel", "first_order"])
def test_projection_onto_a_far_cone(method):
    """Certified (exactly), and at the distance of the shifted problem: projecting
    K + (0, 0, 0, M) onto the centred rate, which is of unit size and solved as given."""
    K = dj.LTIController.random(jr.PRNGKey(0), n_state=3, n_in=1, n_out=1)
    fallbacks = dji.projection_fo.FALLBACKS["rows"]
    Kp, P = dj.project(K, FAR, method=method)
    assert exactly_dissipative(Kp, FAR, P)
    if method == "first_order":  # ADMM's own answer passed the check: no Clarabel rescue
        assert dji.projection_fo.FALLBACKS["rows"] == fallbacks
    M = -(A_FAR + 0.5)
    shifted = dj.LTIController(K.A, K.B, K.C, K.D + M)
    Kc, _ = dj.project(shifted, CENTRED, method=method)
    # Clarabel: both solves stop at a duality gap of 1e-8, so the distances agree to
    # ~sqrt(1e-8) relative; ADMM stops at residuals 1e-4 relative to the scaled LMI.
    tol = 1e-3 if method == "clarabel" else 3e-2
    assert abs(_dist(Kp, K) - _dist(Kc, shifted)) <= tol * _dist(Kc, shifted)
    np.testing.assert_allclose(np.asarray(Kp.D) + M, Kc.D, atol=tol * _dist(Kc, shifted))


def test_the_float64_check_proves_a_far_cone_and_stays_sound():
    """On the far cone a KYP margin of 1e-6 is computed from terms of 4e6, an error of
    about 1e-8 at most. The Jacobi-scaled round-off bound alone could not prove it when the
    input block's diagonal is itself that small (scaling it by ~1e3 on each side magnified
    the error a millionfold), so the projection was solved again with a 100x margin; the
    unscaled bound proves it. Rates R - t move that diagonal to -d. Sound: whatever the
    check certifies is dissipative in exact arithmetic."""
    K = dj.LTIController.random(jr.PRNGKey(0), n_state=3, n_in=1, n_out=1)
    Kp, P = dj.project(K, FAR)
    mats = [np.asarray(M, np.float64) for M in (Kp.A, Kp.B, Kp.C, Kp.D)]
    kyp = lambda rate: dj.kyp_matrix(*mats, rate, P)
    # the first solve's margin eps = 1e-6 (in the rate divided by 4), not a retry's 1e-4
    assert 0 < -np.linalg.eigvalsh(kyp(FAR))[-1] < 1e-5
    corner = kyp(FAR)[-1, -1]
    for d in np.logspace(-7, -4, 7):
        rate = dj.QSR(FAR.Q, FAR.S, FAR.R + corner + d)  # input block's diagonal now -d
        margin = -np.linalg.eigvalsh(kyp(rate))[-1]
        ours = bool(dji.kyp_certified(*mats, rate, P))
        assert not ours or exactly_dissipative(Kp, rate, P), d
        assert ours or margin < 1e-7, (d, margin)  # 7x the unscaled round-off bound


@pytest.fixture(scope="module")
def far_windows():
    """Windows of a far-cone expert (a projected random controller) with output noise
    0.01 over h = 10 steps: the expert's own loss is about h * 0.01^2 = 1e-3."""
    with jax.enable_x64(True):
        w, _ = realisable_windows(jr.PRNGKey(1), FAR, n_state=3, num_windows=20,
                                  horizon=10, noise=NOISE)
    return w


@pytest.mark.parametrize("trainer", ["direct", "pgd"])
def test_trainers_fit_a_far_cone(trainer, far_windows):
    """Certified exactly in the user's rate, the final loss that of the returned
    controller on the user's windows, and within 10x the noise floor (`fit_direct`'s
    median was 2.1, 2000x PGD's, before the centring)."""
    fit = getattr(dj, f"fit_{trainer}")
    with jax.enable_x64(True):
        res = fit(jr.PRNGKey(0), far_windows, FAR, n_state=3, num_inits=4, progress=False)
        losses = [float(dj.imitation_loss(K, far_windows)) for K in _each(res.controllers)]
    assert np.all(res.certified)
    for K, P in zip(_each(res.controllers), res.P):
        assert exactly_dissipative(K, FAR, P)
    # the centred windows u - y M' round at ~1e-16 * 1e3: the losses agree far below 1e-6
    np.testing.assert_allclose(losses, res.final_loss, rtol=1e-6)
    floor = far_windows.y.shape[1] * NOISE**2
    assert np.median(losses) < 10 * floor


def test_ico_fits_a_far_cone():
    """ICO's SDP failed on every run (`solver_failed`) before the centring; two-step
    windows, as ICO needs."""
    with jax.enable_x64(True):
        w, _ = realisable_windows(jr.PRNGKey(1), FAR, n_state=2, num_windows=20, horizon=2,
                                  noise=NOISE)
        res = dj.fit_ico(jr.PRNGKey(0), w, FAR, num_inits=2, progress=False)
    assert np.all(res.certified)
    for K, P in zip(_each(res.controllers), res.P):
        assert exactly_dissipative(K, FAR, P)
    assert np.median(np.asarray(res.final_loss)) < 10 * 2 * NOISE**2


def test_ren_fits_a_far_cone(far_windows):
    """A REN's feedthrough D22 carries the centre; certified by the trainer's check and by
    a fresh SDP (`certify_ren`) in the user's rate."""
    with jax.enable_x64(True):
        res = dj.fit_ren(jr.PRNGKey(0), far_windows, FAR, n_state=3, width=4, num_inits=2,
                         progress=False)
        assert np.all(res.certified)
        for K in _each(res.controllers):
            assert dj.certify_ren(K, FAR).holds
    floor = far_windows.y.shape[1] * NOISE**2
    assert np.median(np.asarray(res.final_loss)) < 10 * floor


def _each(K):
    return [jax.tree.map(lambda M, i=i: M[i], K) for i in range(K.A.shape[0])]


def test_one_cone_per_channel_trains_as_given():
    """The per-channel cones are not centred. Centred, `fit_pgd` ended at 0.36 and
    `fit_direct` at 1070 against the zero controller's 3.9 (the expert's 4e-4); as given,
    PGD reaches 0.002. `fit_direct` stays far from the expert here (0.8: its map's known
    weakness at the edge of the set, where this expert sits), so it is held to a gross
    bound only."""
    with jax.enable_x64(True):
        w, _ = realisable_windows(jr.PRNGKey(0), PER_CHANNEL, n_state=2, num_windows=50,
                                  noise=NOISE)
        pgd = dj.fit_pgd(jr.PRNGKey(1), w, PER_CHANNEL, n_state=2, progress=False)
        direct = dj.fit_direct(jr.PRNGKey(1), w, PER_CHANNEL, n_state=2, progress=False)
    zero = float(np.mean(np.sum(np.asarray(w.u) ** 2, axis=(1, 2))))
    assert np.all(pgd.certified) and np.all(direct.certified)
    assert np.median(np.asarray(pgd.final_loss)) < 0.01 * zero
    assert np.median(np.asarray(direct.final_loss)) < 0.5 * zero
