"""The reproduction command line and its report, at small size."""

import json
import math

import jax
import numpy as np
import pytest

import dissil_jax as dj
from dissil_jax.experiments import __main__ as cli
from dissil_jax.experiments.protocol import example_spec, run_config
from dissil_jax.experiments.report import load_records, merge_records, tables_markdown, write_report
from dissil_jax.internal import FIGURES, TABLES, sdp

#: The metric fields a record needs to be loaded (`report.REQUIRED_FIELDS`).
METRICS = dict(percent_stable=50.0, percent_change_cost=-99.0, train_time_s=0.5, mse_q1=0.02,
               mse_median=0.03, mse_q3=0.04, mse_max=0.05)
KEYS = {"example", "data", "method", "segments", "percent_stable", "percent_change_cost",
        "train_time_s", "mse_median", "mse_max", "mse_q1", "mse_q3", "percent_bounded",
        "equilibrium_steps", "test_steps"}


def test_cli_writes_summary_tables_and_figures(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["nonlinear", "--data", "initial", "--segments", "2", "--inits", "2",
            "--methods", "pgd", "mlp", "--out", str(out), "--quick"]
    assert cli.main(argv) == 0
    records = load_records(out)
    assert {(r["method"], r["segments"]) for r in records} == {("pgd", 2), ("mlp", 2)}
    for r in records:
        assert KEYS <= set(r)
        assert r["mse_q1"] <= r["mse_median"] <= r["mse_q3"] <= r["mse_max"]
        # every trained controller's stopping rule is counted
        assert sum(r["stop_reasons"].values()) == r["controllers"]
        # the test loops ran to the expert's equilibrium, and at least 30 steps
        assert r["test_steps"] == [max(t, 30) for t in r["equilibrium_steps"]]
        assert r["percent_bounded"] >= r["percent_stable"]
    pgd = next(r for r in records if r["method"] == "pgd")
    assert pgd["percent_stable"] == 100.0 and pgd["certified"] is True
    tables = (out / "tables.md").read_text()
    # the paper's own PGD numbers for N = 2 appear beside ours
    assert "(-96.90)" in tables and "(11.4)" in tables
    for stat in ("median", "max", "quartiles"):
        png = out / f"nonlinear_{stat}.png"
        assert png.exists() and png.stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "tables:" in printed and "nonlinear_median.png" in printed
    # the printed table says what its columns are, with PGD certified and GD+NN not checked
    rows = {line.split()[1]: line.split()[-1] for line in printed.splitlines()
            if line.startswith("initial ")}
    assert rows == {"PGD": "all", "GD+NN": "–"} and "s/ctrl: training seconds" in printed
    # a second invocation adds to the same report instead of replacing it
    assert cli.main(["nonlinear", "--data", "initial", "--segments", "2", "--inits", "2",
                     "--methods", "ico_nc", "--out", str(out), "--quick"]) == 0
    methods = {r["method"] for r in load_records(out)}
    assert methods == {"pgd", "mlp", "ico_nc"}


def test_cli_rejects_bad_arguments():
    with pytest.raises(SystemExit):
        cli.main(["quadratic"])
    with pytest.raises(SystemExit):
        cli.main(["linear", "--methods", "sgd"])
    assert cli.main(["linear", "--segments", "0", "--out", "/nonexistent"]) == 2


@pytest.mark.parametrize("argv", [["--inits", "0"], ["--inits", "-3"], ["--lr-sweep", "-1"],
                                  ["--lr-sweep", "nan"], ["--out", "/proc/forbidden/x"]])
def test_cli_rejects_bad_values_before_any_training(argv, tmp_path, capsys, monkeypatch):
    """Refused up front with exit code 2 and a message naming the option; nothing is
    trained (a bad `--inits` used to start the full default run, a bad `--out` to fail
    after all the training)."""
    monkeypatch.setattr("dissil_jax.experiments.protocol.run_config",
                        lambda *a, **k: pytest.fail("trained despite a bad argument"))
    out = [] if "--out" in argv else ["--out", str(tmp_path)]
    assert cli.main(["linear", *argv, *out]) == 2
    assert argv[0] in capsys.readouterr().err


def _no_training(monkeypatch):
    monkeypatch.setattr("dissil_jax.experiments.protocol.run_config",
                        lambda *a, **k: pytest.fail("trained despite a bad argument"))


def test_cli_refuses_a_corrupt_summary_before_any_training(tmp_path, capsys, monkeypatch):
    """A `summary.json` that is not JSON used to fail after all the training, losing it."""
    _no_training(monkeypatch)
    (tmp_path / "summary.json").write_text("{not json")
    assert cli.main(["nonlinear", "--quick", "--methods", "gd", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "summary.json is not valid JSON" in err
    (tmp_path / "summary.json").write_text('{"example": "linear"}')  # JSON, not records
    assert cli.main(["nonlinear", "--quick", "--methods", "gd", "--out", str(tmp_path)]) == 2
    assert "is not a list of records" in capsys.readouterr().err


def test_cli_refuses_to_mix_seeds_inits_or_quick_in_one_report(tmp_path, capsys,
                                                               monkeypatch):
    """Records of other settings used to merge silently into one table."""
    _no_training(monkeypatch)
    old = dict(example="nonlinear", data="initial", method="gd", segments=2, inits=2, seed=0,
               quick=True, **METRICS)  # a record of 0.1.0: no version, no dtype
    (tmp_path / "summary.json").write_text(json.dumps([old]))
    base = ["nonlinear", "--segments", "2", "3", "--methods", "pgd", "--out", str(tmp_path)]
    for other in (["--inits", "2", "--seed", "1", "--quick"], ["--inits", "3", "--quick"],
                  ["--inits", "2"]):
        assert cli.main([*base, *other]) == 2
        err = capsys.readouterr().err
        assert "--out" in err and "seed 0, inits 2, quick True" in err, err
        assert "pick another --out" in err
    parse = lambda argv: cli._parser().parse_args(argv)  # noqa: E731
    # the same settings, another example, or replacing every old record are fine
    assert cli._argument_error(parse([*base, "--inits", "2", "--quick"])) is None
    assert cli._argument_error(parse(["linear", "--seed", "5", "--out", str(tmp_path)])) is None
    assert cli._argument_error(parse(["nonlinear", "--segments", "2", "--methods", "gd",
                                      "--seed", "1", "--out", str(tmp_path)])) is None
    with pytest.raises(ValueError, match="seed 0, inits 2, quick True"):
        merge_records([old], [dict(old, segments=3, seed=1)])


def test_cli_options_help_and_repeats(tmp_path, capsys, monkeypatch):
    _no_training(monkeypatch)
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert cli.main(["linear", "--out", str(a_file)]) == 2
    assert "is a file, not a directory" in capsys.readouterr().err
    assert cli.main(["linear", "--lr-sweep", "1", "--methods", "gd", "--out",
                     str(tmp_path)]) == 2
    assert "--methods does not apply to --lr-sweep" in capsys.readouterr().err
    args = cli._parser().parse_args(["linear", "--data", "initial", "initial", "--segments",
                                     "2", "3", "2", "--methods", "gd", "pgd", "gd"])
    assert cli._configs(args) == [("initial", m, s) for m in ("gd", "pgd") for s in (2, 3)]
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "(default: runs/latest)" in help_text and "random seed" in help_text


def test_solver_thread_count_must_be_a_positive_integer(monkeypatch):
    """`DISSIL_JAX_THREADS` (which `--jobs` sets for its workers) sizes the solver pool:
    `abc` used to fail in `int()` without naming the variable, 0 and -1 were clipped to 1."""
    import re

    monkeypatch.setattr(sdp, "_POOL", None)
    for bad in ("abc", "0", "-1", "2.5"):
        monkeypatch.setenv("DISSIL_JAX_THREADS", bad)
        with pytest.raises(ValueError, match=f"DISSIL_JAX_THREADS must be a positive "
                                             f"integer.*{re.escape(repr(bad))}"):
            sdp.pool()
    # and from a projection as a ValueError, not inside the host callback's runtime error
    K = dj.LTIController.random(jax.random.PRNGKey(0), 1, 1, 1)
    with pytest.raises(ValueError, match="DISSIL_JAX_THREADS must be a positive"):
        dj.project(K, dj.QSR.passive(1))
    monkeypatch.setenv("DISSIL_JAX_THREADS", " 2 ")
    assert sdp.num_workers() == 2
    sdp.pool().shutdown()


def test_protocol_rejects_bad_arguments():
    with pytest.raises(ValueError, match="`example`"):
        example_spec("quadratic")
    with pytest.raises(ValueError, match="`data`"):
        run_config("nonlinear", "random", "pgd", 2, inits=1)


def test_tables_markdown_formats_infinity_and_merges():
    base = dict(example="nonlinear", data="sliding", segments=25, percent_stable=50.0,
                percent_change_cost=-99.0, train_time_s=0.5, mse_min=0.01, mse_q1=0.02,
                mse_median=0.03, mse_q3=math.inf, mse_max=math.inf)
    old = [dict(base, method="gd", percent_stable=0.0)]
    new = [dict(base, method="gd"), dict(base, method="ico")]
    merged = merge_records(old, new)
    assert [r["method"] for r in merged] == ["ico", "gd"]
    assert merged[1]["percent_stable"] == 50.0
    md = tables_markdown(merged)
    assert "∞" in md and "Sliding window".lower() in md
    assert "**50** (32)" in md  # ours vs the paper's GD, sliding window, N = 25
    assert "Quick run" not in md
    assert "Quick run" in tables_markdown([dict(r, quick=True) for r in merged])


def test_summary_json_is_strict_json_and_reads_back(tmp_path, monkeypatch):
    monkeypatch.setattr("dissil_jax.experiments.report.plot_figures", lambda records, out: [])
    rec = dict(example="nonlinear", data="sliding", method="gd", segments=25, percent_stable=50.0,
               percent_change_cost=-99.0, train_time_s=0.5, mse_min=0.01, mse_q1=0.02,
               mse_median=0.03, mse_q3=math.inf, mse_max=math.nan,
               stop_reasons={"non_finite": 2})
    write_report([rec], tmp_path)

    def refuse(token):
        raise AssertionError(f"non-standard JSON token {token}")

    strict = json.loads((tmp_path / "summary.json").read_text(), parse_constant=refuse)
    assert strict[0]["mse_q3"] == "inf" and strict[0]["mse_max"] == "nan"
    (back,) = load_records(tmp_path)
    assert back["mse_q3"] == math.inf and math.isnan(back["mse_max"])
    assert back["stop_reasons"] == {"non_finite": 2} and back["mse_median"] == 0.03


def test_paper_numbers_transcribed():
    # spot checks against the paper's text: nonlinear initial segments, N = 25
    assert TABLES[("nonlinear", "initial")]["ico"][1][1] == -96.31
    med = dict(FIGURES[("nonlinear", "initial", "median")]["ico"])[25]
    assert med == pytest.approx(0.0101, abs=1e-4)
    q1, m, q3 = dict(FIGURES[("nonlinear", "initial", "quartiles")]["ico"])[25]
    assert q1 < m < q3 and m == pytest.approx(med)
    assert np.isfinite(dict(FIGURES[("linear", "initial", "max")]["pgd"])[200])


@pytest.mark.slow
def test_demo_configuration_matches_the_papers_claims(tmp_path):
    """`make demo`'s configuration: dissipative methods always stable, ICO close to the paper."""
    out = tmp_path / "demo"
    assert cli.main(["nonlinear", "--data", "initial", "--segments", "25", "--inits", "10",
                     "--out", str(out)]) == 0
    by = {r["method"]: r for r in load_records(out)}
    assert set(by) == {"pgd", "gd", "ico", "ico_nc", "mlp"}
    for m in ("pgd", "ico"):
        assert by[m]["percent_stable"] == 100.0 and by[m]["certified"] is True
    # paper, Fig. 4: median test MSE 0.010 (ICO), 0.11 (PGD) at 25 initial segments
    assert by["ico"]["mse_median"] < 0.05
    assert by["pgd"]["mse_median"] < 0.2


def test_entry_point_with_jobs_gives_the_serial_records(tmp_path):
    """`python -m dissil_jax.experiments` as `make demo` calls it (float64 set up by the CLI),
    with spawned workers as `make reproduce` runs it (`--jobs 2`, one solver thread each),
    writes the records of the serial in-process run; `--methods direct` runs our extension.

    One test for the three, since each CLI run compiles the NMPC expert's closed loop anew.
    """
    import os
    import subprocess
    import sys

    argv = ["nonlinear", "--data", "initial", "--segments", "2", "3", "--inits", "2",
            "--methods", "pgd", "ico_nc", "direct", "--quick"]
    assert cli.main(argv + ["--out", str(tmp_path / "serial")]) == 0
    assert cli.main(argv + ["--out", str(tmp_path / "bad"), "--jobs", "0"]) == 2
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-m", "dissil_jax.experiments", *argv, "--out",
                           str(tmp_path / "jobs"), "--jobs", "2"],
                          capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "nonlinear_median.png" in proc.stdout
    serial, jobs = (json.loads((tmp_path / d / "summary.json").read_text())
                    for d in ("serial", "jobs"))
    assert len(serial) == 6
    # the times, the date and the command line (its --out and --jobs) differ
    varying = {"train_time_s", "train_time_per_plant_s", "date", "command"}
    drop = lambda r: {k: v for k, v in r.items() if k not in varying}  # noqa: E731
    assert [drop(r) for r in jobs] == [drop(r) for r in serial]
    for rec in serial:
        if rec["method"] in ("pgd", "direct"):
            assert rec["certified"] is True and rec["percent_stable"] == 100.0, rec
    assert "Direct (ours)" in (tmp_path / "serial" / "tables.md").read_text()
    default_methods = {m for _, m, _ in cli._configs(cli._parser().parse_args(["linear"]))}
    assert "direct" not in default_methods  # not a paper method


def test_quick_runs_default_to_ten_initialisations():
    parse = lambda argv: cli._parser().parse_args(argv)  # noqa: E731
    assert cli._inits(parse(["nonlinear"])) == 100
    assert cli._inits(parse(["nonlinear", "--quick"])) == 10
    assert cli._inits(parse(["nonlinear", "--quick", "--inits", "3"])) == 3
    assert cli._inits(parse(["linear"])) == 10
