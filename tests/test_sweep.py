"""`dj.sweep`: on one device it is `jax.jit(jax.vmap(fn))`; past one device, shard-local
projections and host threads per device.

The sweeps run in a subprocess (`sweep_checks.py`) with 2 forced host CPU devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=2`), float64 and a 2-thread pool; the
slow-marked test runs two `jax.distributed` processes, as on two hosts.
"""

import json
import os
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import dissipation_ok, index, through_solves, tree_allclose

import dissil_jax as dj
from dissil_jax.internal import sdp as _sdp

CHECKS = Path(__file__).with_name("sweep_checks.py")
# One worker runs every test here, so the subprocess behind `found` runs once per test run.
pytestmark = pytest.mark.xdist_group("sharding")
SHARDED = ("pgd", "recipe", "gd", "project")  # dj.sweep of PGD, the raw recipe, GD, project


def _env(devices: int) -> dict:
    """Float64, `devices` forced host devices, a 2-thread pool, the package under test."""
    root = str(Path(dj.__file__).resolve().parents[1])
    flags = os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}"
    return {**os.environ, "XLA_FLAGS": flags.strip(), "JAX_ENABLE_X64": "1",
            "JAX_PLATFORMS": "cpu", "OPENBLAS_NUM_THREADS": "1", "DISSIL_JAX_THREADS": "2",
            "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}


@pytest.fixture(scope="session")  # kept while the worker runs other modules in between
def found():
    proc = subprocess.run([sys.executable, str(CHECKS)], capture_output=True, text=True,
                          timeout=600, env=_env(devices=2))
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _calls(case):
    """{shard: [batch shapes of its callbacks, in order]}."""
    out = {}
    for shard, shape, _ in case["calls"]:
        out.setdefault(shard, []).append(tuple(shape))
    return out


def test_sharded_sweeps_equal_the_unsharded_sweep(found):
    for name in (*SHARDED, "uneven"):
        assert found[name]["diff"] <= 1e-12, (name, found[name]["diff"])


def test_sharded_sweep_output_spans_both_devices(found):
    for name in SHARDED:
        assert found[name]["devices"] == 2 and found[name]["sharded"], (name, found[name])


def test_no_gather_of_the_callback(found):
    # The check sees the defect: `jax.jit(jax.vmap(run), in_shardings=...)` alone puts the
    # callback on device 0, and XLA warns while gathering to it and scattering back.
    assert found["plain"]["remat"] > 0
    assert set(_calls(found["plain"])) == {0}
    for name in (*SHARDED, "uneven"):
        assert found[name]["remat"] == 0, (name, found[name]["remat"])


def test_each_shard_calls_back_with_its_local_batch(found):
    # 4 learning rates x 2 initialisations: the initial projection (2 inits, the same for
    # every rate) on each shard, then one callback per training step with the shard's
    # 2 rates x 2 inits, until the shard's own rates have stopped (shard 0's run all 15
    # steps, shard 1's stop earlier), and one after the last step, in which no lane is
    # active, so that it solves nothing (the driver loop's last `update`).
    steps = found["steps"]
    own = [max(steps[:2]), max(steps[2:])]
    assert own[0] == 15 > own[1], steps
    for name in ("pgd", "recipe"):
        calls = _calls(found[name])
        for shard in (0, 1):
            assert calls[shard] == [(2,)] + [(2, 2)] * (own[shard] + 1), (name, shard, calls)
            last = [c for c in found[name]["calls"] if c[0] == shard][-1]
            assert last[2] == 0, (name, shard, last)  # peak solves at once: none
    assert _calls(found["plain"])[0] == [(2,)] + [(4, 2)] * (max(steps) + 1)
    # 8 keys x 2 random draws (ICO's initialisations), 4 keys per shard.
    assert _calls(found["project"]) == {0: [(4, 2)], 1: [(4, 2)]}
    assert _calls(found["gd"]) == {}


def test_each_shard_uses_its_share_of_the_host_threads(found):
    share = found["workers"] // 2
    for name in ("pgd", "recipe", "project"):
        assert max(peak for *_, peak in found[name]["calls"]) <= share, found[name]["calls"]
    # one callback for the whole batch (unsharded) uses every worker
    assert max(peak for *_, peak in found["plain"]["calls"]) == found["workers"]
    assert found["peak_solves"] <= found["workers"]


@pytest.mark.parametrize("items", [1, 3])
def test_thread_map_gives_concurrent_callers_their_share(monkeypatch, items):
    """4 callers at once (`shards=4`) on a 2-worker pool: at most 2 solves at once in all,
    at most one per caller, also when a caller has a single item."""
    monkeypatch.setattr(_sdp, "_POOL", ThreadPoolExecutor(2))
    lock, active, peak = threading.Lock(), {"all": 0}, {"all": 0}

    def caller(i):
        def work(chunk):
            with lock:
                for k in ("all", i):
                    active[k] = active.get(k, 0) + 1
                    peak[k] = max(peak.get(k, 0), active[k])
            time.sleep(0.02)
            with lock:
                for k in ("all", i):
                    active[k] -= 1
            return chunk

        start.wait()
        results[i] = _sdp.thread_map(work, range(items), shards=4)

    start, results = threading.Barrier(4), {}
    threads = [threading.Thread(target=caller, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == {i: [list(range(items))] for i in range(4)}
    assert peak["all"] <= 2 and all(peak[i] == 1 for i in range(4)), peak


def test_thread_map_solves_on_its_own_thread_when_the_pool_refuses_work(monkeypatch):
    """A shut-down pool (as at interpreter exit) raises on `submit`; the solves then run on
    the caller's thread and give the pool's results."""
    closed = ThreadPoolExecutor(2)
    closed.shutdown()
    monkeypatch.setattr(_sdp, "_POOL", closed)
    for balance in (False, True):
        assert _sdp.thread_map(lambda chunk: [2 * i for i in chunk], range(5),
                               balance=balance) == (
            [[0], [2], [4], [6], [8]] if balance else [[0, 2, 4], [6, 8]])


_EXIT_EARLY = """
import jax, jax.numpy as jnp
import dissil_jax as dj
key = jax.random.PRNGKey(0)
y = jax.random.normal(key, (20, 3, 1))
windows = dj.Windows(x0=y[:, 0], y=y, u=-0.5 * y)
run = lambda lr: dj.pgd_run(key, windows, dj.QSR.passive(1), learning_rate=lr, num_inits=4,
                            max_steps=30, throw=False)
res = dj.sweep(run)(jnp.logspace(-2, 0.5, 4))  # the script ends before the sweep does
"""


def test_a_script_may_end_before_its_sweep():
    """JAX returns before a sweep's results are ready; a script ending right after it
    reaches the host callback during interpreter shutdown, when the solver pool refuses
    work. The sweep must still finish cleanly (no `pure_callback failed`)."""
    proc = subprocess.run([sys.executable, "-c", _EXIT_EARLY], capture_output=True, text=True,
                          timeout=600, env=_env(devices=2))
    assert proc.returncode == 0 and "callback" not in proc.stderr.lower(), proc.stderr[-4000:]


@pytest.mark.slow
def test_two_processes_each_solve_their_own_shard():
    """Two `jax.distributed` processes on this machine (one CPU device each), as on two
    hosts: each process's callback solves its own shard's projections only."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = _env(devices=1)
    procs = [subprocess.Popen([sys.executable, str(CHECKS), "--process", str(i), str(port)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for i in (0, 1)]
    outs = [p.communicate(timeout=600) for p in procs]
    for pid, (p, (out, err)) in enumerate(zip(procs, outs)):
        assert p.returncode == 0, err[-4000:]
        found = json.loads(out.strip().splitlines()[-1])
        assert found["diff"] <= 1e-12, found["diff"]
        assert {shard for shard, *_ in found["calls"]} == {pid}, found["calls"]
        own = max(found["steps"][2 * pid:2 * pid + 2])  # this process's learning rates
        # the initial projection, one per step, and the empty one after the last step
        assert [tuple(b) for _, b, _ in found["calls"]] == [(2,)] + [(2, 2)] * (own + 1)
        assert found["calls"][-1][2] == 0, found["calls"]


def test_sweep_on_one_device_and_its_argument_errors():
    """In the test process (one device) `dj.sweep` is `jax.jit(jax.vmap(fn))`."""
    def fn(x, y):
        return {"sum": x + y, "prod": x * y}

    x, y = jnp.arange(5.0), jnp.linspace(0.0, 1.0, 5)
    assert tree_allclose(dj.sweep(fn)(x, y), jax.jit(jax.vmap(fn))(x, y), rtol=0, atol=0)
    with pytest.raises(ValueError, match="same leading"):
        dj.sweep(fn)(x, y[:4])
    with pytest.raises(ValueError, match="same leading"):
        dj.sweep(fn)(x, jnp.float64(1.0))
    with pytest.raises(ValueError, match="`mesh`"):
        dj.sweep(fn, mesh="sweep")
    with pytest.raises(ValueError, match="by position only.*'y'"):
        dj.sweep(fn)(x, y=y)
    with pytest.raises(ValueError, match="list or tuple of scalars.*jnp.asarray"):
        dj.sweep(fn)([0.1, 0.3], y[:2])
    with pytest.raises(ValueError, match="at least one swept"):
        dj.sweep(lambda: 1.0)()


@pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)
def test_sweep_of_projections_equals_a_plain_loop(getkey):
    """The host-callback path on one device: each lane of a swept `dj.project` is the
    projection of that target alone, and is certified by the independent check."""
    qsr = dj.QSR.passive(2)
    Ks = jax.vmap(lambda k: dj.LTIController.random(k, 2, 2, 2, scale=1.0))(jr.split(getkey(), 3))
    out = dj.sweep(lambda K: dj.project(K, qsr))(Ks)
    for i in range(3):
        ref = dj.project(index(Ks, i), qsr)
        # One Clarabel solve each, of the same problem assembled alone or in a batch: they
        # agree to the solver's tolerance, not to round-off.
        tol = through_solves(1)
        assert tree_allclose(index(out.controller, i), ref.controller, rtol=tol, atol=tol)
        assert dissipation_ok(index(out.controller, i), qsr, np.asarray(out.P[i]))


def test_sweep_over_a_mesh_of_two_axes(getkey):
    """A mesh with several axes splits the sweep over their product; with one device it is
    still the vmapped function, with the swept axis of any length."""
    mesh = jax.make_mesh((1, 1), ("a", "b"))
    K = dj.LTIController.random(getkey(), 2, 1, 1, scale=0.5)
    windows = dj.Windows(None, jr.normal(getkey(), (4, 3, 1)), jr.normal(getkey(), (4, 3, 1)))
    scales = jnp.array([0.5, 1.0, 2.0])
    losses = dj.sweep(lambda c: dj.imitation_loss(jax.tree.map(lambda a: c * a, K), windows),
                      mesh=mesh)(scales)
    loop = [dj.imitation_loss(jax.tree.map(lambda a: float(c) * a, K), windows) for c in scales]
    np.testing.assert_allclose(losses, loop, rtol=1e-12)
