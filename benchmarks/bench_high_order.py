"""`fit_direct` at high order: the order-dependent defaults, the deadlock fix, step times.

Problems (`benchmarks/_high_order.py`, m = p = 2, passive): mass-spring chains of
n̂/2 masses with two collocated actuators and an LQR expert ("chain"), and windows of a
random order-n̂ passive expert ("real.", length 10, which some controller fits exactly).

1. **Defaults** (`--defaults`): median over 8 initialisations of the initial and the final
   loss after 300 Adam steps (tol 0), relative to the zero controller's loss J(0), for the
   old fixed defaults (η = 0.3, σ = 0.5), the order-dependent defaults of
   `dissil_jax._train.direct.default_hyperparameters`, and the best of a grid
   η ∈ {0.3, 0.1, 0.03, 0.01} × σ ∈ {0.5, 0.2, 0.05} (one vmapped run); "regret" is
   new defaults / best.
2. **Hang** (`--hang R`): the issue's reproducer, `fit_direct` at n̂ = 48 with 32
   initialisations, 300 steps and defaults otherwise, R times, each in a fresh subprocess
   with a 600 s timeout; reports finished runs, wall times and whether every controller was
   certified. Run with `--lapack` to put LAPACK's batched custom calls back (the old map).
3. **Step time** (`--steps`): seconds per step of `direct_run` (8 initialisations, 150
   steps, compiled), loop-based solves against the LAPACK custom calls in the same run (the
   latter in a subprocess with a timeout, since it can hang).

4. **Order 16, every trainer** (`--order16`): `fit_direct`, `fit_pgd`, `fit_ico`, `fit_gd`,
   `fit_mlp` and `fit_ren`, each with all its defaults (8 initialisations), on the
   realisable order-16 problem ("real.", two seeds): the final loss of each returned
   controller over its own initial loss (median and worst), the share certified, each
   trainer's median final loss over the best trainer's, and the median loss on 200 fresh windows of the same
   expert over the zero controller's there ("held-out"). Then the static floor: the loss
   of the best static map of any kind, in expectation, over the same two references.

5. **Plain GD's step** (`--gd`): `fit_gd` (8 initialisations, 150 steps, its defaults
   otherwise) with Adam at the fixed 0.1 and at the two width rules 0.1 min(1, 9/w) and
   0.1 min(1, sqrt(9/w)), w = n̂ + p: final over initial loss per run (median, worst) on
   the chains (the tuning problems); `--gd --report` runs the realisable order-16 problem
   (held out: the rule was chosen on the chains).

6. **Plain GD's step budget** (`--gd-budget`): `fit_gd` with its defaults but for the
   budget and stopping `rtol` (150, 300 and 600 steps at 1e-7, 600 at 1e-8): final over
   initial loss per run (median, worst) and median steps on the chains (tuning);
   `--gd-budget --report` on the realisable order-16 problems of seeds 0–5 (held out).

7. **Plain GD's initial scale** (`--gd-init`): `fit_gd` with its defaults (600 steps) from the
   constant N(0, 0.3²) draw and from its order rule 0.3 min(1, 3/sqrt(n̂)) (the default):
   median initial and final loss over the zero controller's, median steps and the fraction
   of returned controllers with a stable Â, on the chains of order 6–48 (tuning);
   `--gd-init --report` on realisable problems of orders 12, 20 and 32, seeds 0–3 (held
   out), with the median loss on 200 fresh windows over the zero controller's.

Usage: python benchmarks/bench_high_order.py [--defaults] [--hang R] [--steps] [--order16]
       [--gd [--report]] [--gd-budget [--report]] [--gd-init [--report]]
"""

import argparse
import itertools
import os
import subprocess
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(__file__))
from _high_order import PASSIVE, chain_windows, realisable  # noqa: E402

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import realisable_windows  # noqa: E402
from dissil_jax.internal import default_hyperparameters  # noqa: E402

LRS, SCALES = (0.3, 0.1, 0.03, 0.01), (0.5, 0.2, 0.05)


def use_lapack():
    """Put the LAPACK custom calls back into the direct map (for the reference only)."""
    import jax.scipy.linalg as jsl

    from dissil_jax.internal import direct_map as _direct_map

    class Lapack:
        cholesky = staticmethod(jnp.linalg.cholesky)
        solve = staticmethod(jnp.linalg.solve)

        @staticmethod
        def solve_triangular(T, B, lower, trans=False):
            return jsl.solve_triangular(T, B, lower=lower, trans=1 if trans else 0)

    _direct_map._linalg = Lapack


def defaults(steps=300):
    problems = [("chain", s, n) for s in (0, 1) for n in (6, 12, 24, 48)]
    problems += [("real.", 0, n) for n in (6, 12, 16)]
    grid = np.array(list(itertools.product(LRS, SCALES)))
    print("| problem | n̂ | (η, σ) new | J_0/J(0) old | J_0/J(0) new | final old | final new "
          "| best (η, σ) | final best | regret |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for kind, seed, n in problems:
        w = chain_windows(seed, n // 2) if kind == "chain" else realisable(seed, n)
        J0 = float(jnp.mean(jnp.sum(w.u ** 2, axis=(1, 2))))
        lr_new, s_new = default_hyperparameters(n, 2)
        rows = np.concatenate([grid, [[0.3, 0.5], [lr_new, s_new]]])
        run = jax.jit(jax.vmap(lambda lr, s: dj.direct_run(
            jr.PRNGKey(1), w, PASSIVE, num_inits=8, max_steps=steps, atol=0.0, rtol=0.0,
            learning_rate=lr, init_scale=s, throw=False)))
        r = run(jnp.asarray(rows[:, 0]), jnp.asarray(rows[:, 1]))
        fin = np.median(np.asarray(r.final_loss), axis=1) / J0
        ini = np.median(np.asarray(r.loss_history[:, :, 0]), axis=1) / J0
        b = int(np.argmin(fin[:len(grid)]))
        print(f"| {kind} {seed} | {n} | ({lr_new:.3g}, {s_new:.2g}) | {ini[-2]:.3g} | "
              f"{ini[-1]:.3g} | {fin[-2]:.3g} | {fin[-1]:.3g} | ({grid[b, 0]:g}, "
              f"{grid[b, 1]:g}) | {fin[b]:.3g} | {fin[-1] / fin[b]:.2f} |", flush=True)


_CHILD = """
import os, sys, time
sys.path.insert(0, {here!r})
import jax, jax.numpy as jnp, jax.random as jr
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
import bench_high_order as b
if {lapack}:
    b.use_lapack()
k = jr.split(jr.PRNGKey({seed}), 3)
n, p = {n}, 2
w = dj.Windows(jr.normal(k[0], (25, n)), jr.normal(k[1], (25, 10, p)), jr.normal(k[2], (25, 10, p)))
t = time.perf_counter()
r = dj.fit_direct(jr.PRNGKey({seed}), w, dj.QSR.passive(p), num_inits={inits},
                  max_steps={steps}, {extra} throw=False)
print("RESULT", time.perf_counter() - t, bool(r.certified.all()), int(r.projected.sum()))
"""


def child(seed, n, inits, steps, lapack=False, timeout=600, extra=""):
    code = _CHILD.format(here=os.path.dirname(os.path.abspath(__file__)), lapack=lapack,
                         seed=seed, n=n, inits=inits, steps=steps, extra=extra)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=timeout, env=env).stdout
    except subprocess.TimeoutExpired:
        return None
    line = [ln for ln in out.splitlines() if ln.startswith("RESULT")]
    return line[0].split()[1:] if line else ["error"]


def hang(repeats, lapack):
    done = 0
    for i in range(repeats):
        t = time.perf_counter()
        res = child(i, 48, 32, 300, lapack=lapack)
        done += res is not None
        print(f"run {i}: {'TIMEOUT (hang)' if res is None else res} "
              f"({time.perf_counter() - t:.0f} s with start-up)", flush=True)
    print(f"{done}/{repeats} finished ({'LAPACK' if lapack else 'loop-based'} solves)")


def steps():
    code = """
import sys, time
sys.path.insert(0, {here!r})
import jax, jax.numpy as jnp, jax.random as jr
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
import bench_high_order as b
if {lapack}:
    b.use_lapack()
n = {n}
k = jr.split(jr.PRNGKey(0), 3)
w = dj.Windows(jr.normal(k[0], (25, n)), jr.normal(k[1], (25, 10, 2)), jr.normal(k[2], (25, 10, 2)))
run = jax.jit(lambda key: dj.direct_run(key, w, dj.QSR.passive(2), num_inits=8, max_steps=150,
                                        atol=0.0, rtol=0.0, throw=False))
jax.block_until_ready(run(jr.PRNGKey(1)))
t = time.perf_counter(); jax.block_until_ready(run(jr.PRNGKey(2)))
print("RESULT", (time.perf_counter() - t) / 150)
"""
    print("| n̂ | loop (ms/step) | LAPACK (ms/step) | loop / LAPACK |")
    print("|---|---|---|---|")
    for n in (6, 24, 48):
        t = {}
        for lapack in (False, True):
            src = code.format(here=os.path.dirname(os.path.abspath(__file__)), lapack=lapack,
                              n=n)
            try:
                out = subprocess.run([sys.executable, "-c", src], capture_output=True,
                                     text=True, timeout=300).stdout
                t[lapack] = float(out.split("RESULT")[1])
            except (subprocess.TimeoutExpired, IndexError):
                t[lapack] = float("nan")  # hung (or failed)
        print(f"| {n} | {1e3 * t[False]:.2f} | {1e3 * t[True]:.2f} | "
              f"{t[False] / t[True]:.2f} |", flush=True)


def order16(seeds=(0, 1)):
    """Every trainer with its defaults (8 initialisations) on the realisable order-16
    problem: per run, the returned controller's final loss over its initial loss; the
    median and worst over runs, the share certified, the wall time; and each method's
    median final loss over the best median of all methods."""
    fits = {
        "fit_direct": lambda k, w: dj.fit_direct(k, w, PASSIVE, throw=False),
        "fit_pgd": lambda k, w: dj.fit_pgd(k, w, PASSIVE, throw=False),
        "fit_ico": lambda k, w: dj.fit_ico(k, w, PASSIVE, throw=False),
        "fit_gd": lambda k, w: dj.fit_gd(k, w, throw=False),
        "fit_mlp": lambda k, w: dj.fit_mlp(k, w, throw=False),
        "fit_ren": lambda k, w: dj.fit_ren(k, w, PASSIVE, throw=False),
    }
    print("| seed | trainer | final / initial, median | worst | certified | steps (median) "
          "| wall (s) | median final / best method's | held-out / zero controller's |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for seed in seeds:
        w = realisable(seed, 16)
        rows = {}
        for name, fit in fits.items():
            t = time.perf_counter()
            try:
                r = fit(jr.PRNGKey(seed + 1), w)
            except ValueError as e:  # a trainer that does not accept the problem
                print(f"| {seed} | `{name}` | refuses: {str(e).split(', but')[0]} | | | | | |",
                      flush=True)
                continue
            wall = time.perf_counter() - t
            rel = np.asarray(r.final_loss) / np.asarray(r.loss_history)[:, 0]
            cert = "–" if r.certified is None else f"{np.mean(np.asarray(r.certified)):.0%}"
            rows[name] = (rel, cert, float(np.median(np.asarray(r.steps))), wall,
                          float(np.median(np.asarray(r.final_loss))),
                          float(np.median(np.asarray(r.loss_history)[:, 0])),
                          held_out(seed, 16, r.controllers))
            print(f"  ({name}: {np.median(rel):.3g} median, {wall:.1f} s)", flush=True)
        best = min(v[4] for v in rows.values())
        for name, (rel, cert, st, wall, med, _, test) in rows.items():
            print(f"| {seed} | `{name}` | {np.median(rel):.3g} | {np.max(rel):.3g} | {cert} | "
                  f"{st:.0f} | {wall:.1f} | {med / best:.2f} | {test:.3g} |", flush=True)
        if "fit_mlp" in rows:
            w = realisable(seed, 16)
            zero = float(np.mean(np.sum(np.asarray(w.target) ** 2, axis=(-2, -1))))
            print(f"  (static floor: {static_floor(seed, 16) / rows['fit_mlp'][5]:.3g} of "
                  f"fit_mlp's median initial loss, {static_floor(seed, 16) / zero:.3g} of the "
                  "zero controller's on the training windows)", flush=True)


def _fresh(seed: int, n: int, num: int = 200):
    """`num` new windows of `realisable(seed, n)`'s expert (new states and inputs)."""
    K = realisable_windows(jr.PRNGKey(seed), PASSIVE, n_state=n, num_windows=1, horizon=10)[1]
    kx, ky = jr.split(jr.PRNGKey(10_000 + seed))
    x0, y = jr.normal(kx, (num, n)), jr.normal(ky, (num, 10, PASSIVE.n_in))
    u = -jax.vmap(lambda x, yk: dj.rollout(K, x, yk))(x0, y)
    return dj.Windows(x0, y, u)


def held_out(seed: int, n: int, controllers) -> float:
    """The median over `controllers` (a batch) of their loss on `_fresh` windows, over the
    zero controller's loss there."""
    w = _fresh(seed, n)
    if isinstance(controllers, dj.MLPController):
        pred = jax.vmap(lambda K: jax.vmap(jax.vmap(K.mlp))(w.y))(controllers)
        loss = jnp.mean(jnp.sum((pred - w.target) ** 2, axis=(-2, -1)), axis=-1)
    elif isinstance(controllers, dj.RENController):
        loss = jax.vmap(dj.ren_imitation_loss, in_axes=(0, None))(controllers, w)
    else:
        loss = jax.vmap(dj.imitation_loss, in_axes=(0, None))(controllers, w)
    zero = jnp.mean(jnp.sum(w.target**2, axis=(-2, -1)))
    return float(np.median(np.asarray(loss / zero)))


def static_floor(seed: int, n: int) -> float:
    """The loss on `realisable(seed, n)` of the best static map $\\hat y = f(y)$ of any
    kind, in expectation over the windows' distribution: the inputs $y_k$ are white and
    independent of the expert's state $x_k$, so $E[u_k \\mid y_k] = -D_\\star y_k$ and
    no static map does better on average than the expert's own feedthrough, whose loss is
    $E\\lVert C_\\star x_k\\rVert^2$ summed over the window. Estimated on the windows
    themselves (a map fitted to these samples can go lower only by memorising them)."""
    w, K = realisable_windows(jr.PRNGKey(seed), PASSIVE, n_state=n, num_windows=25,
                              horizon=10)
    err = np.asarray(w.y) @ np.asarray(K.D).T - np.asarray(w.target)
    return float(np.mean(np.sum(err**2, axis=(-2, -1))))


def gd_rule(report=False):
    probs = ([("real.", s, 16) for s in (0, 1)] if report else
             [("chain", s, n) for s in (0, 1) for n in (6, 12, 24, 48)])
    rules = (("0.1", lambda w: 0.1), ("0.1 min(1, 9/w)", lambda w: 0.1 * min(1, 9 / w)),
             ("0.1 min(1, sqrt(9/w))", lambda w: 0.1 * min(1, (9 / w) ** 0.5)))
    print("| problem | n̂ | " + " | ".join(f"{name}: median, worst" for name, _ in rules) + " |")
    print("|---|---:|" + "---:|" * len(rules))
    for kind, seed, n in probs:
        w = chain_windows(seed, n // 2) if kind == "chain" else realisable(seed, n)
        cells = []
        for _, rule in rules:
            r = dj.fit_gd(jr.PRNGKey(seed + 1), w, optimizer=optax.adam(rule(n + w.n_in)),
                          n_state=n, throw=False)
            rel = np.asarray(r.final_loss) / np.asarray(r.loss_history)[:, 0]
            cells.append(f"{np.median(rel):.3g}, {np.max(rel):.3g}")
        print(f"| {kind} {seed} | {n} | " + " | ".join(cells) + " |", flush=True)


def gd_budget(report=False):
    budgets = ((150, 1e-7), (300, 1e-7), (600, 1e-7), (600, 1e-8))
    probs = ([("real.", s, 16) for s in range(6)] if report else
             [("chain", s, n) for s in (0, 1) for n in (6, 12, 24, 48)])
    print("| problem | n̂ | " + " | ".join(f"{n} steps, rtol {r:g}" for n, r in budgets) + " |")
    print("|---|---:|" + "---:|" * len(budgets))
    for kind, seed, n in probs:
        w = chain_windows(seed, n // 2) if kind == "chain" else realisable(seed, n)
        cells = []
        for steps, rtol in budgets:
            r = dj.fit_gd(jr.PRNGKey(seed + 1), w, n_state=n, max_steps=steps, rtol=rtol,
                          throw=False)
            rel = np.asarray(r.final_loss) / np.asarray(r.loss_history)[:, 0]
            cells.append(f"{np.median(rel):.3g}, {np.max(rel):.3g} "
                         f"({np.median(np.asarray(r.steps)):.0f})")
        print(f"| {kind} {seed} | {n} | " + " | ".join(cells) + " |", flush=True)


def gd_init(report=False):
    probs = ([("real.", s, n) for s in range(4) for n in (12, 20, 32)] if report else
             [("chain", s, n) for s in (0, 1) for n in (6, 12, 24, 48)])
    rules = (("0.3", lambda n: 0.3), ("0.3 min(1, 3/sqrt(n̂)) (default)", lambda n: None))
    cols = "J_0, final (over J(0)), steps, stable Â"
    print("| problem | n̂ | " + " | ".join(f"{name}: {cols}" for name, _ in rules)
          + (" | fresh windows (over J(0)) |" if report else " |"))
    print("|---|---:|" + "---|" * (len(rules) + report))
    for kind, seed, n in probs:
        w = chain_windows(seed, n // 2) if kind == "chain" else realisable(seed, n)
        zero = float(jnp.mean(jnp.sum(w.u ** 2, axis=(1, 2))))
        cells, fresh = [], []
        for _, rule in rules:
            r = dj.fit_gd(jr.PRNGKey(seed + 1), w, n_state=n, init_scale=rule(n),
                          throw=False, progress=False)
            radius = np.max(np.abs(np.linalg.eigvals(np.asarray(r.controllers.A))), axis=-1)
            cells.append(f"{np.median(np.asarray(r.loss_history)[:, 0]) / zero:.3g}, "
                         f"{np.median(np.asarray(r.final_loss)) / zero:.3g}, "
                         f"{np.median(np.asarray(r.steps)):.0f}, {np.mean(radius < 1):.2f}")
            if report:
                fresh.append(f"{held_out(seed, n, r.controllers):.3g}")
        print(f"| {kind} {seed} | {n} | " + " | ".join(cells)
              + (" | " + ", ".join(fresh) if report else "") + " |", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--defaults", action="store_true")
    ap.add_argument("--hang", type=int, default=0)
    ap.add_argument("--lapack", action="store_true")
    ap.add_argument("--steps", action="store_true")
    ap.add_argument("--order16", action="store_true")
    ap.add_argument("--gd", action="store_true")
    ap.add_argument("--gd-budget", action="store_true")
    ap.add_argument("--gd-init", action="store_true")
    ap.add_argument("--report", action="store_true")
    a = ap.parse_args()
    if a.gd:
        gd_rule(a.report)
    if a.gd_budget:
        gd_budget(a.report)
    if a.gd_init:
        gd_init(a.report)
    if a.order16:
        order16()
    if a.defaults:
        defaults()
    if a.hang:
        hang(a.hang, a.lapack)
    if a.steps:
        steps()
