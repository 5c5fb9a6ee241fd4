"""`fit_mlp` with and without `balance`: the network trained in the data's units or in units
of the data's own size.

1. `--scales`: a static nonlinear expert $u = \\tanh(0.7y_1 - 0.4y_2) + 0.3y_1^2$ on
   Gaussian $y$ (100 windows of 5 steps, $p = 2$, $m = 1$), with $y$ and $u$ put in other
   units ($y \\to a y$, $u \\to b u$). Per cell the final loss over the zero controller's
   (median and worst of 4 initialisations, hidden (32, 32), every other argument default).
2. `--zoo tuning` (chose the default) and `--zoo held_out` (reported, not used to choose):
   the problem zoo's halves, `fit_mlp` with all its defaults (8 initialisations) but
   `balance`; per problem the median held-out imitation error relative to the zero
   controller's (`zoo.evaluate`), the median training loss relative to the zero
   controller's, and the wall time of each call. `--balance true` runs the balanced column
   only, `--problems` some problems of the half.

Usage: python benchmarks/bench_mlp_units.py [--scales] [--zoo tuning|held_out]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import zoo  # noqa: E402


def scales() -> None:
    rng = np.random.default_rng(0)
    N, h, p = 100, 5, 2
    y = rng.normal(size=(N, h, p))
    u = np.tanh(y @ np.array([[0.7], [-0.4]])) + 0.3 * y[..., :1] ** 2
    print("| y units | u units | balance=False: median (worst) | balance=True: median (worst) |")
    print("|---:|---:|---:|---:|")
    for a, b in [(1, 1), (1e3, 1), (1, 1e-3), (1e3, 1e-3), (1e-3, 1e3), (1e-3, 1)]:
        w = dj.Windows(jnp.zeros((N, 1)), jnp.asarray(y * a), jnp.asarray(u * b))
        zero = float(np.mean(np.sum((u * b) ** 2, axis=(-2, -1))))
        cells = []
        for balance in (False, True):
            res = dj.fit_mlp(jr.PRNGKey(0), w, hidden=(32, 32), num_inits=4, throw=False,
                             balance=balance, progress=False)
            rel = np.asarray(res.final_loss, np.float64) / zero
            cells.append(f"{np.median(rel):.2g} ({np.max(rel):.2g})")
        print(f"| {a:g} | {b:g} | {cells[0]} | {cells[1]} |", flush=True)


def zoo_half(half: str, balances=(False, True), only=None) -> None:
    names = zoo.TUNING if half == "tuning" else zoo.HELD_OUT
    names = [n for n in names if only is None or n in only]
    print(f"{half}: median held-out imitation error / zero controller's (median training "
          "loss / zero controller's; wall s)")
    print("| problem | " + " | ".join(f"balance={b}" for b in balances)
          + (" | ratio True/False |" if len(balances) == 2 else " |"))
    print("|---|" + "---:|" * (len(balances) + (len(balances) == 2)))
    ratios = []
    for name in names:
        problem = zoo.problem(name)
        cells, meds = [], []
        for balance in balances:
            began = time.perf_counter()
            rep = zoo.evaluate(problem, lambda t, b=balance: dj.fit_mlp(
                t.key, t.windows, throw=False, balance=b, progress=False))
            wall = time.perf_counter() - began
            med = float(np.median(rep.imitation_error))
            zero = float(np.mean(np.sum(np.asarray(problem.train.u, np.float64) ** 2,
                                        axis=(1, 2))))
            meds.append(med)
            cells.append(f"{med:.3g} ({np.median(rep.train_loss) / zero:.3g}; {wall:.0f} s)")
        if len(balances) == 1:
            print(f"| {name} | {cells[0]} |", flush=True)
            continue
        ratios.append(meds[1] / meds[0])
        print(f"| {name} | {cells[0]} | {cells[1]} | {ratios[-1]:.3g} |", flush=True)
    if ratios:
        print(f"ratio True/False: median {np.median(ratios):.3g}, range "
              f"{min(ratios):.3g}-{max(ratios):.3g}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scales", action="store_true")
    ap.add_argument("--zoo", choices=("tuning", "held_out"))
    ap.add_argument("--balance", choices=("both", "true"), default="both",
                    help="`true`: balanced runs only (the unbalanced column of the held-out "
                         "half is the `mlp` column of `bench_defaults.py --part report`)")
    ap.add_argument("--problems", default=None,
                    help="comma-separated zoo problems of the half (default: all)")
    args = ap.parse_args()
    if args.scales:
        scales()
    if args.zoo:
        zoo_half(args.zoo, (True,) if args.balance == "true" else (False, True),
                 None if args.problems is None else args.problems.split(","))
