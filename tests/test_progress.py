"""Progress reports of long training runs: printed from inside the compiled loop (and
ICO's host loop) once a run has taken `DELAY` seconds, silent with `progress=False`, under
a user's `jax.vmap`, and for runs shorter than the delay."""

import time

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
    # (the heartbeat's lines, while compiling and checking, come as the machine's speed has
    # it; `test_the_heartbeat_says_what_a_run_does_between_reports` checks them)
    first = [line for line in err.splitlines() if "after" in line or " step" in line][0]
    assert first.startswith(f"{name}: compiled and started after ")
    assert first.endswith("3 runs of at most 60 steps")
    assert len(lines) == 60, lines[:3]
    assert lines[0].startswith(f"{name}: step 1 of at most 60, 3 of 3 runs training")
    assert lines[-1].startswith(f"{name}: step 60 of at most 60, 0 of 3 runs training")
    # the lowest loss reported last is the lowest the runs reached, in the user's units
    # (printed to 3 significant digits)
    best = float(lines[-1].split("lowest loss ")[1].split(",")[0])
    np.testing.assert_allclose(best, float(np.min(res.final_loss)), rtol=0.01)


def test_the_heartbeat_says_what_a_run_does_between_reports(monkeypatch, capsys):
    """A run silent for minutes before its loop's first step (compiling; projecting the
    first iterates at a high order, three minutes for `fit_pgd` at order 48) or after its
    last (the float64 check) looked hung: a heartbeat thread says what it does, once the
    run is past the delay, at most once an interval, and not while the loop reports."""
    monkeypatch.setattr(progress, "DELAY", 0.05)
    monkeypatch.setattr(progress, "INTERVAL", 0.05)
    monkeypatch.setattr(progress, "_BEAT", 0.01)
    with progress.reporting("fit_x", 10, True) as token:
        time.sleep(0.3)
        before = capsys.readouterr().err.splitlines()
        progress._dispatch(token, np.int32(0), np.ones(2), np.zeros(2, bool))
        time.sleep(0.3)  # stepping (no call back in this while): the loop's lines only
        stepping = capsys.readouterr().err.splitlines()
        progress.phase(token, progress.CHECKING)
        time.sleep(0.3)
        after = capsys.readouterr().err.splitlines()
    time.sleep(0.1)
    assert capsys.readouterr().err == ""  # the thread ends with the run
    assert 2 <= len(before) <= 8, before  # ~0.3 s / 0.05 s, with room for a slow machine
    assert all(line.startswith("fit_x: compiling the training loop and preparing the runs, ")
               for line in before)
    # on a loaded machine one beat of the compiling phase can land between the read above
    # and the first report; it comes first, and nothing but the report follows it
    if len(stepping) == 2 and stepping[0].startswith("fit_x: compiling the training loop"):
        stepping = stepping[1:]
    assert len(stepping) == 1 and stepping[0].startswith("fit_x: compiled and started after")
    assert 2 <= len(after) <= 8, after
    assert all(line.startswith(f"fit_x: {progress.CHECKING}, ") for line in after)
    with progress.reporting("fit_x", 10, False) as token:  # progress=False: no thread
        time.sleep(0.2)
    monkeypatch.setattr(progress, "DELAY", 60.0)
    with progress.reporting("fit_x", 10, True) as token:  # within the delay: silent
        time.sleep(0.2)
    assert capsys.readouterr().err == ""


def test_certify_says_it_is_searching_unless_asked_not_to(monkeypatch, capsys):
    """`certify(max_margin=True)` at order 64 searched for eleven minutes without a word;
    its heartbeat names the work, `progress=False` silences it, and inside a trainer's run
    (which reports already) it is silent."""
    monkeypatch.setattr(progress, "DELAY", 0.0)
    monkeypatch.setattr(progress, "INTERVAL", 0.0)
    monkeypatch.setattr(progress, "_BEAT", 0.002)
    rng = np.random.default_rng(0)
    n = 12
    K = dj.LTIController(0.5 * rng.standard_normal((n, n)) / np.sqrt(n),
                         rng.standard_normal((n, 1)), 0.01 * rng.standard_normal((1, n)),
                         np.array([[0.05]]))
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    assert dj.certify(K, qsr, max_margin=True, progress=False).holds
    assert capsys.readouterr().err == ""
    assert dj.certify(K, qsr, max_margin=True).holds  # an SDP: far longer than 2 ms
    lines = capsys.readouterr().err.splitlines()
    assert lines and all(line.startswith(
        "certify: searching a storage for a controller of order 12, ") for line in lines)
    with progress.reporting("fit_x", 10, True):
        capsys.readouterr()
        progress.INTERVAL = 1e9  # the trainer's own heartbeat stays quiet here
        assert dj.certify(K, qsr, max_margin=True).holds
    assert "certify:" not in capsys.readouterr().err


def test_project_says_it_is_solving(monkeypatch, capsys):
    """A batch of projection SDPs (minutes at high orders with an indefinite Q) said
    nothing; its heartbeat names the work, except inside a trainer's run."""
    monkeypatch.setattr(progress, "DELAY", 0.0)
    monkeypatch.setattr(progress, "INTERVAL", 0.0)
    monkeypatch.setattr(progress, "_BEAT", 0.002)
    rng = np.random.default_rng(1)
    n = 6
    K = dj.LTIController(0.9 * rng.standard_normal((4, n, n)) / np.sqrt(n),
                         rng.standard_normal((4, n, 1)), rng.standard_normal((4, 1, n)),
                         rng.standard_normal((4, 1, 1)))
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    dj.project(K, qsr, method="clarabel")
    lines = capsys.readouterr().err.splitlines()
    assert lines and all(line.startswith("project: solving 4 projection SDP(s) of order 6, ")
                         for line in lines)
    with progress.reporting("fit_x", 10, True):
        capsys.readouterr()
        progress.INTERVAL = 1e9
        dj.project(K, qsr, method="clarabel")
    assert "project:" not in capsys.readouterr().err


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
    # runs not started yet (waiting for a thread) are counted apart, not as runs at step 0
    assert lines[0].startswith("fit_ico: step 5 of at most 10, 1 of 3 runs training "
                               "(2 waiting for a thread)")
    assert lines[1].startswith("fit_ico: steps 2-5 of at most 10, 2 of 3 runs training "
                               "(1 waiting for a thread)")
    assert lines[2].startswith("fit_ico: steps 2-10 of at most 10, 3 of 3 runs training, ")
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
