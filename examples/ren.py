"""Certified nonlinear dynamic controllers: a REN against the LTI direct map.

On the paper's nonlinear example (plant x+ = 0.5x + 0.4 sin x + u, y = x - 2u; NMPC expert;
controller supply rate (-29.867, 3.556, 0.601), which closes the loop stably by the paper's
Theorem 1), this script trains on the same 25 initial segments

- LTI controllers with `dj.fit_direct` (the paper's controller class), and
- REN controllers with `dj.fit_ren` (an LTI system in feedback with `width` ReLU neurons,
  the experiments' settings: odd, since the expert is, so each REN is two copies of a
  network, the second driven by -y and started at -x0),

checks every REN's certificate twice (the float64 check of the trainer's (P, Lambda), and
a fresh SDP with `dj.certify_ren`), and tests all controllers in closed loop against the
expert as the reproduction does.

Run:  python examples/ren.py [--quick] [--inits 10] [--width 16] [--seed 0]
"""

import argparse
import time

import jax
import jax.random as jr
import numpy as np

import dissil_jax as dj
from dissil_jax.experiments import equilibrium_horizon, evaluate
from dissil_jax.experiments.protocol import controller_start, example_spec, fit, training_data


def main(quick=False, inits=10, width=16, seed=0):
    jax.config.update("jax_enable_x64", True)
    spec = example_spec("nonlinear", quick)
    if quick:
        inits, width = min(inits, 3), min(width, 4)
    spec = spec.__class__(**{**spec.__dict__, "ren_width": width})
    plant, expert, windows, (k_fit, k_test, k_noise) = training_data(spec, 0, seed,
                                                                      "initial", 25)
    # the test states and length of `protocol.run_config`
    x0 = spec.test_std * jr.normal(k_test, (spec.num_test, plant.n_state), windows.y.dtype)
    steps = max(spec.min_test_steps, equilibrium_horizon(
        jr.fold_in(k_noise, 1), plant, expert, x0, max_steps=spec.equilibrium_search))
    print(f"nonlinear example, 25 initial segments, {inits} initialisations, REN width "
          f"{width}, {spec.num_test} test states, {steps} test steps")
    print()
    print("| controller | train time (s) | median train loss | % certified | % stable "
          "| median test MSE |")
    print("|---|---|---|---|---|---|")
    for method in ("direct", "ren"):
        t = time.perf_counter()
        res = fit(method, k_fit, windows, spec, inits)
        train = time.perf_counter() - t
        certified = np.array(res.certified, bool)
        if method == "ren":  # an independent certificate: the SDP in (P, Lambda)
            certified &= np.asarray(dj.certify_ren(res.controllers, spec.qsr).holds, bool)
        ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                      xhat0=controller_start(spec, method, x0))
        print(f"| {method} | {train:.1f} | {float(np.median(res.final_loss)):.4g} "
              f"| {100 * certified.mean():.0f} | {100 * np.mean(ev.stable):.0f} "
              f"| {float(np.median(ev.mse)):.4g} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (CI)")
    parser.add_argument("--inits", type=int, default=10, help="initialisations per method")
    parser.add_argument("--width", type=int, default=16, help="REN neurons")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.quick, args.inits, args.width, args.seed)
