"""Command line: reproduce the paper's experiments.

    python -m dissil_jax.experiments {linear,nonlinear} --data initial sliding \
        --segments 2 25 50 --inits 10 --methods pgd gd ico ico_nc mlp --out runs/x [--quick]

Writes `summary.json`, `tables.md` and the figures into `--out`; records already in
`--out/summary.json` are kept (new ones replace those of the same configuration), so
several invocations build up one report. The records of one example in a report must
share `--seed`, `--inits` and `--quick`: a run with other settings is refused before any
training (pick another `--out`). Repeated values of `--data`, `--segments` and `--methods`
run once. `--lr-sweep` tunes PGD and GD only, so it refuses `--methods`.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time


def _parser() -> argparse.ArgumentParser:
    from .data import REGIMES
    from .protocol import EXAMPLES, METHODS, PAPER_METHODS

    p = argparse.ArgumentParser(prog="python -m dissil_jax.experiments",
                                description="Reproduce the paper's tables and figures.")
    p.add_argument("example", choices=EXAMPLES)
    p.add_argument("--data", nargs="+", choices=REGIMES, default=["initial"],
                   help="data regime(s): initial segments and/or sliding window")
    p.add_argument("--segments", nargs="+", type=int, default=None,
                   help="numbers of training segments N (default: the paper's)")
    p.add_argument("--inits", type=int, default=None,
                   help="random initialisations per plant (default: 10 linear, 100 nonlinear; "
                        "10 with --quick)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=None,
                   help=f"default: the paper's methods ({' '.join(PAPER_METHODS)}); `direct` "
                        "(dj.fit_direct) and `ren` (dj.fit_ren, certified REN controllers) "
                        "are ours; not with --lr-sweep")
    p.add_argument("--out", default="runs/latest",
                   help="output directory (default: %(default)s); records of its "
                        "summary.json are kept, and must have the same --seed, --inits and "
                        "--quick for the same example")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed of the linear example's plants, the training data, the "
                        "initialisations and the test states (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="small sizes (at most 2 plants, 50 test states, 30 training steps, "
                        "10 initialisations unless --inits)")
    p.add_argument("--jobs", type=int, default=1,
                   help="worker processes sharing the configurations (each gets cores/jobs "
                        "solver threads); the records do not depend on it")
    p.add_argument("--lr-sweep", nargs="+", type=float, default=None, metavar="LR",
                   help="instead of the experiments, sweep PGD's and GD's learning rate over "
                        "these values on training loss in every --data x --segments "
                        "configuration (default N = 25; --inits per plant, at most 2 plants), "
                        "choose the rate with the smallest worst-case regret and write "
                        "lr_sweep_EXAMPLE.{md,json}; always PGD and GD, so --methods is "
                        "refused with it")
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    import jax

    if not jax.config.read("jax_enable_x64"):
        # The experiments run in float64. `jax.enable_x64` is thread-local and does not reach
        # the host-callback threads, and the library never flips global config, so a
        # command-line run re-executes itself with JAX_ENABLE_X64=1 set before jax loads.
        if argv is not None:
            raise ValueError("run the experiments with float64 enabled: set JAX_ENABLE_X64=1 "
                             "before importing jax (or use the command line).")
        env = dict(os.environ, JAX_ENABLE_X64="1", OPENBLAS_NUM_THREADS="1")
        os.execve(sys.executable, [sys.executable, "-m", "dissil_jax.experiments",
                                   *sys.argv[1:]], env)
    return _run(args)


def _sweep(args) -> int:
    import pathlib

    from .protocol import example_spec
    from .report import write_json
    from .tuning import learning_rate_sweep, sweep_markdown

    spec = example_spec(args.example, args.quick)
    sweeps = [learning_rate_sweep(args.example, m, _unique(args.lr_sweep), segments=n,
                                  data=data, inits=args.inits or 10,
                                  plants=min(spec.num_plants, 2), seed=args.seed, spec=spec)
              for m in ("pgd", "gd") for data in _unique(args.data)
              for n in (_unique(args.segments) or [25])]
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    text = sweep_markdown(sweeps)
    (out / f"lr_sweep_{args.example}.md").write_text(
        f"# Step-size sweep: the {args.example} example\n\n{text}")
    write_json(out / f"lr_sweep_{args.example}.json", sweeps)
    print(text)
    return 0


def _argument_error(args) -> str | None:
    """What is wrong with the arguments argparse accepted, before any training starts."""
    import math
    import pathlib

    if args.segments is not None and any(s < 1 for s in args.segments):
        return "--segments must be positive integers"
    if args.inits is not None and args.inits < 1:
        return f"--inits must be a positive integer, got {args.inits}"
    if args.jobs < 1:
        return "--jobs must be a positive integer"
    if args.lr_sweep is not None and not all(math.isfinite(v) and v > 0
                                             for v in args.lr_sweep):
        return f"--lr-sweep takes positive learning rates, got {args.lr_sweep}"
    if args.lr_sweep is not None and args.methods is not None:
        return "--methods does not apply to --lr-sweep, which always tunes PGD and GD"
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


def _report_error(args) -> str | None:
    """What keeps this run's records from joining the report in `--out`, if anything."""
    from .report import load_records, merge_records

    try:
        old = load_records(args.out)
    except ValueError as err:
        return f"--out {args.out!r}: {err}; move the file away or pick another --out"
    settings = dict(example=args.example, seed=args.seed, inits=_inits(args),
                    quick=bool(args.quick))
    planned = [dict(settings, data=d, method=m, segments=s) for d, m, s in _configs(args)]
    try:
        merge_records(old, planned)
    except ValueError as err:
        return (f"--out {args.out!r}: {err}; pick another --out, or the same --seed, "
                "--inits and --quick")
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
    from tqdm import tqdm

    error = _argument_error(args)
    if error is not None:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.lr_sweep:
        return _sweep(args)

    from .protocol import METHOD_LABELS, run_config
    from .report import load_records, merge_records, write_report

    configs = _configs(args)
    start = time.perf_counter()
    run = functools.partial(run_config, args.example, inits=_inits(args), seed=args.seed,
                            quick=args.quick)
    bar = tqdm(total=len(configs), desc=f"{args.example}", unit="config", file=sys.stderr)
    if args.jobs == 1:
        records = []
        for data, method, n in configs:
            bar.set_postfix_str(f"{data} {METHOD_LABELS[method]} N={n}")
            records.append(run(data, method, n))
            bar.update()
    else:
        from ._jobs import in_workers

        records = in_workers(run, configs, args.jobs, bar)
    bar.close()
    all_records = merge_records(load_records(args.out), records)
    tables, figures = write_report(all_records, args.out)
    print(f"\n{args.example}: {len(configs)} configurations in "
          f"{time.perf_counter() - start:.0f} s\n")
    width = max(7, *(len(METHOD_LABELS[r["method"]]) for r in records))
    print(f"{'data':8s} {'method':{width}s} {'N':>4s} {'% stable':>9s} {'% dJ':>8s} "
          f"{'time/ctrl':>10s} {'MSE median':>11s} {'MSE max':>10s}")
    for r in records:
        print(f"{r['data']:8s} {METHOD_LABELS[r['method']]:{width}s} {r['segments']:4d} "
              f"{r['percent_stable']:9.0f} {r['percent_change_cost']:8.2f} "
              f"{r['train_time_s']:10.3g} {r['mse_median']:11.4g} {r['mse_max']:10.4g}")
    print(f"\ntables: {tables}")
    for f in figures:
        print(f"figure: {f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
