"""`dj.project` (paper eq. 13): certified results, batching, caching, errors and the thread pool."""

import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dissipation_matrix, dissipation_ok, index, tree_allclose
from hypothesis import given, settings, strategies as st

import dissil_jax as dj
from dissil_jax.internal import (
    LRU,
    outcome as _outcome,
    projection as _projection,
    projection_cache as _cache,
    sdp as _sdp,
)

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

Outcome = type("Codes", (), {n: _outcome.code(n) for n in _outcome.NAMES})  # codes by name


def _with_status(K, qsr, P_ref=None, active=True, **kw):
    """`(K_proj, P, outcome codes)` of `dj.project(..., throw=False)`."""
    proj = dj.project(K, qsr, P_ref, throw=False, active=active, **kw)
    return proj[0], proj[1], _outcome.codes(proj.result)

CASES = [
    ("nonlinear-paper", dj.QSR(-29.867, 3.556, 0.601), 1),
    ("passive-6x3", dj.QSR.passive(3), 6),
    ("conic", dj.QSR.conic(-0.5, 2.0, dim=2), 3),
    ("bounded-gain-rect", dj.QSR.bounded_gain(0.7, n_in=3, n_out=2), 2),
    ("degenerate-conic", dj.QSR.degenerate_conic(-0.2, dim=2), 2),
]


def _random_targets(key, n, qsr, batch, scale=1.0):
    keys = jax.random.split(key, batch)
    return jax.vmap(lambda k: dj.LTIController.random(k, n, qsr.n_in, qsr.n_out, scale=scale))(keys)


@pytest.mark.parametrize("name, qsr, n", CASES, ids=[c[0] for c in CASES])
def test_projection_certified_eager_jit_vmap(getkey, name, qsr, n):
    Ks = _random_targets(getkey(), n, qsr, 4)
    K0 = index(Ks, 0)
    eager = dj.project(K0, qsr)
    jitted = jax.jit(lambda K: dj.project(K, qsr))(K0)
    # Solvers are reused across calls and threads with in-place updates; results must not
    # depend on which solver object handled which target.
    assert tree_allclose(eager, jitted, rtol=1e-10, atol=1e-12)
    batch = jax.jit(jax.vmap(lambda K: dj.project(K, qsr)))(Ks)
    leading = dj.project(Ks, qsr)  # leading batch axes without an explicit vmap
    for i in range(4):
        Ki, Pi = index(batch, i)
        assert dissipation_ok(Ki, qsr, Pi)
        assert dj.certify(Ki, qsr).holds
        # the batched host path equals the one-at-a-time path
        assert tree_allclose(index(leading, i), index(batch, i), rtol=1e-10, atol=1e-12)
    assert tree_allclose(index(batch, 0), eager, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name, qsr, n", CASES[:3], ids=[c[0] for c in CASES[:3]])
def test_certified_controller_projects_onto_itself(getkey, name, qsr, n):
    K, P = dj.project(_random_targets(getkey(), n, qsr, 1), qsr)
    K, P = index(K, 0), P[0]
    K2, P2 = dj.project(K, qsr, P)
    assert tree_allclose(K2, K, rtol=0, atol=0) and np.array_equal(P2, P)
    # also under jit, with the outcome: unchanged, no solve
    proj = jax.jit(lambda K, P: dj.project(K, qsr, P, throw=False))(K, P)
    assert bool(proj.result == dj.Outcome.unchanged)


def test_projection_is_no_further_than_a_known_feasible_point(getkey):
    # Any certified controller K_c is feasible for the set at P~ = its own P, so the projection
    # of a target with P_ref = P_c is at least as close to the target as K_c.
    qsr = dj.QSR.passive(2)
    Kc, Pc = dj.project(dj.LTIController.random(getkey(), 2, 2, 2, scale=1.0), qsr)
    target = jax.tree.map(lambda a: a + 0.3, Kc)
    Kp, _ = dj.project(target, qsr, Pc)
    dist = lambda K: sum(float(jnp.sum((a - b) ** 2)) for a, b in
                         zip(jax.tree.leaves(K), jax.tree.leaves(target)))
    assert dist(Kp) <= dist(Kc) + 1e-8
    assert dist(Kp) < dist(Kc)  # and it actually moved towards the target


def test_projection_in_float32_is_still_certified(getkey):
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    K = dj.LTIController.random(getkey(), 1, 1, 1, scale=3.0).astype(jnp.float32)
    Kp, P = dj.project(K, qsr)
    assert Kp.A.dtype == jnp.float32 and P.dtype == jnp.float32
    assert dissipation_ok(Kp, qsr, P)


def test_positive_q_accepted():
    # An indefinite (here positive) Q is linearised, not refused (tests/test_indefinite_q.py).
    qsr = dj.QSR(1.0, 0.5, 1.0)
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    Kp, P = dj.project(K, qsr)
    assert dissipation_ok(Kp, qsr, P)


def test_shape_mismatch_rejected():
    K = dj.LTIController.random(jax.random.PRNGKey(0), 2, 2, 1)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.project(K, dj.QSR.passive(2))
    with pytest.raises(ValueError, match="`P_ref`"):
        dj.project(K, dj.QSR.bounded_gain(1.0, n_in=2, n_out=1), jnp.eye(3))


def test_infeasible_supply_rate_raises():
    # Q = -I, S = 0, R = -I: w = -|y|^2 - |u|^2 < 0, no system is dissipative.
    qsr = dj.QSR(-1.0, 0.0, -1.0)
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    # refused up front as a bad argument, naming `qsr`, whatever `throw` says: no static
    # feedthrough is strictly dissipative, so no controller of any order is
    for throw in (True, False):
        with pytest.raises(ValueError, match="`qsr` is infeasible"):
            dj.project(K, qsr, throw=throw)
    with pytest.raises(Exception, match="infeasible"):
        jax.block_until_ready(jax.jit(lambda K: dj.project(K, qsr))(K))


def test_qsr_is_a_static_argument():
    """A supply rate passes through `jax.jit` like any static value, by value."""
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    qsr = dj.QSR.passive(1)
    assert hash(qsr) == hash(dj.QSR.passive(1))
    eager = dj.project(K, qsr)[0]
    static = jax.jit(lambda K, q: dj.project(K, q)[0], static_argnums=1)(K, qsr)
    as_pytree = jax.jit(lambda K, q: dj.project(K, q)[0])(K, dj.QSR.passive(1))
    assert tree_allclose(static, eager, rtol=0, atol=0)
    assert tree_allclose(as_pytree, eager, rtol=0, atol=0)


@settings(max_examples=15, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 3),
    p=st.integers(1, 2),
    scale=st.floats(0.05, 5.0),
    kind=st.sampled_from(["passive", "gain", "conic"]),
)
def test_property_every_projection_is_certified(seed, n, p, scale, kind):
    qsr = {"passive": dj.QSR.passive(p), "gain": dj.QSR.bounded_gain(1.5, n_in=p, n_out=p),
           "conic": dj.QSR.conic(0.1, 3.0, dim=p)}[kind]
    K = dj.LTIController.random(jax.random.PRNGKey(seed), n, p, p, scale=scale)
    Kp, P = dj.project(K, qsr)
    assert dissipation_ok(Kp, qsr, P)
    K2, P2 = dj.project(Kp, qsr, P)
    assert tree_allclose(K2, Kp, rtol=0, atol=0)


# -- options: active, eps, reg, refine -------------------------------------------------------


def _dist(K, target):
    return sum(float(jnp.sum((a - b) ** 2)) for a, b in
               zip(jax.tree.leaves(K), jax.tree.leaves(target)))


def test_inactive_lanes_are_skipped(getkey):
    qsr = dj.QSR.passive(2)
    Ks = _random_targets(getkey(), 2, qsr, 3, scale=1.0)
    P_ref = jnp.stack([2.0 * jnp.eye(2)] * 3)
    active = jnp.array([True, False, True])
    jitted = jax.jit(lambda K, P, a: _with_status(K, qsr, P, a))
    eager = lambda K, P, a: _with_status(K, qsr, P, a)
    for fn in (eager, jitted):
        for ref in (None, P_ref):
            Kp, P, status = fn(Ks, ref, active)
            assert [int(s) for s in status] == [Outcome.solved, Outcome.skipped,
                                                Outcome.solved]
            assert tree_allclose(index(Kp, 1), index(Ks, 1), rtol=0, atol=0)
            np.testing.assert_array_equal(P[1], 2.0 * np.eye(2) if ref is not None else np.eye(2))
            for i in (0, 2):
                assert not tree_allclose(index(Kp, i), index(Ks, i))
                assert dissipation_ok(index(Kp, i), qsr, P[i])
    # a single controller, inactive: returned as is, no solve
    K0 = index(Ks, 0)
    Kp, P, status = _with_status(K0, qsr, active=False)
    assert int(status) == Outcome.skipped and tree_allclose(Kp, K0, rtol=0, atol=0)
    assert not dj.certify(K0, qsr).holds  # so SKIPPED really did not project it


def test_eps_is_the_margin_of_the_exact_lmi(getkey):
    """With P_ref = I the convexified LMI <= -eps I implies KYP(P) <= -eps I and P >= eps I."""
    qsr = dj.QSR.passive(2)
    K = dj.LTIController.random(jax.random.PRNGKey(1), 2, 2, 2, scale=1.0)
    out = {}
    for eps in (1e-6, 0.05):
        Kp, P, status = _with_status(K, qsr, jnp.eye(2), eps=eps)
        assert int(status) == Outcome.solved
        lam = np.linalg.eigvalsh(dissipation_matrix(Kp, qsr, P))[-1]
        assert lam <= -eps * (1 - 1e-6)
        assert np.linalg.eigvalsh(np.asarray(P))[0] >= eps * (1 - 1e-6)
        out[eps] = (lam, _dist(Kp, K))
    assert out[0.05][0] < out[1e-6][0] - 0.04  # the margin is really imposed ...
    assert out[0.05][1] > out[1e-6][1]  # ... and costs distance to the target


def test_reg_pulls_P_to_the_reference(getkey):
    qsr = dj.QSR.conic(-0.5, 2.0, dim=2)
    K = dj.LTIController.random(jax.random.PRNGKey(1), 2, 2, 2, scale=1.0)
    P_ref = 2.0 * jnp.eye(2)
    gap = {}
    for reg in (1e-6, 1e3):
        Kp, P, status = _with_status(K, qsr, P_ref, reg=reg)
        assert int(status) == Outcome.solved and dissipation_ok(Kp, qsr, P)
        gap[reg] = (np.linalg.norm(np.asarray(P) - 2.0 * np.eye(2)), _dist(Kp, K))
    assert gap[1e3][0] < 1e-2 < gap[1e-6][0]
    assert gap[1e3][1] > gap[1e-6][1]  # pinning P costs distance to the target


def test_refine_rounds_move_closer(getkey):
    qsr = dj.QSR.passive(2)
    K = dj.LTIController.random(jax.random.PRNGKey(1), 2, 2, 2, scale=1.0)
    dists = {}
    for refine in (0, 1, 2, 3, 5):
        Kp, P, status = _with_status(K, qsr, refine=refine)
        assert int(status) == Outcome.solved and dissipation_ok(Kp, qsr, P)
        dists[refine] = _dist(Kp, K)
    assert dists[0] == dists[1]  # at least one round
    assert dists[1] > dists[2] > dists[3] > dists[5]
    assert dists[5] < 0.2 * dists[1]


def test_solver_caches_are_bounded_and_rebuilt_alike(getkey, monkeypatch):
    """A sweep over supply rates keeps at most `CACHE_SIZE` LMIs and solvers per thread
    (unbounded, the caches grew with every rate); a rate whose entries were dropped is
    rebuilt and projects bit for bit as before."""
    monkeypatch.setattr(_cache, "CACHE_SIZE", 2)
    monkeypatch.setattr(_cache, "_LMI_CACHE", LRU(2))
    monkeypatch.setattr(_cache, "_LOCAL", threading.local())
    K = dj.LTIController.random(getkey(), 2, 1, 1, scale=1.0)
    rates = [dj.QSR.bounded_gain(g, n_in=1, n_out=1) for g in (0.5, 0.6, 0.7, 0.8)]
    first = dj.project(K, rates[0])
    for qsr in rates[1:]:
        dj.project(K, qsr)
        assert len(_cache._LMI_CACHE) <= 2
    assert (rates[0], 2) not in _cache._LMI_CACHE
    again = dj.project(K, rates[0])
    assert tree_allclose(again, first, rtol=0, atol=0)
    # this thread's solvers, used the same way
    for qsr in rates:
        _cache.thread_solver(qsr, 2, 1e-6, 0.0)
    solvers = _cache._LOCAL.solvers
    assert len(solvers) == 2 and solvers.keys()[-1][0] == rates[-1]


def test_lru_drops_the_least_recently_used():
    lru = LRU(2)
    lru.put("a", 1)
    lru.put("b", 2)
    assert lru.get("a") == 1  # "a" is now the most recent
    lru.put("c", 3)
    assert "b" not in lru and lru.keys() == ["a", "c"]
    assert lru.get_or_build("d", lambda: 4) == 4 and lru.keys() == ["c", "d"]
    assert lru.get_or_build("c", lambda: 99) == 3  # present: not rebuilt


# -- failures never return an uncertified controller ------------------------------------------


def _inject(monkeypatch, obj, name, value):
    """Patch `obj.name` and start from empty thread-local solver caches (dropped afterwards),
    so that no solver built before the patch is reused and none built with it survives."""
    monkeypatch.setattr(_cache, "_LOCAL", threading.local())
    monkeypatch.setattr(obj, name, value)


def _failure_cases(qsr, key):
    """A target, and a batch [certified by P_ref, uncertified] with P_ref."""
    Kc, Pc = dj.project(dj.LTIController.random(key, 2, 2, 2, scale=1.0), qsr)
    target = jax.tree.map(lambda a: a + 1.0, Kc)
    assert not dj.certify(target, qsr, P=Pc).holds
    batch = jax.tree.map(lambda a, b: jnp.stack([a, b]), Kc, target)
    return target, batch, jnp.stack([Pc, Pc])


def _assert_flagged(qsr, target, batch, P_ref, code, match):
    Kp, P, status = _with_status(target, qsr)
    assert int(status) == code
    assert tree_allclose(Kp, target, rtol=0, atol=0)  # the target, flagged: never a new point
    with pytest.raises(ValueError, match=match):
        dj.project(target, qsr)
    with pytest.raises(Exception, match=match):  # EquinoxRuntimeError via the callback
        jax.block_until_ready(jax.jit(lambda K: dj.project(K, qsr))(target))
    Kb, Pb, sb = _with_status(batch, qsr, P_ref)
    assert int(sb[0]) == Outcome.unchanged and bool(_outcome.failed(int(sb[1])))
    assert tree_allclose(Kb, batch, rtol=0, atol=0)
    assert dissipation_ok(index(Kb, 0), qsr, Pb[0])  # the certified lane is untouched
    return int(sb[1])


def test_solver_failure_is_flagged(getkey, monkeypatch):
    qsr = dj.QSR.passive(2)
    target, batch, P_ref = _failure_cases(qsr, getkey())
    monkeypatch.setattr(_cache, "_LOCAL", threading.local())
    monkeypatch.setitem(_sdp.PROJECTION_SETTINGS, "max_iter", 1)
    code = _assert_flagged(qsr, target, batch, P_ref, Outcome.solver_failed, "Clarabel failed")
    assert code == Outcome.solver_failed


def _corrupt_solves(monkeypatch, broken=lambda n: True):
    """Make Clarabel's answers unstable (A + 5 * ones: dissipative for no P) on the calls
    `broken(n)` picks; returns the list of the margins eps the solver was asked for."""
    original, original_data = _cache._ProjectionSolver.solve, _cache._ProjectionSolver.data
    calls, margins = [], []

    def data(self, targets, P_tilde, eps, weights):
        margins.extend(np.asarray(eps).tolist())
        return original_data(self, targets, P_tilde, eps, weights)

    def corrupted(self, q, vals, b, diag):
        x, status, t = original(self, q, vals, b, diag)
        calls.append(margins[len(calls)])
        if x is not None and broken(len(calls)):
            x = x.copy()
            x[: self.lmi.nA] += 5.0
        return x, status, t

    _inject(monkeypatch, _cache._ProjectionSolver, "solve", corrupted)
    monkeypatch.setattr(_cache._ProjectionSolver, "data", data)
    return calls


def test_uncertified_solution_is_never_returned(getkey, monkeypatch):
    """A solver answer that fails the exact KYP check (here: made unstable) is refused."""
    qsr = dj.QSR.passive(2)
    target, batch, P_ref = _failure_cases(qsr, getkey())
    calls = _corrupt_solves(monkeypatch)
    _assert_flagged(qsr, target, batch, P_ref, Outcome.not_certified,
                    "exact float64 KYP check")
    # the margin was enlarged before giving up
    assert max(calls) >= 0.99e4 * min(calls)


def test_uncertified_solution_status_with_reference(getkey, monkeypatch):
    qsr = dj.QSR.passive(2)
    _, batch, P_ref = _failure_cases(qsr, getkey())
    _corrupt_solves(monkeypatch)
    _, _, sb = _with_status(batch, qsr, P_ref)
    assert int(sb[1]) == Outcome.not_certified


def test_enlarged_margin_rescues_a_rounding_failure(getkey, monkeypatch):
    """Only the first attempt is broken: the retry with 100x eps is returned, certified."""
    qsr = dj.QSR.passive(2)
    target, _, _ = _failure_cases(qsr, getkey())
    calls = _corrupt_solves(monkeypatch, broken=lambda n: n == 1)
    Kp, P, status = _with_status(target, qsr, refine=1)
    assert int(status) == Outcome.solved and dissipation_ok(Kp, qsr, P)
    assert calls == [pytest.approx(1e-6), pytest.approx(1e-4)]


def test_projection_option_errors(getkey):
    qsr = dj.QSR.passive(1)
    K = dj.LTIController.random(getkey(), 2, 1, 1)
    Ks = _random_targets(getkey(), 2, qsr, 3)
    for kw, name in [(dict(eps=0.0), "`eps`"), (dict(eps=-1e-6), "`eps`"),
                     (dict(eps=np.nan), "`eps`"), (dict(reg=-1.0), "`reg`"),
                     (dict(reg=np.inf), "`reg`"), (dict(refine=-1), "`refine`"),
                     (dict(refine=1.5), "`refine`")]:
        with pytest.raises(ValueError, match=name):
            dj.project(K, qsr, **kw)
    with pytest.raises(ValueError, match="`active`"):
        _with_status(Ks, qsr, None, jnp.array([True, False]))
    with pytest.raises(ValueError, match="`active`"):
        _with_status(K, qsr, None, jnp.array([True, False]))
    for P_ref, what in [(jnp.array([[1.0, np.nan], [np.nan, 1.0]]), "NaN"),
                        (jnp.array([[1.0, 0.5], [0.0, 1.0]]), "symmetric"),
                        (-jnp.eye(2), "positive definite")]:
        with pytest.raises(ValueError, match=f"`P_ref`.*{what}"):
            dj.project(K, qsr, P_ref)
    with pytest.raises(ValueError, match="`P_ref`"):
        dj.project(Ks, qsr, jnp.stack([jnp.eye(2), jnp.eye(2), -jnp.eye(2)]))
    with pytest.raises(ValueError, match="`K`"):
        dj.project((K.A, K.B, K.C, K.D), qsr)
    with pytest.raises(ValueError, match="`qsr`"):
        dj.project(K, "passive")
    with pytest.raises(ValueError, match="`A`"):
        dj.project(dj.LTIController(np.eye(2, dtype=bool), np.ones((2, 1)), np.ones((1, 2)),
                                    np.ones((1, 1))), qsr)


# -- the storage's conditioning and the retry from a scaled identity ---------------------------


def test_projected_storage_is_well_conditioned(getkey):
    """lambda_min(P) >= rho * mean eigenvalue (rho = P_FLOOR), to Clarabel's tolerance."""
    qsr, n = dj.QSR.passive(2), 5
    Kp, P = dj.project(_random_targets(getkey(), n, qsr, 6, scale=2.0), qsr)
    for i in range(6):
        lam = np.linalg.eigvalsh(np.asarray(P[i]))
        # feasibility tolerance 1e-8 of Clarabel, relative to the data (entries of order |P|)
        assert lam[0] >= _projection.P_FLOOR * lam.mean() - 1e-7 * (1 + lam[-1])
        assert dissipation_ok(index(Kp, i), qsr, P[i])


def test_projection_at_a_degenerate_reference_is_retried(getkey):
    """A P_ref whose smallest eigenvalue is below the margin eps leaves the linearised set
    empty (eps I <= P <= 2 P_ref - eps I); the projection starts again from a scaled identity."""
    qsr, n = dj.QSR.passive(2), 4
    Kc, Pc = dj.project(dj.LTIController.random(getkey(), n, 2, 2, scale=1.0), qsr)
    lam, V = np.linalg.eigh(np.asarray(Pc))
    lam[0] = 5e-7  # below eps = 1e-6
    P_bad = (V * lam) @ V.T
    target = jax.tree.map(lambda a: a + 0.3, Kc)
    assert not dj.certify(target, qsr, P=P_bad).holds
    # linearised at P_bad alone, the projection fails
    layout = _cache.lmi(qsr, n).layout
    theta = layout.pack(target.A, target.B, target.C, target.D)[None]
    _, codes = _projection._project_rows(
        qsr, theta, P_bad[None], np.ones_like(theta), 1, eps=1e-6, reg=1e-6,
        dtype=np.float64, shards=1)
    assert int(codes[0]) != Outcome.solved
    Kp, P, status = _with_status(target, qsr, P_bad)
    assert int(status) == Outcome.solved
    assert dissipation_ok(Kp, qsr, P)
