"""Building blocks of the zoo: plants, expert designs, supply rates and demonstrations."""

from __future__ import annotations

from typing import cast

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import scipy.linalg

from ..._certify.certify import certify
from ..._controller import LTIController
from ..._data import Windows
from ..._plant_qsr import (
    input_passivity_qsr,
    lti_cone_qsr,
    passivity_indices,
    sector_plant_qsr,
)
from ..._supply import QSR
from ..._theorem1 import closed_loop_certificate, stabilising_qsr
from ...systems import LinearPlant, SectorPlant, mass_spring_chain
from ..data import initial_segments, sliding_windows
from ..simulate import Noise, Trajectories, simulate_expert
from ._record import Facts, ObserverExpert, Problem, StateFeedbackExpert

#: Noise levels per unit of the initial state: (process noise, control noise) standard
#: deviations. "light" is the paper's (0.04, 0.02) at x0_std = 1.
NOISE = {"none": (0.0, 0.0), "light": (0.04, 0.02), "heavy": (0.2, 0.1)}

#: Number of held-out windows and of closed-loop test states of every problem.
NUM_TEST_WINDOWS, NUM_TEST_STATES = 100, 16


# -- plants -----------------------------------------------------------------------------


def chain_plant(seed: int, masses: int, actuated=None) -> LinearPlant:
    """A passive mass-spring-damper chain (paper §5.1, zero-order hold at dt = 0.1) with
    collocated force inputs and velocity outputs at the masses `actuated` (None: all).

    A collocated sub-block of a passive transfer matrix is passive, so every such plant is."""
    chain = mass_spring_chain(jr.PRNGKey(seed), masses, check_passive=False)
    A, B, C, D = chain.plant.matrices()
    idx = np.arange(masses) if actuated is None else np.asarray(actuated)
    return LinearPlant(A, B[:, idx], C[idx], D[np.ix_(idx, idx)])


def random_stable_plant(seed: int, n: int, m: int, p: int, radius: float = 0.8,
                        feedthrough: float = 0.3) -> LinearPlant:
    """A random discrete plant with spectral radius `radius` (entries drawn by `seed`)."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= radius / np.abs(np.linalg.eigvals(A)).max()
    B = rng.standard_normal((n, m)) / np.sqrt(n)
    C = rng.standard_normal((p, n)) / np.sqrt(n)
    D = feedthrough * rng.standard_normal((p, m))
    return LinearPlant(A, B, C, D)


# -- expert designs -----------------------------------------------------------------------


def dlqr(A, B, q: float = 10.0, r: float = 1.0) -> np.ndarray:
    """The discrete LQR gain $K = (rI + B^\\top\\Pi B)^{-1}B^\\top\\Pi A$ (cost $q|x|^2 + r|u|^2$)."""
    A, B = np.asarray(A, np.float64), np.asarray(B, np.float64)
    Pi = scipy.linalg.solve_discrete_are(A, B, q * np.eye(A.shape[0]), r * np.eye(B.shape[1]))
    return np.linalg.solve(r * np.eye(B.shape[1]) + B.T @ Pi @ B, B.T @ Pi @ A)


def observer_controller(plant, q: float = 10.0, r: float = 1.0) -> LTIController:
    """LQR gain plus a predictor-form Kalman observer, as a controller $y\\mapsto\\hat y = -u$.

    $u = -K\\hat x$, $\\hat x^+ = A\\hat x + Bu + L(y - C\\hat x - Du)$, so
    $(A_c, B_c, C_c, D_c) = (A - BK - LC + LDK,\\ L,\\ K,\\ 0)$."""
    A, B, C, D = plant.matrices()
    K = dlqr(A, B, q, r)
    S = scipy.linalg.solve_discrete_are(A.T, C.T, np.eye(A.shape[0]), np.eye(C.shape[0]))
    L = A @ S @ C.T @ np.linalg.inv(C @ S @ C.T + np.eye(C.shape[0]))
    return LTIController(A - B @ K - L @ C + L @ D @ K, L, K, np.zeros((B.shape[1], C.shape[0])))


def static_expert(plant, q=10.0, r=1.0, saturation=None, linearise=True):
    """LQR state feedback (on $A + \\alpha I$ for a sector plant: its linearisation at 0),
    and the equivalent `LTIController` $(A - BK, 0, K, 0)$ when it is linear and exact."""
    A, B, C, _ = plant.matrices()
    alpha = float(getattr(plant, "alpha", 0.0))
    K = dlqr(A + alpha * np.eye(A.shape[0]) if linearise else A, B, q, r)
    exact = None
    if saturation is None and isinstance(plant, LinearPlant):
        exact = LTIController(A - B @ K, np.zeros((A.shape[0], C.shape[0])), K,
                              np.zeros((B.shape[1], C.shape[0])))
    return StateFeedbackExpert(jnp.asarray(K), saturation), exact


# -- supply rates -------------------------------------------------------------------------


def bounded_gain_qsr(plant, *, grid: int = 512, factor: float = 1.05) -> QSR:
    """$\\gamma$-bounded gain of a stable LTI plant, certified by `dj.certify`.

    $\\gamma$ starts at `factor` times the largest singular value of the frequency response
    on a grid of the unit circle (a lower bound of the $H_\\infty$ norm) and grows by
    `factor` until the exact check of `dj.certify` proves it."""
    A, B, C, D = plant.matrices()
    n = A.shape[0]
    zs = np.exp(1j * np.linspace(0.0, np.pi, grid))
    gain = max(np.linalg.svd(C @ np.linalg.solve(z * np.eye(n) - A, B) + D, compute_uv=False)[0]
               for z in zs)
    gamma = factor * gain
    for _ in range(40):
        qsr = QSR.bounded_gain(gamma, n_in=B.shape[1], n_out=C.shape[0])
        if certify(LTIController(A, B, C, D), qsr).holds:
            return qsr
        gamma *= factor
    raise ValueError("`plant` has no certifiable bounded gain near its H-infinity norm; "
                     "pass a stable plant.")


def plant_supply(plant, kind: str):
    """`(plant_qsr, storage)` of the given kind through the library's plant tools."""
    if kind == "sector":
        A, B, C, D = plant.matrices()
        return sector_plant_qsr(A, B, C, D, float(plant.alpha), return_storage=True)
    make = {"passivity": passivity_indices, "degenerate_cone": input_passivity_qsr,
            "interior_cone": lti_cone_qsr, "bounded_gain": bounded_gain_qsr}[kind]
    return make(plant), None


def controller_supply(plant_qsr: QSR, margin: float = 0.05) -> QSR:
    """Theorem 1's controller supply rate for the plant's, with $Q \\preceq 0$.

    `stabilising_qsr` with $\\alpha = 1$, $M_1 = $ `margin` $\\cdot(1 + \\lVert Q_1\\rVert)$ and
    $M_2$ the smallest margin that keeps $Q_2 = -(R_1 + M_2) \\preceq 0$: every trainer
    (including `fit_direct`, which needs $Q\\preceq0$) applies. For $R_1 = -\\nu I$ with
    $\\nu>0$ (input passivity) this gives the degenerate cone $Q_2 = 0$."""
    R1, Q1 = plant_qsr.R, plant_qsr.Q
    top = float(np.linalg.eigvalsh(-R1)[-1])
    m2 = top if top > 0 else margin * (1.0 + np.abs(R1).max())
    m1 = margin * (1.0 + np.abs(Q1).max())
    qsr = stabilising_qsr(plant_qsr, alpha=1.0, margins=(m1, m2))
    if not closed_loop_certificate(plant_qsr, qsr).holds:  # pragma: no cover - by design
        raise ValueError("internal: the controller supply rate does not pair with the plant's.")
    return qsr


# -- demonstrations -----------------------------------------------------------------------


def make_problem(name: str, split: str, seed: int, *, plant, expert, expert_controller,
                 supply: str, expert_kind: str, has_state: bool, units: float, noise: str,
                 num_windows: int, horizon: int, sliding: bool = False,
                 n_state: int | None = None) -> Problem:
    """Simulate the demonstrations, derive the supply rates and assemble the `Problem`.

    Windows with state are initial segments (or sliding windows within 10 steps); windows
    without state are initial segments of runs whose expert starts at rest, cut with
    `Windows(None, y, u)`: exact for an observer expert whatever the plant's initial state."""
    plant_qsr, storage = plant_supply(plant, supply)
    qsr = controller_supply(plant_qsr)
    sw, se = (units * s for s in NOISE[noise])
    rng = np.random.default_rng(seed)
    span = max(10, horizon) if sliding else horizon
    per = span - horizon + 1
    n_train, n_test = -(-num_windows // per), -(-NUM_TEST_WINDOWS // per)
    # One simulation (one compilation) for the training and the held-out trajectories;
    # numpy draws, so that building needs no per-shape compilation of the samplers.
    num, n, m = n_train + n_test, plant.n_state, plant.n_in
    dtype = plant.A.dtype
    x0 = jnp.asarray(units * rng.standard_normal((num, n)), dtype)
    draws = Noise(jnp.asarray(sw * rng.standard_normal((num, span, n)), dtype),
                  jnp.asarray(se * rng.standard_normal((num, span, m)), dtype))
    traj = simulate_expert(plant, expert, x0, draws)

    def windows(part, count):
        t = Trajectories(*(a[part] for a in (traj.x, traj.y, traj.u)))
        W = (sliding_windows(t, count, horizon, span) if sliding
             else initial_segments(t, count, horizon))
        return W if has_state else Windows(None, W.y, W.u)

    train = windows(slice(0, n_train), num_windows)
    test = windows(slice(n_train, num), NUM_TEST_WINDOWS)
    x0_test = jnp.asarray(units * rng.standard_normal((NUM_TEST_STATES, n)), dtype)
    n_hat = plant.n_state if has_state else int(cast(int, n_state))  # given without state
    facts = Facts(plant.n_state, plant.n_in, plant.n_out, supply, has_state, float(units), noise,
                  int(num_windows), int(horizon), expert_kind)
    return Problem(name, split, plant, expert, expert_controller, train, test, plant_qsr,
                   storage, qsr, n_hat, x0_test, facts)


def observer(plant):
    """An `ObserverExpert` for `plant` and its exact `LTIController`."""
    Kc = observer_controller(plant)
    return ObserverExpert(Kc, plant.C, plant.D), Kc


def sector_plant(seed: int, n: int, m: int, p: int, alpha: float, radius: float = 0.5):
    """A `SectorPlant` $x^+ = Ax + \\alpha\\sin x + Bu$ (paper eq. 20 generalised to $n$
    states) with $A$ = `radius` times a random orthogonal matrix, so that
    $\\lVert A\\rVert_2 = $ `radius` and Lemma 8 applies when $2(\\text{radius}^2 +
    \\alpha^2) < 1$."""
    rng = np.random.default_rng(seed)
    Qm, _ = np.linalg.qr(rng.standard_normal((n, n)))
    B = rng.standard_normal((n, m)) / np.sqrt(n)
    C = rng.standard_normal((p, n)) / np.sqrt(n)
    D = rng.standard_normal((p, m))
    return SectorPlant(radius * Qm, B, C, D, alpha)
