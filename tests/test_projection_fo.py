"""The first-order projection (`_projection/first_order.py`, `dj.project(method="first_order")`)."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, index

import dissil_jax as dj
from dissil_jax.internal import (
    ConvexifiedLMI,
    projection as projection_mod,
    projection_admm as admm,
    projection_admm_rate as admm_rate,
    projection_fo as fo,
)

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

RATES = {"passive": dj.QSR.passive(2),
         "strict": dj.QSR(-np.eye(2), 0.5 * np.eye(2), 0.5 * np.eye(2))}


def _batch(key, num, n=3):
    return jax.vmap(lambda k: dj.LTIController.random(k, n, 2, 2, scale=1.0))(
        jr.split(key, num))


def _dist(K, T, W=None):
    W = jax.tree.map(jnp.ones_like, K) if W is None else W
    return sum(float(jnp.sum(w * (a - b) ** 2)) for a, b, w in
               zip(jax.tree.leaves(K), jax.tree.leaves(T), jax.tree.leaves(W)))


def _metric(key, K, spread=2.0):
    """Positive per-entry weights over about e^(+-2 spread): Adam's sqrt(nu) spans decades."""
    leaves, tree = jax.tree.flatten(K)
    keys = jr.split(key, len(leaves))
    return jax.tree.unflatten(tree, [jnp.exp(spread * jr.normal(k, a.shape))
                                     for k, a in zip(keys, leaves)])


@pytest.mark.parametrize("name", RATES)
def test_lmi_matrix_is_the_convexified_lmi(getkey, name):
    # Built independently: the host class assembles M from its affine basis.
    qsr, n = RATES[name], 3
    K = dj.LTIController.random(getkey(), n, 2, 2, scale=1.0)
    X, Y = jr.normal(getkey(), (2, n, n))
    P, Pt = X @ X.T + jnp.eye(n), Y @ Y.T + jnp.eye(n)
    lmi = ConvexifiedLMI(n, 2, 2, qsr)
    x = lmi.layout.pack(*(np.asarray(M) for M in (K.A, K.B, K.C, K.D)), np.asarray(P))
    np.testing.assert_allclose(fo.lmi_matrix(K.A, K.B, K.C, K.D, P, Pt, qsr),
                               lmi.evaluate(x, np.asarray(Pt)), atol=1e-12)


def test_psd_part_matches_eigh(getkey):
    X = jr.normal(getkey(), (9, 9))
    X = X + X.T
    w, V = np.linalg.eigh(np.asarray(X))
    ref = (V * np.maximum(w, 0)) @ V.T
    # The scaled Newton-Schulz schedule resolves eigenvalues above 1e-7 |X|_F; these are
    # O(1) and well separated from 0, so the two agree to round-off after the quadratic phase.
    assert np.min(np.abs(w)) > 1e-3
    np.testing.assert_allclose(fo.psd_part(X), ref, atol=1e-10)


@pytest.mark.parametrize("name", RATES)
def test_first_order_agrees_with_clarabel_and_is_certified(getkey, monkeypatch, name):
    monkeypatch.setattr(fo, "TOL_FO", 1e-7)  # tight: the comparison below is at 1e-3
    monkeypatch.setattr(fo, "MARGIN_FO", 1e-6)
    monkeypatch.setattr(fo, "MAX_ITER_FO", 20000)
    qsr, K = RATES[name], _batch(getkey(), 3)
    P_ref = jnp.broadcast_to(jnp.eye(3), (3, 3, 3))
    fo.FALLBACKS["rows"] = 0
    a = dj.project(K, qsr, P_ref, method="first_order")
    b = dj.project(K, qsr, P_ref, method="clarabel")
    assert fo.FALLBACKS["rows"] == 0  # the first-order results passed the check themselves
    for i in range(3):
        Ka, Kb, Ki = index(a.controller, i), index(b.controller, i), index(K, i)
        assert dissipation_ok(Ka, qsr, a.P[i])
        # The first-order solve aims at the margin 1e-4 (Clarabel: eps = 1e-6) and stops
        # at residuals ~1e-6 |M|: the solutions differ by about that margin shift times
        # the constraint's sensitivity (O(1) here), so 1e-3 on entries and on the
        # distance relative to the distance moved.
        assert max(float(jnp.abs(x - y).max()) for x, y in
                   zip(jax.tree.leaves(Ka), jax.tree.leaves(Kb))) < 1e-3
        da, db = _dist(Ka, Ki), _dist(Kb, Ki)
        assert abs(da - db) <= 1e-3 * db + 1e-9


@pytest.mark.parametrize("weighted", [False, True])
def test_vmapped_equals_a_python_loop(getkey, weighted):
    qsr, K = RATES["strict"], _batch(getkey(), 3)
    W = _metric(getkey(), K) if weighted else None
    P_ref = jnp.broadcast_to(jnp.eye(3), (3, 3, 3))
    batched = dj.project(K, qsr, P_ref, method="first_order", metric=W)
    for i in range(3):
        one = dj.project(index(K, i), qsr, jnp.eye(3), method="first_order",
                         metric=None if W is None else index(W, i))
        # A batched while_loop freezes converged rows, so each row runs the same
        # iterations as alone; only the summation order of batched products differs.
        for x, y in zip(jax.tree.leaves(index(batched.controller, i)),
                        jax.tree.leaves(one.controller)):
            np.testing.assert_allclose(x, y, atol=1e-9)


@pytest.mark.parametrize("weighted", [False, True])
def test_fallback_to_clarabel_when_the_budget_is_too_small(getkey, monkeypatch, weighted):
    qsr, K = RATES["passive"], _batch(getkey(), 2)
    W = _metric(getkey(), K) if weighted else None  # the fallback projects in it too
    monkeypatch.setattr(fo, "MAX_ITER_FO", 1)  # one ADMM step: far from feasible
    # and no repair towards the static point (as for a supply rate without one)
    monkeypatch.setattr(admm_rate, "static_point", lambda qsr: (np.zeros((2, 2)), -1.0))
    fo.FALLBACKS["rows"] = 0
    a = dj.project(K, qsr, method="first_order", metric=W)
    b = dj.project(K, qsr, method="clarabel", metric=W)
    assert fo.FALLBACKS["rows"] == 2
    assert bool(np.all(a.result == b.result))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):  # Clarabel's own answer
        np.testing.assert_array_equal(x, y)
    for i in range(2):
        assert dissipation_ok(index(a.controller, i), qsr, a.P[i])


def test_method_argument(getkey):
    K = _batch(getkey(), 1)
    with pytest.raises(ValueError, match="`method`"):
        dj.project(K, RATES["passive"], method="admm")
    assert not fo.use_first_order("auto", K.n_state, False, RATES["passive"])  # n = 3: Clarabel
    assert fo.use_first_order("first_order", K.n_state, False, RATES["passive"])
    assert fo.use_first_order("first_order", K.n_state, True, RATES["passive"])  # with a metric too
    # an indefinite Q (here Q = 0.5 I > 0) needs the linearisation only Clarabel's path has
    indefinite = dj.QSR(0.5 * np.eye(2), 0.5 * np.eye(2), -2.0 * np.eye(2))
    assert not fo.use_first_order("auto", K.n_state, False, indefinite)
    with pytest.raises(ValueError, match="`qsr.Q` negative semidefinite"):
        dj.project(K, indefinite, method="first_order")


def test_pgd_with_the_first_order_projection(getkey):
    # Every PGD iterate goes through the exact check (the callback after ADMM).
    from helpers import expert_windows

    w = expert_windows(0, 2, 1, 1)
    qsr = dj.QSR.passive(1)
    for kw in (dict(learning_rate=1.0), {}):  # the paper's rule; Adam, in its metric
        res = dj.fit_pgd(getkey(), w, qsr, num_inits=3, max_steps=5, atol=0.0, rtol=0.0,
                         method="first_order", **kw)
        assert bool(res.certified.all())
        for i in range(3):
            assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])


def test_psd_part_resolves_small_eigenvalues(getkey):
    # Eigenvalues spread over [1e-6, 1] in magnitude, both signs: the schedule starts at
    # 1e-7 |X|_F (|X|_F ~ 1.5 here), so all are resolved; the projection error is round-off
    # of ~25 products of O(1) matrices.
    n = 12
    Q, _ = np.linalg.qr(np.asarray(jr.normal(getkey(), (n, n))))
    w = np.logspace(-6, 0, n) * np.where(np.arange(n) % 2, 1.0, -1.0)
    X = (Q * w) @ Q.T
    ref = (Q * np.maximum(w, 0)) @ Q.T
    np.testing.assert_allclose(fo.psd_part(jnp.asarray(X)), ref, atol=1e-12)


def _kappa_ref(key, n, cond):
    """A reference storage with condition number `cond` (PGD reaches ~1e3)."""
    Q, _ = np.linalg.qr(np.asarray(jr.normal(key, (n, n))))
    return jnp.asarray((Q * np.logspace(0, np.log10(cond), n)) @ Q.T / cond)


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("name", RATES)
def test_ill_conditioned_reference_agrees_with_clarabel(getkey, monkeypatch, name, weighted):
    # The congruence by P~^{-1/2} keeps ADMM's work independent of cond(P~). With a tight
    # tolerance (1e-7 relative) and the scaled slack 1e-6 the solution is Clarabel's to the
    # sensitivity of the projection to these (O(1) here): 1e-3 on the distance. With a
    # metric (weights over e^+-4, the consensus block) the distance is the weighted one.
    monkeypatch.setattr(fo, "TOL_FO", 1e-7)
    monkeypatch.setattr(fo, "MARGIN_FO", 1e-6)
    monkeypatch.setattr(fo, "MAX_ITER_FO", 20000)
    qsr, n = RATES[name], 4
    K = _batch(getkey(), 2, n)
    W = _metric(getkey(), K) if weighted else None
    P_ref = jnp.stack([_kappa_ref(getkey(), n, 1e3) for _ in range(2)])
    fo.FALLBACKS["rows"] = 0
    a = dj.project(K, qsr, P_ref, method="first_order", throw=False, metric=W)
    b = dj.project(K, qsr, P_ref, method="clarabel", throw=False, metric=W)
    assert fo.FALLBACKS["rows"] == 0
    for i in range(2):
        Ki, Wi = index(K, i), None if W is None else index(W, i)
        assert dissipation_ok(index(a.controller, i), qsr, a.P[i])
        da, db = (_dist(index(r.controller, i), Ki, Wi) for r in (a, b))
        assert abs(da - db) <= 1e-3 * db + 1e-9
    if weighted:  # and the metric matters: the Frobenius projection is far in it
        c = dj.project(K, qsr, P_ref, method="first_order", throw=False)
        for i in range(2):
            Ki, Wi = index(K, i), index(W, i)
            assert _dist(index(c.controller, i), Ki, Wi) > 1.2 * _dist(index(a.controller, i),
                                                                      Ki, Wi)


def test_repair_reaches_the_constraint(getkey):
    # An arbitrary (infeasible) scaled point moved towards the static point satisfies
    # Mhat <= -diag(c); checked by eigvalsh, with the margin's size as the slack.
    qsr, n = RATES["strict"], 5
    x = tuple(jr.normal(k, s) for k, s in zip(jr.split(getkey(), 5),
                                               [(n, n), (n, 2), (2, n), (2, 2), (n, n)]))
    x = x[:4] + ((x[4] + x[4].T) / 2,)
    lam = jnp.asarray(np.logspace(-2, 0, n))
    c = 1e-4 * jnp.concatenate([1 / lam, jnp.ones(4), 1 / lam])  # p + r = 2 + 2
    M0 = fo.lmi_matrix(*x, jnp.eye(n), qsr) + jnp.diag(c)
    assert np.linalg.eigvalsh(np.asarray(M0)).max() > 0.1  # far from feasible
    y, t = admm.repair(x, c, qsr)
    assert 0 < float(t) < 1
    M = fo.lmi_matrix(*y, jnp.eye(n), qsr) + jnp.diag(c)
    assert np.linalg.eigvalsh(np.asarray(M)).max() < 0


def test_conditioning_bound_holds(getkey):
    # project's set asks P >= (P_FLOOR / n) tr(P) I; the first-order path meets it to its
    # residual tolerance (1e-4 relative to the scaled LMI, whose X ~ I): 1e-3 of tr(P) / n.
    qsr, n = RATES["passive"], 4
    K = _batch(getkey(), 3, n)
    P_ref = jnp.stack([_kappa_ref(getkey(), n, 1e3) for _ in range(3)])
    a = dj.project(K, qsr, P_ref, method="first_order")
    for P in np.asarray(a.P):
        mean = np.trace(P) / n
        assert np.linalg.eigvalsh(P).min() >= (projection_mod.P_FLOOR - 1e-3) * mean


@pytest.mark.parametrize("weighted", [False, True])
def test_warm_start_from_the_solution_state(getkey, weighted):
    # A second solve of the same problem from the first one's final ADMM state starts at its
    # fixed point: it stops within a few iterations (the penalty adaptation's period) and
    # returns the same projection to the tolerance. With a metric the state holds the
    # consensus block too (the cold one starts it at the target).
    qsr, n = RATES["passive"], 4
    K = _batch(getkey(), 3, n)
    W = _metric(getkey(), K) if weighted else None
    P_ref = jnp.stack([_kappa_ref(getkey(), n, 1e2) for _ in range(3)])
    cold = jax.vmap(lambda K: fo.cold_state(n, qsr, K.A.dtype,
                                            (K.A, K.B, K.C, K.D) if weighted else None))(K)
    warm_fn = projection_mod.project_first_order_warm
    active = jnp.ones(3, bool)
    before = fo.FALLBACKS["iterations"]
    # at `project`'s tolerance (PGD's own is looser), so that the cold call below is the same
    a, state = warm_fn(K, qsr, P_ref, cold, active=active, eps=1e-6, metric=W, tol=fo.TOL_FO)
    first = fo.FALLBACKS["iterations"] - before
    before = fo.FALLBACKS["iterations"]
    b, _ = warm_fn(K, qsr, P_ref, state, active=active, eps=1e-6, metric=W, tol=fo.TOL_FO)
    second = fo.FALLBACKS["iterations"] - before
    assert second <= 3 * admm.ADAPT_EVERY < first
    for i in range(3):
        assert dissipation_ok(index(b.controller, i), qsr, b.P[i])
        # both stop at residuals 1e-4 |Mhat|; the distance moves by that relative amount
        Wi = None if W is None else index(W, i)
        da, db = (_dist(index(r.controller, i), index(K, i), Wi) for r in (a, b))
        assert abs(da - db) <= 1e-3 * da + 1e-9
    # the cold call through `project` is the same computation as the first one
    c = dj.project(K, qsr, P_ref, method="first_order", metric=W)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(c)):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_warm_started_pgd_is_certified(getkey):
    # PGD with the first-order path carries the ADMM state across steps (its `PGDSteps.warm`):
    # every returned controller passes the independent check.
    from helpers import expert_windows

    w = expert_windows(0, 3, 1, 1)
    qsr = dj.QSR.passive(1)
    res = dj.pgd_run(getkey(), w, qsr, num_inits=3, max_steps=4, atol=0.0, rtol=0.0,
                     learning_rate=1.0, method="first_order", throw=False)
    assert bool(res.certified.all())
    for i in range(3):
        assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])


def test_auto_follows_the_measured_order(getkey, monkeypatch):
    qsr = RATES["passive"]
    lo = fo.AUTO_MIN_ORDER
    assert lo is not None and lo > 6  # the paper's sizes (1, 6) keep Clarabel
    assert fo.use_first_order("auto", lo, False, qsr)
    assert not fo.use_first_order("auto", lo - 1, False, qsr)
    lo_w = fo.AUTO_MIN_ORDER_METRIC  # with a metric (projected Adam's)
    assert lo_w is not None and lo_w > 6
    assert fo.use_first_order("auto", lo_w, True, qsr)
    assert not fo.use_first_order("auto", lo_w - 1, True, qsr)
    monkeypatch.setattr(fo, "AUTO_MIN_ORDER", None)
    assert not fo.use_first_order("auto", lo, False, qsr)
    monkeypatch.setattr(fo, "AUTO_MIN_ORDER_METRIC", None)
    assert not fo.use_first_order("auto", lo_w, True, qsr)


def _custom_calls(fn, *args, platform):
    import re

    text = jax.jit(fn).trace(*args).lower(lowering_platforms=(platform,)).as_text()
    return set(re.findall(r"stablehlo\.custom_call @(\w+)", text))


def test_eigh_of_the_reference_is_host_on_cpu_and_device_elsewhere(getkey):
    # On a CPU, P~'s eigen-decomposition is a host callback (a batched LAPACK call inside
    # PGD's loop can deadlock XLA's thread pool); lowered for a GPU or TPU it is device code
    # with no callback. Both branches return the same decomposition.
    X = jr.normal(getkey(), (3, 5, 5))
    P = X @ jnp.swapaxes(X, 1, 2) + jnp.eye(5)
    fn = jax.vmap(fo._eigh)
    cpu = _custom_calls(fn, P, platform="cpu")
    assert any("callback" in c for c in cpu) and not any("lapack" in c for c in cpu)
    for platform in ("cuda", "tpu"):
        calls = _custom_calls(fn, P, platform=platform)
        assert not any("callback" in c for c in calls), (platform, calls)
    w_host, V_host = fn(P)
    w_dev, V_dev = jax.vmap(fo._eigh_device)(P)  # the device branch, run here
    # float64; eigenvalues >= 1 and |P| ~ 30: both backward stable, agreement to ~1e-14
    np.testing.assert_allclose(w_dev, w_host, rtol=1e-12)
    for i in range(3):  # eigenvectors up to sign: the reconstructions agree
        np.testing.assert_allclose((V_dev[i] * w_dev[i]) @ V_dev[i].T, P[i], atol=1e-10)


def test_a_far_repair_goes_to_clarabel(getkey):
    """On a rate with little room (gain bound 0.01: R = 1e-4) ADMM's residual tolerance,
    relative to the scaled LMI, left answers far from feasible, and the repair moved them
    most of the way to the zero controller: certified, but twice Clarabel's distance from
    the target. A repair step above `REPAIR_MAX` now hands the row to Clarabel, so the
    answer is the projection (both Clarabel's; a second, independent check: the distance)."""
    qsr, K = dj.QSR.bounded_gain(0.01, n_in=2, n_out=2), _batch(getkey(), 3, n=4)
    before = dict(fo.FALLBACKS)
    a = dj.project(K, qsr, method="first_order")
    b = dj.project(K, qsr, method="clarabel")
    assert fo.FALLBACKS["far_repairs"] - before["far_repairs"] >= 1
    for i in range(3):
        assert dissipation_ok(index(a.controller, i), qsr, a.P[i])
        da, db = (_dist(index(r.controller, i), index(K, i)) for r in (a, b))
        assert da <= db * (1 + 1e-6) + 1e-12
