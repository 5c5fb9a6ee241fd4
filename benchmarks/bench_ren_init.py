"""`fit_ren(init=...)` started at `fit_direct`'s controllers, on the problem zoo.

For each zoo problem with $Q\\preceq0$ of one half (`--split tuning|held_out`): `fit_direct`
with its defaults (8 initialisations), then `fit_ren` (width 4, its default activation)
started at those 8 controllers with each candidate Adam step, and `fit_ren` from its
random draws with its defaults. Printed per problem, each as a ratio to `fit_direct`'s:

- the median final training loss (a warm start can only lower each run's: `keep="best"`
  keeps the start when no step improves on it);
- the median held-out imitation error (`zoo.evaluate`), and % stable loops.

Then the worst and the geometric mean of each ratio per candidate. The default step with
`init` (`ren_init.WARM_LEARNING_RATE`) is chosen on the tuning half and reported on the
held-out half.

`--gap`: three problems outside the zoo (20 windows of 5 steps from random realisable
experts, `realisable_windows`) where `fit_ren` from random draws fits worse than
`fit_direct` even at width 0: the median final loss of `fit_ren` (width 0, random draws,
defaults) and of `fit_ren` (width 4) started at `fit_direct`'s controllers at each step,
over `fit_direct`'s, with the margin `fit_ren` chose.

`--paper`: the paper's nonlinear example (25 initial segments, 100 initialisations, the
reproduction's data and test loops, seeds 1 and 2 then 0): the experiments' REN (odd,
ReLU, width 16, 150 steps) started at the LTI direct map's controllers of the same run
(`protocol.fit("direct", ...)`) at each step, against the protocol's REN from random
draws: median test MSE and % stable.

`--cost`: the time to map one start back (`ren_inverse.ren_params_of`, a value of the REN
map of each size, bounded gain 2, 2 inputs and outputs) against one `certify_ren` SDP of
the same REN in the same run (the trainers' fallback certificate), BLAS single-threaded.

Usage: python benchmarks/bench_ren_init.py [--split tuning|held_out] [--steps 0.01,0.003]
       [--gap] [--paper] [--cost]
"""

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import zoo  # noqa: E402
from dissil_jax.internal import is_indefinite  # noqa: E402

CANDIDATES = (0.1, 0.03, 0.01, 0.003, 0.001)


def main(split, candidates=CANDIDATES):
    names = [n for n in (zoo.TUNING if split == "tuning" else zoo.HELD_OUT)
             if not is_indefinite(zoo.problem(n).qsr)]
    labels = [f"init, step {lr:g}" for lr in candidates] + ["random draws (defaults)"]
    loss, err = {}, {}
    for name in names:
        problem = zoo.problem(name)
        t = zoo.task(problem)
        order = {} if t.windows.x0 is not None else {"n_state": t.n_state}
        found = {}

        def direct(t):
            found["d"] = dj.fit_direct(t.key, t.windows, t.qsr, throw=False, progress=False,
                                       **order)
            return found["d"]

        base = zoo.evaluate(problem, direct)
        d_loss, d_err = np.median(base.train_loss), np.median(base.imitation_error)
        loss[name], err[name] = [], []
        for lr in (*candidates, None):
            kw = dict(width=4, throw=False, progress=False, **order)
            if lr is not None:
                kw.update(init=found["d"], learning_rate=lr)
            def ren(t):
                found["r"] = dj.fit_ren(t.key, t.windows, t.qsr, **kw)
                return found["r"]

            rep = zoo.evaluate(problem, ren)
            loss[name].append(np.median(rep.train_loss) / d_loss)
            err[name].append(np.median(rep.imitation_error) / d_err)
            if lr is not None:  # per run, never above the start
                assert np.all(rep.train_loss <= base.train_loss * (1 + 1e-6)), name
            stable = 100 * np.mean(rep.stable)
            print(f"{name}: {lr}: loss {loss[name][-1]:.3g} error {err[name][-1]:.3g} "
                  f"stable {stable:.0f} % (direct {100 * np.mean(base.stable):.0f} %), "
                  f"certified {100 * np.mean(rep.certified):.0f} % (`certify_ren`), "
                  f"margin {found['r'].margin:g}",
                  flush=True)
    for title, table in (("median final training loss", loss),
                         ("median held-out imitation error", err)):
        print(f"\nzoo {split}: {title} over fit_direct's")
        print("| problem | " + " | ".join(labels) + " |")
        print("|---|" + "---:|" * len(labels))
        for name, row in table.items():
            print(f"| {name} | " + " | ".join(f"{v:.3g}" for v in row) + " |")
        rows = np.array(list(table.values()))
        print("| **worst** | " + " | ".join(f"{v:.3g}" for v in rows.max(0)) + " |")
        print("| **geometric mean** | " + " | ".join(
            f"{v:.3g}" for v in np.exp(np.log(rows).mean(0))) + " |")


def gap(candidates):
    import jax.random as jr

    from dissil_jax.experiments.data import realisable_windows

    key = jr.PRNGKey(1)
    print("| rate | fit_ren, width 0, random | " + " | ".join(
        f"init, step {lr:g}" for lr in candidates) + " |")
    print("|---|---:|" + "---:|" * len(candidates))
    for name, qsr, n in [("degenerate_conic(0)", dj.QSR.degenerate_conic(0.0, dim=1), 2),
                         ("degenerate_conic(5)", dj.QSR.degenerate_conic(5.0, dim=1), 2),
                         ("bounded_gain(1e3), 1 in, 3 out",
                          dj.QSR.bounded_gain(1e3, n_in=1, n_out=3), 3)]:
        w, _ = realisable_windows(key, qsr, n_state=n, num_windows=20, horizon=5, noise=0.01)
        d = dj.fit_direct(key, w, qsr, progress=False)
        base = np.median(d.final_loss)
        cold = dj.fit_ren(key, w, qsr, width=0, progress=False)
        cells = [f"{np.median(cold.final_loss) / base:.3g}"]
        for lr in candidates:
            r = dj.fit_ren(key, w, qsr, width=4, init=d, learning_rate=lr, progress=False)
            cells.append(f"{np.median(r.final_loss) / base:.3g} (margin {r.margin:g})")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def paper(candidates, seeds=(1, 2, 0)):
    from dissil_jax.experiments.metrics import evaluate
    from dissil_jax.experiments.protocol import (
        controller_start,
        evaluation_setup,
        example_spec,
        fit,
        training_data,
    )

    spec = example_spec("nonlinear", False)
    print("nonlinear example, 25 initial segments, 100 initialisations: median test MSE "
          "(% stable)")
    print("| REN | " + " | ".join(f"seed {s}" for s in seeds) + " |")
    print("|---|" + "---:|" * len(seeds))
    rows = {"random draws (the protocol's)": None,
            **{f"init = direct, step {lr:g}": lr for lr in candidates}}
    for label, lr in rows.items():
        cells = []
        for seed in seeds:
            plant, expert, windows, (k_fit, _, k_noise) = training_data(spec, 0, seed,
                                                                        "initial", 25)
            if lr is None:
                res = fit("ren", k_fit, windows, spec, 100)
            else:
                start = fit("direct", k_fit, windows, spec, 100)
                res = dj.fit_ren(k_fit, windows, spec.qsr, width=spec.ren_width,
                                 activation=spec.ren_activation, learning_rate=lr,
                                 init_scale=spec.ren_init_scale, odd=spec.ren_odd,
                                 init=start, num_inits=100, max_steps=spec.max_steps,
                                 atol=0.0, rtol=0.0, balance=False, throw=False,
                                 progress=False)
            assert bool(np.all(res.certified))
            x0, _, steps = evaluation_setup(spec, 0, seed)
            ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                          xhat0=controller_start(spec, "ren", x0))
            cells.append(f"{np.median(np.asarray(ev.mse)):.4g} "
                         f"({100 * np.mean(np.asarray(ev.stable)):.0f} %)")
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)


def cost(sizes=((2, 4), (8, 8), (20, 16))):
    import time

    import jax.numpy as jnp
    import jax.random as jr

    from dissil_jax.internal import ren_inverse, ren_map

    qsr = dj.QSR.bounded_gain(2.0, n_in=2, n_out=2)
    sizes = (sizes[0], *sizes)  # the first round warms cvxpy and Clarabel up: not printed
    print("| order | width | map back (s) | certify_ren (s) | ratio |")
    print("|---:|---:|---:|---:|---:|")
    for i, (n, q) in enumerate(sizes):
        theta = jax.tree.map(lambda a: a[0], ren_map.init_ren_params(
            jr.PRNGKey(0), 1, n, q, 2, 2, 0.3, jnp.float64))
        K, _, _ = ren_map.ren_map(theta, qsr, q, "tanh")
        mats = tuple(np.asarray(M) for M in K.matrices)
        t = time.perf_counter()
        assert ren_inverse.ren_params_of(mats, qsr, ren_map.MARGIN, False)[1] >= 0
        back = time.perf_counter() - t
        t = time.perf_counter()
        assert dj.certify_ren(K, qsr, progress=False).holds
        sdp = time.perf_counter() - t
        if i:
            print(f"| {n} | {q} | {back:.2f} | {sdp:.2f} | {back / sdp:.2f} |", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=("tuning", "held_out"), default="tuning")
    parser.add_argument("--steps", default=",".join(map(str, CANDIDATES)),
                        help="comma-separated Adam steps to start from `init` with")
    parser.add_argument("--gap", action="store_true",
                        help="the three problems outside the zoo where fit_ren fit worst")
    parser.add_argument("--paper", action="store_true",
                        help="the paper's nonlinear example, started at the direct map's")
    parser.add_argument("--cost", action="store_true",
                        help="the time to map one start back, against one certify_ren SDP")
    args = parser.parse_args()
    steps = tuple(float(v) for v in args.steps.split(","))
    if args.cost:
        cost()
    elif args.paper:
        paper(steps)
    elif args.gap:
        gap(steps)
    else:
        main(args.split, steps)
