"""Projected Adam: the optimiser's metric in the projection against the Frobenius distance.

Adam steps by -lr m / sqrt(nu) per entry. Projected in the Frobenius distance, such a step
is biased at the boundary of the dissipative set (the preconditioned normal component of the
gradient has a part along the boundary), and the iterate can drift uphill. `fit_pgd`
therefore projects in the metric W = sqrt(nu) (`dissil_jax._train.steps.optimizer_metric`).
The reference in the same run is the same loop with that metric switched off.

Problems: those of `bench_optimizers.py` (realisable, noisy, the paper's linear and nonlinear
examples with 25 initial segments). 8 initialisations, `atol=0`, `--steps` steps (default
1000). Reported per problem, rate and metric: the batch's total loss over its initial total
after 150 steps, after 300 and at the end, the worst run's final/initial ratio, the largest
rise of a run above its own best loss ((final - minimum along the run) / initial; 0 means
the run ended at its best), failed runs, and wall seconds per run.

Usage: python benchmarks/bench_adam_metric.py [--quick] [--steps N]
"""

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from bench_optimizers import problems  # noqa: E402

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import pgd  # noqa: E402

_METRIC = pgd.optimizer_metric


def run(windows, qsr, rate, steps, metric):
    """One batch of 8 projected-Adam runs, traced afresh (so the switch takes effect)."""
    pgd.optimizer_metric = _METRIC if metric else (lambda *_: None)
    try:
        fn = jax.jit(lambda key: dj.pgd_run(key, windows, qsr, optimizer=optax.adam(rate),
                                            max_steps=steps, atol=0.0, rtol=0.0, throw=False))
        jax.block_until_ready(fn(jr.PRNGKey(2)))  # compile
        start = time.perf_counter()
        res = jax.block_until_ready(fn(jr.PRNGKey(1)))
        return res, (time.perf_counter() - start) / res.num_inits
    finally:
        pgd.optimizer_metric = _METRIC


def summary(res, steps):
    h = np.asarray(res.loss_history)
    h = np.where(np.isnan(h), np.nan, h)
    last = np.array([row[~np.isnan(row)][-1] for row in h])
    total = lambda s: np.sum(np.where(np.isnan(h[:, s]), last, h[:, s])) / np.sum(h[:, 0])
    rise = np.max((last - np.nanmin(h, axis=1)) / h[:, 0])
    failed = int(np.sum(~np.isin(res.result_names(), ["converged", "max_steps"])))
    return [total(min(150, steps)), total(min(300, steps)), total(steps),
            np.max(last / h[:, 0]), rise, failed]


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    steps = 300 if args.quick else args.steps
    rates = (0.01,) if args.quick else (0.01, 0.03, 0.1)
    probs = problems()
    if args.quick:
        probs = {k: probs[k] for k in ("realisable", "nonlinear")}
    print(f"| problem | adam rate | projection | total @150 | total @300 | total @{steps} "
          "| worst run | largest rise | failed | s/run |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, (windows, qsr) in probs.items():
        for rate in rates:
            for metric in (False, True):
                res, wall = run(windows, qsr, rate, steps, metric)
                cells = summary(res, steps)
                label = "sqrt(nu) metric" if metric else "Frobenius"
                print(f"| {name} | {rate:g} | {label} | " + " | ".join(
                    f"{v:.3g}" if isinstance(v, float) else str(v) for v in cells)
                    + f" | {wall:.3f} |", flush=True)


if __name__ == "__main__":
    main()
