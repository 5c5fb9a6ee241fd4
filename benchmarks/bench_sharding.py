"""Sweep throughput on 1 against 2 forced host devices, measured in one run.

A learning-rate sweep of `dj.pgd_run` (n̂ = 6, m = p = 3, passive supply rate, `atol=0`)
runs with `dj.sweep` in subprocesses with
`XLA_FLAGS=--xla_force_host_platform_device_count=1` and with `...=2`, alternated for 3
rounds (the fastest run of each form is kept). On 2 devices the gathering form
`jax.jit(jax.vmap(run), in_shardings=...)` (the defect) runs too. Prints per form: wall
time, lane-steps and projections (SDP solves) per second, Clarabel's own
time per solve, the throughput model `cores / solve time` (one host), the number of host
callbacks and their batch sizes per shard, and the ratios of the 2-device runs to the
1-device run.

Usage: python benchmarks/bench_sharding.py [--quick]
"""

import argparse
import json
import os
import subprocess
import sys
import time


def child(quick: bool):
    import jax
    import jax.numpy as jnp
    from jax.sharding import AxisType, NamedSharding, PartitionSpec as P

    import dissil_jax as dj
    from dissil_jax.experiments import realisable_windows
    from dissil_jax.internal import projection as _projection, sdp as _sdp

    qsr = dj.QSR.passive(3)
    windows, _ = realisable_windows(jax.random.PRNGKey(0), qsr, n_state=6, num_windows=25,
                                    noise=0.1)
    lanes, inits, steps, reps = (4, 2, 10, 1) if quick else (8, 4, 30, 2)
    lrs = jnp.logspace(-1.0, 0.5, lanes)

    def run(lr):
        return dj.pgd_run(jax.random.PRNGKey(1), windows, qsr, learning_rate=lr,
                          num_inits=inits, max_steps=steps, atol=0.0, rtol=0.0, throw=False)

    forms = {"sweep": dj.sweep(run)}
    if jax.device_count() > 1:
        mesh = jax.make_mesh((jax.device_count(),), ("sweep",), axis_types=(AxisType.Auto,))
        forms["gather"] = jax.jit(jax.vmap(run), in_shardings=NamedSharding(mesh, P("sweep")))
    stats, out = _projection.solver_stats(), []
    for name, f in forms.items():
        jax.block_until_ready(f(lrs))  # compile, build the solvers
        best = None
        for _ in range(reps):
            s0, t0, c0 = stats["solves"], stats["solve_time"], stats["callbacks"].copy()
            start = time.perf_counter()
            res = jax.block_until_ready(f(lrs))
            wall = time.perf_counter() - start
            if best is None or wall < best["wall"]:
                calls = stats["callbacks"] - c0
                best = dict(form=name, wall=wall, solves=stats["solves"] - s0,
                            solve_time=stats["solve_time"] - t0,
                            lane_steps=int(res.steps.sum()),
                            calls=sorted([s, b, n] for (s, b), n in calls.items()))
        out.append(dict(best, devices=jax.device_count(), cores=os.cpu_count(),
                        workers=_sdp.num_workers()))
    print(json.dumps(out))


def _spawn(devices: int, quick: bool):
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}",
           "JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu", "OPENBLAS_NUM_THREADS": "1"}
    cmd = [sys.executable, __file__, "--child"] + (["--quick"] if quick else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if proc.returncode:
        sys.exit(proc.stderr[-4000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _per_shard(calls):
    """'shard s: n calls of batch b, ...' from [shard, batch, count] rows."""
    shards = {}
    for s, b, n in calls:
        shards.setdefault(s, []).append(f"{n}×{b}")
    return "; ".join(f"shard {s}: {', '.join(v)}" for s, v in sorted(shards.items()))


def main(quick: bool):
    # The machine is shared and noisy: alternate the 1- and 2-device processes for a few
    # rounds and keep each form's fastest run.
    best = {}
    for _ in range(1 if quick else 3):
        for devices in (1, 2):
            for r in _spawn(devices, quick):
                key = (r["devices"], r["form"])
                if key not in best or r["wall"] < best[key]["wall"]:
                    best[key] = r
    rows = list(best.values())
    base = rows[0]
    print(f"{base['cores']} cores, pool of {base['workers']} threads per process; "
          f"{base['lane_steps']} lane-steps per sweep (learning rates x inits x steps)")
    print(f"{'devices':>7s} {'form':>7s} {'wall s':>7s} {'lane-steps/s':>13s} "
          f"{'solves/s':>9s} {'ms/solve':>9s} {'model/s':>8s} {'meas/model':>11s} "
          f"{'speed-up':>9s}  callbacks (count × batch size, per shard)")
    for r in rows:
        t_solve = r["solve_time"] / max(r["solves"], 1)
        model = r["workers"] / t_solve  # one host: cores / solve time
        print(f"{r['devices']:7d} {r['form']:>7s} {r['wall']:7.2f} "
              f"{r['lane_steps'] / r['wall']:13.1f} {r['solves'] / r['wall']:9.1f} "
              f"{1e3 * t_solve:9.2f} {model:8.1f} {r['solves'] / r['wall'] / model:11.2f} "
              f"{base['wall'] / r['wall']:9.2f}  {_per_shard(r['calls'])}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    child(args.quick) if args.child else main(args.quick)
