"""Learning from input-output logs alone: controllers started at rest (x̂0 = 0).

The paper's windows record the plant state at each window start and start the controller
there (x̂0 = x0), which fixes the controller order to the plant's. `dj.Windows(None, y, u)`
drops the state: the controller starts every window at rest, x̂0 = 0, and may have any
order n̂ (`n_state=` of the trainers). This script compares, on the paper's nonlinear example
(plant x+ = 0.5x + 0.4 sin x + u, y = x - 2u, one state; NMPC expert; controller supply rate
(-29.867, 3.556, 0.601)) and the same demonstrations:

- n̂ = 1 trained with x̂0 = x0 (the paper), tested from x̂0 = x0 and from rest;
- n̂ = 1 and n̂ = 2 trained at rest (x0 dropped), tested from rest.

n̂ = 2 is only possible at rest: the plant state is one-dimensional. Training is PGD with
the example's settings (as `dissil_jax.experiments.protocol.fit`), and testing is as
`protocol.run_config`: closed loop against the expert from the same test states with the
same noise, for max(expert equilibrium horizon, 30) steps.

Run:  python examples/no_state.py [--quick] [--inits 20] [--seed 0]
"""

import argparse
import time

import jax
import jax.random as jr
import numpy as np

import dissil_jax as dj
from dissil_jax.experiments import equilibrium_horizon, evaluate
from dissil_jax.experiments.protocol import example_spec, training_data

REGIMES = ("initial", "sliding")
# (label of the training windows, n̂, initial controller state in the test loops)
ROWS = (("x̂0 = x0", 1, "x0"), ("x̂0 = x0", 1, "rest"), ("x̂0 = 0", 1, "rest"),
        ("x̂0 = 0", 2, "rest"))


def fit(key, windows, spec, inits, n_state):
    """PGD with the example's settings (as protocol.fit: the paper's step rule, in the
    data's units), with an explicit order."""
    return dj.fit_pgd(key, windows, spec.qsr, num_inits=inits, n_state=n_state,
                      max_steps=spec.max_steps, atol=spec.tol,
                      learning_rate=spec.pgd_learning_rate, decay=spec.pgd_decay,
                      init_scale=spec.init_scale, balance=False, throw=False)


def run(regime, segments, spec, inits, seed):
    plant, expert, logged, (k_fit, k_test, k_noise) = training_data(
        spec, 0, seed, regime, segments)
    io_only = dj.Windows(None, logged.y, logged.u)  # the same data without the plant state
    x0 = spec.test_std * jr.normal(k_test, (spec.num_test, plant.n_state), logged.y.dtype)
    T = equilibrium_horizon(jr.fold_in(k_noise, 1), plant, expert, x0,
                            max_steps=spec.equilibrium_search)
    steps = max(T, spec.min_test_steps)
    fits = {}
    rows = []
    for label, n_hat, start in ROWS:
        windows = logged if label == "x̂0 = x0" else io_only
        if (label, n_hat) not in fits:
            fits[label, n_hat] = fit(k_fit, windows, spec, inits, n_hat)
        res = fits[label, n_hat]
        ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                      xhat0=None if start == "x0" else "rest")
        mse = np.sort(np.asarray(ev.mse))
        rows.append(dict(
            regime=regime, train=label, n_hat=n_hat, test=f"x̂0 = {'x0' if start == 'x0' else '0'}",
            stable=100 * float(np.mean(ev.stable)),
            certified=100 * float(np.mean(np.asarray(res.certified))),
            loss=float(np.median(np.asarray(res.final_loss))),
            mse_min=mse[0], mse_med=float(np.median(mse)), mse_max=mse[-1], steps=steps))
    return rows


def fmt(v):
    return "∞" if not np.isfinite(v) else f"{v:.4f}"


def main(quick=False, inits=20, seed=0):
    jax.config.update("jax_enable_x64", True)
    spec = example_spec("nonlinear", quick)
    inits = min(inits, 4) if quick else inits
    t = time.perf_counter()
    regimes = REGIMES[:1] if quick else REGIMES
    rows = [r for regime in regimes for r in run(regime, 25, spec, inits, seed)]
    print(f"nonlinear example, N = 25 windows of h = 2, {inits} PGD initialisations per row, "
          f"seed {seed}, {spec.num_test} test states, {rows[0]['steps']} test steps "
          f"({time.perf_counter() - t:.0f} s)")
    print()
    print("| data | training windows | n̂ | test start | % stable | % certified "
          "| median train loss | MSE min | MSE median | MSE max |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['regime']} | {r['train']} | {r['n_hat']} | {r['test']} | {r['stable']:.0f} "
              f"| {r['certified']:.0f} | {r['loss']:.4f} | {fmt(r['mse_min'])} "
              f"| {fmt(r['mse_med'])} | {fmt(r['mse_max'])} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (CI)")
    parser.add_argument("--inits", type=int, default=20, help="PGD initialisations per row")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.quick, args.inits, args.seed)
