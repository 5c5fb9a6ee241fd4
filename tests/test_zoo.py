"""The problem zoo: every problem builds, its claims hold on its data, its supply rates hold,
and `evaluate` gives the known answers for known methods."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, loop_predict

import dissil_jax as dj
from dissil_jax.experiments import zoo

NAMES = list(zoo.PROBLEMS)
# One worker runs every test here, so the zoo (about a minute of simulation) is built once.
pytestmark = pytest.mark.xdist_group("zoo")


def test_the_zoo_is_built_on_one_worker(request):
    """Under `make test` (`--dist loadgroup`) this module's tests share one worker, so the
    zoo is built once: pytest-xdist marks a grouped test by adding `@group` to its id. With
    pytest 9.2 that no longer takes effect (pytest-dev/pytest-xdist#1386) and every group's
    setup (the zoo, the docs site, the two-device sweep) silently runs on both workers;
    constraints.txt pins a pytest where it works."""
    if getattr(request.config.option, "loadgroup", False):
        assert request.node.nodeid.endswith("@zoo"), request.node.nodeid


@pytest.fixture(scope="module")
def problems():
    return {name: zoo.problem(name) for name in NAMES}


def _zero(t):
    n, p, m = t.n_state, t.windows.n_in, t.windows.n_out
    return dj.LTIController(np.zeros((n, n)), np.zeros((n, p)), np.zeros((m, n)),
                            np.zeros((m, p)))


def test_split_is_fixed_and_disjoint(problems):
    assert len(NAMES) >= 16
    assert set(zoo.TUNING).isdisjoint(zoo.HELD_OUT)
    assert set(zoo.TUNING) | set(zoo.HELD_OUT) == set(NAMES)
    # The split is part of the zoo's definition: changing it invalidates the held-out table.
    assert zoo.HELD_OUT == ("scalar_heavy", "chain2_passive", "chain4_4x4_io", "chain8_siso_io",
                            "cone_3x2", "gain_saturated", "sector_2x2", "sector_io",
                            "chain2_sliding")
    for name, p in problems.items():
        assert p.name == name
        assert p.split == ("tuning" if name in zoo.TUNING else "held_out")


@pytest.mark.parametrize("name", NAMES)
def test_claims_hold_on_the_data(problems, name):
    p = problems[name]
    f, W, V = p.facts, p.train, p.test
    assert (f.order, f.n_in, f.n_out) == (p.plant.n_state, p.plant.n_in, p.plant.n_out)
    assert (W.num_windows, W.horizon) == (f.num_windows, f.horizon)
    assert W.y.shape[2] == f.n_out and W.u.shape[2] == f.n_in
    assert V.horizon == f.horizon and V.num_windows >= 50
    assert (W.x0 is not None) == f.has_state == (V.x0 is not None)
    if f.has_state:
        assert p.n_state == f.order and W.x0.shape[1] == f.order
    assert p.qsr.S.shape == (f.n_in, f.n_out)  # the controller maps y (p) to -u (m)
    assert p.plant_qsr.S.shape == (f.n_out, f.n_in)
    assert isinstance(p.plant, dj.SectorPlant) == (f.supply == "sector")
    # units: x0 ~ N(0, units^2); 16 * order draws put the RMS within a factor 2 w.h.p.
    rms = float(jnp.sqrt(jnp.mean(p.x0_test**2)))
    assert f.units / 2 < rms < 2 * f.units
    for arr in (W.y, W.u, V.y, V.u):
        assert bool(jnp.all(jnp.isfinite(arr)))


def test_zoo_covers_the_claimed_range(problems):
    facts = [p.facts for p in problems.values()]
    orders = [f.order for f in facts]
    assert min(orders) == 1 and max(orders) == 24
    assert max(max(f.n_in, f.n_out) for f in facts) == 4
    assert any(f.n_in == f.n_out == 4 for f in facts)  # a 4x4 plant
    assert any(f.n_in == f.n_out == 1 for f in facts)
    assert {f.supply for f in facts} == {"passivity", "bounded_gain", "interior_cone",
                                         "degenerate_cone", "sector"}
    assert {f.has_state for f in facts} == {True, False}
    assert min(f.units for f in facts) <= 1e-3 and max(f.units for f in facts) >= 1e3
    assert {f.noise for f in facts} == {"none", "light", "heavy"}
    assert min(f.num_windows for f in facts) == 2 and max(f.num_windows for f in facts) == 1000
    assert {f.horizon for f in facts} >= {2, 10}
    assert all(2 <= f.horizon <= 10 for f in facts)
    assert {f.expert for f in facts} == {"static", "observer", "nonlinear"}
    # both halves hold state and state-free logs, LTI and sector plants
    for half in (zoo.TUNING, zoo.HELD_OUT):
        fs = [problems[n].facts for n in half]
        assert {f.has_state for f in fs} == {True, False}
        assert "sector" in {f.supply for f in fs}


def test_problems_are_deterministic():
    a, b = zoo.PROBLEMS["scalar_heavy"](0), zoo.PROBLEMS["scalar_heavy"](0)
    c = zoo.PROBLEMS["scalar_heavy"](1)
    for x, y, z in ((a.train.y, b.train.y, c.train.y), (a.test.u, b.test.u, c.test.u)):
        assert np.array_equal(np.asarray(x), np.asarray(y))
        assert not np.allclose(np.asarray(x), np.asarray(z))


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", NAMES)
def test_plant_satisfies_its_supply_rate(problems, name):
    p = problems[name]
    A, B, C, D = p.plant.matrices()
    if isinstance(p.plant, dj.SectorPlant):
        # Sampled from the definition: V(x+) - V(x) <= w(u, y), V = x'Px, with the sine.
        P, alpha = p.plant_storage, float(p.plant.alpha)
        Q, S, R = p.plant_qsr.Q, p.plant_qsr.S, p.plant_qsr.R
        rng = np.random.default_rng(0)
        n, m = B.shape
        for scale in (1e-2, 1.0, 10.0, 1e3):
            x = scale * rng.standard_normal((4000, n))
            u = scale * rng.standard_normal((4000, m))
            xn = x @ A.T + alpha * np.sin(x) + u @ B.T
            y = x @ C.T + u @ D.T
            V = lambda v: np.einsum("ki,ij,kj->k", v, P, v)
            w = (np.einsum("ki,ij,kj->k", y, Q, y) + 2 * np.einsum("ki,ij,kj->k", y, S, u)
                 + np.einsum("ki,ij,kj->k", u, R, u))
            # float64 round-off of terms of size |P| |x|^2 and |Q, S, R| |(x, u)|^2
            size = (np.abs(P).max() + np.abs(Q).max() + np.abs(R).max() + 1) * (
                np.sum(x**2, 1) + np.sum(u**2, 1)) * (1 + np.abs(A).max() + alpha) ** 2
            assert np.all(V(xn) - V(x) - w <= 1e-12 * size)
    else:
        plant = dj.LTIController(A, B, C, D)
        cert = dj.certify(plant, p.plant_qsr)
        assert cert.holds
        assert dissipation_ok(plant, p.plant_qsr, cert.P, python_control=False)
    # Theorem 1 with alpha = 1, the multiplier the zoo's controller rates are built with.
    Q1, S1, R1 = p.plant_qsr.Q, p.plant_qsr.S, p.plant_qsr.R
    Q2, S2, R2 = p.qsr.Q, p.qsr.S, p.qsr.R
    M = np.block([[Q1 + R2, -S1 + S2.T], [(-S1 + S2.T).T, R1 + Q2]])
    assert np.linalg.eigvalsh(M)[-1] < 0
    assert np.linalg.eigvalsh(Q2)[-1] <= 1e-12  # Q <= 0: fit_direct applies everywhere


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", NAMES)
def test_evaluate_zero_controller(problems, name):
    p = problems[name]
    rep = zoo.evaluate(p, _zero)
    assert rep.certified.shape == rep.stable.shape == rep.imitation_error.shape == (1,)
    assert rep.train_loss is None and rep.wall_time >= 0
    # The zero controller's KYP matrix is diag(-P, -R): dissipative iff R > 0.
    lam = np.linalg.eigvalsh(p.qsr.R)[0]
    if abs(lam) > 1e-6:
        assert bool(rep.certified[0]) == (lam > 0)
    # Its loop is the plant alone: stable (every zoo plant is; sector plants contract since
    # ||A|| + alpha < 1).
    A = p.plant.matrices()[0]
    if isinstance(p.plant, dj.SectorPlant):
        assert np.linalg.norm(A, 2) + float(p.plant.alpha) < 1
    else:
        assert np.abs(np.linalg.eigvals(A)).max() < 1
    assert rep.stable[0]
    np.testing.assert_allclose(rep.imitation_error, 1.0, rtol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_simulated_stability_agrees_with_the_exact_test(problems, name):
    # A width-0 REN computes what its LTI controller computes, but is judged by simulation:
    # the zero controller's loop is the stable plant, so both verdicts must be True (on
    # chain12_siso_io, half-life 116 steps, a fixed 200-step horizon said unstable).
    p = problems[name]
    K = jax.tree.map(lambda M: jnp.asarray(M)[None], _zero(zoo.task(p)))  # a batch of one
    assert zoo.stable(p, dj.RENController.from_lti(K))[0]
    if isinstance(p.plant, dj.LinearPlant):
        assert zoo.stable(p, K)[0]  # the exact (spectral) test


def _expert_loop_matrix(p):
    A, B, C, D = p.plant.matrices()
    Ac, Bc, Cc, _ = (np.asarray(M, np.float64) for M in (p.expert_controller.A,
                                                          p.expert_controller.B,
                                                          p.expert_controller.C,
                                                          p.expert_controller.D))
    if p.facts.expert == "static":
        return A - B @ Cc
    # u = -Cc xh, y = Cx + Du, xh+ = Ac xh + Bc y
    return np.block([[A, -B @ Cc], [Bc @ C, Ac - Bc @ D @ Cc]])


@pytest.mark.parametrize("name", [n for n in NAMES if n in (
    "chain5_siso_io", "cone_siso_tiny", "chain8_siso_io", "chain3_paper", "gain_2x2_io")])
@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_evaluate_expert(problems, name):
    p = problems[name]
    rep = zoo.evaluate(p, lambda t: p.expert_controller)
    rho = np.abs(np.linalg.eigvals(_expert_loop_matrix(p))).max()
    assert bool(rep.stable[0]) == (rho < 1)
    if p.facts.noise == "none":
        # exact demonstrator: the loss is round-off of terms of size |u|^2
        assert rep.imitation_error[0] < 1e-20
    else:
        assert 0 < rep.imitation_error[0] < 1


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
@pytest.mark.parametrize("name", ["chain4_4x4_io", "cone_3x2"])
def test_imitation_error_against_loops(problems, name):
    p = problems[name]
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, p.n_state, p.facts.n_out, p.facts.n_in,
                                                    scale=0.3))(jr.split(jr.PRNGKey(1), 3))
    err = zoo.imitation_error(p, Ks)
    target = -np.asarray(p.test.u, np.float64)
    J0 = np.mean(np.sum(target**2, axis=(1, 2)))
    for i in range(3):
        Ki = jax.tree.map(lambda M: M[i], Ks)
        pred = loop_predict(Ki, p.test)
        J = np.mean(np.sum((pred - target) ** 2, axis=(1, 2)))
        np.testing.assert_allclose(err[i], J / J0, rtol=1e-10)


def test_evaluate_trained_and_nonfinite(problems):
    p = problems["chain2_passive"]
    rep = zoo.evaluate(p, lambda t: dj.fit_pgd(t.key, t.windows, t.qsr, num_inits=2,
                                               max_steps=5, throw=False))
    res = dj.fit_pgd(jr.PRNGKey(0), p.train, p.qsr, num_inits=2, max_steps=5, throw=False)
    np.testing.assert_allclose(rep.train_loss, np.asarray(res.final_loss), rtol=1e-9)
    assert rep.certified.all()
    for i in range(2):
        Ki = jax.tree.map(lambda M: M[i], res.controllers)
        assert dissipation_ok(Ki, p.qsr, res.P[i], python_control=False)
    assert rep.stable.all()  # Theorem 1: certified controllers stabilise the plant
    assert np.all(rep.imitation_error < 1)

    def nan_method(t):
        K = jax.vmap(_zero_like, in_axes=(None, 0))(t, jnp.arange(2))
        return jax.tree.map(lambda M: M.at[0].set(jnp.nan), K)

    bad = zoo.evaluate(p, nan_method)
    assert not bad.certified[0] and not bad.stable[0] and bad.imitation_error[0] == np.inf
    assert bad.stable[1] and bad.imitation_error[1] == pytest.approx(1.0, rel=1e-12)


def test_evaluate_rens_certified_and_odd_ones_started_where_asked(problems):
    """A REN's certificate is its trainer's pair, checked by `certify_ren` (it was reported
    False for every REN); an odd REN (order 2n) starts at `start(x0)`, and without `start`
    the mismatch with the plant state is named. The errors are checked against a plain
    loop of `ren_predict`."""
    p = problems["chain2_passive"]
    assert p.test.x0 is not None
    fits = {odd: (lambda t, odd=odd: dj.fit_ren(t.key, t.windows, t.qsr, width=2,
                                                num_inits=2, max_steps=5, odd=odd))
            for odd in (False, True)}
    mirror = lambda x0: jnp.concatenate([x0, -x0], -1)
    rep = zoo.evaluate(p, fits[False])
    n = p.test.x0.shape[1]
    with pytest.raises(ValueError, match=f"order {2 * n}, .* {n}-dimensional plant state.*`start`"):
        zoo.evaluate(p, fits[True])
    odd = zoo.evaluate(p, fits[True], start=mirror)
    target = -np.asarray(p.test.u, np.float64)
    J0 = np.mean(np.sum(target**2, axis=(1, 2)))
    for report, odd_run in ((rep, False), (odd, True)):
        res = fits[odd_run](zoo.task(p))
        assert report.certified.all() and report.stable.all()
        x0 = mirror(p.test.x0) if odd_run else p.test.x0
        for i in range(2):
            Ki = jax.tree.map(lambda M: M[i], res.controllers)
            assert dj.certify_ren(Ki, p.qsr).holds  # its own SDP, not the trainer's pair
            pred = dj.ren_predict(Ki, dj.Windows(x0, p.test.y, p.test.u))
            J = np.mean(np.sum((np.asarray(pred) - target) ** 2, axis=(1, 2)))
            np.testing.assert_allclose(report.imitation_error[i], J / J0, rtol=1e-10)


def test_evaluate_a_memoryless_network_on_a_problem_without_state(problems):
    """The MLP has no order: on a problem whose windows start at rest its loops used to
    fail with `AttributeError: n_state`. The errors are checked against a plain loop."""
    p = problems["chain4_4x4_io"]
    assert p.test.x0 is None
    keys = jr.split(jr.PRNGKey(0), 2)
    Ks = jax.vmap(lambda k: dj.MLPController(k, p.facts.n_out, p.facts.n_in, (4,),
                                             dtype=jnp.float64))(keys)
    rep = zoo.evaluate(p, lambda t: Ks)
    target = -np.asarray(p.test.u, np.float64)
    J0 = np.mean(np.sum(target**2, axis=(1, 2)))
    for i in range(2):
        f = jax.tree.map(lambda M: M[i], Ks).mlp
        pred = np.asarray(jax.vmap(jax.vmap(f))(p.test.y))
        J = np.mean(np.sum((pred - target) ** 2, axis=(1, 2)))
        np.testing.assert_allclose(rep.imitation_error[i], J / J0, rtol=1e-10)
    assert rep.stable.shape == (2,) and rep.certified.shape == (2,)
    assert not rep.certified.any()


def _zero_like(t, i):
    n, pp, m = t.n_state, t.windows.n_in, t.windows.n_out
    return dj.LTIController(jnp.zeros((n, n)), jnp.zeros((n, pp)), jnp.zeros((m, n)),
                            jnp.zeros((m, pp)))


def test_unknown_problem_names_the_argument():
    with pytest.raises(ValueError, match="`name`"):
        zoo.problem("no_such_problem")


def test_fit_gd_defaults_stay_finite_on_the_held_out_half(problems):
    """`fit_gd`'s default step (Adam) never diverges on problems nobody tuned it on; the
    paper's rule at PGD's default rate, run the same way, does (so the check has teeth)."""
    paper_diverged, needed = 0, len(zoo.HELD_OUT) // 2
    for name in zoo.HELD_OUT:
        p = problems[name]
        kw = dict(num_inits=4, n_state=p.n_state, max_steps=40, atol=0.0, rtol=0.0, throw=False)
        res = dj.fit_gd(jr.PRNGKey(0), p.train, **kw)
        assert res.result_names() == ["max_steps"] * 4, name
        hist = np.asarray(res.loss_history)
        assert np.all(np.isfinite(hist)), name
        assert np.all(hist[:, -1] < hist[:, 0]), name
        if paper_diverged < needed:  # each run is a compilation: stop once the point is made
            paper = dj.fit_gd(jr.PRNGKey(0), p.train, learning_rate=1.0, decay=0.99,
                              init_scale=1.0, **kw)  # the paper's rule at PGD's defaults
            paper_diverged += "non_finite" in paper.result_names()
    assert paper_diverged >= needed
    # The failure message is true for GD (nothing certified) and names the fix.
    with pytest.raises(ValueError) as err:
        dj.fit_gd(jr.PRNGKey(0), p.train, learning_rate=1e3, decay=0.99, num_inits=2,
                  n_state=p.n_state, max_steps=40, atol=0.0, rtol=0.0)
    msg = str(err.value)
    assert ("non_finite" in msg and "`learning_rate`" in msg
            and "returns the iterate at which it stopped" in msg)
    assert "certified" not in msg and ".." not in msg
