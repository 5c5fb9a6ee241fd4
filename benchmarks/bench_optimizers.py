"""Which optimiser should PGD use by default? Loss reached and time, on four problems.

Problems (all with the library's unit normalisation, so step sizes are unit-free):
- **realisable**: a random passive order-2 expert (m = p = 2), 40 noiseless 2-step windows;
- **noisy**: the same expert with N(0, 0.3²) noise on the demonstrated inputs;
- **linear**: the paper's linear example, first plant, 25 initial segments;
- **nonlinear**: the paper's nonlinear example, 25 initial segments.

Candidates: the paper's decaying-step rule (`learning_rate` η0, decay 0.99) at several η0,
`optax.adam` at several rates, and ICO (no step size). Each runs 8 initialisations for
150 steps with `atol=0`. Reported per problem: the median over initialisations of the final
loss over the initial loss, after all 150 steps and where the run would have stopped with
`fit_pgd`'s default `atol` (the same iterates, cut at the first step whose loss changed by
less than `tol`), the median number of steps to reach 1 % of the initial loss (— if the
median run never does), and the wall time per run. A default is used with the default
`tol`, so it is judged there: a candidate's regret on a problem is its median final/initial
ratio at the default `tol` over the best candidate's; among the candidates whose
worst-case regret is within 2x of the smallest, the default is the fastest (least total
wall time). Ratios are what to read; the machine is shared and noisy.

Usage: python benchmarks/bench_optimizers.py [--quick]
"""

import argparse
import inspect
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import realisable_windows  # noqa: E402
from dissil_jax.experiments.protocol import example_spec, training_data  # noqa: E402


def problems():
    passive = dj.QSR.passive(2)
    out = {}
    for name, noise in (("realisable", 0.0), ("noisy", 0.3)):
        w, _ = realisable_windows(jr.PRNGKey(0), passive, n_state=2, num_windows=40, noise=noise)
        out[name] = (w, passive)
    for example in ("linear", "nonlinear"):
        spec = example_spec(example)
        _, _, w, _ = training_data(spec, 0, 0, "initial", 25)
        out[example] = (w, spec.qsr)
    return out


def candidates(quick):
    rates = (0.3, 1.0) if quick else (0.1, 0.3, 1.0, 3.0)
    adams = (0.03,) if quick else (0.01, 0.03, 0.1)
    out = {f"paper rule η0={lr:g}": dict(learning_rate=lr) for lr in rates}
    out.update({f"adam({lr:g})": dict(optimizer=optax.adam(lr)) for lr in adams})
    out["ICO"] = None
    return out


DEFAULT_TOL = inspect.signature(dj.fit_pgd).parameters["atol"].default


def run(name, kw, windows, qsr, steps, inits):
    key = jr.PRNGKey(1)
    t0 = time.perf_counter()
    if kw is None:
        if windows.horizon != 2:
            return None
        res = dj.fit_ico(key, windows, qsr, num_inits=inits, max_steps=steps, atol=0.0, rtol=0.0,
                         throw=False)
    else:
        res = dj.fit_pgd(key, windows, qsr, num_inits=inits, max_steps=steps, atol=0.0, rtol=0.0,
                         throw=False, **kw)
    wall = (time.perf_counter() - t0) / inits
    hist = np.asarray(res.loss_history)
    ratio = hist / hist[:, :1]
    below = np.where(np.nan_to_num(ratio, nan=np.inf) <= 0.01, np.arange(hist.shape[1]),
                     np.iinfo(np.int64).max).min(axis=1)
    med_steps = np.median(below)
    final = np.asarray(res.final_loss) / hist[:, 0]
    assert bool(np.all(res.certified)), f"{name}: a controller is not certified"
    CURVES[name] = np.nanmedian(np.fmin.accumulate(np.nan_to_num(ratio, nan=np.inf), axis=1),
                                axis=0)
    return float(np.median(final)), med_steps, wall, float(np.median(stopped(hist)))


def stopped(hist, tol=DEFAULT_TOL):
    """Final/initial loss of each run had it stopped at the default `tol`: the same iterates
    up to the first step whose loss changed by less than `tol` (user units)."""
    out = []
    for row in hist:
        row = row[~np.isnan(row)]
        small = np.nonzero(np.abs(np.diff(row)) < tol)[0]
        out.append(row[small[0] + 1 if len(small) else -1] / row[0])
    return np.array(out)


CURVES = {}


def plot(curves, path):
    """Median (over initialisations) of the best loss so far / initial loss, per problem."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    probs = list(dict.fromkeys(p for p, _ in curves))
    fig, axes = plt.subplots(1, len(probs), figsize=(4 * len(probs), 3.4), sharey=True)
    for ax, p in zip(np.atleast_1d(axes), probs):
        for (pp, c), y in curves.items():
            if pp == p:
                ax.semilogy(y, label=c, lw=2.0 if c == "ICO" else 1.2)
        ax.set_title(p)
        ax.set_xlabel("step")
        ax.axhline(0.01, color="k", lw=0.5, ls=":")
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("loss / initial loss (median)")
    np.atleast_1d(axes)[-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(quick=False):
    steps, inits = (40, 4) if quick else (150, 8)
    probs, cands = problems(), candidates(quick)
    table, curves = {}, {}
    for pname, (w, qsr) in probs.items():
        for cname, kw in cands.items():
            run(cname, kw, w, qsr, 2, 2)  # compile
            table[pname, cname] = run(cname, kw, w, qsr, steps, inits)
            curves[pname, cname] = CURVES[cname]
            print(pname, cname, table[pname, cname], flush=True)
    names = [c for c in cands if c != "ICO"]
    ratios = np.array([[table[p, c][3] for c in names] for p in probs])
    regret = ratios / ratios.min(axis=1, keepdims=True)
    worst = regret.max(axis=0)
    near = [c for c, r in zip(names, worst) if r <= 2 * worst.min()]
    best = min(near, key=lambda c: sum(table[p, c][2] for p in probs))
    print(f"\n{len(probs)} problems, {inits} initialisations x {steps} steps, atol=0 "
          f"(and stopped at the default atol={DEFAULT_TOL:g})\n")
    head = " | ".join(f"{p}: final/initial (tol 0; default tol), steps to 1 %, s/run"
                      for p in probs)
    print(f"| candidate | {head} | worst regret |")
    print("|---|" + "---|" * (len(probs) + 1))
    for c in cands:
        cells = []
        for p in probs:
            r = table[p, c]
            if r is None:
                cells.append("n/a")
                continue
            st = "—" if r[1] > steps else f"{r[1]:.0f}"
            cells.append(f"{r[0]:.2e}; {r[3]:.2e}, {st}, {r[2]:.3f}")
        wr = f"{regret[:, names.index(c)].max():.3g}" if c in names else "—"
        mark = " ←" if c == best else ""
        print(f"| {c}{mark} | " + " | ".join(cells) + f" | {wr} |")
    print(f"\nchosen default: {best}")
    if not quick:
        path = os.path.join(os.path.dirname(__file__), "..", "docs", "images", "optimizers.png")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        plot(curves, path)
        print(f"loss curves: {os.path.normpath(path)}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    main(parser.parse_args().quick)
