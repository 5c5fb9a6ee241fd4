"""Run a method on a zoo problem: certificate, closed-loop stability, held-out error, time."""

from __future__ import annotations

import time
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from ..._certify.certify import certify
from ..._controller import LTIController
from ..._ren.certify import certify_ren
from ..._ren.controller import RENController
from ..._train.result import FitResult
from ...systems import LinearPlant
from ..metrics import lti_spectral_radius, rule_stable
from ..simulate import Noise, simulate_controllers
from ._record import Problem, Report, Task, as_batch, predict_any

#: Closed-loop simulation of nonlinear loops: the fewest steps, the plant's half-lives the
#: horizon spans at least (`sim_steps`), and the end-state bound of `rule_stable` per unit
#: of the problem's data (the loop must at least halve a large initial state and settle
#: near the origin; the simulation is noise free).
SIM_STEPS, SIM_HALF_LIVES, SIM_ABS = 200, 20, 1e-2


def sim_steps(problem: Problem) -> int:
    """The simulation horizon of `stable` for `problem`: `SIM_STEPS`, or `SIM_HALF_LIVES`
    half-lives $\\ln\\tfrac12/\\ln\\rho(A)$ of the plant's slowest mode when that is longer.

    A loop around a slow plant cannot settle faster than the plant lets it: on
    `chain12_siso_io` ($\\rho(A) = 0.994$, a half-life of 116 steps) 200 steps did not halve
    the test states even with the zero controller, whose loop is the stable plant itself,
    so every controller was judged unstable. Twenty half-lives shrink the plant's own
    response by $10^{-6}$."""
    A = np.asarray(problem.plant.matrices()[0], np.float64)
    rho = float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0
    if not 0.0 < rho < 1.0:
        return SIM_STEPS
    return max(SIM_STEPS, int(np.ceil(SIM_HALF_LIVES * np.log(0.5) / np.log(rho))))


def task(problem: Problem, key=None) -> Task:
    """The [`Task`][dissil_jax.experiments.zoo.Task] a method gets for `problem` (key 0 by default)."""
    return Task(jr.PRNGKey(0) if key is None else key, problem.train, problem.qsr,
                problem.n_state)


def _finite(controllers) -> np.ndarray:
    leaves = [np.asarray(l) for l in jax.tree.leaves(eqx.filter(controllers, eqx.is_array))]
    k = leaves[0].shape[0]
    return np.all([np.isfinite(l.reshape(k, -1)).all(axis=1) for l in leaves], axis=0)


def _take(tree, idx):
    return jax.tree.map(lambda l: l[idx] if eqx.is_array(l) else l, tree)


def certified(problem: Problem, controllers, P=None, multiplier=None) -> np.ndarray:
    """`[K]` exact float64 certificates: `dj.certify` of LTI controllers (with the storages
    `P` if given), `dj.certify_ren` of RENs (with the pairs `(P, multiplier)` if given,
    else its SDP); False for any other controller (the MLP) and non-finite ones."""
    ok = _finite(controllers)
    out = np.zeros(ok.shape, bool)
    ren = isinstance(controllers, RENController)
    if not (ren or isinstance(controllers, LTIController)) or not ok.any():
        return out
    idx = np.nonzero(ok)[0]
    K = _take(controllers, idx)
    # the trainer's certificate when it is given in full and finite, else a search
    given = [np.asarray(a)[idx] for a in ((P, multiplier) if ren else (P,)) if a is not None]
    full = len(given) == (2 if ren else 1) and all(np.isfinite(a).all() for a in given)
    if ren:
        P_i, lam_i = given if full else (None, None)
        out[idx] = np.asarray(certify_ren(K, problem.qsr, P=P_i, multiplier=lam_i).holds)
    else:
        out[idx] = np.asarray(certify(K, problem.qsr, P=given[0] if full else None).holds)
    return out


def _start(problem: Problem, K, x0, start):
    """The controllers' initial states for plant states `x0` (`[N, n]`): `start(x0)`, or
    `x0` itself (as in the training windows), refused when the orders differ."""
    if start is not None:
        xhat0 = jnp.asarray(start(x0))
        if xhat0.shape != (x0.shape[0], K.n_state):
            raise ValueError(f"`start` must map the plant states {tuple(x0.shape)} to "
                             f"controller states ({x0.shape[0]}, {K.n_state}), got shape "
                             f"{xhat0.shape}.")
        return xhat0
    if getattr(K, "n_state", x0.shape[1]) != x0.shape[1]:  # (the MLP has no order)
        raise ValueError(
            f"the controllers have order {K.n_state}, but the problem's windows start them "
            f"at its {x0.shape[1]}-dimensional plant state. Pass `start`, the map from plant "
            "states to controller states (for `fit_ren(odd=True)`: `start=lambda x0: "
            "jnp.concatenate([x0, -x0], -1)`).")
    return x0


def _order(problem: Problem, K) -> int:
    """The controllers' state size: their order, or the problem's for a memoryless
    controller (the MLP carries a state it never reads)."""
    return K.n_state if isinstance(K, (LTIController, RENController)) else problem.n_state


def stable(problem: Problem, controllers, start=None) -> np.ndarray:
    """`[K]` closed-loop stability with the plant (negative feedback, controller at rest or
    at the plant state as in the training windows, or at `start(x0)`).

    Exact for an `LTIController` on a `LinearPlant` (spectral radius of the loop below 1);
    otherwise a noise-free simulation of `sim_steps(problem)` steps (at least 200, and at
    least 20 half-lives of the plant's slowest mode) from `problem.x0_test`, judged by
    [`rule_stable`][dissil_jax.experiments.rule_stable] with the end bound scaled to the
    problem's units."""
    ok = _finite(controllers)
    out = np.zeros(ok.shape, bool)
    if not ok.any():
        return out
    idx = np.nonzero(ok)[0]
    K = _take(controllers, idx)
    if isinstance(problem.plant, LinearPlant) and isinstance(K, LTIController):
        out[idx] = lti_spectral_radius(problem.plant, K) < 1.0
        return out
    x0 = problem.x0_test
    dtype = x0.dtype
    N, n, m, T = x0.shape[0], problem.plant.n_state, problem.plant.n_in, sim_steps(problem)
    noise = Noise(jnp.zeros((N, T, n), dtype), jnp.zeros((N, T, m), dtype))
    if problem.facts.has_state:
        xhat0 = _start(problem, K, x0, start)
    else:
        xhat0 = "rest" if isinstance(K, LTIController) else jnp.zeros(
            (N, _order(problem, K)), dtype)
    traj = simulate_controllers(problem.plant, K, x0, noise, xhat0)
    out[idx] = rule_stable(traj, abs_tol=SIM_ABS * problem.facts.units)
    return out


def imitation_error(problem: Problem, controllers, start=None) -> np.ndarray:
    """`[K]` held-out loss relative to the zero controller's, $J(K)/J(0)$ ($\\infty$ if not
    finite); the controllers start at the windows' states, or at `start(x0)`."""
    ok = _finite(controllers)
    out = np.full(ok.shape, np.inf)
    if not ok.any():
        return out
    idx = np.nonzero(ok)[0]
    K = _take(controllers, idx)
    W = problem.test
    if W.x0 is not None:
        W = eqx.tree_at(lambda w: w.x0, W, _start(problem, K, W.x0, start))
    pred = np.asarray(predict_any(K, W, _order(problem, K)), np.float64)
    target = np.asarray(W.target, np.float64)
    J = np.mean(np.sum((pred - target[None]) ** 2, axis=(-2, -1)), axis=-1)
    J0 = np.mean(np.sum(target**2, axis=(-2, -1)))
    out[idx] = np.where(np.isfinite(J), J / J0, np.inf)
    return out


def evaluate(problem: Problem, method: Callable, *, key=None, start=None) -> Report:
    """Run `method` on `problem` and report what it learned (see [`Report`][dissil_jax.experiments.zoo.Report]).

    **Arguments:**

    - `problem`: a zoo [`Problem`][dissil_jax.experiments.zoo.Problem].
    - `method`: a callable taking a [`Task`][dissil_jax.experiments.zoo.Task] (training
      windows, controller supply rate, controller order, key) and returning a
      `dj.FitResult`, a batch of controllers (leading axis) or one `LTIController`.
    - `key`: the PRNG key handed to the method (default `PRNGKey(0)`).
    - `start`: where the controllers start on a problem whose windows record the plant
      state $x_0$: a map `[N, n] -> [N, n_state]` (default: at $x_0$ itself, as in
      training). An odd REN of `fit_ren(odd=True)` starts at $(x_0, -x_0)$:
      `start=lambda x0: jnp.concatenate([x0, -x0], -1)`.

    **Returns:** a `Report` with one entry per returned controller.

    ```python
    from dissil_jax.experiments import zoo
    p = zoo.problem("chain3_paper")
    rep = zoo.evaluate(p, lambda t: dj.fit_pgd(t.key, t.windows, t.qsr, n_state=t.n_state))
    ```
    """
    began = time.perf_counter()
    out = method(task(problem, key))
    out = jax.block_until_ready(out)
    wall = time.perf_counter() - began
    P = multiplier = train_loss = None
    if isinstance(out, FitResult):
        P, train_loss = out.P, np.asarray(out.final_loss, np.float64)
        multiplier = getattr(out, "multiplier", None)  # a REN's certificate: (P, multiplier)
        out = out.controllers
    K = as_batch(out)
    return Report(certified(problem, K, P, multiplier), stable(problem, K, start),
                  imitation_error(problem, K, start), train_loss, float(wall))
