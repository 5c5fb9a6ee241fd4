"""Sharded sweeps against unsharded ones, on 2 forced host devices.

Run by `tests/test_sweep.py`: `main` in a subprocess with
`XLA_FLAGS=--xla_force_host_platform_device_count=2`, `JAX_ENABLE_X64=1` and a 2-thread
pool (`DISSIL_JAX_THREADS=2`); prints one JSON line of findings, one entry per case:
the largest difference to the unsharded sweep, the devices holding the output, XLA's
"Involuntary full rematerialization" warnings while compiling and running, and every
projection callback's shard, batch shape and the peak number of its solves at once.
`process` is one of two `jax.distributed` processes on this machine, as on two hosts.
"""

import collections
import json
import os
import sys
import tempfile
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, NamedSharding, PartitionSpec as P

import dissil_jax as dj
from dissil_jax.internal import projection as _projection, sdp as _sdp

REMAT = "Involuntary full rematerialization"
CALLS = []  # per projection callback: [shard, batch shape, peak solves at once]
_LOCK = threading.Lock()
_host_batch, _thread_map = _projection._host_batch, _sdp.thread_map
_ACTIVE = collections.Counter()
_PEAK = {"total": 0}


def _spy_host_batch(*args, **kw):
    shard = int(np.ravel(args[-1])[0]) if np.size(args[-1]) else None  # the last argument
    call = [shard, list(np.shape(args[0])[:-2]), 0]
    _LOCAL.call = call
    out = _host_batch(*args, **kw)
    CALLS.append(call)
    return out


def _spy_thread_map(fn, items, **kw):
    """Count the solves of this callback running at once, and of all callbacks."""
    call = getattr(_LOCAL, "call", None) or [None, None, 0]
    key = id(call)

    def counted(chunk):
        with _LOCK:
            _ACTIVE[key] += 1
            _ACTIVE["all"] += 1
            call[2] = max(call[2], _ACTIVE[key])
            _PEAK["total"] = max(_PEAK["total"], _ACTIVE["all"])
        try:
            time.sleep(0.002)  # let the chunks of one call overlap if they are allowed to
            return fn(chunk)
        finally:
            with _LOCK:
                _ACTIVE[key] -= 1
                _ACTIVE["all"] -= 1

    return _thread_map(counted, items, **kw)


_LOCAL = threading.local()
_projection._host_batch = _spy_host_batch
_sdp.thread_map = _spy_thread_map


def run_capturing_stderr(fn):
    """`fn()` (blocked on), with file descriptor 2, where XLA's C++ log writes, captured."""
    with tempfile.TemporaryFile() as f:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(f.fileno(), 2)
        try:
            out = jax.block_until_ready(fn())
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        f.seek(0)
        return out, f.read().decode(errors="replace")


def max_diff(a, b) -> float:
    """The largest absolute difference of two pytrees (inf if their NaNs differ)."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    worst = 0.0
    for x, y in zip(la, lb):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if x.shape != y.shape or np.any(np.isnan(x) != np.isnan(y)):
            return float("inf")
        both = ~np.isnan(x)
        worst = max(worst, float(np.max(np.abs(x[both] - y[both]), initial=0.0)))
    return worst


def case(fn, ref):
    """Run `fn` and report it against the unsharded `ref`."""
    CALLS.clear()
    out, log = run_capturing_stderr(fn)
    leaf = jax.tree.leaves(out)[0]
    return dict(diff=max_diff(out, ref), remat=log.count(REMAT),
                devices=len(leaf.sharding.device_set),
                sharded=not leaf.sharding.is_fully_replicated, calls=list(CALLS))


def problem():
    """A passive order-2 problem and a PGD run of one learning rate over 2 initialisations.

    Shard 0 of a 2-way split gets the rates [0.1, 3.0] (15 steps), shard 1 [1.0, 1.5],
    which stop earlier: the shards' loops run for different numbers of steps.
    """
    qsr = dj.QSR.passive(2)
    # Windows that a projected random expert fits exactly (as `realisable_windows`).
    kK, kx, ky = jax.random.split(jax.random.PRNGKey(0), 4)[:3]
    expert, _ = dj.project(dj.LTIController.random(kK, 2, 2, 2), qsr)
    x0, y = jax.random.normal(kx, (10, 2)), jax.random.normal(ky, (10, 2, 2))
    windows = dj.Windows(x0, y, -jax.vmap(lambda x, yk: dj.rollout(expert, x, yk))(x0, y))

    def pgd(lr, qsr=qsr):
        return dj.pgd_run(jax.random.PRNGKey(1), windows, qsr, learning_rate=lr, num_inits=2,
                          max_steps=15, atol=1e-2, rtol=0.0, init_scale=1.0, throw=False)

    return qsr, pgd, jnp.array([0.1, 3.0, 1.0, 1.5])


def main():
    assert jax.device_count() == 2, jax.devices()
    qsr, pgd, lrs = problem()

    def gd(lr):  # a tenth of PGD's rates: at 1.0 and above plain GD diverges here, and a
        # diverging lane amplifies any difference of rounding between two compilations
        return pgd(lr / 10, qsr=None)

    def inits(key):  # ICO's random initialisations: two N(0, 1) draws per key, projected
        K = jax.vmap(lambda k: dj.LTIController.random(k, 2, 2, 2))(jax.random.split(key, 2))
        return dj.project(K, qsr, throw=False)

    keys = jax.random.split(jax.random.PRNGKey(2), 8)
    ref = {name: jax.block_until_ready(jax.jit(jax.vmap(f))(x))
           for name, f, x in (("pgd", pgd, lrs), ("gd", gd, lrs), ("project", inits, keys))}
    mesh = jax.make_mesh((2,), ("sweep",), axis_types=(AxisType.Auto,))
    lanes = NamedSharding(mesh, P("sweep"))
    swept = dj.sweep(pgd)
    found = {
        # the defect: jit with sharded inputs alone
        "plain": case(lambda: jax.jit(jax.vmap(pgd), in_shardings=lanes)(lrs), ref["pgd"]),
        "pgd": case(lambda: swept(lrs), ref["pgd"]),
        "recipe": case(lambda: jax.jit(jax.shard_map(
            jax.vmap(pgd), mesh=mesh, in_specs=P("sweep"), out_specs=P("sweep"),
            check_vma=False))(jax.device_put(lrs, lanes)), ref["pgd"]),
        "gd": case(lambda: dj.sweep(gd)(lrs), ref["gd"]),
        "project": case(lambda: dj.sweep(inits)(keys), ref["project"]),
        "uneven": case(lambda: swept(lrs[:3]),  # padded to 4: compiled above
                       jax.tree.map(lambda x: x[:3], ref["pgd"])),
    }
    found["workers"], found["peak_solves"] = _sdp.num_workers(), _PEAK["total"]
    found["steps"] = np.asarray(ref["pgd"].steps).max(axis=1).tolist()  # per learning rate
    print(json.dumps(found))


def process(pid: int, port: int):
    """Process `pid` of 2 (`jax.distributed`, one CPU device each), as on two hosts."""
    from jax.experimental import multihost_utils

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"localhost:{port}", num_processes=2, process_id=pid)
    assert jax.device_count() == 2 and jax.local_device_count() == 1
    _, pgd, lrs = problem()
    ref = jax.block_until_ready(jax.jit(jax.vmap(pgd))(lrs))  # on this process's device
    CALLS.clear()
    res = jax.block_until_ready(dj.sweep(pgd)(lrs))
    calls = list(CALLS)
    res = multihost_utils.process_allgather(res, tiled=True)
    steps = np.asarray(ref.steps).max(axis=1).tolist()
    print(json.dumps(dict(diff=max_diff(res, ref), calls=calls, steps=steps)))


if __name__ == "__main__":
    if len(sys.argv) > 1:  # --process PID PORT
        process(int(sys.argv[2]), int(sys.argv[3]))
    else:
        main()
