"""What longer training windows buy: PGD with h = 2, 5, 10 at an equal number of samples.

The paper trains on windows of h = 2 steps. `dj.fit_pgd` accepts any h; its loss (paper
eq. 16) then compares the controller's whole h-step rollout, started at the plant state
and driven by the recorded plant outputs, with the expert's inputs. This script measures,
on the paper's nonlinear example (plant x+ = 0.5x + 0.4 sin x + u, y = x - 2u; NMPC
expert; controller supply rate (-29.867, 3.556, 0.601)), what h = 5 and h = 10 buy over
h = 2 when the number of demonstrated samples N*h is held fixed (100 samples: N = 50,
20, 10 windows; 20 samples: N = 10, 4, 2), in both of the paper's data regimes.

Per seed, every h uses the same PGD initialisations and is tested exactly as
`dissil_jax.experiments.protocol.run_config` does: in closed loop against the expert from
the same 1,000 test states with the same noise, for max(expert equilibrium horizon, 30)
steps. Besides the test metrics it reports the training loss per sample (J / h: J sums over
the horizon), and the imitation error of every learned controller on the same held-out
10-step expert windows, split into steps 0-1 (what h = 2 trains on) and steps 2-9.

Run:  python examples/horizons.py [--quick] [--seeds 10] [--inits 20] [--samples 100 20]
                                  [--learning-rate LR]
"""

import argparse
import dataclasses
import time

import jax
import jax.random as jr
import numpy as np

import dissil_jax as dj
from dissil_jax.experiments import demonstration_windows, equilibrium_horizon, evaluate
from dissil_jax.experiments.protocol import example_spec, make_problem

HORIZONS = (2, 5, 10)
REGIMES = ("initial", "sliding")
HELD_OUT = 10  # horizon of the held-out windows that score every controller


def window_error(controllers, windows, steps):
    """Per controller: (1/N) sum_i sum_{k < steps} |yhat_k + u_k|^2 on the first `steps` steps."""
    w = dj.Windows(windows.x0, windows.y[:, :steps], windows.u[:, :steps])
    return np.asarray(jax.vmap(dj.imitation_loss, in_axes=(0, None))(controllers, w))


def fit_and_test(k_fit, k_noise, windows, spec, inits, plant, expert, x0, steps, held_out,
                 compiled):
    """Train with the example's PGD settings (as protocol.fit), test as protocol.run_config."""
    def fit():
        return dj.fit_pgd(k_fit, windows, spec.qsr, num_inits=inits, max_steps=spec.max_steps,
                          atol=spec.tol, learning_rate=spec.pgd_learning_rate,
                          decay=spec.pgd_decay, init_scale=spec.init_scale, throw=False,
                          balance=False)

    if windows.y.shape not in compiled:  # compile outside the timed run (one per shape)
        jax.block_until_ready(fit().final_loss)
        compiled.add(windows.y.shape)
    t = time.perf_counter()
    res = fit()
    jax.block_until_ready(res.final_loss)
    train_time = time.perf_counter() - t
    ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps)
    first2 = window_error(res.controllers, held_out, 2)
    return dict(
        mse=np.asarray(ev.mse), stable=np.asarray(ev.stable, bool),
        train_loss=np.asarray(res.final_loss) / windows.horizon,
        held_first=first2,
        held_tail=window_error(res.controllers, held_out, HELD_OUT) - first2,  # causal rollout
        steps=np.asarray(res.steps), time=train_time,
        converged=np.array([r == "converged" for r in res.result_names()]),
        certified=bool(np.all(np.asarray(res.certified))),
    )


def run_seed(seed, spec, budgets, inits, regimes, compiled, num_held_out=500):
    """All (regime, N*h, h) runs of one seed: one record of raw results per run."""
    plant, expert = make_problem(spec, 0, seed)
    # The keys of protocol.training_data / run_config for plant 0 of this seed.
    k_data, k_fit, k_test, k_noise = jr.split(jr.fold_in(jr.PRNGKey(seed), 0), 4)
    x0 = spec.test_std * jr.normal(k_test, (spec.num_test, plant.n_state), plant.A.dtype)
    T = equilibrium_horizon(jr.fold_in(k_noise, 1), plant, expert, x0,
                            max_steps=spec.equilibrium_search)
    steps = max(T, spec.min_test_steps)
    held_out = demonstration_windows(jr.fold_in(k_data, 999), plant, expert, num_held_out,
                                     "initial", horizon=HELD_OUT, x0_std=spec.train_std)
    u2 = np.sum(np.asarray(held_out.u) ** 2, axis=(0, 2))  # expert input energy per step
    rows = []
    for regime in regimes:
        for samples in budgets:
            for h in HORIZONS:
                N = samples // h
                windows = demonstration_windows(
                    jr.fold_in(k_data, 10_000 * samples + 100 * h + REGIMES.index(regime)),
                    plant, expert, N, regime, horizon=h, x0_std=spec.train_std)
                rows.append(dict(
                    regime=regime, samples=samples, h=h, N=N, seed=seed, test_steps=steps,
                    share_first2=float(u2[:2].sum() / u2.sum()),
                    **fit_and_test(k_fit, k_noise, windows, spec, inits, plant, expert, x0,
                                   steps, held_out, compiled)))
    return rows


def table(rows, regimes, budgets):
    """Markdown table: medians pooled over seeds and initialisations."""
    lines = [
        "| regime | N·h | h | N | median test MSE (per-seed range) | seeds better than h = 2 "
        "| % stable | train J/h | held-out error, steps 0–1 | held-out error, steps 2–9 "
        "| PGD steps (% converged) | train time (s) |",
        "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for regime in regimes:
        for samples in budgets:
            def select(h):
                return sorted((r for r in rows if r["regime"] == regime
                               and r["samples"] == samples and r["h"] == h),
                              key=lambda r: r["seed"])

            base = [np.median(r["mse"]) for r in select(HORIZONS[0])]
            for h in HORIZONS:
                sel = select(h)
                cat = {k: np.concatenate([r[k] for r in sel]) for k in
                       ("mse", "stable", "train_loss", "held_first", "held_tail", "steps",
                        "converged")}
                med = [np.median(r["mse"]) for r in sel]
                spread = f" ({min(med):.4f}–{max(med):.4f})" if len(sel) > 1 else ""
                wins = ("–" if h == HORIZONS[0] else
                        f"{sum(m < b for m, b in zip(med, base))}/{len(sel)}")
                lines.append(
                    f"| {regime} | {samples} | {h} | {sel[0]['N']} | "
                    f"{np.median(cat['mse']):.4f}{spread} | {wins} | "
                    f"{100 * cat['stable'].mean():.0f} | {np.median(cat['train_loss']):.5f} | "
                    f"{np.median(cat['held_first']):.4f} | {np.median(cat['held_tail']):.4f} | "
                    f"{cat['steps'].mean():.0f} ({100 * cat['converged'].mean():.0f}) | {np.mean([r['time'] for r in sel]):.2f} |")
    return "\n".join(lines)


def main(quick: bool = False, seeds: int = 10, inits: int = 20, budgets=(100, 20),
         learning_rate: float | None = None):
    jax.config.update("jax_enable_x64", True)
    spec = example_spec("nonlinear", quick)
    if learning_rate is not None:
        spec = dataclasses.replace(spec, pgd_learning_rate=learning_rate)
    regimes, num_held_out = REGIMES, 500
    if quick:
        seeds, inits, budgets, regimes, num_held_out = 1, 3, (20,), ("initial",), 50
    for samples in budgets:
        if samples % np.lcm.reduce(HORIZONS):
            raise ValueError(f"N*h = {samples} must be divisible by every h in {HORIZONS}.")
    t0 = time.perf_counter()
    rows, compiled = [], set()
    for seed in range(seeds):
        rows += run_seed(seed, spec, budgets, inits, regimes, compiled, num_held_out)
        print(f"seed {seed} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    share = np.mean([r["share_first2"] for r in rows])
    print(f"\nNonlinear example, PGD, {seeds} seed(s) x {inits} initialisations, "
          f"{spec.num_test} test states, {rows[0]['test_steps']} test steps, at most "
          f"{spec.max_steps} PGD steps (initial step {spec.pgd_learning_rate:g}, decay "
          f"{spec.pgd_decay:g}, tol {spec.tol:g}); every controller certified: "
          f"{all(r['certified'] for r in rows)}\n")
    print(table(rows, regimes, budgets))
    print(f"\nMedians pool seeds x initialisations; the range is that of the per-seed medians, "
          f"and 'seeds better' counts seeds whose median test MSE is below h = 2's. J/h: "
          f"training loss per sample. Held-out error: sum of squared errors per window on "
          f"{num_held_out} fresh 10-step expert windows (x0 ~ N(0, {spec.train_std:g}^2)), "
          f"whose steps 0-1 carry {100 * share:.1f} % of the expert's squared inputs. Train "
          f"time: one fit of {inits} initialisations, compilation excluded. "
          f"Total {time.perf_counter() - t0:.0f} s.")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (CI)")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--inits", type=int, default=20)
    parser.add_argument("--samples", type=int, nargs="+", default=[100, 20],
                        help="sample budgets N*h (each divisible by 2, 5 and 10)")
    parser.add_argument("--learning-rate", type=float, default=None,
                        help="PGD's initial step (default: the example's pgd_learning_rate)")
    a = parser.parse_args()
    main(a.quick, a.seeds, a.inits, tuple(a.samples), a.learning_rate)
