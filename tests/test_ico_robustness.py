"""ICO started from the paper's N(0, 1) draws: no run may end early on the solver."""

from collections import Counter

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import expert_windows

import dissil_jax as dj
from dissil_jax.experiments.protocol import example_spec, training_data
from dissil_jax.internal import ICOProblem, ICOSolver, ico, outcome as _outcome


def test_large_initial_draws_do_not_stop_ico_early():
    """The nonlinear example at N = 25 with 100 N(0, 1) draws: before the SDP solved for
    P / lambda_max(P~), 4 of these runs stopped at their first SDP (InsufficientProgress)."""
    spec = example_spec("nonlinear")
    _, _, windows, (k_fit, _, _) = training_data(spec, 0, 0, "initial", 25)
    res = dj.fit_ico(k_fit, windows, spec.qsr, num_inits=100, max_steps=150, atol=spec.tol,
                     init_scale=1.0)
    reasons = Counter(res.result_names())
    assert set(reasons) <= {"converged", "max_steps"}, reasons
    assert bool(jnp.all(res.certified)) and bool(jnp.all(res.steps > 0))


def test_p_scale_is_the_square_root_of_p():
    rng = np.random.default_rng(0)
    G = rng.standard_normal((3, 3))
    P = G @ G.T + 1e-3 * np.eye(3)
    Ph = ICOProblem.p_scale(P)
    np.testing.assert_allclose(Ph, Ph.T, rtol=0, atol=1e-15)
    np.testing.assert_allclose(Ph @ Ph, P, rtol=1e-12, atol=1e-12)  # a few eigh round-offs
    assert ICOProblem.p_scale(None) == 1.0


@pytest.mark.parametrize("fail_every_time", [False, True])
def test_failed_solve_recentres_on_the_certificate_once(monkeypatch, fail_every_time):
    """When the updated solver and a new one both fail, the run re-centres once."""
    windows = expert_windows(0, 1, 1, 1, N=10)
    qsr = dj.QSR.passive(1)
    calls = {"solve": 0, "certify": 0}
    solve, certify = ICOSolver.solve, ico.certify

    def flaky(self, *args, **kwargs):
        calls["solve"] += 1
        if fail_every_time or calls["solve"] <= 2:  # the updated solver, then a new one
            return None, None, None, _outcome.code("solver_failed"), 0.0
        return solve(self, *args, **kwargs)

    def counted(*args, **kwargs):
        calls["certify"] += 1
        return certify(*args, **kwargs)

    monkeypatch.setattr(ICOSolver, "solve", flaky)
    monkeypatch.setattr(ico, "certify", counted)
    res = dj.fit_ico(jr.PRNGKey(3), windows, qsr, num_inits=1, max_steps=5, atol=0.0, rtol=0.0,
                     throw=False)
    assert calls["certify"] == 1  # one re-centring, at the first failure only
    assert bool(res.certified[0])
    if fail_every_time:
        assert res.result_names() == ["solver_failed"] and int(res.steps[0]) == 0
    else:
        assert res.result_names() == ["max_steps"] and int(res.steps[0]) == 5
