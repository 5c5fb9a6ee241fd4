"""Command line: reproduce the paper's experiments.

    python -m dissil_jax.experiments {linear,nonlinear} --data initial sliding \
        --segments 2 25 50 --inits 10 --methods pgd gd ico ico_nc mlp --out runs/x [--quick]

Writes `summary.json`, `tables.md` and the figures into `--out`; records already in
`--out/summary.json` are kept (new ones replace those of the same configuration), so
several invocations build up one report. `summary.json` is saved after every finished
configuration: after Ctrl-C (exit code 130) the same command with `--resume` runs the
rest. The records of one example in a report must share `--seed`, `--inits` and `--quick`
(and the library version and dtype, where recorded): a run with other settings is refused
before any training (pick another `--out`). Repeated values of `--data`, `--segments` and
`--methods` run once. `--lr-sweep` tunes PGD and GD only, in one process, so it refuses
`--methods`, `--jobs` and `--resume`.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time


def _parser() -> argparse.ArgumentParser:
    from ._paper import SEGMENTS
    from .data import REGIMES, SEED_LIMIT
    from .protocol import EXAMPLES, METHODS, PAPER_METHODS

    paper_n = "; ".join(f"{e} {' '.join(map(str, SEGMENTS[e]))}" for e in EXAMPLES)
    p = argparse.ArgumentParser(prog="python -m dissil_jax.experiments",
                                description="Reproduce the paper's tables and figures.")
    p.add_argument("example", choices=EXAMPLES,
                   help="the paper's example: linear (ten mass-spring-damper chains, "
                        "passive controllers) or nonlinear (the scalar plant x+ = 0.5x + "
                        "0.4 sin x + u, a conic controller rate); every option below "
                        "applies to either")
    p.add_argument("--data", nargs="+", choices=REGIMES, default=["initial"],
                   help="data regime(s): initial segments and/or sliding window (default: "
                        "initial only, the paper's Tables 2 and 4; add sliding for its "
                        "Tables 3 and 5)")
    p.add_argument("--segments", nargs="+", type=int, default=None,
                   help=f"numbers of training segments N (default: the paper's, {paper_n}; "
                        "25 with --lr-sweep)")
    p.add_argument("--inits", type=int, default=None,
                   help="random initialisations per plant (default: 10 linear, 100 nonlinear; "
                        "10 with --quick or --lr-sweep)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=None,
                   help=f"default: the paper's methods ({' '.join(PAPER_METHODS)}); `direct` "
                        "(dj.fit_direct) and `ren` (dj.fit_ren, certified REN controllers) "
                        "are ours; not with --lr-sweep")
    p.add_argument("--out", default="runs/latest",
                   help="output directory, a non-empty path (default: %(default)s); records of its "
                        "summary.json are kept, and must have the same --seed, --inits and "
                        "--quick for the same example")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed of the linear example's plants, the training data, the "
                        f"initialisations and the test states, from 0 to {SEED_LIMIT - 1} "
                        "(default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="small sizes (at most 2 plants, 50 test states, 30 training steps "
                        "for every method, 10 initialisations unless --inits)")
    p.add_argument("--jobs", type=int, default=1,
                   help="worker processes sharing the configurations (each gets cores/jobs "
                        "solver threads); the records do not depend on it, except the "
                        "training times, which include compilation (each worker compiles "
                        "anew); not with --lr-sweep (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="skip the configurations whose records are already in --out's "
                        "summary.json (after an interrupted run); without it they run again "
                        "and replace their records")
    p.add_argument("--lr-sweep", nargs="+", type=float, default=None, metavar="LR",
                   help="instead of the experiments, sweep PGD's and GD's learning rate over "
                        "these values on training loss in every --data x --segments "
                        "configuration (default N = 25; --inits per plant, default 10; at "
                        "most 2 plants), choose the rate with the smallest worst-case regret "
                        "and write lr_sweep_EXAMPLE.{md,json}; always PGD and GD in one "
                        "process, so --methods, --jobs and --resume are refused with it")
    return p


def main(argv=None) -> int:
    import shlex

    args = _parser().parse_args(argv)
    args.command = "python -m dissil_jax.experiments " + shlex.join(
        sys.argv[1:] if argv is None else list(argv))
    import jax

    from .protocol import FLOAT64_MESSAGE

    if not jax.config.read("jax_enable_x64"):
        # The experiments run in float64. `jax.enable_x64` is thread-local and does not reach
        # the host-callback threads, and the library never flips global config, so a
        # command-line run re-executes itself with JAX_ENABLE_X64=1 set before jax loads.
        if argv is not None:
            raise ValueError(FLOAT64_MESSAGE)
        env = dict(os.environ, JAX_ENABLE_X64="1", OPENBLAS_NUM_THREADS="1")
        os.execve(sys.executable, [sys.executable, "-m", "dissil_jax.experiments",
                                   *sys.argv[1:]], env)
    return _run(args)


def _sweep(args) -> int:
    import pathlib

    from .protocol import example_spec, provenance
    from .report import write_json
    from .tuning import learning_rate_sweep, sweep_markdown

    spec = example_spec(args.example, args.quick)
    configs = [(m, data, n) for m in ("pgd", "gd") for data in _unique(args.data)
               for n in (_unique(args.segments) or [25])]
    inits, plants, start = args.inits or 10, min(spec.num_plants, 2), time.perf_counter()
    sweeps = []
    for k, (m, data, n) in enumerate(configs):
        print(f"lr-sweep {args.example} {k + 1}/{len(configs)}: {m.upper()} {data} N={n} "
              f"({time.perf_counter() - start:.0f} s)", file=sys.stderr, flush=True)
        sweeps.append(dict(learning_rate_sweep(
            args.example, m, _unique(args.lr_sweep), segments=n, data=data, inits=inits,
            plants=plants, seed=args.seed, spec=spec), quick=bool(args.quick),
            command=args.command))
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    text = sweep_markdown(sweeps)
    made = provenance(sweeps[0]["dtype"])
    settings = (f"Seed {args.seed}; {inits} initialisations per plant, at most {plants} "
                f"plant(s); at most {spec.max_steps} steps, decay {spec.pgd_decay:g} per "
                f"step, stopping tolerance {spec.tol:g}; "
                f"{'--quick' if args.quick else 'not --quick'}; dissil_jax "
                f"{made['dissil_jax_version']}, jax {made['jax_version']}, {made['dtype']}.")
    (out / f"lr_sweep_{args.example}.md").write_text(
        f"# Step-size sweep: the {args.example} example\n\n{settings}\n\n{text}")
    write_json(out / f"lr_sweep_{args.example}.json", sweeps)
    print(text)
    return 0


def _argument_error(args) -> str | None:
    """What is wrong with the arguments argparse accepted, before any training starts."""
    import math
    import pathlib

    from .data import SEED_LIMIT

    if args.segments is not None and any(s < 1 for s in args.segments):
        return "--segments must be positive integers"
    if args.inits is not None and args.inits < 1:
        return f"--inits must be a positive integer, got {args.inits}"
    if not 0 <= args.seed < SEED_LIMIT:
        return f"--seed must be an integer from 0 to {SEED_LIMIT - 1}, got {args.seed}"
    if args.jobs < 1:
        return "--jobs must be a positive integer"
    if args.lr_sweep is not None and not all(math.isfinite(v) and v > 0
                                             for v in args.lr_sweep):
        return f"--lr-sweep takes positive learning rates, got {args.lr_sweep}"
    if args.lr_sweep is not None:
        for option, given in (("--methods", args.methods is not None),
                              ("--jobs", args.jobs != 1), ("--resume", args.resume)):
            if given:
                return (f"{option} does not apply to --lr-sweep, which always tunes PGD and "
                        "GD, in one process")
    if not args.out:
        return "--out must not be empty (use --out . for the current directory)"
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        return f"--out {args.out!r} is a file, not a directory"
    try:  # now, not after hours of training
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return f"--out {args.out!r} cannot be created: {err.strerror or err}"
    if not os.access(out, os.W_OK):
        return f"--out {args.out!r} is not writable"
    return None if args.lr_sweep is not None else _report_error(args)


def _planned(args) -> list[dict]:
    """The key, settings and provenance of the records this run would write."""
    from .. import __version__

    settings = dict(example=args.example, seed=args.seed, inits=_inits(args),
                    quick=bool(args.quick), dissil_jax_version=__version__, dtype="float64")
    return [dict(settings, data=d, method=m, segments=s) for d, m, s in _configs(args)]


def _report_error(args) -> str | None:
    """What keeps this run's records from joining the report in `--out`, if anything."""
    from .report import load_records, merge_records

    try:
        old = load_records(args.out)
    except ValueError as err:
        return f"--out {args.out!r}: {err}; move the file away or pick another --out"
    planned = _planned(args)
    try:
        merge_records(old, planned)
    except ValueError as err:
        version = planned[0]["dissil_jax_version"]
        other = any(r.get("dissil_jax_version") not in (None, version) for r in old
                    if r["example"] == args.example)
        return (f"--out {args.out!r}: {err}; pick another --out"
                + ("" if other else ", or the same --seed, --inits and --quick"))
    return None


def _unique(values) -> list:
    """`values` without repeats, in their order (empty for None)."""
    return list(dict.fromkeys(values or ()))


def _inits(args) -> int:
    """`--inits`, else the paper's 10 per plant (linear) or 100 (nonlinear); 10 with
    `--quick`."""
    return args.inits or (10 if args.example == "linear" or args.quick else 100)


def _configs(args) -> list[tuple]:
    """The (data, method, segments) configurations of a run, each once."""
    from ._paper import SEGMENTS
    from .protocol import PAPER_METHODS

    segments = _unique(args.segments) or list(SEGMENTS[args.example])
    methods = _unique(args.methods) or list(PAPER_METHODS)
    return [(d, m, s) for d in _unique(args.data) for m in methods for s in segments]


def _run(args) -> int:
    error = _argument_error(args)
    if error is not None:
        print(f"error: {error}", file=sys.stderr)
        return 2
    # what a Ctrl-C leaves behind, kept up to date by the run
    args.saved = "nothing was written (a sweep writes its files at the end)"
    try:
        return _sweep(args) if args.lr_sweep else _experiments(args)
    except KeyboardInterrupt:
        print(f"\ninterrupted: {args.saved}", file=sys.stderr)
        return 130


def _experiments(args) -> int:
    import pathlib

    from tqdm import tqdm

    from . import _jobs
    from .protocol import METHOD_LABELS, run_config
    from .report import certified_cell, load_records, merge_records, write_json, write_report

    configs, old, summary = _configs(args), load_records(args.out), pathlib.Path(args.out)
    summary = summary / "summary.json"
    have = {(r["example"], r["data"], r["method"], r["segments"]) for r in old}
    todo = [c for c in configs if not (args.resume and (args.example, *c) in have)]
    if len(todo) < len(configs):
        print(f"--resume: {len(configs) - len(todo)} of {len(configs)} configurations are in "
              f"{summary} already", file=sys.stderr)
    missing = sum(r.get("dissil_jax_version") is None for r in old)
    if missing:
        print(f"note: {missing} record(s) in {summary} do not say which library version "
              "wrote them (written before records stated it); they are kept", file=sys.stderr)
    start, finished = time.perf_counter(), {}

    def on_record(i: int, record: dict) -> None:
        finished[i] = dict(record, command=args.command)
        write_json(summary, merge_records(old, list(finished.values())))
        args.saved = (f"{len(finished)} of {len(todo)} configurations finished and saved in "
                      f"{summary}; the same command with --resume runs the other "
                      f"{len(todo) - len(finished)}")

    args.saved = f"none of the {len(todo)} configurations finished; nothing was saved"
    run = functools.partial(run_config, args.example, inits=_inits(args), seed=args.seed,
                            quick=args.quick)
    bar = tqdm(total=len(todo), desc=f"{args.example}", unit="config", file=sys.stderr)
    try:
        if args.jobs == 1 or not todo:
            _jobs.in_process(run, todo, bar, on_record)
        else:
            _jobs.in_workers(run, todo, args.jobs, bar, on_record)
    finally:
        bar.close()
    args.saved = (f"all {len(todo)} configurations finished and saved in {summary}; the "
                  "same command with --resume writes the tables and figures")
    all_records = merge_records(old, list(finished.values()))
    tables, figures = write_report(all_records, args.out)
    by_key = {(r["data"], r["method"], r["segments"]): r for r in all_records
              if r["example"] == args.example}
    records = [by_key[c] for c in configs]
    print(f"\n{args.example}: {len(todo)} configurations in "
          f"{time.perf_counter() - start:.0f} s\n")
    width = max(7, *(len(METHOD_LABELS[r["method"]]) for r in records))
    print(f"{'data':8s} {'method':{width}s} {'N':>4s} {'% stable':>9s} {'% ΔJ':>8s} "
          f"{'s/ctrl':>8s} {'MSE median':>11s} {'MSE max':>10s} {'certified':>9s}")
    for r in records:
        cert = certified_cell(r)
        print(f"{r['data']:8s} {METHOD_LABELS[r['method']]:{width}s} {r['segments']:4d} "
              f"{r['percent_stable']:9.0f} {r['percent_change_cost']:8.2f} "
              f"{r['train_time_s']:8.3g} {r['mse_median']:11.4g} {r['mse_max']:10.4g} "
              f"{cert:>9s}")
    print("(% ΔJ: mean change of the training loss; s/ctrl: training seconds per "
          "controller, compilation included)")
    print(f"\ntables: {tables}")
    for f in figures:
        print(f"figure: {f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
