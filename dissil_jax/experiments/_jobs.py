"""Running the command line's configurations: in this process, or shared among worker
processes (`--jobs`), handing each finished record on as soon as it exists.

The workers are spawned processes, so this lives in an importable module: functions of
the `-m` entry point's `__main__` cannot be pickled into them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable
from typing import Any

# Relative cost of one configuration, for handing the dearest out first: PGD's projections
# dominate, then ICO's SDPs; cost grows with N.
_COST = {"pgd": 8.0, "ico": 2.0}


def label(config: tuple) -> str:
    """`(data, method, N)` as the progress bar shows it: "initial PGD N=25"."""
    from .protocol import METHOD_LABELS

    data, method, n = config
    return f"{data} {METHOD_LABELS.get(method, method)} N={n}"


def in_process(run, configs, bar, on_record: Callable[[int, dict], Any]) -> None:
    """`run(*config, on_plant=...)` for every config in turn; `on_record(i, record)` after
    each, and the bar names the configuration and, for several plants, the plant."""
    for i, config in enumerate(configs):
        name = label(config)
        bar.set_postfix_str(name)

        def on_plant(k, n, name=name):
            if n > 1:
                bar.set_postfix_str(f"{name}, plant {k + 1}/{n}")

        on_record(i, run(*config, on_plant=on_plant))
        bar.update()


def in_workers(run, configs, jobs: int, bar, on_record: Callable[[int, dict], Any]) -> None:
    """`run(*config)` for every config on `jobs` spawned processes; `on_record(i, record)`
    as each finishes (in this process), while the bar names the configurations running.

    Each worker keeps its own per-process caches (plants, data, test setups) and a solver
    pool of `cores // jobs` threads; the dearest configurations go first, so the workers
    finish together, and a worker gets its next configuration when it is free. Every
    record depends only on its configuration and the seed (the training times aside: they
    include compilation, which each worker pays anew). The workers inherit the caller's
    float64 setting through `JAX_ENABLE_X64`, set in the environment only while they
    start. They ignore SIGINT: on Ctrl-C (or any error) here they are terminated at once
    instead of finishing their configurations, and the exception goes on to the caller.
    A worker that dies (killed, out of memory) is an error naming its configuration.
    """
    import multiprocessing
    from multiprocessing.connection import wait

    import jax

    pending = sorted(range(len(configs)),
                     key=lambda i: -_COST.get(configs[i][1], 1.0) * configs[i][2])
    jobs = min(jobs, len(configs))
    threads = max(1, (os.cpu_count() or 1) // jobs)
    env = {"DISSIL_JAX_THREADS": str(threads),
           "JAX_ENABLE_X64": "1" if jax.config.read("jax_enable_x64") else "0"}
    ctx = multiprocessing.get_context("spawn")
    workers: list = []
    try:
        with _environment(env), _sigint_ignored():  # SIG_IGN is inherited by the workers
            for _ in range(jobs):
                conn, child = ctx.Pipe()
                proc = ctx.Process(target=_serve, args=(child, run), daemon=True)
                proc.start()
                child.close()
                workers.append((proc, conn))
        busy: dict[int, int] = {}  # worker -> configuration
        while pending or busy:
            for w in range(jobs):
                if pending and w not in busy:
                    busy[w] = pending.pop(0)
                    workers[w][1].send(configs[busy[w]])
            bar.set_postfix_str("running: " + "; ".join(label(configs[i])
                                                        for i in sorted(busy.values())))
            wait([workers[w][1] for w in busy] + [workers[w][0].sentinel for w in busy])
            for w in list(busy):
                proc, conn = workers[w]
                if not (conn.poll() or not proc.is_alive()):
                    continue
                i = busy.pop(w)
                try:
                    error, record = conn.recv()
                except EOFError:
                    raise RuntimeError(f"the worker running {label(configs[i])} ended "
                                       f"(exit code {proc.exitcode})") from None
                if error is not None:
                    raise RuntimeError(f"{label(configs[i])} failed in a worker:\n{error}")
                on_record(i, record)
                bar.update()
        for proc, conn in workers:
            conn.send(None)
        for proc, _ in workers:
            proc.join()
    finally:
        for proc, _ in workers:
            if proc.is_alive():
                proc.terminate()
                proc.join()


def _serve(conn, run) -> None:
    """A worker: `run(*config)` for each config received, until None; sends back `(None,
    record)`, or `(traceback, None)` when the run raised."""
    import traceback

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while (config := conn.recv()) is not None:
        try:
            conn.send((None, run(*config)))
        except Exception:
            conn.send((traceback.format_exc(), None))


@contextlib.contextmanager
def _environment(env: dict):
    """`env` in `os.environ` inside the block (spawned processes copy the environment)."""
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored inside the block (only the main thread can change handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
