"""PGD with the first-order projection against the Clarabel projection (same run).

Problems: the collocated mass-spring chains of `benchmarks/_high_order.py` (m = p = 2,
passive, order n̂ = 2 × masses, initial segments of length 10), PGD with the paper's rule
(`learning_rate=1.0`, Frobenius projections, so both methods solve the same problem), 8
initialisations, `--steps` steps (tol 0). Per order and method: seconds per PGD step of the
compiled run (second call, compilation excluded), its ratio to Clarabel's, the median final
loss relative to Clarabel's, the share of iterates the exact float64 check certified
(`certified`, from every step's check), the rows the first-order path handed to Clarabel and
the mean number of ADMM iterations per projection (the first-order run warm-starts each
step's ADMM from the previous step's state).

`--adam`: both methods with `pgd_run`'s default step, projected Adam, whose projections are
in its metric (the first-order path carries it by a consensus block).

`--tol`: PGD's ADMM tolerance (`first_order.TOL_FO_PGD`) at 1e-4, 3e-4 and 1e-3, with
projected Adam and with the paper's rule, on the chains of `--seeds` (first-order path only):
seconds per step, ADMM iterations per projection, rows handed to Clarabel, and the median
and worst final/initial loss.

`--against-default`: instead, `pgd_run` with all its defaults (Adam with its metric, so
Clarabel projections) against the paper's rule (`learning_rate=1.0`, Frobenius, so
`method="auto"` takes the first-order path from `AUTO_MIN_ORDER` on), on the chains of
`--seeds`: seconds per step, its ratio, and the median and worst final/initial loss of each.

`--to-loss`: time to equal loss, with `pgd_run`'s default step (projected Adam) on the
chains of `--seeds`. Clarabel runs `--steps` steps, the first-order path twice as many; the
target is Clarabel's median loss after its last step, and each method's time to it is its
seconds per step times the steps (initial projection included) until its median loss
curve first reaches the target. Every iterate of both runs is checked in float64.

Usage: python benchmarks/bench_fo_projection.py [--steps 10] [--orders 6,12,24] [--adam]
       python benchmarks/bench_fo_projection.py --tol [--steps 60] [--orders 12,16] [--seeds 0,1]
       python benchmarks/bench_fo_projection.py --against-default [--steps 150] [--orders 12]
              [--seeds 0,1]
       python benchmarks/bench_fo_projection.py --to-loss [--steps 30] [--orders 24]
              [--seeds 0,1]
"""

import argparse
import itertools
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.dirname(__file__))

from _high_order import PASSIVE, chain_windows  # noqa: E402

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import projection_fo as _projection_fo  # noqa: E402


def run(windows, method, steps, learning_rate=1.0):
    """PGD with the paper's rule at `learning_rate` (None: `pgd_run`'s default step)."""
    fn = jax.jit(lambda key: dj.pgd_run(key, windows, PASSIVE, num_inits=8, max_steps=steps,
                                        learning_rate=learning_rate, atol=0.0, rtol=0.0,
                                        throw=False, method=method))
    jax.block_until_ready(fn(jr.PRNGKey(0)))
    before = dict(_projection_fo.FALLBACKS)
    t = time.perf_counter()
    res = jax.block_until_ready(fn(jr.PRNGKey(0)))
    per_step = (time.perf_counter() - t) / (steps + 1)  # + the initial projection
    diff = {k: _projection_fo.FALLBACKS[k] - before[k] for k in before}
    return res, per_step, diff


def _header(*columns):
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))


def _relative(res):
    """Each run's final loss over its initial loss."""
    return np.asarray(res.final_loss) / np.asarray(res.loss_history)[:, 0]


def main(steps, orders, learning_rate=1.0):
    _header("n̂", "Clarabel (s/step)", "first-order (s/step)", "speed-up", "loss FO / Clarabel",
            "certified (FO, Clarabel)", "rows to Clarabel", "ADMM iterations / projection")
    for n in orders:
        w = chain_windows(0, n // 2)
        rc, tc, _ = run(w, "clarabel", steps, learning_rate)
        rf, tf, fb = run(w, "first_order", steps, learning_rate)
        ratio = float(np.median(rf.final_loss) / np.median(rc.final_loss))
        cert = (np.mean(np.asarray(rf.certified)), np.mean(np.asarray(rc.certified)))
        its = fb["iterations"] / max(fb["projections"], 1)
        print(f"| {n} | {tc:.3f} | {tf:.3f} | {tc / tf:.1f}x | {ratio:.4f} | "
              f"{cert[0]:.0%}, {cert[1]:.0%} | {fb['rows']} | {its:.0f} |", flush=True)
        print("median loss per step, Clarabel:",
              np.round(np.median(np.asarray(rc.loss_history), axis=0), 4).tolist(),
              "\nfirst-order:", np.round(np.median(np.asarray(rf.loss_history), axis=0), 4).tolist(),
              flush=True)


def tolerances(steps, orders, seeds):
    _header("n̂", "seed", "rule", "tol", "s/step", "iterations / projection",
            "rows to Clarabel", "median final/initial", "worst")
    for n, seed in itertools.product(orders, seeds):
        w = chain_windows(seed, n // 2)
        for rule, lr in (("Adam", None), ("paper", 1.0)):
            for tol in (1e-4, 3e-4, 1e-3):
                _projection_fo.TOL_FO_PGD = tol
                r, t, fb = run(w, "first_order", steps, lr)
                rel = _relative(r)
                its = fb["iterations"] / max(fb["projections"], 1)
                print(f"| {n} | {seed} | {rule} | {tol:g} | {t:.3f} | {its:.0f} | {fb['rows']} "
                      f"| {np.median(rel):.4g} | {np.max(rel):.4g} |", flush=True)


def against_default(steps, orders, seeds):
    _header("n̂", "chain seed", "default (s/step)", "paper rule (s/step)", "speed-up",
            "default: median (worst) final/initial", "paper rule: median (worst)",
            "certified (default, paper)")
    for n, seed in itertools.product(orders, seeds):
        w = chain_windows(seed, n // 2)
        rd, td, _ = run(w, "auto", steps, learning_rate=None)
        rp, tp, _ = run(w, "auto", steps)
        rel = [_relative(r) for r in (rd, rp)]
        cells = [f"{np.median(r):.2g} ({np.max(r):.2g})" for r in rel]
        cert = [f"{np.mean(np.asarray(r.certified)):.0%}" for r in (rd, rp)]
        print(f"| {n} | {seed} | {td:.3f} | {tp:.3f} | {td / tp:.1f}x | {cells[0]} | {cells[1]} "
              f"| {cert[0]}, {cert[1]} |", flush=True)


def _steps_to(curve, target):
    """Steps (the initial projection counted as one) until `curve` first reaches `target`,
    or None when it never does."""
    hit = np.nonzero(np.asarray(curve) <= target)[0]
    return int(hit[0]) + 1 if len(hit) else None


def to_loss(steps, orders, seeds):
    _header("n̂", "chain seed", "target (Clarabel's median at its last step)",
            "Clarabel: steps, s", "first-order: steps, s", "speed-up at equal loss",
            "runs with every iterate certified (FO, Clarabel)", "rows to Clarabel")
    for n, seed in itertools.product(orders, seeds):
        w = chain_windows(seed, n // 2)
        rc, tc, _ = run(w, "clarabel", steps, learning_rate=None)
        rf, tf, fb = run(w, "first_order", 2 * steps, learning_rate=None)
        curves = [np.median(np.asarray(r.loss_history), axis=0) for r in (rc, rf)]
        target = float(curves[0][-1])
        kc, kf = (_steps_to(c, target) for c in curves)
        # A run stops `not_certified` at the first iterate that fails the float64 check.
        cert = [f"{np.mean([x == 'max_steps' for x in r.result_names()]):.0%}" for r in (rf, rc)]
        fo = "not reached" if kf is None else f"{kf}, {kf * tf:.1f}"
        ratio = "–" if kf is None else f"{kc * tc / (kf * tf):.1f}x"
        print(f"| {n} | {seed} | {target:.4g} | {kc}, {kc * tc:.1f} | {fo} | {ratio} "
              f"| {cert[0]}, {cert[1]} | {fb['rows']} |", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--orders", default="6,12,24")
    ap.add_argument("--against-default", action="store_true")
    ap.add_argument("--tol", action="store_true", help="PGD's ADMM tolerance")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--to-loss", action="store_true",
                    help="time until each method's median loss reaches Clarabel's final one")
    ap.add_argument("--adam", action="store_true",
                    help="PGD's default step (Adam, projected in its metric) for both methods")
    a = ap.parse_args()
    orders = [int(x) for x in a.orders.split(",")]
    if a.tol:
        tolerances(a.steps, orders, [int(x) for x in a.seeds.split(",")])
    elif a.to_loss:
        to_loss(a.steps, orders, [int(x) for x in a.seeds.split(",")])
    elif a.against_default:
        against_default(a.steps, orders, [int(x) for x in a.seeds.split(",")])
    else:
        main(a.steps, orders, None if a.adam else 1.0)
