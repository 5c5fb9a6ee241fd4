"""Bad inputs raise a `ValueError` that names the argument (never a silent broadcast, cast or
truncation, nor an error from deep inside JAX or scipy); and `certify` of a static
controller, which has no storage to search."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import through_solves

import dissil_jax as dj
import dissil_jax.internal as dji


def _lti(A, B, C, D):
    f = lambda M: jnp.atleast_2d(jnp.asarray(M, jnp.float64))
    return dj.LTIController(f(A), f(B), f(C), f(D))


def _static(D):
    D = jnp.atleast_2d(jnp.asarray(D, jnp.float64))
    m, p = D.shape[-2:]
    batch = D.shape[:-2]
    return dj.LTIController(jnp.zeros(batch + (0, 0)), jnp.zeros(batch + (0, p)),
                            jnp.zeros(batch + (m, 0)), D)


# --- 1. output/input widths of the controller against the windows ------------------------


@pytest.fixture
def K11():
    return _lti(0.5, 1.0, 1.0, 1.0)  # one input, one output, one state


@pytest.mark.parametrize("fn", [dj.imitation_loss, dj.predict])
def test_output_width_mismatch_is_refused(K11, fn):
    W = dj.Windows(None, jnp.ones((3, 2, 1)), jnp.ones((3, 2, 2)))  # u has m = 2 columns
    with pytest.raises(ValueError, match=r"`windows.u` has 2 outputs .* 1 \(`K.n_out`\)"):
        fn(K11, W)


@pytest.mark.parametrize("fn", [dj.imitation_loss, dj.predict])
def test_input_width_mismatch_is_refused(K11, fn):
    W = dj.Windows(None, jnp.ones((3, 2, 2)), jnp.ones((3, 2, 1)))  # y has p = 2 columns
    with pytest.raises(ValueError, match=r"`windows.y` has 2 columns .* 1 inputs \(`K.n_in`\)"):
        fn(K11, W)


def test_state_width_mismatch_is_refused(K11):
    W = dj.Windows(jnp.ones((3, 2)), jnp.ones((3, 2, 1)), jnp.ones((3, 2, 1)))
    with pytest.raises(ValueError, match="`windows.x0` has width 2"):
        dj.imitation_loss(K11, W)


def test_width_checks_hold_under_jit_and_vmap(K11):
    """Shapes are static: the checks fire while tracing, also for a vmapped batch."""
    W = dj.Windows(None, jnp.ones((3, 2, 1)), jnp.ones((3, 2, 2)))
    with pytest.raises(ValueError, match="`windows.u`"):
        jax.jit(dj.imitation_loss)(K11, W)
    Ks = jax.tree.map(lambda M: jnp.stack([M, 2 * M]), K11)  # batch of 2, as the trainers
    with pytest.raises(ValueError, match="`windows.u`"):
        jax.vmap(dj.imitation_loss, in_axes=(0, None))(Ks, W)
    good = dj.Windows(None, jnp.ones((3, 2, 1)), jnp.ones((3, 2, 1)))
    losses = jax.jit(jax.vmap(dj.imitation_loss, in_axes=(0, None)))(Ks, good)
    assert losses.shape == (2,)
    np.testing.assert_allclose(losses[0], dj.imitation_loss(K11, good))


def test_rollout_input_width_is_checked(K11):
    with pytest.raises(ValueError, match=r"`u_in` must have shape \[h, 1\]"):
        dj.rollout(K11, jnp.zeros(1), jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match="`u_in`"):
        dj.rollout(K11, None, jnp.zeros(4))
    with pytest.raises(ValueError, match="`u_in`"):
        jax.vmap(dj.rollout, in_axes=(None, None, 0))(K11, None, jnp.zeros((3, 4, 2)))
    assert dj.rollout(K11, None, jnp.ones((4, 1))).shape == (4, 1)


def test_ren_twins_check_widths(K11):
    R = dj.RENController.from_lti(K11, width=2)
    W_m = dj.Windows(None, jnp.ones((3, 2, 1)), jnp.ones((3, 2, 2)))
    W_p = dj.Windows(None, jnp.ones((3, 2, 2)), jnp.ones((3, 2, 1)))
    W_n = dj.Windows(jnp.ones((3, 2)), jnp.ones((3, 2, 1)), jnp.ones((3, 2, 1)))
    for fn in (dj.ren_predict, dj.ren_imitation_loss):
        with pytest.raises(ValueError, match="`windows.u` has 2 outputs"):
            fn(R, W_m)
        with pytest.raises(ValueError, match="`windows.y` has 2 columns"):
            fn(R, W_p)
        with pytest.raises(ValueError, match="`windows.x0` has width 2"):
            fn(R, W_n)
    with pytest.raises(ValueError, match="`u_in`"):
        dj.ren_rollout(R, None, jnp.zeros((4, 2)))
    good = dj.Windows(None, jnp.ones((3, 2, 1)), jnp.ones((3, 2, 1)))
    np.testing.assert_allclose(dj.ren_imitation_loss(R, good), dj.imitation_loss(K11, good))


# --- 2. certify a static controller (n = 0) ------------------------------------------------


def _phi(D, qsr):
    """$\\Phi(D) = R + S^\\top D + D^\\top S + D^\\top QD$, from the definition."""
    D = np.asarray(D, np.float64)
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    return R + S.T @ D + D.T @ S + D.T @ Q @ D


def test_certify_static_controller_matches_an_eigenvalue_computation():
    rng = np.random.default_rng(0)
    supplies = [dj.QSR.passive(2), dj.QSR.bounded_gain(1.5, n_in=2, n_out=2),
                dj.QSR.bounded_gain(0.7, n_in=2, n_out=2)]
    seen = set()
    for qsr in supplies:
        for _ in range(6):
            D = rng.normal(size=(2, 2)) * rng.choice([0.3, 1.0])
            if qsr is supplies[0]:
                D = D @ D.T + rng.choice([-1.0, 0.5]) * np.eye(2)  # passive iff D + D' > 0
            lam = np.linalg.eigvalsh(_phi(D, qsr))[0]
            cert = dj.certify(_static(D), qsr)
            assert cert.P.shape == (0, 0)
            assert cert.source.startswith("static")
            np.testing.assert_allclose(cert.margin, lam, rtol=1e-10, atol=1e-12)
            assert cert.holds == (lam > 1e-9), (D, lam)
            assert cert.result == (dj.Outcome.solved if lam > 0 else dj.Outcome.infeasible)
            seen.add(bool(cert.holds))
    assert seen == {True, False}


def test_certify_static_batched_and_given_P():
    qsr = dj.QSR.passive(1)
    Ks = _static(jnp.array([1.0, -1.0, 0.0]).reshape(3, 1, 1))
    cert = dj.certify(Ks, qsr)
    assert cert.P.shape == (3, 0, 0)
    np.testing.assert_array_equal(cert.holds, [True, False, False])
    assert dj.certify(_static(2.0), qsr, P=np.zeros((0, 0))).holds
    assert not dj.certify(_static(-2.0), qsr, P=np.zeros((0, 0))).holds


# --- 3. Windows dtypes --------------------------------------------------------------------


def test_windows_convert_integers_exactly_to_the_default_float():
    W = dj.Windows(np.arange(6).reshape(3, 2), np.arange(6).reshape(3, 2, 1),
                   -np.ones((3, 2, 1), int))
    for M in (W.x0, W.y, W.u):
        assert M.dtype == jnp.result_type(float)
    np.testing.assert_array_equal(W.y[:, :, 0], np.arange(6).reshape(3, 2))
    with pytest.raises(ValueError, match="`u` is an integer array with entries too large"):
        dj.Windows(None, np.ones((2, 1, 1)), np.full((2, 1, 1), 2**60))
    # the trainers then work (they failed inside `jax.random.normal` on integer data)
    res = dj.fit_gd(jr_key(), W, num_inits=2, max_steps=2)
    assert res.controllers.A.dtype == jnp.result_type(float)


def jr_key():
    return jax.random.PRNGKey(0)


@pytest.mark.parametrize("field", ["x0", "y", "u"])
@pytest.mark.parametrize("bad", ["complex", "bool"])
def test_windows_refuse_complex_and_bool(field, bad):
    arrays = dict(x0=np.ones((3, 2)), y=np.ones((3, 2, 1)), u=np.ones((3, 2, 1)))
    arrays[field] = arrays[field] + 1j if bad == "complex" else arrays[field] > 0
    with pytest.raises(ValueError, match=f"`{field}` must be a real floating-point array"):
        dj.Windows(arrays["x0"], arrays["y"], arrays["u"])


# --- 4. fit_mlp's hidden widths ------------------------------------------------------------


@pytest.fixture
def W11():
    y = jnp.linspace(-1.0, 1.0, 6).reshape(3, 2, 1)
    return dj.Windows(None, y, -0.5 * y)


@pytest.mark.parametrize("hidden", [(2.5,), ("a",), 10, "10", (0,), (-3,), (4, 2.5)])
def test_fit_mlp_refuses_bad_hidden(W11, hidden):
    with pytest.raises(ValueError, match="`hidden"):
        dj.fit_mlp(jr_key(), W11, hidden=hidden, num_inits=1, max_steps=2)
    with pytest.raises(ValueError, match="`hidden"):
        dj.MLPController(jr_key(), 1, 1, hidden)


def test_fit_mlp_empty_hidden_is_an_affine_map(W11):
    res = dj.fit_mlp(jr_key(), W11, hidden=(), num_inits=2, max_steps=2)
    layers = res.controllers.params.layers
    assert len(layers) == 1 and layers[0].weight.shape == (2, 1, 1)
    res = dj.fit_mlp(jr_key(), W11, hidden=(3.0, 3), num_inits=1, max_steps=2)
    assert res.controllers.params.layers[0].weight.shape == (1, 3, 1)


# --- 5. certify with a non-symmetric P -----------------------------------------------------


def test_certify_refuses_a_nonsymmetric_P():
    K = _lti(0.5 * np.eye(2), [[1.0], [0.0]], [[1.0, 0.0]], 2.0)  # passive: Re G >= 4/3
    qsr = dj.QSR.passive(1)
    with pytest.raises(ValueError, match="`P` must be symmetric"):
        dj.certify(K, qsr, P=np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="`hint` must be symmetric"):
        dj.certify(K, qsr, hint=np.array([[1.0, 0.5], [0.0, 1.0]]))
    P = dj.certify(K, qsr).P
    bumped = P + np.array([[0.0, 1e-12], [0.0, 0.0]]) * np.abs(P).max()  # round-off
    assert dj.certify(K, qsr, P=bumped).holds
    Ks = jax.tree.map(lambda M: jnp.stack([M, M]), K)
    with pytest.raises(ValueError, match="`P` must be symmetric"):
        dj.certify(Ks, qsr, P=np.stack([P, P + np.array([[0.0, 1.0], [0.0, 0.0]])]))


# --- 6. certify's not_certified message ----------------------------------------------------


def test_certify_message_does_not_advise_eps():
    K = _lti(0.5, 1.0, 1.0, 1.0)
    cert = dj.certify(K, dj.QSR.passive(1), P=np.array([[1e3]]))  # a P that proves nothing
    assert cert.result == dj.Outcome.not_certified
    assert "`eps`" not in cert.message and "`P`" in cert.message
    # the item's own sentence says where `eps` applies, and the trainers keep their advice
    assert "`certify` (which has no `eps`)" in dj.Outcome[dj.Outcome.not_certified]
    assert "pass a larger `eps`" in dji.outcome.message("not_certified")
    for name in ("infeasible", "solver_failed"):
        text = dji.outcome.message(name, caller="certify")
        assert "`eps`" not in text and "`P_ref`" not in text and "`init_scale`" not in text
    batched = dj.certify(jax.tree.map(lambda M: jnp.stack([M, M]), K), dj.QSR.passive(1),
                         P=np.array([[1e3]]))
    assert batched.message == [cert.message] * 2


# --- 7. n_state: integers, as num_inits ----------------------------------------------------


def test_n_state_takes_integers_like_num_inits(W11):
    assert dji.check_n_state(W11, 2.0) == 2 and type(dji.check_n_state(W11, 2.0)) is int
    for bad in (2.5, True, "2", 0):
        with pytest.raises(ValueError, match="`n_state`"):
            dji.check_n_state(W11, bad)
    with pytest.raises(ValueError, match="`n_state`"):
        dj.fit_gd(jr_key(), W11, n_state=2.5, num_inits=2, max_steps=2)
    with pytest.raises(ValueError, match="`num_inits`"):
        dj.fit_gd(jr_key(), W11, n_state=2, num_inits=2.5, max_steps=2)
    res = dj.fit_gd(jr_key(), W11, n_state=2.0, num_inits=2.0, max_steps=2)
    assert res.controllers.A.shape == (2, 2, 2)


def test_project_refuses_a_static_controller():
    with pytest.raises(ValueError, match=r"`K` has no state"):
        dj.project(_static([[2.0]]), dj.QSR.passive(1))


def test_traceable_runs_take_integral_floats_like_the_trainers(W11):
    for run in (lambda **kw: dj.pgd_run(jr_key(), W11, dj.QSR.passive(1), **kw),
                lambda **kw: dj.direct_run(jr_key(), W11, dj.QSR.passive(1), **kw)):
        res = run(num_inits=2.0, max_steps=2.0, n_state=1, throw=False)
        assert res.final_loss.shape == (2,) and res.loss_history.shape == (2, 3)


def test_an_eps_beyond_the_rates_room_is_refused_naming_eps():
    """A gain bound of 1e-4 leaves every feedthrough a room of at most 1e-8 in the KYP
    LMI's input block, below the default margin eps = 1e-6: refused before any solve,
    naming `eps`; with eps below the room the projection is certified."""
    qsr = dj.QSR.bounded_gain(1e-4, n_in=1, n_out=1)
    K = _lti(0.5, 1.0, 1.0, 0.1)
    y = jnp.linspace(-1.0, 1.0, 6).reshape(3, 2, 1)
    W = dj.Windows(y[:, 0], y, -1e-5 * y)
    # (balanced, the trainers would solve the outputs times 2^17, where the bound has room:
    # `test_fit_pgd_judges_eps_on_the_balanced_rate`)
    for call in (lambda: dj.project(K, qsr),
                 lambda: dj.fit_pgd(jr_key(), W, qsr, num_inits=1, max_steps=1, balance=False),
                 lambda: dj.fit_ico(jr_key(), W, qsr, num_inits=1, max_steps=1, balance=False)):
        with pytest.raises(ValueError, match=r"`eps` = 1e-06 is not below the supply rate's room"):
            call()
    K_proj, P = dj.project(K, qsr, eps=1e-12)
    assert dj.certify(K_proj, qsr, P=P).holds


def test_rollout_refuses_a_ren_like_the_other_lti_tools(K11):
    R = dj.RENController.from_lti(K11, width=2)
    with pytest.raises(ValueError, match=r"`K` must be a `dj.LTIController`.*ren_rollout"):
        dj.rollout(R, None, jnp.zeros((3, 1)))


@pytest.mark.parametrize("scale, word", [(1e20, "overflow"), (1e-20, "underflow")])
@pytest.mark.parametrize("fit", ["fit_direct", "fit_pgd", "fit_gd", "fit_ico"])
def test_float32_data_beyond_its_range_is_refused(scale, word, fit):
    """float32 windows of size 1e20 or 1e-20 have squares outside float32: the loss was NaN
    or 0 and the runs ended `max_steps` without a step. They are refused, naming `windows`."""
    rng = np.random.default_rng(0)
    w = dj.Windows(*(np.float32(scale) * rng.standard_normal(s).astype(np.float32)
                     for s in ((20, 1), (20, 2, 1), (20, 2, 1))))
    assert w.y.dtype == np.float32 and np.all(np.isfinite(np.asarray(w.y)))
    qsr = () if fit == "fit_gd" else (dj.QSR.passive(1),)
    with pytest.raises(ValueError, match=f"`windows`.*{word}"):
        getattr(dj, fit)(jax.random.PRNGKey(0), w, *qsr, num_inits=2, max_steps=3)
    # the same data in float64 are within range and train
    w64 = dj.Windows(*(np.asarray(a, np.float64) for a in (w.x0, w.y, w.u)))
    getattr(dj, fit)(jax.random.PRNGKey(0), w64, *qsr, num_inits=2, max_steps=3, throw=False)


@pytest.mark.parametrize("call", ["fit_pgd", "fit_ico", "project"])
@pytest.mark.parametrize("rate", ["negative", "rectangular_passive"])
def test_a_rate_without_any_dissipative_controller_is_refused_up_front(call, rate):
    """w = -|y|^2 - |u|^2, or a 'passivity' S of shape 1x2 (no D makes Phi(D) > 0): refused
    by name before any SDP. fit_pgd and fit_ico used to run, then report `infeasible` as if
    a certified iterate had been kept; project blamed the reference storage."""
    qsr = (dj.QSR(-1.0, 0.0, -1.0) if rate == "negative" else
           dj.QSR(np.zeros((1, 1)), 0.5 * np.ones((1, 2)), np.zeros((2, 2))))
    p = qsr.n_in
    rng = np.random.default_rng(0)
    w = dj.Windows(rng.standard_normal((10, 1)), rng.standard_normal((10, 2, p)),
                   rng.standard_normal((10, 2, 1)))
    with pytest.raises(ValueError, match="`qsr` is infeasible"):
        if call == "project":
            dj.project(dj.LTIController.random(jax.random.PRNGKey(0), 1, p, 1), qsr)
        else:
            getattr(dj, call)(jax.random.PRNGKey(0), w, qsr, num_inits=2, max_steps=2,
                              throw=False)


@pytest.mark.parametrize("fit", ["fit_direct", "fit_pgd", "fit_gd", "fit_ico", "fit_ren",
                                 "fit_mlp", "pgd_run", "direct_run"])
def test_a_key_that_is_not_a_prng_key_is_refused_by_name(fit):
    """An integer seed (as in numpy or scikit-learn) used to fail inside JAX with "invalid
    PRNG key data"; every trainer names `key`. Raw and typed keys both work."""
    rng = np.random.default_rng(0)
    w = dj.Windows(rng.standard_normal((6, 1)), rng.standard_normal((6, 2, 1)),
                   rng.standard_normal((6, 2, 1)))
    qsr = () if fit in ("fit_gd", "fit_mlp") else (dj.QSR.passive(1),)
    kw = dict(num_inits=2, max_steps=2, throw=False)
    # raw uint32 arrays that are not one key (a split batch, a wrong length) too
    for bad in (0, None, np.zeros(2), jnp.zeros(3, jnp.uint32), jax.random.split(jax.random.PRNGKey(0))):
        with pytest.raises(ValueError, match="`key` must be a JAX PRNG key"):
            getattr(dj, fit)(bad, w, *qsr, **kw)
    for good in (jax.random.PRNGKey(0), jax.random.key(0)):
        getattr(dj, fit)(good, w, *qsr, **kw)


def test_rollouts_of_a_batch_say_to_vmap():
    """`dj.rollout` and `dj.ren_rollout` take one controller; a batch used to fail inside
    JAX's dot_general."""
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, 2, 1, 1))(jax.random.split(
        jax.random.PRNGKey(0), 3))
    u = jnp.ones((4, 1))
    with pytest.raises(ValueError, match=r"`K` must be a single controller.*vmap"):
        dj.rollout(Ks, None, u)
    with pytest.raises(ValueError, match=r"`K` must be a single controller.*vmap"):
        dj.ren_rollout(jax.vmap(dj.RENController.from_lti)(Ks), None, u)
    out = jax.vmap(dj.rollout, (0, None, None))(Ks, None, u)
    for i in range(3):  # the vmapped rollout against one controller at a time
        Ki = jax.tree.map(lambda a: a[i], Ks)
        np.testing.assert_array_equal(out[i], dj.rollout(Ki, None, u))


@pytest.mark.parametrize("fit", ["fit_direct", "fit_pgd", "fit_gd", "fit_ico", "fit_ico_nc",
                                 "fit_ren", "fit_mlp", "pgd_run", "direct_run"])
def test_throw_must_be_a_bool(fit):
    """`throw="no"` is truthy: it used to be read as True without a word."""
    rng = np.random.default_rng(0)
    w = dj.Windows(rng.standard_normal((6, 1)), rng.standard_normal((6, 2, 1)),
                   rng.standard_normal((6, 2, 1)))
    qsr = () if fit in ("fit_gd", "fit_mlp", "fit_ico_nc") else (dj.QSR.passive(1),)
    with pytest.raises(ValueError, match="`throw` must be True or False"):
        getattr(dj, fit)(jax.random.PRNGKey(0), w, *qsr, num_inits=2, max_steps=2, throw="no")


@pytest.mark.parametrize("fit, alternative", [("fit_direct", "dj.direct_run"),
                                              ("fit_pgd", "dj.pgd_run"), ("fit_ico", None),
                                              ("fit_ren", None)])
def test_certified_trainers_under_vmap_say_why_they_cannot_be_traced(fit, alternative):
    """The certified trainers check every controller in float64 on the host; under
    `jax.vmap` over keys they used to fail with JAX's TracerArrayConversionError. Plain GD
    has no host check and still runs under vmap, equal to a loop over the keys."""
    rng = np.random.default_rng(0)
    w = dj.Windows(rng.standard_normal((6, 1)), rng.standard_normal((6, 2, 1)),
                   rng.standard_normal((6, 2, 1)))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    run = lambda k: getattr(dj, fit)(k, w, dj.QSR.passive(1), num_inits=2, max_steps=2,
                                     throw=False).final_loss
    with pytest.raises(ValueError, match=f"`{fit}` cannot run under `jax.jit` or `jax.vmap`"
                       + (f".*`{alternative}`" if alternative else "")):
        jax.vmap(run)(keys)
    gd = lambda k: dj.fit_gd(k, w, num_inits=2, max_steps=3, throw=False).final_loss
    batched = jax.vmap(gd)(keys)
    for i in range(2):
        np.testing.assert_allclose(batched[i], gd(keys[i]), rtol=1e-6)
    np.testing.assert_allclose(jax.jit(gd)(keys[1]), gd(keys[1]), rtol=1e-6)
    # over traced windows the outputs' units cannot be chosen on the host: said by name
    arrays = [jnp.stack([a, 2 * a]) for a in (w.x0, w.y, w.u)]
    over = lambda bal: jax.vmap(lambda x, y, u: dj.fit_gd(
        keys[0], dj.Windows(x, y, u), num_inits=2, max_steps=3, balance=bal).final_loss)
    with pytest.raises(ValueError, match="`balance=True`.*pass `balance=False`"):
        over(True)(*arrays)
    assert over(False)(*arrays).shape == (2, 2)


@pytest.mark.parametrize("fit, hyper", [("fit_direct", "learning_rate"), ("fit_pgd", "decay"),
                                        ("fit_ico", "init_scale"), ("fit_ren", "margin")])
def test_certified_trainers_name_a_traced_hyperparameter(fit, hyper):
    """A sweep over a hyperparameter alone (key and windows constant) failed deep inside
    the host check with JAX's TracerArrayConversionError; the error now names it."""
    rng = np.random.default_rng(0)
    w = dj.Windows(rng.standard_normal((6, 1)), rng.standard_normal((6, 2, 1)),
                   rng.standard_normal((6, 2, 1)))
    run = lambda v: getattr(dj, fit)(jax.random.PRNGKey(0), w, dj.QSR.passive(1),
                                     num_inits=2, max_steps=2, throw=False,
                                     **{hyper: v}).final_loss
    with pytest.raises(ValueError, match=f"`{fit}` cannot run .*its `{hyper}` is traced"):
        jax.vmap(run)(jnp.array([0.5, 0.9]))


def test_decay_of_the_papers_rule_must_decay():
    rng = np.random.default_rng(0)
    w = dj.Windows(rng.standard_normal((6, 1)), rng.standard_normal((6, 2, 1)),
                   rng.standard_normal((6, 2, 1)))
    for bad in (1.5, 0.0, -0.5):  # a negative one fails the earlier non-negativity check
        with pytest.raises(ValueError, match="`decay` must be"):
            dj.fit_pgd(jax.random.PRNGKey(0), w, dj.QSR.passive(1), optimizer=None,
                       learning_rate=1.0, decay=bad, num_inits=2, max_steps=2)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_windows_are_refused(dtype):
    """float16 ended in failed projections or non-finite losses, bfloat16 in "not
    inexact" errors from numpy, far from the cause."""
    y = jnp.ones((4, 2, 1), dtype)
    with pytest.raises(ValueError, match="`y` has dtype .*float32 or float64"):
        dj.Windows(None, y, jnp.ones((4, 2, 1), jnp.float32))


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_controllers_are_refused(dtype, K11):
    """Like the windows: the controllers' certificates need float32 at least."""
    half = lambda mats: [jnp.asarray(M, dtype) for M in mats]
    with pytest.raises(ValueError, match="`A` has dtype .*float32 or float64"):
        dj.LTIController(*half((K11.A, K11.B, K11.C, K11.D)))
    with pytest.raises(ValueError, match="`A` has dtype .*float32 or float64"):
        dj.RENController(*half(dj.RENController.from_lti(K11, width=2).matrices))


def test_one_step_names_a_wrong_state_or_input(K11):
    """A single step of either controller refuses a wrong state or input size, or a batch,
    by name (a raw shape error from a matrix product before)."""
    for K in (K11, dj.RENController.from_lti(K11, width=2)):
        with pytest.raises(ValueError, match="`u` must have shape \\(1,\\)"):
            K(jnp.ones(1), jnp.ones(2))
        with pytest.raises(ValueError, match="`x` must have shape \\(1,\\).*vmap"):
            K(jnp.ones((3, 1)), jnp.ones(1))
        with pytest.raises(ValueError, match="`x` must have shape"):
            jax.jit(lambda x: K(x, jnp.ones(1)))(jnp.ones(2))


def test_rollouts_promote_an_integer_or_narrow_start():
    """An integer `x0` (or `u_in`) runs in the controller's dtype: the scan's carry keeps
    its type (a raw TypeError from `lax.scan` before), with the outputs of a float start."""
    K = _lti(np.eye(2) * 0.5, np.ones((2, 1)), np.ones((1, 2)), 1.0)
    R = dj.RENController.from_lti(K, width=2, activation="tanh")
    u = np.arange(3.0)[:, None]
    for roll, C in ((dj.rollout, K), (dj.ren_rollout, R)):
        ref = roll(C, jnp.asarray([1.0, -2.0]), u)
        for x0, u_in in (([1, -2], u), (np.array([1, -2]), u.astype(int)),
                         (np.array([1.0, -2.0], np.float32), u)):
            out = roll(C, x0, u_in)
            assert out.dtype == ref.dtype
            np.testing.assert_array_equal(out, ref)
        # complex signals (tanh of complex numbers) and booleans are refused by name, as
        # `dj.Windows` refuses them
        with pytest.raises(ValueError, match="`u_in` must be a real array"):
            roll(C, None, u.astype(np.complex64))
        with pytest.raises(ValueError, match="`x0` must be a real array"):
            roll(C, np.array([True, False]), u)


def test_project_shares_one_reference_storage_across_a_batch():
    """`P_ref` of shape [n, n] with a batch of targets (as `certify` takes a shared `P`)
    used to fail inside vmap; each member is projected as it would be alone."""
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, 3, 1, 1))(
        jax.random.split(jax.random.PRNGKey(0), 3))
    qsr = dj.QSR.passive(1)
    P = 2.0 * jnp.eye(3)
    out = dj.project(Ks, qsr, P_ref=P, throw=False)
    for i in range(3):
        one = dj.project(jax.tree.map(lambda a: a[i], Ks), qsr, P_ref=P, throw=False)
        np.testing.assert_array_equal(one.controller.D, out.controller.D[i])
        np.testing.assert_array_equal(one.P, out.P[i])
    with pytest.raises(ValueError, match=r"`P_ref` must be 3x3 \(shared by the batch\) or "
                                         r"\(3, 3, 3\)"):
        dj.project(Ks, qsr, P_ref=jnp.eye(2))
    # one controller: one shape to name (the batch's alternative read the same)
    with pytest.raises(ValueError, match=r"`P_ref` must be 3x3 \(the controller's order\), "
                                         r"got \(2, 2\)\.$"):
        dj.project(jax.tree.map(lambda a: a[0], Ks), qsr, P_ref=jnp.eye(2))


def test_fit_pgd_judges_eps_on_the_balanced_rate():
    """Outputs 1000x smaller than the inputs with the cone [0.5e-3, 1.5e-3]: in the user's
    units the cone's room (2.5e-7) is below the default eps, but the trainer solves the
    balanced problem (outputs times 1024, the cone [0.51, 1.54]), where it is not; the
    same problem in balanced units always trained."""
    rng = np.random.default_rng(0)
    y = rng.standard_normal((8, 3, 1))
    w = dj.Windows(None, y, -1e-3 * y)
    res = dj.fit_pgd(jax.random.PRNGKey(0), w, dj.QSR.conic(0.5e-3, 1.5e-3, dim=1), n_state=1,
                     num_inits=2, max_steps=5)
    assert bool(np.all(res.certified))
    with pytest.raises(ValueError, match="`eps`"):  # without balancing the room is too small
        dj.fit_pgd(jax.random.PRNGKey(0), w, dj.QSR.conic(0.5e-3, 1.5e-3, dim=1), n_state=1,
                   num_inits=2, max_steps=5, balance=False)


def test_flags_of_certify_and_project_must_be_bools(K11):
    """A string such as "no" is truthy: it used to read as True."""
    qsr = dj.QSR.bounded_gain(2.0, n_in=1, n_out=1)
    with pytest.raises(ValueError, match="`max_margin`"):
        dj.certify(K11, qsr, max_margin="no")
    with pytest.raises(ValueError, match="`throw`"):
        dj.project(K11, qsr, throw="no")
    with pytest.raises(ValueError, match="`active`"):
        dj.project(K11, qsr, active="no")
    with pytest.raises(ValueError, match="`active`"):
        dj.project(K11, qsr, active=1)


@pytest.mark.parametrize("trainer", ["pgd", "direct"])
def test_bad_hyperparameters_in_a_vmapped_run_end_as_non_finite(trainer):
    """Under `jax.vmap` hyperparameters cannot be checked eagerly. A NaN or negative step
    (a negative one trained uphill), a NaN or negative initial scale and, for PGD, a decay
    outside (0, 1] end their run as `non_finite`, not as a projection's solver failure,
    and leave the other lanes alone (each equals its own run)."""
    rng = np.random.default_rng(0)
    y = jnp.asarray(rng.standard_normal((4, 3, 1)))
    W = dj.Windows(jnp.asarray(rng.standard_normal((4, 2))), y, -0.3 * y)
    key, qsr = jax.random.PRNGKey(0), dj.QSR.passive(1)
    fn = dj.pgd_run if trainer == "pgd" else dj.direct_run
    decay = {"decay": 0.99} if trainer == "pgd" else {}

    def run(lr, scale, *d):
        return fn(key, W, qsr, learning_rate=lr, init_scale=scale, max_steps=5, num_inits=1,
                  throw=False, **dict(zip(decay, d)))

    nan = jnp.nan
    lanes = [(0.1, 0.3, 0.99), (nan, 0.3, 0.99), (-0.1, 0.3, 0.99), (0.1, nan, 0.99),
             (0.1, -0.3, 0.99)]
    if decay:
        lanes += [(0.1, 0.3, 0.0), (0.1, 0.3, 1.5)]
    args = [jnp.array(a) for a in zip(*lanes)][:3 if decay else 2]
    res = jax.jit(jax.vmap(run))(*args)
    codes = np.asarray(dji.outcome.codes(res.result))[:, 0]
    assert codes[0] != dji.outcome.code("non_finite")
    assert (codes[1:] == dji.outcome.code("non_finite")).all(), res.result_names()
    alone = jax.jit(run)(*(a[0] for a in args))
    # PGD's lane passed through 6 projections, solved in a batch of 7 rows or alone (other
    # BLAS paths: 4e-9 apart under OPENBLAS_CORETYPE=SkylakeX); the direct map is pure JAX
    rtol = through_solves(6) if trainer == "pgd" else 1e-9
    np.testing.assert_allclose(res.final_loss[0], alone.final_loss, rtol=rtol)
    if trainer == "pgd":  # a failed lane is not a certified result (a bad step's lane kept
        # its projected draw and read `certified=True`, against the sweep tutorial)
        assert np.asarray(res.certified)[:, 0].tolist() == [True] + [False] * (len(lanes) - 1)
    # `dj.certify` of the whole sweep, as `direct_run`'s docstring suggests: the non-finite
    # lanes (NaN controllers) are judged `non_finite`, the others as they are; it raised
    # numpy's LinAlgError for the whole batch
    cert = dj.certify(res.controllers, qsr, P=res.P)
    finite = np.all(np.isfinite(np.asarray(res.controllers.A)), axis=(-2, -1))
    assert not finite.all()  # the premise: some lanes' controllers are NaN
    np.testing.assert_array_equal(np.asarray(cert.holds), finite & np.asarray(
        dj.certify(jax.tree.map(lambda a: jnp.where(jnp.isnan(a), 0.0, a), res.controllers),
                   qsr, P=jnp.where(jnp.isnan(res.P), 1.0, res.P)).holds))
    assert set(np.asarray(cert.source)[~finite]) == {"non-finite"}
    assert "NaN or inf" in np.asarray(cert.message, dtype=object)[~finite][0]
    searched = dj.certify(res.controllers, qsr)
    assert (np.asarray(searched.holds)[~finite] == False).all()  # noqa: E712
    with pytest.raises(ValueError, match="`K` contains NaN or inf"):
        dj.certify(jax.tree.map(lambda a: a[~finite][0], res.controllers), qsr)


def test_hyperparameters_must_be_scalars_also_in_a_sweep():
    """A learning rate with a shape (a 2-d array swept over its first axis leaves each lane
    a vector) failed deep inside JAX with a broadcasting error; eagerly an array passed."""
    rng = np.random.default_rng(0)
    y = jnp.asarray(rng.standard_normal((4, 3, 1)))
    W = dj.Windows(jnp.asarray(rng.standard_normal((4, 2))), y, -0.3 * y)
    key, qsr = jax.random.PRNGKey(0), dj.QSR.passive(1)
    run = lambda lr: dj.direct_run(key, W, qsr, learning_rate=lr, max_steps=2, num_inits=1,
                                   throw=False).final_loss
    with pytest.raises(ValueError, match="`learning_rate` must be a scalar"):
        jax.vmap(run)(jnp.full((2, 2), 0.1))
    with pytest.raises(ValueError, match="`init_scale` must be a scalar"):
        dj.pgd_run(key, W, qsr, init_scale=np.array([0.1, 0.2]), max_steps=2, num_inits=1)


def test_zero_init_scale_with_several_inits_warns_at_the_callers_line():
    """`init_scale=0` trained `num_inits` copies of one run without a word; the warning
    points at the user's call, not at the library's internals."""
    rng = np.random.default_rng(0)
    y = jnp.asarray(rng.standard_normal((4, 3, 1)))
    W = dj.Windows(jnp.asarray(rng.standard_normal((4, 2))), y, -0.3 * y)
    key, qsr = jax.random.PRNGKey(0), dj.QSR.passive(1)
    for fn in (dj.direct_run, dj.pgd_run):
        with pytest.warns(UserWarning, match="`init_scale` = 0 draws 3 identical") as rec:
            fn(key, W, qsr, init_scale=0.0, max_steps=1, num_inits=3)
        assert rec[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one initialisation, or a positive scale: no warning
        dj.direct_run(key, W, qsr, init_scale=0.0, max_steps=1, num_inits=1)
        dj.direct_run(key, W, qsr, init_scale=0.1, max_steps=1, num_inits=3)
        # an optimizer of one's own: the default rule's (unused) step is not checked
        dj.direct_run(key, W, qsr, optimizer=optax.sgd(0.1), max_steps=1, num_inits=1)
        dj.pgd_run(key, W, qsr, optimizer=optax.sgd(0.1), max_steps=1, num_inits=1)
    # a zero step trains nothing: said so (it passed silently)
    for fn in (dj.direct_run, dj.pgd_run, dj.fit_ren):
        with pytest.warns(UserWarning, match="`learning_rate` = 0 takes no step"):
            fn(key, W, qsr, learning_rate=0.0, max_steps=1, num_inits=1)


@pytest.mark.parametrize("fit", [dj.fit_direct, dj.fit_ren])
def test_a_step_too_large_to_train_warns(fit):
    """A learning rate far too large made the loss climb from the first step (55 -> 7e13
    for `fit_ren`); the run ended as `max_steps` with its initial controller and no word.
    The trainers now warn; a run that trains does not."""
    rng = np.random.default_rng(0)
    y = jnp.asarray(rng.standard_normal((6, 3, 1)))
    W = dj.Windows(jnp.asarray(rng.standard_normal((6, 1))), y, -0.3 * y)
    key, qsr = jax.random.PRNGKey(0), dj.QSR.passive(1)
    kw = dict(width=2) if fit is dj.fit_ren else {}
    with pytest.warns(UserWarning, match="2 of 2 runs returned their initial controller"):
        res = fit(key, W, qsr, learning_rate=1e6, num_inits=2, max_steps=20, **kw)
    assert (np.asarray(res.kept_step) == 0).all() and (np.asarray(res.steps) > 0).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fit(key, W, qsr, num_inits=2, max_steps=20, **kw)
    assert (np.asarray(res.kept_step) > 0).all()


def test_margins_and_weights_of_ico_and_the_direct_fallback_are_checked():
    """`fit_ico(prox=-1)` ended in a misleading solver failure, `fit_ico(eps=-1)` and
    `fit_direct(fallback_eps=-1)` were accepted (the latter failing after training)."""
    rng = np.random.default_rng(0)
    y = jnp.asarray(rng.standard_normal((6, 2, 1)))
    W = dj.Windows(jnp.asarray(rng.standard_normal((6, 1))), y, -0.3 * y)
    key, qsr = jax.random.PRNGKey(0), dj.QSR.passive(1)
    for kw, name in [(dict(prox=-1.0), "prox"), (dict(prox=np.nan), "prox"),
                     (dict(eps=-1.0), "eps"), (dict(eps=0.0), "eps")]:
        with pytest.raises(ValueError, match=f"`{name}` must be a finite"):
            dj.fit_ico(key, W, qsr, num_inits=1, max_steps=1, **kw)
    for bad in (-1.0, np.nan, "1e-6"):
        with pytest.raises(ValueError, match="`fallback_eps` must be a finite positive"):
            dj.fit_direct(key, W, qsr, num_inits=1, max_steps=1, fallback_eps=bad)
