"""Defaults measured on the problem zoo (`dissil_jax.experiments.zoo`).

Parts (`--part`):

- `stop`: every trainer with its defaults on the zoo's TUNING half, without early stop
  (`atol=0`) for its default step budget. From the loss histories, offline, the step at which
  the relative rule $|J_k - J_{k-1}| \\le \\text{rtol}\\,|J_0|$ would stop each run, for
  candidate `rtol`s, and the loss there against the full budget's. Writes
  `benchmarks/results/defaults_stop.json` and prints a markdown table.
- `regret`: per trainer a small grid of step rules and initial scales (`GRID`, the first
  entry the defaults) on both halves, without early stop; the defaults' median final loss
  and held-out imitation error against the best of the grid, per problem (the regret).
  Writes `benchmarks/results/defaults_regret.json` and `.md`.
- `report`: every trainer with its true defaults (its relative stopping rule, its returned
  iterate) and 8 initialisations on the HELD-OUT half, against the best of the grid above
  (run there without early stop): the regret, diverged runs, certified and stable shares.
  Writes `benchmarks/results/defaults_report.json` and `.md`. With `--half tuning` (and
  optionally a candidate `--init-scale`), the same on the tuning half, to
  `defaults_report_tuning.json`: where candidate defaults are compared.
- `gd-budget`: `fit_gd` with its defaults but for the step budget and stopping `rtol`
  (`GD_BUDGETS`), 8 initialisations, on one half (`--half`): per problem the median and
  worst final/initial loss, the median held-out imitation error, the stable share and the
  median steps. Writes `benchmarks/results/defaults_gd_budget_<half>.md`.
- `gd`: `fit_gd`'s step rules (the paper's at PGD's default and Adam at three rates) on both
  halves: diverged runs and the median final/initial loss.

Run: `OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_defaults.py --part stop`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _zoo_runs import TRAINERS, applies, run_defaults, run_full, stop_steps  # noqa: E402

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import zoo  # noqa: E402

RESULTS = Path(__file__).parent / "results"
#: The grid entry that is each trainer's default (step rule and initial scale).
DEFAULT = {"pgd": "adam 0.1, init 0.3", "gd": "adam 0.1, init 0.3", "direct": "default",
           "ico": "default", "mlp": "default (1e-3)"}
RTOLS = (1e-2, 1e-3, 1e-4, 1e-5, 3e-6, 1e-6, 1e-7, 1e-8, 1e-9)
#: Each trainer's default `max_steps`, so that the stop table and the grid measure against
#: the budget a default run has.
BUDGET = {"pgd": 150, "gd": 150, "direct": 600, "ico": 150, "mlp": 2000}
NUM_INITS = 4


def part_stop(trainers, names):
    out = {}
    path = RESULTS / "defaults_stop.json"
    if path.exists():
        out = json.loads(path.read_text())
    for trainer in trainers:
        for name in names:
            p = zoo.problem(name)
            if not applies(trainer, p) or f"{trainer}/{name}" in out:
                continue
            t = time.perf_counter()
            res, rep = run_full(trainer, p, num_inits=NUM_INITS, max_steps=BUDGET[trainer])
            hist = np.asarray(res.loss_history, np.float64)
            out[f"{trainer}/{name}"] = dict(
                hist=[[float(v) for v in h] for h in hist],
                test_error=[float(v) for v in rep.imitation_error],
                certified=None if res.certified is None else [bool(v) for v in rep.certified],
                stable=[bool(v) for v in rep.stable],
                reasons=res.result_names(), wall=time.perf_counter() - t)
            print(f"{trainer:7s} {name:18s} {time.perf_counter() - t:7.1f} s", flush=True)
            path.write_text(json.dumps(out))
    return out


def stop_table(out) -> str:
    """Per trainer and rtol: worst and median (over problems) of the median (over runs) loss
    at the stop relative to the full budget's, and the median fraction of steps used."""
    lines = ["| trainer | rtol | median J_stop / J_budget | worst problem | steps used |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for trainer in TRAINERS:
        keys = [k for k in out if k.startswith(trainer + "/")]
        if not keys:
            continue
        for rtol in RTOLS:
            ratios, used = [], []
            for k in keys:
                hist = np.asarray(out[k]["hist"], np.float64)
                s = stop_steps(hist, rtol)
                fin = np.array([h[np.isfinite(h)][-1] for h in hist])
                at = hist[np.arange(len(s)), s]
                ratios.append(float(np.median(at / fin)))
                used.append(float(np.median(s / (hist.shape[1] - 1))))
            lines.append(f"| {trainer} | {rtol:g} | {np.median(ratios):.3f} | "
                         f"{np.max(ratios):.3f} | {np.median(used):.0%} |")
    return "\n".join(lines)


def _r1(p) -> float:
    return min(1.0, p.n_state ** -0.5)


def _r2(p) -> float:
    return min(1.0, (p.n_state * max(1, p.facts.horizon - 1)) ** -0.5)


def _grid():
    from dissil_jax.internal import default_hyperparameters

    def direct(factor):
        # fit_direct's default step scales with the width n + p; a factor on it
        def kw(p):
            lr, _ = default_hyperparameters(p.n_state, p.facts.n_out)
            return dict(learning_rate=factor * lr)
        return kw

    const = lambda **k: (lambda p: k)
    return {
        # first entry: the defaults (fit_gd's init_scale 0.3 was chosen on the tuning half)
        "gd": {"adam 0.1, init 0.3": const(init_scale=0.3),
               "adam 0.1, init 1": const(init_scale=1.0),
               "adam 0.03": const(optimizer=optax.adam(0.03), init_scale=1.0),
               "adam 0.3": const(optimizer=optax.adam(0.3), init_scale=1.0)},
        "direct": {"default": const(), "lr x0.3": direct(0.3), "lr x3": direct(3.0)},
        "mlp": {"default (1e-3)": const(), "lr 1e-2": const(learning_rate=1e-2),
                "lr 3e-3": const(learning_rate=3e-3)},
        "pgd": {"default": const(), "init 0.3": const(init_scale=0.3),
                "adam 0.1": const(optimizer=optax.adam(0.1)),
                # candidate defaults: Adam (fit_gd's) and initial scales that follow the
                # order n and window length h: r1 = min(1, 1/sqrt(n)), r2 = min(1,
                # 1/sqrt(n (h - 1)))
                "adam 0.1, init 0.3": const(optimizer=optax.adam(0.1), init_scale=0.3),
                "adam 0.1, init r1": lambda p: dict(optimizer=optax.adam(0.1),
                                                    init_scale=_r1(p)),
                "adam 0.1, init r2": lambda p: dict(optimizer=optax.adam(0.1),
                                                    init_scale=_r2(p)),
                "init r1": lambda p: dict(init_scale=_r1(p)),
                "init r2": lambda p: dict(init_scale=_r2(p))},
        "ico": {"default": const(), "init 0.3": const(init_scale=0.3),
                "init 1 (the paper's)": const(init_scale=1.0)},
    }


def _regret_path(half: str) -> Path:
    return RESULTS / ("defaults_regret.json" if half == "held_out"
                      else f"defaults_regret_{half}.json")


def load_regret() -> dict:
    out = {}
    for half in ("tuning", "held_out"):
        if _regret_path(half).exists():
            out.update(json.loads(_regret_path(half).read_text()))
    return out


def part_regret(trainers, names, half):
    path = _regret_path(half)
    out = json.loads(path.read_text()) if path.exists() else {}
    grid = _grid()
    for trainer in trainers:
        for name in names:
            p = zoo.problem(name)
            if not applies(trainer, p):
                continue
            for label, kw in grid[trainer].items():
                key = f"{trainer}/{name}/{label}"
                if key in out:
                    continue
                t = time.perf_counter()
                res, rep = run_full(trainer, p, num_inits=NUM_INITS,
                                    max_steps=BUDGET[trainer], **kw(p))
                out[key] = dict(
                    final=[float(v) for v in np.asarray(res.final_loss)],
                    test_error=[float(v) for v in rep.imitation_error],
                    certified=None if res.certified is None else
                    [bool(v) for v in rep.certified],
                    stable=[bool(v) for v in rep.stable], reasons=res.result_names(),
                    wall=time.perf_counter() - t)
                print(f"{key:50s} {time.perf_counter() - t:7.1f} s", flush=True)
                path.write_text(json.dumps(out))
    return out


def regret_table(out, names) -> str:
    """Per trainer and problem: the defaults' median final loss and median held-out error
    over the best grid entry's (by median final loss), with the defaults' failure counts."""
    lines = ["| trainer | problem | half | loss regret | test-error regret | best of grid | "
             "diverged | certified | stable |", "| --- | --- | --- | ---: | ---: | --- | ---: "
             "| ---: | ---: |"]
    grid = _grid()
    for trainer in TRAINERS:
        for name in names:
            labels = [lab for lab in grid[trainer] if f"{trainer}/{name}/{lab}" in out]
            if DEFAULT[trainer] not in labels:
                continue
            labels.remove(DEFAULT[trainer])
            labels.insert(0, DEFAULT[trainer])
            rows = {lab: out[f"{trainer}/{name}/{lab}"] for lab in labels}
            med = {lab: np.median(r["final"]) for lab, r in rows.items()}
            err = {lab: np.median(r["test_error"]) for lab, r in rows.items()}
            best = min(labels, key=lambda lab: med[lab] if np.isfinite(med[lab]) else np.inf)
            d = rows[labels[0]]
            div = sum(r == "non_finite" for r in d["reasons"])
            cert = "-" if d["certified"] is None else f"{np.mean(d['certified']):.0%}"
            half = "tuning" if name in zoo.TUNING else "held-out"
            lines.append(
                f"| {trainer} | {name} | {half} | {med[labels[0]] / med[best]:.2f} | "
                f"{err[labels[0]] / err[best]:.2f} | {best} | {div}/{len(d['reasons'])} | "
                f"{cert} | {np.mean(d['stable']):.0%} |")
    return "\n".join(lines)


def part_report(trainers, half="held_out", inits=8, **kw):
    """Every trainer with its true defaults (stopping rule, returned iterate) and `inits`
    initialisations on the HELD-OUT half; written to `defaults_report.json`. With
    `half="tuning"`, the same on the tuning half (`defaults_report_tuning.json`), where
    candidate defaults are compared (`kw` go to the trainer)."""
    names = zoo.HELD_OUT if half == "held_out" else zoo.TUNING
    path = RESULTS / ("defaults_report.json" if half == "held_out"
                      else "defaults_report_tuning.json")
    out = json.loads(path.read_text()) if path.exists() else {}
    for trainer in trainers:
        for name in names:
            p = zoo.problem(name)
            key = "/".join([trainer, name] + [f"{k} {v}" for k, v in kw.items()])
            if not applies(trainer, p) or key in out:
                continue
            t = time.perf_counter()
            res, rep = run_defaults(trainer, p, num_inits=inits, **kw)
            out[key] = dict(
                final=[float(v) for v in np.asarray(res.final_loss)],
                test_error=[float(v) for v in rep.imitation_error],
                certified=None if res.certified is None else [bool(v) for v in rep.certified],
                stable=[bool(v) for v in rep.stable], reasons=res.result_names(),
                steps=[int(v) for v in np.asarray(res.steps)], wall=time.perf_counter() - t)
            print(f"{key:40s} {time.perf_counter() - t:7.1f} s", flush=True)
            path.write_text(json.dumps(out))
    return out


def report_table(report, grid_runs) -> str:
    """Per trainer and held-out problem: the defaults' (8 runs, their own stopping rule)
    median final loss and test error over the best grid entry's (4 runs, full budget),
    diverged runs, certified and stable shares, median steps."""
    lines = ["| trainer | problem | loss regret | test-error regret | diverged | certified | "
             "stable | median steps |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    grid = _grid()
    worst = {}
    for trainer in TRAINERS:
        for name in zoo.HELD_OUT:
            d = report.get(f"{trainer}/{name}")
            rows = [grid_runs[k] for k in (f"{trainer}/{name}/{lab}" for lab in grid[trainer])
                    if k in grid_runs]
            if d is None or not rows:
                continue
            best = min(np.median(r["final"]) for r in rows)
            best_err = min(np.median(r["test_error"]) for r in rows)
            reg = float(np.median(d["final"]) / best)  # below 1: the defaults beat the grid
            worst[trainer] = max(worst.get(trainer, 0.0), reg)
            div = sum(r == "non_finite" for r in d["reasons"])
            cert = "-" if d["certified"] is None else f"{np.mean(d['certified']):.0%}"
            lines.append(
                f"| {trainer} | {name} | {reg:.2f} | "
                f"{np.median(d['test_error']) / best_err:.2f} | {div}/{len(d['reasons'])} | "
                f"{cert} | {np.mean(d['stable']):.0%} | {np.median(d['steps']):.0f} |")
    lines.append("")
    lines.append("Worst loss regret per trainer: " + ", ".join(
        f"{t} {v:.2f}" for t, v in worst.items()))
    return "\n".join(lines)


def choice_table(report) -> str:
    """Which trainer wins where: per held-out problem and trainer (defaults, 8 runs) the
    median held-out imitation error (relative to the zero controller's) and the wall time;
    the lowest error among the certified trainers in bold."""
    lines = ["| problem | " + " | ".join(TRAINERS) + " |", "| --- |" + " ---: |" * len(TRAINERS)]
    for name in zoo.HELD_OUT:
        cells, errs = {}, {}
        for t in TRAINERS:
            d = report.get(f"{t}/{name}")
            if d is None:
                cells[t] = "n/a"
                continue
            errs[t] = float(np.median(d["test_error"]))
            cells[t] = f"{errs[t]:.3g} ({d['wall']:.0f} s)"
        cert = {t: e for t, e in errs.items() if t in ("pgd", "direct", "ico")}
        if cert:
            win = min(cert, key=cert.get)
            cells[win] = f"**{cells[win]}**"
        lines.append(f"| {name} | " + " | ".join(cells[t] for t in TRAINERS) + " |")
    return "\n".join(lines)


def part_gd(names):
    rules = {"paper (1, 0.99)": dict(learning_rate=1.0, decay=0.99),
             "adam 0.01": dict(optimizer=optax.adam(0.01)),
             "adam 0.03": dict(optimizer=optax.adam(0.03)),
             "adam 0.1 (default)": {}, "adam 0.3": dict(optimizer=optax.adam(0.3))}
    lines = ["| problem | split | " + " | ".join(rules) + " |",
             "| --- | --- |" + " ---: |" * len(rules)]
    for name in names:
        p = zoo.problem(name)
        cells = []
        for kw in rules.values():
            res = dj.fit_gd(jr.PRNGKey(0), p.train, n_state=p.n_state, num_inits=8,
                            max_steps=150, atol=0.0, rtol=0.0, throw=False, **kw)
            bad = int(sum(r == "non_finite" for r in res.result_names()))
            ratio = np.asarray(res.final_loss) / np.asarray(res.initial_loss)
            cells.append(f"{bad}/8 diverged" if bad else f"{np.median(ratio):.2e}")
        lines.append(f"| {name} | {p.split} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return "\n".join(lines)


#: `fit_gd`'s candidate (max_steps, rtol): the old default first.
GD_BUDGETS = ((150, 1e-7), (300, 1e-7), (600, 1e-7), (600, 1e-8))


def part_gd_budget(names):
    head = [f"{n} steps, rtol {r:g}" for n, r in GD_BUDGETS]
    lines = ["median (worst) final/initial; median imitation error; stable; median steps", "",
             "| problem | split | " + " | ".join(head) + " |",
             "| --- | --- |" + " ---: |" * len(head)]
    for name in names:
        p = zoo.problem(name)
        cells = []
        for steps, rtol in GD_BUDGETS:
            res, rep = run_defaults("gd", p, num_inits=8, max_steps=steps, rtol=rtol)
            ratio = np.asarray(res.final_loss) / np.asarray(res.initial_loss)
            cells.append(f"{np.median(ratio):.3g} ({np.max(ratio):.3g}); "
                         f"{np.median(rep.imitation_error):.3g}; {np.mean(rep.stable):.0%}; "
                         f"{np.median(np.asarray(res.steps)):.0f}")
        lines.append(f"| {name} | {p.split} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=("stop", "gd", "gd-budget", "regret", "report"), required=True)
    ap.add_argument("--half", choices=("tuning", "held_out", "both"), default="both")
    ap.add_argument("--trainers", default=",".join(TRAINERS))
    ap.add_argument("--init-scale", type=float, default=None,
                    help="with `--part report --half tuning`: a candidate initial scale")
    args = ap.parse_args()
    RESULTS.mkdir(exist_ok=True)
    if args.part == "stop":
        out = part_stop(args.trainers.split(","), zoo.TUNING)
        table = stop_table(out)
        (RESULTS / "defaults_stop.md").write_text(table + "\n")
    elif args.part == "regret":
        names = {"tuning": zoo.TUNING, "held_out": zoo.HELD_OUT,
                 "both": zoo.TUNING + zoo.HELD_OUT}[args.half]
        part_regret(args.trainers.split(","), names, args.half)
        table = regret_table(load_regret(), zoo.TUNING + zoo.HELD_OUT)
        (RESULTS / "defaults_regret.md").write_text(table + "\n")
    elif args.part == "report" and args.half == "tuning":
        kw = {} if args.init_scale is None else dict(init_scale=args.init_scale)
        report = part_report(args.trainers.split(","), "tuning", **kw)
        table = json.dumps({k: v["reasons"] for k, v in report.items()}, indent=1)
    elif args.part == "report":
        report = part_report(args.trainers.split(","))
        table = report_table(report, load_regret()) + "\n\n" + choice_table(report)
        (RESULTS / "defaults_report.md").write_text(table + "\n")
    elif args.part == "gd-budget":
        names = {"tuning": zoo.TUNING, "held_out": zoo.HELD_OUT,
                 "both": zoo.TUNING + zoo.HELD_OUT}[args.half]
        table = part_gd_budget(list(names))
        (RESULTS / f"defaults_gd_budget_{args.half}.md").write_text(table + "\n")
    else:
        table = part_gd(list(zoo.TUNING) + list(zoo.HELD_OUT))
        (RESULTS / "defaults_gd.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
