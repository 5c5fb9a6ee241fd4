"""Cost against controller order: every training path and the certificate, n̂ from 2 to 64.

For each output/input size m = p and each order n̂ it measures, in one process:

- `project`: one `dj.project(K, qsr, refine=1)` of a random N(0, 1) controller (setup of
  the LMI and the solver included, a fresh size each time), its peak memory growth, and
  the LMI's own size: dimension N = 2n̂ + p + rank Q and nonzeros;
- `certify`: `dj.certify` of that projected controller with the projection cache cleared
  (the Riccati storage) and the maximum-margin SDP (`max_margin=True`);
- one PGD step (8 initialisations): `dj.fit_pgd` with `max_steps=3` minus `max_steps=1`,
  halved (compilation cancels);
- one ICO iteration (one initialisation): `dj.fit_ico` with `max_steps=3` minus `1`, halved;
- one direct step (8 initialisations): `dj.fit_direct` with `max_steps=40` minus `20`,
  divided by 20.

Windows: 100 random two-step windows of a passive supply rate (`QSR.passive(m)`).
A path whose cell took longer than a quarter of `--budget` seconds skips the larger sizes
(the next cell would exceed the budget); skipped cells are listed. At the end, power-law
exponents t ~ n̂^k fitted on n̂ >= 8 (least squares in log-log), beside the exponents of N
and of the nonzeros.

Usage: python benchmarks/bench_scaling.py [--quick] [--budget SECONDS] [--sizes 2 4 ...]
       [--io 1 2 4] [--paths project certify pgd ico direct]
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
from dissil_jax import _certify_fast, _projection  # noqa: E402
from dissil_jax._lmi import ConvexifiedLMI  # noqa: E402

PATHS = ("project", "certify", "certify_sdp", "pgd", "ico", "direct")
ICO_MAX_N = 24  # ICO's documented range


def _windows(n, m, N=100, seed=0):
    rng = np.random.default_rng(seed)
    x0, y = rng.normal(size=(N, n)), rng.normal(size=(N, 2, m))
    return dj.Windows(x0, y, -0.5 * y)


def _rss_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    jax.block_until_ready(jax.tree.leaves(out))
    return time.perf_counter() - t, out


def _per_step(fit, lo, hi):
    """Time per step of a trainer: (t(hi) - t(lo)) / (hi - lo); compilation cancels."""
    t_lo, _ = _timed(lambda: fit(lo))
    t_hi, res = _timed(lambda: fit(hi))
    return max(t_hi - t_lo, 0.0) / (hi - lo), t_hi, res


def cell(path, n, m, qsr, state):
    """One measurement; returns (seconds, note). `state` carries the projected controller."""
    key = jax.random.PRNGKey(n * 10 + m)
    if path == "project":
        K = dj.LTIController.random(n, m, m, scale=1.0, key=key)
        rss0 = _rss_mib()
        t, proj = _timed(lambda: dj.project(K, qsr, refine=1, throw=False))
        state["K"], state["P"] = proj[0], proj[1]
        ok = bool(dj.certify(proj[0], qsr, P=proj[1]).holds)
        return t, f"certified={ok} peak RSS +{_rss_mib() - rss0:.0f} MiB"
    if path in ("certify", "certify_sdp"):
        if "K" not in state:
            return None, "no projected controller"
        _certify_fast._CACHE.clear()  # no cached storage: the Riccati path or the SDP
        t, cert = _timed(lambda: dj.certify(state["K"], qsr, max_margin=path == "certify_sdp"))
        return t, f"holds={cert.holds} status={cert.status}"
    w = _windows(n, m)
    if path == "pgd":
        fit = lambda s: dj.fit_pgd(key, w, qsr, max_steps=s, tol=0.0, throw=False)
        t, total, res = _per_step(fit, 1, 3)
    elif path == "ico":
        if n > ICO_MAX_N:
            return None, f"ICO beyond n̂ = {ICO_MAX_N} not measured"
        fit = lambda s: dj.fit_ico(key, w, qsr, num_inits=1, max_steps=s, tol=0.0, throw=False)
        t, total, res = _per_step(fit, 1, 3)
    else:
        fit = lambda s: dj.fit_direct(key, w, qsr, max_steps=s, tol=0.0, throw=False)
        t, total, res = _per_step(fit, 20, 40)
    return t, f"certified={bool(np.all(np.asarray(res.certified)))} run {total:.1f} s"


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
    args = ap.parse_args()
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
                if path in stopped:
                    skipped.append((path, n, m))
                    continue
                _projection._LOCAL.__dict__.clear()  # solvers of other sizes: not kept
                t, note = cell(path, n, m, qsr, state)
                if t is None:
                    print(f"  {path:12s}   skipped ({note})")
                    continue
                print(f"  {path:12s} {t:9.3f} s  {note}", flush=True)
                results[m].setdefault(path, []).append((n, t))
                if t > args.budget / 4:
                    stopped.add(path)
    print("\n## skipped (previous cell > budget / 4):",
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
