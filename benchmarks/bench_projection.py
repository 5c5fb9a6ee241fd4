"""Projection and PGD speed against cvxpy references, measured in one run.

Prints, per problem size:
- the batched projection's wall time per controller (jit + vmap, host thread pool),
- Clarabel's own reported solve time per controller (the floor),
- a reference that builds the same problem in cvxpy on every call;
and the PGD throughput (initialisations x steps per second) next to a sequential loop
that projects with a DPP-parametrised cvxpy problem. Ratios are what to read: the machine
is shared and noisy.

Usage: python benchmarks/bench_projection.py [--quick]
"""

import argparse
import concurrent.futures
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import projection as _projection  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _reference import cvxpy_projection_problem, solve_reference  # noqa: E402

CASES = [
    ("n=1, nonlinear-example QSR", dj.QSR(-29.867, 3.556, 0.601), 1),
    ("n=6, m=p=3, passive", dj.QSR.passive(3), 6),
]


def _targets(qsr, n, batch, seed=0):
    """Certified controllers with their P, and perturbed copies as projection targets."""
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    K = jax.vmap(lambda k: dj.LTIController.random(k, n, qsr.n_in, qsr.n_out, scale=0.5))(keys)
    K, P = dj.project(K, qsr)
    noise = jax.vmap(lambda k: dj.LTIController.random(k, n, qsr.n_in, qsr.n_out, scale=0.2))(
        jax.random.split(jax.random.PRNGKey(seed + 1), batch))
    return jax.tree.map(jnp.add, K, noise), P


def bench_projection(qsr, n, batch, ref_calls):
    target, P = _targets(qsr, n, batch)
    proj = jax.jit(jax.vmap(lambda K, P: dj.project(K, qsr, P)))
    jax.block_until_ready(proj(target, P))  # compile + build solvers
    reps = 3
    stats = _projection.solver_stats()
    t0, s0, c0 = time.perf_counter(), stats["solve_time"], stats["solves"]
    for _ in range(reps):
        jax.block_until_ready(proj(target, P))
    wall = (time.perf_counter() - t0) / (reps * batch)
    solves = stats["solves"] - c0
    own = (stats["solve_time"] - s0) / max(solves, 1)
    prob, params, variables = cvxpy_projection_problem(qsr, n)
    # "built per call": a fresh cvxpy problem (canonicalisation included) for each target
    t0 = time.perf_counter()
    for i in range(ref_calls):
        prob, params, variables = cvxpy_projection_problem(qsr, n)
        Ki = [np.asarray(M[i]) for M in (target.A, target.B, target.C, target.D)]
        solve_reference(prob, params, variables, Ki, np.asarray(P[i]))
    ref = (time.perf_counter() - t0) / ref_calls
    return wall, own, ref, solves / (reps * batch)


def bench_overhead(qsr, n, batch, reps):
    """Wall time of a batched projection without `P_ref` (`refine=1`: one solve per
    target) over Clarabel's own solve time, per controller: the host layer's overhead.
    Reported for the default pool and for one thread (no overlap of solves)."""
    keys = jax.random.split(jax.random.PRNGKey(7), batch)
    K = jax.vmap(lambda k: dj.LTIController.random(k, n, qsr.n_in, qsr.n_out, scale=1.0))(keys)
    proj = jax.jit(jax.vmap(lambda K: dj.project(K, qsr, refine=1)))
    jax.block_until_ready(proj(K))
    stats = _projection.solver_stats()
    t0, s0, c0 = time.perf_counter(), stats["solve_time"], stats["solves"]
    for _ in range(reps):
        jax.block_until_ready(proj(K))
    wall = (time.perf_counter() - t0) / (reps * batch)
    own = (stats["solve_time"] - s0) / (stats["solves"] - c0)
    return wall, own


def bench_pgd(qsr, n, num_inits, steps, ref_inits, ref_steps):
    key = jax.random.PRNGKey(3)
    kx, ky = jax.random.split(key)
    N, h = 25, 2
    w = dj.Windows(jax.random.normal(kx, (N, n)), jax.random.normal(ky, (N, h, qsr.n_in)),
                   -0.2 * jax.random.normal(ky, (N, h, qsr.n_out)))
    kw = dict(max_steps=steps, atol=0.0, rtol=0.0, learning_rate=1e-2)
    dj.fit_pgd(key, w, qsr, num_inits=num_inits, **kw)  # compile
    t0 = time.perf_counter()
    dj.fit_pgd(key, w, qsr, num_inits=num_inits, **kw)
    ours = num_inits * steps / (time.perf_counter() - t0)
    # Sequential reference: jitted gradient, cvxpy (DPP, compiled once) projection per step.
    grad = jax.jit(jax.grad(dj.imitation_loss))
    prob, params, variables = cvxpy_projection_problem(qsr, n)
    K0, P0 = _targets(qsr, n, ref_inits)
    t0 = time.perf_counter()
    for i in range(ref_inits):
        K, P = jax.tree.map(lambda a: a[i], K0), np.asarray(P0[i])
        for s in range(ref_steps):
            g = grad(K, w)
            K = jax.tree.map(lambda a, b: a - 1e-2 * 0.99**s * b, K, g)
            A, B, C, D, P = solve_reference(prob, params, variables,
                                            [np.asarray(M) for M in (K.A, K.B, K.C, K.D)], P)
            K = dj.LTIController(A, B, C, D)
    ref = ref_inits * ref_steps / (time.perf_counter() - t0)
    return ours, ref


def main(quick=False):
    batch, ref_calls = (16, 5) if quick else (64, 20)
    print(f"jax {jax.__version__}, {os.cpu_count()} cores, batch {batch}")
    print("\nProjection (per controller, warm P_ref, perturbed certified targets)")
    print(f"{'case':30s} {'ours ms':>9s} {'clarabel ms':>12s} {'cvxpy/call ms':>14s} "
          f"{'ours/clarabel':>14s} {'cvxpy/ours':>11s} {'solves/ctrl':>12s}")
    for name, qsr, n in CASES:
        wall, own, ref, spc = bench_projection(qsr, n, batch, ref_calls)
        print(f"{name:30s} {1e3 * wall:9.3f} {1e3 * own:12.3f} {1e3 * ref:14.2f} "
              f"{wall / own:14.2f} {ref / wall:11.1f} {spc:12.2f}")
    print("\nHost-layer overhead: jit(vmap(project(K, qsr, refine=1))), 32 random controllers")
    print(f"{'case':30s} {'threads':>8s} {'ours ms':>9s} {'clarabel ms':>12s} "
          f"{'ours/clarabel':>14s}")
    from dissil_jax.internal import sdp as _threads

    for name, qsr, n in CASES:
        for threads in (None, 1):
            saved = _threads._POOL
            if threads:
                _threads._POOL = concurrent.futures.ThreadPoolExecutor(threads)
            wall, own = bench_overhead(qsr, n, 32, 5 if quick else 20)
            _threads._POOL = saved
            label = str(threads or _threads.num_workers())
            print(f"{name:30s} {label:>8s} {1e3 * wall:9.3f} {1e3 * own:12.3f} "
                  f"{wall / own:14.2f}")
    print("\nPGD throughput (initialisations x steps per second)")
    print(f"{'case':30s} {'ours':>10s} {'sequential cvxpy':>17s} {'ratio':>8s}")
    for name, qsr, n in CASES:
        inits, steps = (8, 20) if quick else (32, 50)
        ours, ref = bench_pgd(qsr, n, inits, steps, 2, 5 if quick else 15)
        print(f"{name:30s} {ours:10.1f} {ref:17.1f} {ours / ref:8.1f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    main(parser.parse_args().quick)
