"""One projection and one certificate at a large order, with the process's peak memory.

Runs in a fresh child process (so that the peak resident set size, `ru_maxrss`, belongs to
this work alone): `dj.project(K, qsr)` with its defaults (three re-linearisation rounds)
of a random N(0, 1) controller, the exact check of the result, then `dj.certify` of the
result twice: with the projection's cache (its own storage) and with the cache cleared
(the Riccati storage). Prints the times, the outcome and the peak RSS.

Usage: python benchmarks/bench_order48.py [--n 48] [--m 2]
"""

import argparse
import os
import subprocess
import sys

CHILD = r"""
import resource, sys, time
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
from dissil_jax.internal import certify_fast as _certify_fast, projection as _projection
n, m = int(sys.argv[1]), int(sys.argv[2])
qsr = dj.QSR.passive(m)
K = dj.LTIController.random(jax.random.PRNGKey(n), n, m, m, scale=1.0)
t = time.perf_counter()
proj = dj.project(K, qsr, throw=False, method="clarabel")
jax.block_until_ready(proj[1])
t_proj = time.perf_counter() - t
Kp, P = proj
ok = dj.certify(Kp, qsr, P=P).holds
print(f"project n={n} m=p={m}: {t_proj:.1f} s ({_projection.solver_stats()['solves']} solves, "
      f"Clarabel {_projection.solver_stats()['solve_time']:.1f} s), result {proj.result}, "
      f"exact check {ok}", flush=True)
for label in ("cached", "cleared"):
    if label == "cleared":
        _certify_fast._CACHE.clear()
    t = time.perf_counter()
    cert = dj.certify(Kp, qsr)
    print(f"certify ({label} cache): {time.perf_counter() - t:.3f} s, holds {cert.holds}, "
          f"status {cert.status}, margin {cert.margin:.3g}", flush=True)
print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
"""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=48)
    ap.add_argument("--m", type=int, default=2)
    args = ap.parse_args()
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    subprocess.run([sys.executable, "-c", CHILD, str(args.n), str(args.m)], env=env, check=True)


if __name__ == "__main__":
    main()
