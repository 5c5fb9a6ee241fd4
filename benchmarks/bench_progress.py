"""The cost of `progress=True`: the trainers' compiled loops with their host callbacks
against the same loops without, in one run.

100 initialisations × 150 steps (no early stop) of `fit_direct` and `fit_ren` (width 16)
on 25 random windows of 10 steps (n = 6, m = p = 3, passivity); both variants compiled
first, then five calls of each, alternating. Reported: the ratio of the median wall times.

Usage: python benchmarks/bench_progress.py
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import dissil_jax as dj


def main():
    rng = np.random.default_rng(0)
    w = dj.Windows(*(jnp.asarray(rng.normal(size=s)) for s in ((25, 6), (25, 10, 3),
                                                                 (25, 10, 3))))
    qsr = dj.QSR.passive(3)
    print("| trainer | with / without progress reports |\n|---|---|")
    for name in ("fit_direct", "fit_ren"):
        fit = getattr(dj, name)
        run = lambda k, p: fit(jax.random.PRNGKey(k), w, qsr, num_inits=100, max_steps=150,
                               rtol=0.0, progress=p)
        for p in (True, False):
            run(0, p)  # compile
        times = {True: [], False: []}
        for k in range(5):
            for p in (True, False):
                start = time.perf_counter()
                run(k, p)
                times[p].append(time.perf_counter() - start)
        print(f"| `{name}` | {np.median(times[True]) / np.median(times[False]):.2f} |",
              flush=True)


if __name__ == "__main__":
    main()
