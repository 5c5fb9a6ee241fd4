"""The paper's sizes against a reference checkout of dissil_jax, in one run.

Each measurement runs in a child process whose `PYTHONPATH` selects the library: this
checkout ("ours") or `--ref` (e.g. `git worktree add /tmp/ref <commit>`). Children
alternate, `--repeats` times each, and the medians are compared as ratios ref / ours
(above 1: ours is faster). Measured:

- `proj_ref`: wall time per controller of `jax.jit(jax.vmap(dj.project))` with `P_ref`
  (the PGD situation) on 64 certified controllers perturbed by N(0, 0.2^2);
- `proj_new`: one `dj.project(K, qsr)` of a random N(0, 1) controller (no `P_ref`, three
  re-linearisation rounds), solvers already built;
- `pgd`: `dj.fit_pgd` throughput, initialisations x steps per second (8 x 30 steps,
  `atol=0`, the second of two identical calls so compilation is excluded).

Cases: n̂ = 1 with the nonlinear example's supply rate, n̂ = 6 with m = p = 3 passive.

`--order10` instead runs `dj.fit_pgd` with its defaults (8 initialisations, 30 steps) at
n̂ = 10, m = p = 2, passive, on 100 random windows of length 10 (the report of issue 23),
once per library, and prints how each run stopped and its loss.

`--compile` instead times each trainer's one-off compilation at the paper's sizes (n̂ = 6,
m = p = 3, passive, 100 windows of length 2, 8 initialisations, 150 steps): `direct_run`
and `pgd_run` (the paper's rule) lowered and compiled under `jax.jit`; `fit_ren` (width 4),
`fit_mlp` and `fit_gd` as their first call minus their second (compilation plus one-off
setup); and `dj.project(..., method="first_order")` of 4 controllers of order 12 (m = p =
2, passive, no `P_ref`: three re-linearisation rounds) compiled. Each child starts with an empty in-memory cache and no persistent one.

`--step-at N` instead times the host half of one PGD step at order N (m = p = 2, passive):
8 certified iterates perturbed by N(0, 0.2^2) projected at their own P in one batched
`jax.jit(jax.vmap(dj.project))` call (compiled and solvers built before timing), and the
setup (first call), alternating ours and ref `--repeats` times.

Usage: python benchmarks/bench_paper_sizes.py --ref /tmp/ref [--repeats 3] [--order10]
       [--step-at 24] [--compile]
"""

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, sys, time
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
cases = [("n1", dj.QSR(-29.867, 3.556, 0.601), 1), ("n6", dj.QSR.passive(3), 6)]
out = {"lib": dj.__file__}
for name, qsr, n in cases:
    m = qsr.n_in
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    K = jax.vmap(lambda k: dj.LTIController.random(k, n, m, m, scale=0.5))(keys)
    K, P = dj.project(K, qsr)
    noise = jax.vmap(lambda k: dj.LTIController.random(k, n, m, m, scale=0.2))(
        jax.random.split(jax.random.PRNGKey(1), 64))
    target = jax.tree.map(jnp.add, K, noise)
    proj = jax.jit(jax.vmap(lambda K, P: dj.project(K, qsr, P)))
    jax.block_until_ready(proj(target, P))
    t = time.perf_counter()
    for _ in range(3):
        jax.block_until_ready(proj(target, P))
    out[name + " proj_ref"] = (time.perf_counter() - t) / (3 * 64)
    Kr = [dj.LTIController.random(k, n, m, m, scale=1.0) for k in jax.random.split(
        jax.random.PRNGKey(2), 9)]
    jax.block_until_ready(dj.project(Kr[0], qsr)[1])
    t = time.perf_counter()
    for Ki in Kr[1:]:
        jax.block_until_ready(dj.project(Ki, qsr)[1])
    out[name + " proj_new"] = (time.perf_counter() - t) / 8
    rng = np.random.default_rng(0)
    x0, y = rng.normal(size=(100, n)), rng.normal(size=(100, 2, m))
    w = dj.Windows(x0, y, -0.5 * y)
    fit = lambda: dj.fit_pgd(jax.random.PRNGKey(3), w, qsr, num_inits=8, max_steps=30,
                             atol=0.0, rtol=0.0, throw=False)
    fit()
    t = time.perf_counter()
    res = fit()
    out[name + " pgd"] = 8 * 30 / (time.perf_counter() - t)
    out[name + " pgd loss"] = float(np.median(np.asarray(res.final_loss)))
print("RESULT " + json.dumps(out))
"""


COMPILE = r"""
import json, time
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
qsr, n, m = dj.QSR.passive(3), 6, 3
rng = np.random.default_rng(0)
y = rng.normal(size=(100, 2, m))
w = dj.Windows(rng.normal(size=(100, n)), y, -0.5 * y)
key, out = jax.random.PRNGKey(0), {"lib": dj.__file__}
kw = dict(num_inits=8, max_steps=150, atol=0.0, rtol=0.0, throw=False)
runs = {"direct_run": lambda k: dj.direct_run(k, w, qsr, **kw),
        "pgd_run": lambda k: dj.pgd_run(k, w, qsr, learning_rate=1.0, decay=0.99, **kw)}
for name, fn in runs.items():
    t = time.perf_counter()
    lowered = jax.jit(fn).lower(key)
    t1 = time.perf_counter()
    lowered.compile()
    out[name + " trace"], out[name + " compile"] = t1 - t, time.perf_counter() - t1
K12 = jax.vmap(lambda k: dj.LTIController.random(k, 12, 2, 2, scale=1.0))(
    jax.random.split(key, 4))
lowered = jax.jit(lambda K: dj.project(K, dj.QSR.passive(2), throw=False,
                                       method="first_order")).lower(K12)
t = time.perf_counter()
lowered.compile()
out["first-order project n12 compile"] = time.perf_counter() - t
fits = {"fit_ren": lambda: dj.fit_ren(key, w, qsr, width=4, **kw),
        "fit_mlp": lambda: dj.fit_mlp(key, w, num_inits=8, max_steps=150, atol=0.0, rtol=0.0),
        "fit_gd": lambda: dj.fit_gd(key, w, **kw)}
for name, fn in fits.items():
    t = time.perf_counter()
    jax.block_until_ready(fn())
    t1 = time.perf_counter()
    jax.block_until_ready(fn())
    out[name + " first - second"] = (t1 - t) - (time.perf_counter() - t1)
print("RESULT " + json.dumps(out))
"""


ORDER10 = r"""
import json, time
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
n, N = 10, 100
k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
y = jax.random.normal(k2, (N, 10, 2))
w = dj.Windows(jax.random.normal(k1, (N, n)), y, -0.5 * y)
t = time.perf_counter()
res = dj.fit_pgd(k3, w, dj.QSR.passive(2), max_steps=30, throw=False)
reasons = [str(r)[:40] for r in res.result_names()]
out = {"time": time.perf_counter() - t, "loss": np.asarray(res.final_loss).tolist(),
       "stops": reasons}
print("RESULT " + json.dumps(out))
"""


STEP = r"""
import json, resource, sys, time
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
n, qsr = int(sys.argv[1]), dj.QSR.passive(2)
keys = jax.random.split(jax.random.PRNGKey(n), 8)
K0 = jax.vmap(lambda k: dj.LTIController.random(k, n, 2, 2, scale=1.0))(keys)
t = time.perf_counter()
K0, P0 = dj.project(K0, qsr, refine=1)
setup = time.perf_counter() - t
noise = jax.vmap(lambda k: dj.LTIController.random(k, n, 2, 2, scale=0.2))(
    jax.random.split(jax.random.PRNGKey(1), 8))
target = jax.tree.map(lambda a, b: a + b, K0, noise)
proj = jax.jit(jax.vmap(lambda K, P: dj.project(K, qsr, P, throw=False)))
jax.block_until_ready(proj(target, P0))
t = time.perf_counter()
out = proj(target, P0)
jax.block_until_ready(out)
step = time.perf_counter() - t
ok = bool(np.all(np.asarray(dj.certify(out[0], qsr, P=out[1]).holds)))
dist = float(sum(np.sum((np.asarray(a) - np.asarray(b)) ** 2) for a, b in zip(
    jax.tree.leaves(out[0]), jax.tree.leaves(target))))
print("RESULT " + json.dumps({"step": step, "first call": setup, "certified": ok,
      "distance": dist, "peak MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run(path, code=CHILD, *argv):
    env = dict(os.environ, PYTHONPATH=path, OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", code, *argv], env=env, capture_output=True,
                          text=True, cwd="/", check=True)
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ref", required=True, help="a checkout of the reference version")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--order10", action="store_true")
    ap.add_argument("--step-at", type=int, default=0)
    ap.add_argument("--compile", action="store_true")
    args = ap.parse_args()
    ours_path = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if args.step_at:
        for _ in range(args.repeats):
            for who, path in (("ours", ours_path), ("ref", os.path.abspath(args.ref))):
                print(who, json.dumps(run(path, STEP, str(args.step_at))), flush=True)
        return
    if args.order10:
        for who, path in (("ours", ours_path), ("ref", os.path.abspath(args.ref))):
            print(who, json.dumps(run(path, ORDER10)), flush=True)
        return
    runs = {"ours": [], "ref": []}
    for _ in range(args.repeats):
        for who, path in (("ours", ours_path), ("ref", os.path.abspath(args.ref))):
            runs[who].append(run(path, COMPILE if args.compile else CHILD))
            print(who, runs[who][-1], flush=True)
    keys = [k for k in runs["ours"][0] if k != "lib"]
    print("\n| measure | ours | ref | ref / ours |")
    print("| --- | ---: | ---: | ---: |")
    for k in keys:
        a = float(sorted(r[k] for r in runs["ours"])[args.repeats // 2])
        b = float(sorted(r[k] for r in runs["ref"])[args.repeats // 2])
        unit = "/s" if k.endswith("pgd") else ("" if "loss" in k else " ms")
        unit, scale = (" s", 1.0) if args.compile else (unit, 1e3 if unit == " ms" else 1.0)
        ratio = b / a if not k.endswith("pgd") else a / b  # above 1: ours faster
        print(f"| {k}{unit} | {a * scale:.4g} | {b * scale:.4g} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
