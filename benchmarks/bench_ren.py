"""Certified REN controllers (`dj.fit_ren`) against the LTI direct map, on the nonlinear example.

The paper's nonlinear example with 25 initial segments (the reproduction's data), the
protocol's settings (`dissil_jax.experiments.protocol.fit`: all `max_steps` = 150 Adam
steps for both). Printed:

- **speed**: training wall time of `fit_ren` (width 16, the experiments' settings) and of
  `fit_direct` for the same number of initialisations, each the second of two identical
  calls (JIT compilation excluded), and the first calls (compilation included), with
  their ratios;
- **the map's own cost**: the REN map's forward pass and gradient alone for the same steps,
  against `fit_direct`'s whole training;
- **why a direct map, not a projection**: the wall time of one certificate SDP of a
  trained REN (`dj.certify_ren`, cvxpy + Clarabel: the LMI in (P, Lambda) alone, which is
  smaller than a projection onto a convexified REN LMI would be) against the time of one
  whole training step of the direct map for all initialisations;
- **closed loop** (`--loop`): the protocol's record (`run_config`) for REN, direct, ICO
  and the MLP baseline on the same data: certified, % stable, median test MSE;
- **across seeds** (`--seeds 0,3,4`, with `--data sliding` for sliding windows): the same
  closed-loop record for each seed (each seed
  draws its own demonstrations and test states), one median test MSE per method and seed,
  to tell a method's advantage from one draw's luck. With `--seeds` the speed part is
  skipped;
- **demonstrations as wide as the test** (`--wide`): the LTI direct map and a tanh REN
  trained on 400 two-step windows from $x_0 \\sim \\mathcal N(0, 15^2)$, the test states'
  distribution, and tested on seed 0's test loops: how far the 25 small-state windows,
  not the model class, limit the test MSE.

- **the step budget** (`--zoo tuning|held_out`): `fit_ren` (width 4, 8 initialisations) on
  the problem zoo with 150 steps at `rtol` 1e-6 against `fit_direct`'s 600 steps at 1e-8
  (median final loss, median steps, wall time of a compiled call), problems with an
  indefinite Q skipped (the REN map needs Q <= 0).

- **the default activation** (`--activations tuning|held_out`): `fit_ren` with all its
  defaults but the activation, tanh or ReLU, judged by the zoo (`zoo.evaluate`: median
  imitation error on the held-out windows, % stable).

- **tight gain bounds** (`--tight`): `fit_ren` on gain bounds of 1e-1 to 1e-6 (SISO and 4
  outputs x 3 inputs, windows from a state) and on Theorem 1's rates for three random 4x3
  plants of gain near 1e3 (|Q| ~ 1e6): the storages' largest condition number, certified
  runs and the median training loss, against `fit_direct`'s (`--tight --no-units`: the
  same without the REN map's input units).

Usage: python benchmarks/bench_ren.py [--quick] [--inits 100] [--loop] [--seeds 0,3,4]
       [--data sliding] [--wide] [--zoo tuning] [--defaults tuning] [--activations tuning]
       [--tight [--no-units]]
"""

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

from bench_direct import timed  # noqa: E402  (compile once, then time a second run)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments.data import demonstration_windows  # noqa: E402
from dissil_jax.experiments.metrics import evaluate  # noqa: E402
from dissil_jax.experiments.protocol import (  # noqa: E402
    evaluation_setup,
    example_spec,
    fit,
    run_config,
    training_data,
)
from dissil_jax.internal import ren_map  # noqa: E402

METHODS = ("ren", "direct", "ico", "mlp")


def across_seeds(seeds, inits, quick, data="initial"):
    """Median test MSE (and % stable when below 100) per method and seed."""
    regime = "initial segments" if data == "initial" else "sliding windows"
    print(f"nonlinear example, 25 {regime}, {inits} initialisations per seed: "
          "median test MSE (% stable when below 100)")
    print("| method | " + " | ".join(f"seed {s}" for s in seeds) + " | certified |")
    print("|---|" + "---:|" * len(seeds) + "---|")
    for method in METHODS:
        cells, certified = [], []
        for seed in seeds:
            rec = run_config("nonlinear", data, method, 25, inits=inits, seed=seed,
                             quick=quick)
            stable = rec["percent_stable"]
            cells.append(f"{rec['mse_median']:.4g}" + ("" if stable == 100 else
                                                      f" ({stable:.0f} %)"))
            certified.append(rec["certified"])
        cert = "–" if certified[0] is None else str(all(certified))
        print(f"| {method} | " + " | ".join(cells) + f" | {cert} |", flush=True)


def wide(inits, quick):
    """Train on windows drawn like the test states; median test MSE on seed 0's loops."""
    spec = example_spec("nonlinear", quick)
    plant, expert, _, (k_fit, _, k_noise) = training_data(spec, 0, 0, "initial", 25)
    x0, _, steps = evaluation_setup(spec, 0, 0)
    W = demonstration_windows(jax.random.PRNGKey(7), plant, expert, 400, "initial",
                              x0_std=spec.test_std)
    runs = {"direct (LTI)": dj.fit_direct(k_fit, W, spec.qsr, num_inits=inits, max_steps=600,
                                          learning_rate=0.1, init_scale=0.5, throw=False),
            "REN tanh, width 16": dj.fit_ren(k_fit, W, spec.qsr, num_inits=inits, width=16,
                                             activation="tanh", learning_rate=0.03,
                                             max_steps=600, throw=False)}
    print(f"nonlinear example, 400 windows from x0 ~ N(0, {spec.test_std:g}^2), {inits} "
          "initialisations x 600 steps, tested on seed 0's loops")
    print("| method | median test MSE | % stable | median train loss | certified |")
    print("|---|---:|---:|---:|---|")
    for name, res in runs.items():
        ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps)
        print(f"| {name} | {float(np.median(np.asarray(ev.mse))):.4g} "
              f"| {100 * float(np.mean(np.asarray(ev.stable))):.0f} "
              f"| {float(np.median(res.final_loss)):.4g} | {bool(np.all(res.certified))} |")


def zoo_budget(split):
    """`fit_ren`'s two step budgets on one half of the zoo (compiled second calls)."""
    from dissil_jax.experiments import zoo
    from dissil_jax.internal import is_indefinite

    print(f"fit_ren, width 4, 8 initialisations, zoo {split}: median final loss (median steps, "
          "s)")
    print("| problem | initial | 150 steps, rtol 1e-6 | 600 steps, rtol 1e-8 | certified |")
    print("|---|---:|---:|---:|---|")
    for name in zoo.TUNING if split == "tuning" else zoo.HELD_OUT:
        t = zoo.task(zoo.problem(name))
        if is_indefinite(t.qsr):
            print(f"| {name} | indefinite Q: skipped | | | |")
            continue
        kw = dict(width=4, num_inits=8, throw=False,
                  **({} if t.windows.x0 is not None else {"n_state": t.n_state}))
        cells, cert = [], True
        for steps, rtol in ((150, 1e-6), (600, 1e-8)):
            fit = lambda: dj.fit_ren(t.key, t.windows, t.qsr, max_steps=steps, rtol=rtol, **kw)
            res, sec = timed(fit)
            cells.append(f"{float(np.median(res.final_loss)):.3g} "
                         f"({int(np.median(res.steps))}, {sec:.1f})")
            cert &= bool(np.all(res.certified))
        print(f"| {name} | {float(np.median(res.initial_loss)):.3g} | {cells[0]} | {cells[1]} "
              f"| {'all' if cert else 'NOT all'} |", flush=True)


#: Candidate defaults of `fit_ren`'s Adam step and initial scale (`--defaults`): the LTI
#: rule of `default_hyperparameters` at order n + q or at order n, the same rule capped at
#: 0.1 (`fit_ren`'s default, `default_ren_hyperparameters`), and fixed grid points.
CANDIDATES = {"rule(n+q)": "n+q", "rule(n)": "n", "capped rule(n)": "capped",
              **{f"({lr}, {sc})": (lr, sc) for lr in (0.1, 0.03, 0.01) for sc in (0.1, 0.3)}}


def defaults(split):
    """`fit_ren` (width 4, 8 initialisations, default budget) with each candidate (Adam
    step, initial scale) on one half of the zoo: median final loss over the best
    candidate's per problem, and the worst such ratio per candidate."""
    from dissil_jax.experiments import zoo
    from dissil_jax.internal import default_hyperparameters, is_indefinite, ren_train

    default_ren_hyperparameters = ren_train.default_ren_hyperparameters

    names = [n for n in (zoo.TUNING if split == "tuning" else zoo.HELD_OUT)
             if not is_indefinite(zoo.task(zoo.problem(n)).qsr)]
    table = {}
    for name in names:
        t = zoo.task(zoo.problem(name))
        n_state = t.n_state if t.windows.x0 is None else t.windows.x0.shape[-1]
        kw = dict(width=4, num_inits=8, throw=False,
                  **({} if t.windows.x0 is not None else {"n_state": t.n_state}))
        row = {}
        for label, cand in CANDIDATES.items():
            if cand == "capped":
                lr, sc = default_ren_hyperparameters(n_state, t.windows.n_in)
            elif isinstance(cand, str):
                order = n_state + 4 if cand == "n+q" else n_state
                lr, sc = default_hyperparameters(order, t.windows.n_in)
            else:
                lr, sc = cand
            res = dj.fit_ren(t.key, t.windows, t.qsr, learning_rate=lr, init_scale=sc, **kw)
            row[label] = (float(np.median(res.final_loss)), bool(np.all(res.certified)))
        table[name] = row
        best = min(v[0] for v in row.values())
        print(f"{name}: " + ", ".join(f"{k} {v[0] / best:.3g}{'' if v[1] else ' (NOT cert.)'}"
                                      for k, v in row.items()), flush=True)
    print(f"\nfit_ren, width 4, 8 initialisations, zoo {split}: median final loss over the "
          "best candidate's")
    print("| problem | " + " | ".join(CANDIDATES) + " |")
    print("|---|" + "---:|" * len(CANDIDATES))
    for name, row in table.items():
        best = min(v[0] for v in row.values())
        print(f"| {name} | " + " | ".join(f"{v[0] / best:.3g}" for v in row.values()) + " |")
    worst = {k: max(row[k][0] / min(v[0] for v in row.values()) for row in table.values())
             for k in CANDIDATES}
    print("| **worst** | " + " | ".join(f"{worst[k]:.3g}" for k in CANDIDATES) + " |")


def activations(split):
    """`fit_ren` with all its defaults but the activation (tanh, ReLU) on one half of the zoo,
    judged by the zoo (`zoo.evaluate`): median held-out imitation error and % stable."""
    from dissil_jax.experiments import zoo
    from dissil_jax.internal import is_indefinite

    print(f"fit_ren defaults, zoo {split}: median held-out imitation error (% stable), "
          "and the ratio of each to the better of the two")
    print("| problem | tanh | ReLU | tanh / best | ReLU / best |")
    print("|---|---:|---:|---:|---:|")
    worst = {"tanh": 0.0, "relu": 0.0}
    for name in zoo.TUNING if split == "tuning" else zoo.HELD_OUT:
        problem = zoo.problem(name)
        if is_indefinite(problem.qsr):
            continue
        err, stab = {}, {}
        for act in ("tanh", "relu"):
            rep = zoo.evaluate(problem, lambda t: dj.fit_ren(
                t.key, t.windows, t.qsr, activation=act, throw=False,
                **({} if t.windows.x0 is not None else {"n_state": t.n_state})))
            err[act] = float(np.median(rep.imitation_error))
            stab[act] = 100 * float(np.mean(rep.stable))
        best = min(err.values())
        for act in err:
            worst[act] = max(worst[act], err[act] / best)
        print(f"| {name} | {err['tanh']:.3g} ({stab['tanh']:.0f}) | {err['relu']:.3g} "
              f"({stab['relu']:.0f}) | {err['tanh'] / best:.3g} | {err['relu'] / best:.3g} |",
              flush=True)
    print(f"| **worst** | | | {worst['tanh']:.3g} | {worst['relu']:.3g} |")


def _gain_windows(key, n_in, n_out, n):
    """25 five-step windows from a state: outputs N(0, 1), an expert of gain about 0.5."""
    import jax.random as jr

    y = jr.normal(key, (25, 5, n_in))
    G = jr.normal(jr.fold_in(key, 5), (n_in, n_out))
    u = -0.5 * y @ G + 0.1 * jr.normal(jr.fold_in(key, 1), (25, 5, n_out))
    return dj.Windows(jr.normal(jr.fold_in(key, 2), (25, n)), y, u)


def _plant_windows(seed, radius):
    """A random 4x3 plant (4 outputs) near instability, LQR expert, 25 five-step windows from
    N(0, I) states, and Theorem 1's controller rate for its bounded gain."""
    from dissil_jax.internal import zoo_build

    plant = zoo_build.random_stable_plant(seed, 4, 3, 4, radius=radius)
    A, B, C, D = (np.asarray(M) for M in plant.matrices())
    K = zoo_build.dlqr(A, B)
    x0 = np.random.default_rng(seed).standard_normal((25, 4))
    ys, us = np.zeros((25, 5, 4)), np.zeros((25, 5, 3))
    for i, x in enumerate(x0):
        for k in range(5):
            us[i, k] = -K @ x
            ys[i, k] = C @ x + D @ us[i, k]
            x = A @ x + B @ us[i, k]
    qsr = zoo_build.controller_supply(zoo_build.bounded_gain_qsr(plant))
    return dj.Windows(x0, ys, us), qsr


def tight(no_units=False):
    """`fit_ren` (width 4, 4 or 8 initialisations, defaults otherwise) on tight gain bounds
    with windows from a state: storages' condition numbers, certified runs, median training
    loss, against `fit_direct` on the same data. `no_units`: the REN map without its input
    units (all 1, the map as it was before them), for comparison."""
    from dissil_jax.internal import ren_map

    if no_units:  # before any call compiles the map
        ren_map.input_units = lambda qsr, margin=None: np.ones(qsr.R.shape[0])
    key = jax.random.PRNGKey(0)
    print("| rate | step, initial scale | input units | cond(P) max | certified | median loss "
          "| fit_direct's |")
    print("|---|---|---:|---:|---:|---:|---:|")
    cases = [(f"gain {g:g}, {p}x{m}", _gain_windows(key, p, m, n),
              dj.QSR.bounded_gain(g, n_out=m, n_in=p), 4)
             for g in (1e-1, 1e-3, 1e-6) for p, m, n in ((1, 1, 2), (3, 4, 3))]
    cases += [(f"4x3 plant {seed}, |Q| = {{:.1e}}", *_plant_windows(seed, radius), 8)
              for seed, radius in ((2, 0.999), (3, 0.999), (4, 0.998))]
    # the gain bounds at the defaults and at fit_ren's earlier defaults (0.3, 0.5)
    runs = [(case, steps, hyper) for case in cases
            for steps in ((600,) if "gain" in case[0] else (600, 2000))
            for hyper in (((None, None), (0.3, 0.5)) if "gain" in case[0] else ((None, None),))]
    for (label, W, qsr, inits), steps, (lr, scale) in runs:
        units = ren_map.input_units(qsr)
        r = dj.fit_ren(key, W, qsr, width=4, num_inits=inits, throw=False, max_steps=steps,
                       learning_rate=lr, init_scale=scale)
        d = dj.fit_direct(key, W, qsr, num_inits=inits, throw=False)
        cond = max(np.linalg.cond(P) for P in np.asarray(r.P))
        ok = np.asarray(r.certified)
        hyper = "defaults" if lr is None else f"({lr}, {scale})"
        print(f"| {label.format(abs(qsr.Q[0, 0]))}, {steps} steps | {hyper} | {units.min():g} "
              f"| {cond:.2g} | {ok.sum()}/{ok.size} | {np.median(r.final_loss):.4g} "
              f"| {np.median(d.final_loss):.4g} |", flush=True)


def map_time(spec, inits, steps):
    """Wall time of `steps` compiled evaluations of the REN map and its gradient, batched
    over `inits` initialisations (no loss, no layer: the map's own cost)."""
    width = spec.ren_width
    theta = ren_map.init_ren_params(jax.random.PRNGKey(0), inits, 1, width, 1, 1, 0.5,
                                    jax.numpy.float64)

    def value(t):
        K, P, lam = ren_map.ren_map(t, spec.qsr, width, spec.ren_activation)
        return sum(jax.numpy.sum(M**2) for M in K.matrices) + jax.numpy.sum(P)

    grad = jax.jit(jax.vmap(jax.value_and_grad(value)))
    jax.block_until_ready(grad(theta))
    t = time.perf_counter()
    for _ in range(steps):
        out = grad(theta)
    jax.block_until_ready(out)
    return time.perf_counter() - t


def main(quick=False, inits=100, loop=False, seeds=None, wide_data=False, zoo=None,
         defaults_split=None, data="initial", activation_split=None, tight_bounds=False):
    if activation_split:
        return activations(activation_split)
    if tight_bounds:
        return tight(tight_bounds == "no_units")
    if defaults_split:
        return defaults(defaults_split)
    if zoo:
        return zoo_budget(zoo)
    if wide_data:
        return wide(inits, quick)
    if seeds:
        return across_seeds(seeds, inits, quick, data)
    spec = example_spec("nonlinear", quick)
    inits = min(inits, 8) if quick else inits
    _, _, windows, (k_fit, _, _) = training_data(spec, 0, 0, "initial", 25)
    first = {}
    for method in ("ren", "direct"):  # the first call of each compiles its own program
        t = time.perf_counter()
        fit(method, k_fit, windows, spec, inits)
        first[method] = time.perf_counter() - t
    ren, t_ren = timed(lambda: fit("ren", k_fit, windows, spec, inits))
    lti, t_lti = timed(lambda: fit("direct", k_fit, windows, spec, inits))
    print(f"nonlinear example, 25 initial segments, {inits} initialisations x "
          f"{spec.max_steps} steps, REN width {spec.ren_width} ({spec.ren_activation})")
    print("| method | wall, compiled (s) | ratio to direct | first call, with compilation (s) "
          "| ratio to direct | median train loss | % certified |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, res, t, t1 in (("fit_ren", ren, t_ren, first["ren"]),
                             ("fit_direct", lti, t_lti, first["direct"])):
        print(f"| {name} | {t:.3f} | {t / t_lti:.1f} | {t1:.2f} | {t1 / first['direct']:.2f} "
              f"| {float(np.median(res.final_loss)):.4g} "
              f"| {100 * float(np.mean(np.asarray(res.certified))):.0f} |")
    t_map = map_time(spec, inits, steps=spec.max_steps)
    print(f"\nthe REN map alone (forward and gradient, width {spec.ren_width}, {inits} "
          f"initialisations) for {spec.max_steps} steps: {t_map:.3f} s, "
          f"{t_map / t_lti:.1f}x fit_direct's whole training")
    one = jax.tree.map(lambda a: a[0], ren.controllers)
    sdp = []
    for _ in range(3 if quick else 5):
        t = time.perf_counter()
        cert = dj.certify_ren(one, spec.qsr)
        sdp.append(time.perf_counter() - t)
    step = t_ren / spec.max_steps
    print(f"\none certificate SDP (cvxpy + Clarabel, width {spec.ren_width}): "
          f"{1e3 * np.median(sdp):.1f} ms (holds: {cert.holds}); one direct-map training step "
          f"for all {inits} initialisations: {1e3 * step:.2f} ms; a projection per step and "
          f"initialisation would cost >= {np.median(sdp) * inits / step:.0f}x the direct "
          "map's step")
    if loop:
        print("\n| method | certified | % stable | median test MSE | train s / controller |")
        print("|---|---|---:|---:|---:|")
        for method in METHODS:
            rec = run_config("nonlinear", "initial", method, 25, inits=inits, quick=quick)
            print(f"| {method} | {rec['certified']} | {rec['percent_stable']:.0f} "
                  f"| {rec['mse_median']:.4g} | {rec['train_time_s']:.2f} |", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes")
    parser.add_argument("--inits", type=int, default=100)
    parser.add_argument("--loop", action="store_true", help="closed-loop comparison too")
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")],
                        help="closed-loop comparison per seed, e.g. 0,3,4,5,6 (no timing)")
    parser.add_argument("--wide", action="store_true",
                        help="train on windows drawn like the test states (no timing)")
    parser.add_argument("--zoo", choices=("tuning", "held_out"),
                        help="fit_ren's step budget on one half of the problem zoo")
    parser.add_argument("--defaults", choices=("tuning", "held_out"),
                        help="fit_ren's default Adam step and initial scale on one half of the "
                             "problem zoo")
    parser.add_argument("--data", choices=("initial", "sliding"), default="initial",
                        help="the demonstrations of --seeds: 25 initial segments or sliding "
                             "windows")
    parser.add_argument("--activations", choices=("tuning", "held_out"),
                        help="fit_ren's default activation (tanh against ReLU) on one half of "
                             "the problem zoo")
    parser.add_argument("--tight", action="store_true",
                        help="tight gain bounds: storages' conditioning and certified runs")
    parser.add_argument("--no-units", action="store_true",
                        help="with --tight: the REN map without its input units")
    args = parser.parse_args()
    main(args.quick, args.inits, args.loop, args.seeds, args.wide, args.zoo, args.defaults,
         args.data, args.activations, "no_units" if args.tight and args.no_units else args.tight)
