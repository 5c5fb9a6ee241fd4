"""The trainers' driver loop (`internal.iterate`) against a plain Python loop, on a toy
method with every way a lane can end: a failed start, convergence, a failed step, a
non-finite loss and the step budget."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dissil_jax import internal

outcome = internal.outcome
CONVERGED, MAX_STEPS, NON_FINITE, FAILED = (
    outcome.code(n) for n in ("converged", "max_steps", "non_finite", "solver_failed"))

# Gradient descent on J = (theta - c)^2 per lane. A step whose iterate falls below
# `FAIL_BELOW` fails (as a failed projection would); the loss is NaN above `NAN_ABOVE`.
FAIL_BELOW, NAN_ABOVE = -1.0, 3.0
THETA0 = np.array([0.0, 0.0, 0.0, 0.0, 0.5, 0.0])
C = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
# Lanes: converges; its step fails at k = 4 (theta -1.07); its loss is NaN at k = 3 (theta
# 3.20); converges fast; starts failed (as a failed initial projection), so takes no step;
# fits exactly at k = 1 (theta = 1, J = 0), where it stops although |J_1 - J_0| = 1.
LR = np.array([0.1, 1.1, 1.15, 0.3, 0.2, 0.5])
CODE0 = np.array([MAX_STEPS, MAX_STEPS, MAX_STEPS, MAX_STEPS, FAILED, MAX_STEPS])


@jax.jit
def _toy_loss(theta):
    J = (theta - C) ** 2
    return jnp.where(theta > NAN_ABOVE, jnp.nan, J), 2.0 * (theta - C)


class Toy(internal.Method):
    def init(self):
        return jnp.asarray(THETA0), jnp.asarray(CODE0, jnp.int32)

    def evaluate(self, theta):
        J, grad = _toy_loss(theta)
        return (theta, grad), J

    def update(self, state, active):
        theta, grad = state
        new = theta - LR * grad
        return new, jnp.where(new < FAIL_BELOW, FAILED, CONVERGED).astype(jnp.int32)


class ToyLast(Toy):
    keep_non_finite = True  # like GD and the MLP: the last iterate, even a non-finite one


def _reference(max_steps, rtol, keep_non_finite, keep_best):
    """The driver's rule written out per lane with Python floats."""
    lanes = len(THETA0)
    hist = np.full((lanes, max_steps + 1), np.nan)
    out = dict(theta=np.zeros(lanes), final=np.zeros(lanes), steps=np.zeros(lanes, int),
               code=np.zeros(lanes, int), at=np.zeros(lanes, int))
    loss_fn = lambda t, c: math.nan if t > NAN_ABOVE else (t - c) ** 2
    for i in range(lanes):
        theta, J0 = THETA0[i], loss_fn(THETA0[i], C[i])
        hist[i, 0] = J = J0
        best, best_J, at, steps = theta, J0, 0, 0
        failed0 = CODE0[i] == FAILED
        code = CODE0[i] if failed0 else (NON_FINITE if math.isnan(J0) else MAX_STEPS)
        for k in range(1, max_steps + 1):
            if failed0 or math.isnan(J0):
                break
            steps += 1
            new = theta - LR[i] * 2.0 * (theta - C[i])
            J_new = loss_fn(new, C[i])
            if new < FAIL_BELOW:  # a failed step: not accepted, the lane stops
                code = FAILED
                hist[i, k] = J
                break
            if math.isnan(J_new):
                if keep_non_finite:  # accepted, but the lane stops
                    theta, J = new, J_new
                    at = k
                hist[i, k] = J
                code = NON_FINITE
                break
            stop = abs(J_new - J) < rtol * abs(J0) or J_new == 0.0
            theta, J = new, J_new
            hist[i, k] = J
            at = k if not keep_best else at
            if keep_best and J < best_J:
                best, best_J, at = theta, J, k
            if stop:
                code = CONVERGED
                break
        out["theta"][i], out["final"][i] = (best, best_J) if keep_best else (theta, J)
        out["steps"][i], out["code"][i], out["at"][i] = steps, code, at
    return hist, out


@pytest.mark.parametrize("method, keep", [(Toy, "best"), (Toy, "last"), (ToyLast, "best")])
@pytest.mark.parametrize("max_steps", [0, 6, 40])
def test_driver_equals_a_python_loop(method, keep, max_steps):
    rtol = 1e-6
    run = jax.jit(lambda: internal.iterate(method(), max_steps=max_steps, atol=0.0, rtol=rtol,
                                           keep=keep))
    (theta, _), hist, final, steps, code, at = run()
    keep_best = keep == "best" and not method.keep_non_finite
    ref_hist, ref = _reference(max_steps, rtol, method.keep_non_finite, keep_best)
    # The same float64 arithmetic on both sides, but XLA may fuse a multiply-add: each step
    # then rounds theta (|theta| <= 3.2) differently by an ulp or two, < 1e-15, and at most
    # 40 steps (growing by <= 1.3x per step on the unstable lanes, which stop within 4)
    # keep the difference below 1e-13 in theta and 1e-12 in J = (theta - c)^2.
    np.testing.assert_allclose(hist, ref_hist, rtol=0, atol=1e-12)
    np.testing.assert_allclose(theta, ref["theta"], rtol=0, atol=1e-13)
    np.testing.assert_allclose(final, ref["final"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(steps, ref["steps"])
    np.testing.assert_array_equal(code, ref["code"])
    np.testing.assert_array_equal(at, ref["at"])
    if max_steps == 40:  # every ending is exercised
        assert set(np.asarray(code).tolist()) == {CONVERGED, NON_FINITE, FAILED}
    if max_steps:  # the exact fit stops at once
        assert (int(steps[-1]), int(code[-1]), float(final[-1])) == (1, CONVERGED, 0.0)


def _count_calls(jaxpr, name):
    """How often a jitted function called `name` appears in a (nested) jaxpr."""
    count = 0
    for eqn in jaxpr.eqns:
        if eqn.params.get("name") == name:
            count += 1
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None:
                    count += _count_calls(getattr(inner, "jaxpr", inner), name)
    return count


def test_the_loss_is_compiled_once():
    """The evaluation (the loss and its gradient, the bulk of a trainer's program) is in
    the compiled loop once, not once for J_0 and again in the step."""
    jaxpr = jax.make_jaxpr(
        lambda: internal.iterate(Toy(), max_steps=5, atol=0.0, rtol=0.0))()
    assert _count_calls(jaxpr.jaxpr, "_toy_loss") == 1


class CountingToy(Toy):
    """`Toy` counting the Python calls of `evaluate`, i.e. its traces."""

    def evaluate(self, theta):
        TRACES.append(None)
        return super().evaluate(theta)


TRACES: list = []


def test_the_loss_is_traced_once():
    """The carry's shapes come from the same trace of `evaluate` as the loop body: tracing
    a trainer's loss and gradient (seconds for the direct map) happens once per run."""
    TRACES.clear()
    jax.make_jaxpr(lambda: internal.iterate(CountingToy(), max_steps=5, atol=0.0, rtol=0.0))()
    # 0 if an identical run was traced before in this process (the trace is cached); two
    # traces (one for the carry's shapes, one for the loop body) fail
    assert len(TRACES) <= 1
