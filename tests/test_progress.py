"""Progress reports of long training runs: printed from inside the compiled loop (and
ICO's host loop) once a run has taken `DELAY` seconds, silent with `progress=False`, under
a user's `jax.vmap`, and for runs shorter than the delay."""

import jax
import jax.random as jr
import numpy as np
import pytest
from helpers import expert_windows

import dissil_jax as dj
from dissil_jax.internal import progress

QSR = dj.QSR.passive(1)


def _lines(err: str, name: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith(f"{name}: step")]


@pytest.fixture
def immediate(monkeypatch):
    """Reports from the first callback on, one per callback."""
    monkeypatch.setattr(progress, "DELAY", 0.0)
    monkeypatch.setattr(progress, "INTERVAL", 0.0)


@pytest.mark.parametrize("name", ["fit_direct", "fit_ren", "fit_pgd", "fit_gd", "fit_mlp"])
def test_long_runs_report_from_the_compiled_loop(immediate, capsys, name):
    """One line per callback with the batch's state; the MLP's loop is vmapped by its
    caller and calls back once per run, which the reporter gathers into one line."""
    w = expert_windows(2, 2, 1, 1, N=6)
    fit = getattr(dj, name)
    unconstrained = name in ("fit_gd", "fit_mlp")
    args = (jr.PRNGKey(0), w) if unconstrained else (jr.PRNGKey(0), w, QSR)
    kw = dict(hidden=(8,)) if name == "fit_mlp" else {}
    res = fit(*args, num_inits=3, max_steps=60, atol=0.0, rtol=0.0, throw=False, **kw)
    err = capsys.readouterr().err
    lines = _lines(err, name)
    # one callback per step (every max_steps // 100 steps, at least 1), from step 0 on;
    # step 0's says that compilation is over (its time counted towards the first report,
    # where a "step 0" line read as if training had not moved)
    assert err.splitlines()[0].startswith(f"{name}: compiled and started after ")
    assert err.splitlines()[0].endswith("3 runs of at most 60 steps")
    assert len(lines) == 60, lines[:3]
    assert lines[0].startswith(f"{name}: step 1 of at most 60, 3 of 3 runs training")
    assert lines[-1].startswith(f"{name}: step 60 of at most 60, 0 of 3 runs training")
    # the lowest loss reported last is the lowest the runs reached, in the user's units
    # (printed to 3 significant digits)
    best = float(lines[-1].split("lowest loss ")[1].split(",")[0])
    np.testing.assert_allclose(best, float(np.min(res.final_loss)), rtol=0.01)


def test_ico_reports_from_its_host_loop(immediate, capsys):
    w = expert_windows(2, 2, 1, 1, N=6)
    res = dj.fit_ico(jr.PRNGKey(0), w, QSR, num_inits=2, max_steps=3, atol=0.0, rtol=0.0,
                     throw=False)
    lines = _lines(capsys.readouterr().err, "fit_ico")
    assert len(lines) == 2 + int(np.sum(res.steps))  # step 0 and every accepted step
    assert all("of at most 3" in line for line in lines)


def test_host_loops_report_the_slowest_and_furthest_running_runs(immediate, capsys):
    """ICO's runs step at their own pace on threads: a report gives the steps of the
    slowest and the furthest run still training (it gave the furthest of all, so a line
    read "step 150 of at most 150" while most runs had far to go)."""
    host = progress.HostProgress("fit_ico", 10, 3, True)
    host.step(0, 5, 1.0)
    host.step(1, 2, 0.5)
    host.step(2, 10, 0.25)
    host.done(2)
    host.step(0, 6, 1.0)
    lines = _lines(capsys.readouterr().err, "fit_ico")
    assert lines[1].startswith("fit_ico: steps 0-5 of at most 10, 3 of 3 runs training")
    assert lines[2].startswith("fit_ico: steps 2-10 of at most 10, 3 of 3 runs training")
    assert lines[3].startswith("fit_ico: steps 2-6 of at most 10, 2 of 3 runs training, "
                               "lowest loss 2.50e-01")


def test_silent_when_asked_short_or_traced(capsys, monkeypatch):
    w = expert_windows(2, 2, 1, 1, N=6)
    dj.fit_direct(jr.PRNGKey(0), w, QSR, num_inits=2, max_steps=20)  # shorter than DELAY
    assert _lines(capsys.readouterr().err, "fit_direct") == []
    monkeypatch.setattr(progress, "DELAY", 0.0)
    monkeypatch.setattr(progress, "INTERVAL", 0.0)
    dj.fit_direct(jr.PRNGKey(0), w, QSR, num_inits=2, max_steps=20, progress=False)
    jax.vmap(lambda k: dj.fit_gd(k, w, num_inits=2, max_steps=20).final_loss)(
        jr.split(jr.PRNGKey(1), 2))
    assert capsys.readouterr().err == ""
    with pytest.raises(ValueError, match="`progress` must be True or False"):
        dj.fit_ren(jr.PRNGKey(0), w, QSR, progress="yes")
