"""High-order test problems shared by the high-order benchmarks (m = p = 2, passive).

- `chain_windows`: a mass-spring chain of `n_masses` unit masses (order 2·n_masses) with
  two collocated actuators, on the first and the last mass, and the paper's LQR expert
  designed on that two-input model; initial-segment windows (the controller's order is the
  plant's).
- `realisable`: windows of a random order-`n` passive expert (`realisable_windows`), which
  a controller of order `n` fits exactly.
"""

import control
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import dissil_jax as dj
from dissil_jax.experiments import demonstration_windows, realisable_windows

PASSIVE = dj.QSR.passive(2)


def chain_windows(seed: int, n_masses: int, num_windows: int = 25, horizon: int = 10,
                  dt: float = 0.1):
    rng = np.random.default_rng(seed)
    k, c = rng.uniform(1, 5, n_masses), rng.uniform(1, 10, n_masses)
    phi = rng.uniform(0.05, 1.0)
    Ac, Bc, Cc, _ = dj.systems.chain_matrices(k, c, phi)
    act = [0, n_masses - 1]
    Bc, Cc, Dc = Bc[:, act], Cc[act], phi * np.eye(2)
    sysd = control.ss(Ac, Bc, Cc, Dc).sample(dt, method="zoh")
    plant = dj.LinearPlant(*(jnp.asarray(np.asarray(M, np.float64))
                             for M in (sysd.A, sysd.B, sysd.C, sysd.D)))
    expert = dj.experts.lqr_expert(Ac, Bc, Cc)
    return demonstration_windows(jr.PRNGKey(seed), plant, expert, num_windows, "initial",
                                 horizon=horizon)


def realisable(seed: int, n: int, num_windows: int = 25, horizon: int = 10):
    return realisable_windows(jr.PRNGKey(seed), PASSIVE, n_state=n, num_windows=num_windows,
                              horizon=horizon)[0]
