"""Configurations shared among worker processes (the command line's `--jobs`).

The workers are spawned processes, so this lives in an importable module: functions of
the `-m` entry point's `__main__` cannot be pickled into them.
"""

from __future__ import annotations

import os
from typing import Any

# Relative cost of one configuration, for handing the dearest out first: PGD's projections
# dominate, then ICO's SDPs; cost grows with N.
_COST = {"pgd": 8.0, "ico": 2.0}


def in_workers(run, configs, jobs: int, bar) -> list[dict]:
    """`run(*config)` for every config on `jobs` spawned processes; records in config order.

    Each worker keeps its own per-process caches (plants, data, test setups) and a solver
    pool of `cores // jobs` threads; the dearest configurations go first, so the workers
    finish together. Every record depends only on its configuration and the seed. The
    workers inherit the caller's float64 setting through `JAX_ENABLE_X64`, set in the
    environment only while they are started.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    import jax

    order = sorted(range(len(configs)),
                   key=lambda i: -_COST.get(configs[i][1], 1.0) * configs[i][2])
    threads = max(1, (os.cpu_count() or 1) // jobs)
    records: list[Any] = [None] * len(configs)  # every slot is filled below
    env = {"DISSIL_JAX_THREADS": str(threads),
           "JAX_ENABLE_X64": "1" if jax.config.read("jax_enable_x64") else "0"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # spawned workers copy the environment when they start
    try:
        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as ex:
            futures = {ex.submit(run, *configs[i]): i for i in order}
            for f in as_completed(futures):
                records[futures[f]] = f.result()
                bar.update()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return records
