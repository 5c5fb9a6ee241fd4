"""Training under many supply rates in one process: compilations and memory maps per rate.

Each trainer trains under `--rates` gain bounds of one shape (SISO, gamma from 0.5 to 2,
one distinct rate per call), then as many times again under the first rate. Reported per
trainer: the ratio of the distinct rates' mean wall time per call to the repeated rate's
(about 1 when a new rate reuses the compiled run, the compile-to-run ratio when it
compiles its own), and the process's memory maps added per distinct rate (each compiled
executable keeps its code pages mapped; Linux allows 65,530 maps per process by default,
`vm.max_map_count`, and aborts the process with "LLVM ERROR: Unable to allocate section
memory" beyond).

`fit_pgd_first_order` is `fit_pgd(method="first_order")` (ADMM in the compiled run), and
`pgd_run_first_order` the same run through `pgd_run` under `eqx.filter_jit`, whose rate the
caller holds as a static value: the reference that compiles once per rate.

Usage: python benchmarks/bench_rate_sweep.py [--rates 8] [--trainers fit_direct fit_ren fit_pgd
    fit_pgd_first_order pgd_run_first_order]
"""

from __future__ import annotations

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import dissil_jax as dj


def _maps() -> int:
    with open("/proc/self/maps") as f:
        return sum(1 for _ in f)


def _windows():
    rng = np.random.default_rng(0)
    x0, y = rng.normal(size=(20, 2)), rng.normal(size=(20, 10, 1))
    return dj.Windows(jnp.asarray(x0), jnp.asarray(y), jnp.asarray(-0.5 * y))


def _calls(fn, rates):
    start, maps = time.perf_counter(), _maps()
    for qsr in rates:
        jax.block_until_ready(fn(qsr))
    return (time.perf_counter() - start) / len(rates), (_maps() - maps) / len(rates)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=int, default=8)
    parser.add_argument("--trainers", nargs="+", default=[
        "fit_direct", "fit_ren", "fit_pgd", "fit_pgd_first_order", "pgd_run_first_order"])
    args = parser.parse_args()
    w, key = _windows(), jax.random.PRNGKey(0)
    gains = np.geomspace(0.5, 2.0, args.rates + 1)
    print(f"{args.rates} distinct gain bounds, then {args.rates} calls under one; "
          "2 initialisations, 20 steps\n")
    print("| trainer | distinct / repeated wall time per call | maps per distinct rate |")
    print("|---|---|---|")
    kw = dict(num_inits=2, max_steps=20, throw=False)
    for name in args.trainers:
        if name == "fit_pgd_first_order":
            fn = lambda qsr: dj.fit_pgd(key, w, qsr, method="first_order", **kw)
        elif name == "pgd_run_first_order":
            run = eqx.filter_jit(lambda qsr: dj.pgd_run(key, w, qsr, method="first_order", **kw))
            fn = lambda qsr: run(qsr)
        else:
            fit = getattr(dj, name)
            fn = lambda qsr, fit=fit: fit(key, w, qsr, **kw)
        rate = lambda g: dj.QSR.bounded_gain(float(g), n_in=1, n_out=1)
        fn(rate(gains[-1]))  # compile once (the repeated rate's call then reuses it)
        distinct, maps = _calls(fn, [rate(g) for g in gains[:-1]])
        repeated, _ = _calls(fn, [rate(gains[-1])] * args.rates)
        print(f"| `{name}` | {distinct / repeated:.1f} | {maps:.0f} |", flush=True)


if __name__ == "__main__":
    main()
