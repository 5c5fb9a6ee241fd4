"""Training does not depend on the units of the demonstrations (x0, y, u scaled together)."""

import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, index, through_solves

import dissil_jax as dj
from dissil_jax.experiments import realisable_windows

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

QSR = dj.QSR.passive(2)


def _windows(scale, noise=0.1):
    w, _ = realisable_windows(jr.PRNGKey(4), QSR, n_state=2, num_windows=30, noise=noise,
                              scale=scale)
    return w


def _rel(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def _same_controllers(res, ref, rtol):
    for name in "ABCD":
        assert _rel(getattr(res.controllers, name), getattr(ref.controllers, name)) <= rtol


def _certified(res, qsr=QSR):
    assert bool(np.all(res.certified))
    for i in range(res.num_inits):
        assert dissipation_ok(index(res.controllers, i), qsr, res.P[i])


def _check_unit_free(fit, c, rtol, path=True, **kw):
    """Same controllers for data scaled by c; losses reported in the user's units (c^2 J).
    `path=False`: of the loss history only the first entry and the final loss are compared."""
    ref = fit(jr.PRNGKey(0), _windows(1.0), QSR, atol=0.0, rtol=0.0, **kw)
    res = fit(jr.PRNGKey(0), _windows(c), QSR, atol=0.0, **kw)
    _same_controllers(res, ref, rtol)
    if path:
        np.testing.assert_allclose(res.loss_history, c**2 * ref.loss_history, rtol=rtol)
    else:
        np.testing.assert_allclose(res.loss_history[:, 0], c**2 * ref.loss_history[:, 0],
                                   rtol=through_solves(1))
        np.testing.assert_allclose(res.final_loss, c**2 * ref.final_loss, rtol=rtol)
    _certified(res)


# Scaled data are the same problem up to round-off, so the runs agree to the solvers'
# tolerances compounded over their solves (helpers.through_solves): PGD's initial projection
# and 15 steps (Clarabel, 1e-8).
@pytest.mark.parametrize("c", [1e-4, 1e-2, 1e2, 1e4])
def test_pgd_is_unit_free(c):
    _check_unit_free(dj.fit_pgd, c, through_solves(16), num_inits=3, max_steps=15)


# ICO's path is far more sensitive to round-off than PGD's. Its SDP leaves P nearly free
# (P enters only through the LMI and the small margin term rho tr P), so the P it returns,
# around which the next step is linearised, moves far more than the solver's tolerance, and
# the next step with it. Measured (XLA's default settings): data scaled by 1 + 1e-12 moved
# the loss at step 3 by 2.2e-2 relative, though the initial losses agreed to 4e-16 and a
# solver tolerance of 1e-12 instead of 1e-10 changed nothing; the final (step-6) losses
# agreed to 8e-4 and the controllers to 5e-3. So the initial loss is compared to the
# initial projection's tolerance, and the final losses and controllers at 5e-2. A unit
# error is of another order: without the normalisation the SDP at c = 1e4 is infeasible, and
# a loss in the wrong units is off by a factor c or c^2.
ICO_PATH_RTOL = 5e-2


@pytest.mark.parametrize("c", [1e-4, 1e4])
def test_ico_is_unit_free(c):
    _check_unit_free(dj.fit_ico, c, ICO_PATH_RTOL, path=False, num_inits=2, max_steps=6)


def test_ico_trains_on_data_scaled_by_1e6():
    res = dj.fit_ico(jr.PRNGKey(0), _windows(1e6), QSR, num_inits=2, max_steps=8, atol=0.0, rtol=0.0)
    assert res.result_names() == ["max_steps"] * 2  # throw=True would have raised otherwise
    assert bool(np.all(res.final_loss < 0.05 * res.initial_loss))
    _certified(res)


def test_tol_is_in_the_users_units():
    """The same run stops at the same step when tol is scaled with the loss (c^2)."""
    a = dj.fit_pgd(jr.PRNGKey(0), _windows(1.0), QSR, num_inits=3, atol=1e-2)
    b = dj.fit_pgd(jr.PRNGKey(0), _windows(10.0), QSR, num_inits=3, atol=1.0)
    np.testing.assert_array_equal(a.steps, b.steps)
    assert bool(np.any(a.converged))
