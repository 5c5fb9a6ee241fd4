"""The experiments' records: what they say about themselves, what loads, what survives an
interrupted run, and the arguments checked before any work (an audit of the command line)."""

import datetime
import functools
import json
import os
import pathlib
import re
import subprocess
import sys
import time

import jax
import pytest

import dissil_jax as dj
from dissil_jax.experiments import __main__ as cli, zoo
from dissil_jax.experiments.protocol import (
    FLOAT64_MESSAGE,
    example_spec,
    fit,
    hyperparameters,
    run_config,
    training_data,
)
from dissil_jax.experiments.report import REQUIRED_FIELDS, load_records, merge_records
from dissil_jax.experiments.tuning import learning_rate_sweep
from dissil_jax.internal import experiment_jobs

METRICS = dict(percent_stable=100.0, percent_change_cost=-90.0, train_time_s=0.1,
               mse_q1=0.01, mse_median=0.02, mse_q3=0.03, mse_max=0.04)


def _record(method="gd", segments=2, **kw) -> dict:
    base = dict(example="nonlinear", data="initial", method=method, segments=segments,
                inits=2, seed=0, quick=True, plants=1, controllers=2, **METRICS)
    return dict(base, **kw)


def _no_training(monkeypatch):
    monkeypatch.setattr("dissil_jax.experiments.protocol.run_config",
                        lambda *a, **k: pytest.fail("trained despite a bad argument"))


def test_experiments_refuse_float32_with_the_command_lines_message():
    """`run_config` ran silently in float32 (a worst test MSE 27 % off the command line's);
    it, `fit`, the sweep and `main(argv)` now refuse alike."""
    script = """
import dissil_jax.experiments.__main__ as cli
from dissil_jax.experiments import protocol, tuning
spec = protocol.example_spec("nonlinear", quick=True)
calls = [lambda: protocol.run_config("nonlinear", "initial", "pgd", 2, inits=2),
         lambda: protocol.fit("pgd", None, None, spec, 2),
         lambda: tuning.learning_rate_sweep("nonlinear", "gd", [0.1], spec=spec),
         lambda: cli.main(["nonlinear", "--quick"])]
for call in calls:
    try:
        call()
    except ValueError as err:
        print(str(err) == protocol.FLOAT64_MESSAGE)
    else:
        print("ran")
"""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["True"] * 4, proc.stdout
    assert "JAX_ENABLE_X64=1" in FLOAT64_MESSAGE and "float64" in FLOAT64_MESSAGE


def test_record_says_what_produced_it(tmp_path):
    """Records had no version, dtype, date, command or hyperparameters; the training time
    includes compilation, and now says so."""
    plants = []
    rec = run_config("nonlinear", "initial", "gd", 2, inits=2, quick=True,
                     on_plant=lambda i, n: plants.append((i, n)))
    assert plants == [(0, 1)]
    assert rec["dtype"] == "float64"
    assert rec["dissil_jax_version"] == dj.__version__ and rec["jax_version"] == jax.__version__
    assert datetime.datetime.fromisoformat(rec["date"]).tzinfo is not None
    assert rec["command"].startswith("run_config('nonlinear', 'initial', 'gd', 2, inits=2")
    # the version stays 0.1.0 between commits; the commit does not (None when installed)
    root = pathlib.Path(dj.__file__).resolve().parents[1]
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                          text=True)
    if head.returncode == 0 and (root / ".git").exists():
        assert re.fullmatch(head.stdout.strip() + "(-dirty)?", rec["git_commit"])
    else:
        assert rec["git_commit"] is None
    hp = rec["hyperparameters"]
    assert hp == hyperparameters(example_spec("nonlinear", quick=True))
    assert hp["max_steps"] == 30 and hp["mlp_max_steps"] == 30 and hp["tol"] == 1e-5
    assert hp["gd_learning_rate"] == 0.3 and hp["pgd_decay"] == 0.99
    assert hp["hidden"] == [25, 25] and hp["ren_width"] == 16 and hp["num_test"] == 50
    assert hp["qsr"] == {"Q": [[-29.867]], "S": [[3.556]], "R": [[0.601]]}
    assert rec["train_time_includes_compilation"] is True
    assert len(rec["train_time_per_plant_s"]) == rec["plants"] == 1
    assert rec["train_time_s"] == pytest.approx(sum(rec["train_time_per_plant_s"]) / 2)
    assert rec["certified"] is None  # GD is not a certified method
    # it goes through summary.json as it is
    from dissil_jax.experiments.report import write_json

    write_json(tmp_path / "summary.json", [rec])
    assert load_records(tmp_path) == [rec]
    assert not list(tmp_path.glob("*.tmp"))


def test_quick_limits_the_mlp_baseline_too():
    """`--quick` said "30 training steps", but the MLP baseline ran to 289."""
    assert example_spec("nonlinear").mlp_max_steps == 2000  # the full protocol is unchanged
    spec = example_spec("nonlinear", quick=True)
    _, _, windows, (key, _, _) = training_data(spec, 0, 0, "initial", 2)
    res = fit("mlp", key, windows, spec, 2)
    assert int(res.steps.max()) <= 30


@pytest.mark.parametrize("kw, name", [
    (dict(segments=-3), "segments"), (dict(segments=0), "segments"),
    (dict(segments=2.5), "segments"), (dict(inits=0), "inits"), (dict(seed=-1), "seed"),
    (dict(seed=2**32), "seed"), (dict(seed=18446744073709551616), "seed"),
    (dict(seed=1.0), "seed"), (dict(method="sgd"), "method"),
    (dict(example="quadratic"), "example")])
def test_run_config_names_the_bad_argument_before_any_work(kw, name, monkeypatch):
    """`segments=-3` raised an OverflowError, `segments=0` named `num_windows`."""
    monkeypatch.setattr("dissil_jax.experiments.protocol.training_data",
                        lambda *a: pytest.fail("worked despite a bad argument"))
    args = dict(example="nonlinear", data="initial", method="gd", segments=2, inits=2)
    args.update(kw)
    with pytest.raises(ValueError, match=f"`{name}`"):
        run_config(args.pop("example"), args.pop("data"), args.pop("method"),
                   args.pop("segments"), **args)


def test_seeds_and_segments_are_checked_alike_everywhere():
    spec = example_spec("nonlinear", quick=True)
    for seed in (-1, 2**32):
        with pytest.raises(ValueError, match="`seed`"):
            training_data(spec, 0, seed, "initial", 2)
        with pytest.raises(ValueError, match="`seed`"):
            zoo.problem("scalar_static", seed=seed)
        with pytest.raises(ValueError, match="`seed`"):
            learning_rate_sweep("nonlinear", "gd", [0.1], seed=seed, spec=spec)
    with pytest.raises(ValueError, match="`segments`"):
        training_data(spec, 0, 0, "initial", 0)
    with pytest.raises(ValueError, match="`segments`"):
        learning_rate_sweep("nonlinear", "gd", [0.1], segments=-3, spec=spec)


@pytest.mark.parametrize("argv, message", [
    (["--seed", "18446744073709551616"], "--seed must be an integer from 0 to 4294967295"),
    (["--seed", "-1"], "--seed must be an integer from 0 to"),
    (["--out", ""], "--out must not be empty"),
    (["--lr-sweep", "1", "--jobs", "2"], "--jobs does not apply to --lr-sweep"),
    (["--lr-sweep", "1", "--resume"], "--resume does not apply to --lr-sweep")])
def test_cli_refuses_before_any_training(argv, message, tmp_path, capsys, monkeypatch):
    """A huge seed crashed after the progress bar started, `--out ''` wrote into the
    current directory, `--jobs` was silently ignored by `--lr-sweep`."""
    _no_training(monkeypatch)
    monkeypatch.setattr("dissil_jax.experiments.tuning.learning_rate_sweep",
                        lambda *a, **k: pytest.fail("swept despite a bad argument"))
    monkeypatch.chdir(tmp_path)
    out = [] if "--out" in argv else ["--out", str(tmp_path / "out")]
    assert cli.main(["nonlinear", *argv, *out]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and err.count("\n") == 1, err
    assert not list(tmp_path.glob("*.json"))


def test_help_states_the_defaults(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: initial only" in text
    assert "linear 2 25 50 100 200; nonlinear 2 25 50 100; 25 with --lr-sweep" in text
    assert "10 with --quick or --lr-sweep" in text
    assert "except the training times, which include compilation" in text
    assert "30 training steps for every method" in text


@pytest.mark.parametrize("edit, message", [
    (lambda r: r.pop("mse_max"), "lacks the fields mse_max"),
    (lambda r: r.update(method="sgd"), "has method 'sgd', not one of"),
    (lambda r: r.update(data="random"), "has data 'random'"),
    (lambda r: r.update(segments="2"), "has segments '2', not an integer"),
    (lambda r: r.update(percent_stable="high"), "has non-numeric percent_stable")])
def test_load_records_checks_every_field_the_report_reads(edit, message, tmp_path, capsys,
                                                          monkeypatch):
    """A record without its metrics passed the check and crashed after all the training."""
    rec = _record()
    edit(rec)
    (tmp_path / "summary.json").write_text(json.dumps([_record(segments=3), rec]))
    with pytest.raises(ValueError, match=f"record 1 .* {message}"):
        load_records(tmp_path)
    _no_training(monkeypatch)
    assert cli.main(["nonlinear", "--quick", "--inits", "2", "--methods", "pgd",
                     "--segments", "2", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert set(REQUIRED_FIELDS) >= set(METRICS)


def test_records_of_other_versions_are_refused_older_ones_kept(tmp_path, capsys, monkeypatch):
    """Records of several library versions mixed silently in one report. Records written
    before the version was recorded still load and merge."""
    old = _record()  # no version: kept beside new ones
    new = _record(segments=3, dissil_jax_version=dj.__version__, dtype="float64")
    assert len(merge_records([old], [new])) == 2
    other = _record(dissil_jax_version="0.0.1", dtype="float64")
    with pytest.raises(ValueError, match="dissil_jax_version 0.0.1"):
        merge_records([other], [new])
    with pytest.raises(ValueError, match="dtype float32"):
        merge_records([dict(other, dissil_jax_version=dj.__version__, dtype="float32")], [new])
    _no_training(monkeypatch)
    (tmp_path / "summary.json").write_text(json.dumps([other]))
    assert cli.main(["nonlinear", "--quick", "--inits", "2", "--methods", "pgd",
                     "--segments", "2", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "dissil_jax_version 0.0.1" in err and err.rstrip().endswith("pick another --out")


def _fake_run(calls, interrupt_at, example, data, method, n, *, inits, seed, quick,
              on_plant=None):
    calls.append((data, method, n))
    if (data, method, n) == interrupt_at:
        raise KeyboardInterrupt
    return _record(method=method, segments=n, inits=inits, seed=seed, quick=quick,
                   dissil_jax_version=dj.__version__, dtype="float64")


def test_interrupted_run_keeps_finished_records_and_resumes(tmp_path, capsys, monkeypatch):
    """Ctrl-C lost every finished configuration and printed a traceback."""
    monkeypatch.setattr("dissil_jax.experiments.report.plot_figures", lambda records, out: [])
    calls = []
    monkeypatch.setattr("dissil_jax.experiments.protocol.run_config",
                        functools.partial(_fake_run, calls, ("initial", "gd", 3)))
    argv = ["nonlinear", "--quick", "--inits", "2", "--methods", "gd", "--segments", "2", "3",
            "5", "--out", str(tmp_path)]
    assert cli.main(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("interrupted: 1 of 3 configurations finished and saved in")
    assert "the same command with --resume runs the other 2" in err[-1]
    assert "Traceback" not in "\n".join(err)
    (saved,) = load_records(tmp_path)
    assert saved["segments"] == 2
    assert saved["command"] == "python -m dissil_jax.experiments " + " ".join(argv)
    assert not (tmp_path / "tables.md").exists()
    calls.clear()
    monkeypatch.setattr("dissil_jax.experiments.protocol.run_config",
                        functools.partial(_fake_run, calls, None))
    assert cli.main([*argv, "--resume"]) == 0
    assert calls == [("initial", "gd", 3), ("initial", "gd", 5)]  # not N = 2 again
    assert "--resume: 1 of 3 configurations are in" in capsys.readouterr().err
    assert [r["segments"] for r in load_records(tmp_path)] == [2, 3, 5]
    assert (tmp_path / "tables.md").exists()


def _worker_run(marker, data, method, n):
    """A configuration in a worker: N = 1 returns at once, N = 2 takes a minute and then
    writes `marker`, N = 3 fails."""
    if n == 2:
        time.sleep(60)
        pathlib.Path(marker).write_text("finished")
    if n == 3:
        raise ArithmeticError("boom")
    return {"n": n}


class _Bar:
    def __init__(self):
        self.labels = []

    def set_postfix_str(self, text):
        self.labels.append(text)

    def update(self):
        pass


def test_workers_are_stopped_at_once_on_ctrl_c(tmp_path):
    """With --jobs, Ctrl-C waited for the running configurations, then lost them all; the
    bar never said what ran."""
    marker = tmp_path / "finished"
    bar = _Bar()

    def on_record(i, record):
        raise KeyboardInterrupt  # Ctrl-C as the first record arrives

    configs = [("initial", "gd", 1), ("initial", "gd", 2)]
    with pytest.raises(KeyboardInterrupt):
        experiment_jobs.in_workers(functools.partial(_worker_run, str(marker)), configs, 2,
                                   bar, on_record)
    assert not marker.exists()  # the minute-long configuration was stopped, not awaited
    assert bar.labels[0] == "running: initial GD N=1; initial GD N=2"
    # a failing configuration is named, with the worker's traceback
    with pytest.raises(RuntimeError, match="(?s)initial GD N=3 failed in a worker.*boom"):
        experiment_jobs.in_workers(functools.partial(_worker_run, str(marker)),
                                   [("initial", "gd", 3)], 2, _Bar(), lambda i, r: None)


def _fake_sweep(example, method, learning_rates, *, segments, data, inits, plants, seed,
                spec):
    return dict(example=example, method=method, data=data, segments=segments, inits=inits,
                plants=plants, learning_rates=list(learning_rates),
                final_loss=[[[1.0] * inits] * len(learning_rates)],
                median_loss=[1.0 + lr for lr in learning_rates],
                diverged=[0.0] * len(learning_rates), best=learning_rates[0], seed=seed,
                max_steps=spec.max_steps, decay=spec.pgd_decay, tol=spec.tol, dtype="float64")


def test_lr_sweep_reports_progress_and_records_its_settings(tmp_path, capsys, monkeypatch):
    """The sweep printed nothing for 44 s, and its files did not say their seed, --quick,
    step limit, decay or tolerance."""
    monkeypatch.setattr("dissil_jax.experiments.tuning.learning_rate_sweep", _fake_sweep)
    assert cli.main(["nonlinear", "--lr-sweep", "0.1", "1", "--data", "initial", "sliding",
                     "--segments", "2", "--seed", "3", "--quick", "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[0] for line in err] == [
        f"lr-sweep nonlinear {k}/4: {m} {d} N=2" for k, (m, d) in enumerate(
            [(m, d) for m in ("PGD", "GD") for d in ("initial", "sliding")], 1)]
    md = (tmp_path / "lr_sweep_nonlinear.md").read_text()
    assert ("Seed 3; 10 initialisations per plant, at most 1 plant(s); at most 30 steps, "
            "decay 0.99 per step, stopping tolerance 1e-05; --quick;") in md
    sweeps = json.loads((tmp_path / "lr_sweep_nonlinear.json").read_text())
    assert all(s["quick"] is True and s["seed"] == 3 and "--seed 3" in s["command"]
               for s in sweeps)


def test_learning_rate_sweep_records_its_settings():
    spec = example_spec("nonlinear", quick=True)
    out = learning_rate_sweep("nonlinear", "gd", [0.3], segments=2, inits=2, seed=3, spec=spec)
    assert (out["seed"], out["max_steps"], out["decay"], out["tol"]) == (3, 30, 0.99, 1e-5)
    assert out["dtype"] == "float64" and out["dissil_jax_version"] == dj.__version__
