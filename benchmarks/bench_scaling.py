"""Cost against controller order: every training path and the certificate, n̂ from 2 to 64.

For each output/input size m = p and each order n̂ it measures, in one process:

- `project`: one `dj.project(K, qsr, refine=1)` of a random N(0, 1) controller (setup of
  the LMI and the solver included, a fresh size each time), its peak memory growth, and
  the LMI's own size: dimension N = 2n̂ + p + rank Q and nonzeros;
- `certify`: `dj.certify` of that projected controller with the projection cache cleared
  (the Riccati storage) and the maximum-margin SDP (`max_margin=True`);
- one PGD step (8 initialisations): its host half, the 8 iterates projected at their own
  `P` in one batched `jax.jit(jax.vmap(dj.project))` call (compiled before timing; the
  gradients are microseconds beside it);
- one PGD step with `fit_pgd`'s defaults (`pgd_default`, 8 initialisations): projected
  Adam, whose projections `method="auto"` gives to the first-order path from n̂ = 12 on,
  warm-started across steps; `max_steps=6` minus `max_steps=2` (both compiled first),
  divided by the extra steps taken;
- one ICO iteration (one initialisation): the median time between `dj.fit_ico`'s
  per-iteration callbacks (setup excluded);
- one direct step (8 initialisations): `dj.fit_direct` with `max_steps=10 + k` minus `10`
  (both compiled first), divided by the extra steps taken; `k` (50 to 1,000) makes the
  difference last about 20 s, from a first estimate with 30 against 10 steps.

Windows: 100 two-step windows of a random stable order-n̂ expert; supply rate `QSR.passive(m)`.
A path whose next cell, extrapolated from its previous two by a power law, would exceed
`--budget` seconds skips it and the larger sizes; skipped cells are listed. At the end, power-law
exponents t ~ n̂^k fitted on n̂ >= 8 (least squares in log-log), beside the exponents of N
and of the nonzeros.

Usage: python benchmarks/bench_scaling.py [--quick] [--budget SECONDS] [--sizes 2 4 ...]
       [--io 1 2 4] [--paths project certify pgd pgd_default ico direct]
"""

import argparse
import os
import resource
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import (  # noqa: E402
    ConvexifiedLMI,  # noqa: E402
    certify_fast as _certify_fast,
    projection as _projection,
    projection_cache as _projection_cache,
)

PATHS = ("project", "certify", "certify_sdp", "pgd", "pgd_default", "ico", "direct")
ICO_MAX_N = 24  # ICO's documented range (`--ico-max-n` measures beyond it)


def _windows(n, m, N=100, seed=0):
    """Two-step windows of a random stable order-n expert (not dissipative in general)."""
    rng = np.random.default_rng(seed)
    A = 0.5 * rng.normal(size=(n, n)) / np.sqrt(n)
    B, C, D = rng.normal(size=(n, m)), rng.normal(size=(m, n)), rng.normal(size=(m, m))
    x0, y = rng.normal(size=(N, n)), rng.normal(size=(N, 2, m))
    t0 = x0 @ C.T + y[:, 0] @ D.T
    t1 = (x0 @ A.T + y[:, 0] @ B.T) @ C.T + y[:, 1] @ D.T
    return dj.Windows(x0, y, -np.stack([t0, t1], 1))


def _rss_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    jax.block_until_ready(jax.tree.leaves(out))
    return time.perf_counter() - t, out


def _steps(res):
    """Steps the longest run took (finite entries of its loss history, minus the start)."""
    hist = np.asarray(res.loss_history)
    return int(np.max(np.sum(np.isfinite(hist), axis=-1))) - 1


def _per_step(fit, lo, hi):
    """Time per step of a trainer: (t(hi) - t(lo)) / (steps(hi) - steps(lo)), both compiled
    beforehand, so that setup cancels; runs that stop early count only the steps taken."""
    fit(lo), fit(hi)  # compile both
    t_lo, r_lo = _timed(lambda: fit(lo))
    t_hi, r_hi = _timed(lambda: fit(hi))
    d = _steps(r_hi) - _steps(r_lo)
    if d <= 0:
        return None, t_hi, r_hi
    return max(t_hi - t_lo, 0.0) / d, t_hi, r_hi


def cell(path, n, m, qsr, state):
    """One measurement; returns (seconds, note). `state` carries the projected controller."""
    key = jax.random.PRNGKey(n * 10 + m)
    if path == "project":
        K = dj.LTIController.random(key, n, m, m, scale=1.0)
        dj.project(K, qsr, refine=1, throw=False, active=False, method="clarabel")  # trace: not timed
        rss0, stats = _rss_mib(), _projection.solver_stats()
        s0, c0 = stats["solve_time"], stats["solves"]
        t, proj = _timed(lambda: dj.project(K, qsr, refine=1, throw=False, method="clarabel"))
        solve = stats["solve_time"] - s0
        state["K"], state["P"] = proj[0], proj[1]
        ok = bool(dj.certify(proj[0], qsr, P=proj[1]).holds)
        return t, (f"certified={ok} Clarabel {solve:.3f} s in {stats['solves'] - c0} solve(s), "
                   f"peak RSS +{_rss_mib() - rss0:.0f} MiB")
    if path in ("certify", "certify_sdp"):
        if "K" not in state:
            return None, "no projected controller"
        _certify_fast._CACHE.clear()  # no cached storage: the Riccati path or the SDP
        t, cert = _timed(lambda: dj.certify(state["K"], qsr, max_margin=path == "certify_sdp"))
        return t, f"holds={cert.holds} status={cert.status}"
    w = _windows(n, m)
    if path == "pgd":
        # the host half of one PGD step: the batch of 8 iterates projected at their own P
        # (`fit_pgd`'s callback; its gradients are microseconds next to it)
        keys = jax.random.split(key, 8)
        K0 = jax.vmap(lambda k: dj.LTIController.random(k, n, m, m, scale=1.0))(keys)
        K0, P0 = dj.project(K0, qsr, refine=1, method="clarabel")
        noise = jax.vmap(lambda k: dj.LTIController.random(k, n, m, m, scale=0.2))(
            jax.random.split(jax.random.PRNGKey(1), 8))
        target = jax.tree.map(lambda a, b: a + b, K0, noise)
        proj = jax.jit(jax.vmap(lambda K, P: dj.project(K, qsr, P, throw=False, method="clarabel")))
        jax.block_until_ready(proj(target, P0))  # compile and build the solvers
        t, out = _timed(lambda: proj(target, P0))
        ok = bool(np.all(np.asarray(dj.certify(out[0], qsr, P=out[1]).holds)))
        return t, f"8 projections at P_ref, certified={ok}"
    if path == "pgd_default":
        fit = lambda s: dj.fit_pgd(key, w, qsr, max_steps=s, atol=0.0, rtol=0.0, throw=False)
        t, total, res = _per_step(fit, 2, 6)
        if t is None:
            return None, f"no steps taken ({res.result_names()[0]})"
        return t, (f"certified={bool(np.all(np.asarray(res.certified)))} run {total:.1f} s, "
                   f"{_steps(res)} steps")
    if path == "ico":
        if n > ICO_MAX_N:
            return None, f"ICO beyond n̂ = {ICO_MAX_N} not measured"
        stamps = []
        res = dj.fit_ico(key, w, qsr, num_inits=1, max_steps=4, atol=0.0, rtol=0.0, throw=False,
                         callback=lambda *a: stamps.append(time.perf_counter()))
        if len(stamps) < 2:
            return None, f"no steps taken ({res.result_names()[0]})"
        t = float(np.median(np.diff(stamps)))  # per SDP iteration, setup excluded
        return t, (f"certified={bool(np.all(np.asarray(res.certified)))} "
                   f"{len(stamps) - 1} iterations")
    fit = lambda s: dj.fit_direct(key, w, qsr, max_steps=s, atol=0.0, rtol=0.0, throw=False)
    # a first estimate from 10 against 30 steps sizes the measured difference to about
    # 20 s (between 50 and 1,000 extra steps): 1,000 steps at n = 48 took minutes
    guess, _, _ = _per_step(fit, 10, 30)
    extra = 1000 if not guess else int(np.clip(20.0 / guess, 50, 1000))
    t, total, res = _per_step(fit, 10, 10 + extra)
    if t is None:
        return None, f"no steps taken ({res.result_names()[0]})"
    return t, (f"certified={bool(np.all(np.asarray(res.certified)))} run {total:.1f} s, "
               f"{_steps(res)} steps")


def _predicted(done, n):
    """The next cell's time extrapolated from the last two (power law), 0 if unknown."""
    if len(done) < 2 or done[-1][1] <= 0 or done[-2][1] <= 0:
        return 0.0
    (n1, t1), (n2, t2) = done[-2], done[-1]
    k = max(np.log(t2 / t1) / np.log(n2 / n1), 0.0)
    return t2 * (n / n2) ** k


def fit_exponent(ns, ts):
    ns, ts = np.asarray(ns, float), np.asarray(ts, float)
    keep = (ns >= 8) & (ts > 0)
    if keep.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(ns[keep]), np.log(ts[keep]), 1)[0])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="n̂ in 2..16, m = p = 2, budget 20 s")
    ap.add_argument("--budget", type=float, default=240.0, help="seconds per cell")
    ap.add_argument("--sizes", type=int, nargs="*", default=[2, 4, 8, 16, 24, 32, 48, 64])
    ap.add_argument("--io", type=int, nargs="*", default=[1, 2, 4])
    ap.add_argument("--paths", nargs="*", default=list(PATHS), choices=PATHS)
    ap.add_argument("--ico-max-n", type=int, default=ICO_MAX_N,
                    help="largest order of the ICO cells (default: ICO's documented range)")
    args = ap.parse_args()
    globals()["ICO_MAX_N"] = args.ico_max_n
    if args.quick:
        args.sizes, args.io, args.budget = [2, 4, 8, 16], [2], min(args.budget, 20.0)
    print(f"# sizes {args.sizes}, m = p in {args.io}, budget {args.budget:.0f} s per cell")
    results, skipped = {}, []
    for m in args.io:
        qsr = dj.QSR.passive(m)
        stopped = set()
        for n in args.sizes:
            lmi = ConvexifiedLMI(n, m, m, qsr)
            print(f"\n## n̂={n}, m=p={m}: LMI N={lmi.N}, svec {lmi.L}, variables {lmi.nx}, "
                  f"nonzeros {lmi.nnz}", flush=True)
            results.setdefault(m, {}).setdefault("nnz", []).append((n, lmi.nnz))
            results[m].setdefault("N", []).append((n, lmi.N))
            state = {}
            for path in args.paths:
                if path in stopped or _predicted(results[m].get(path, []), n) > args.budget:
                    skipped.append((path, n, m))
                    stopped.add(path)
                    continue
                _projection_cache._LOCAL.__dict__.clear()  # solvers of other sizes: not kept
                t, note = cell(path, n, m, qsr, state)
                if t is None:
                    print(f"  {path:12s}   skipped ({note})")
                    continue
                print(f"  {path:12s} {t * 1e3:10.2f} ms  {note}", flush=True)
                results[m].setdefault(path, []).append((n, t))
    print("\n## skipped (predicted from the previous two cells to exceed the budget):",
          ", ".join(f"{p} n̂={n} m={m}" for p, n, m in skipped) or "none")
    print("\n## power-law exponents k of t ~ n̂^k (fitted on n̂ >= 8)")
    print("| m = p | " + " | ".join(["N", "nonzeros", *args.paths]) + " |")
    print("| --- |" + " ---: |" * (2 + len(args.paths)))
    for m, res in results.items():
        ks = [fit_exponent(*zip(*res[k])) if len(res.get(k, [])) else float("nan")
              for k in ["N", "nnz", *args.paths]]
        print(f"| {m} | " + " | ".join(f"{k:.2f}" for k in ks) + " |")


if __name__ == "__main__":
    main()
