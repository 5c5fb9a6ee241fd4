"""Shared by `bench_defaults.py`: run a trainer on a zoo problem, with or without early stop."""

from __future__ import annotations

import numpy as np

import dissil_jax as dj
from dissil_jax.experiments import zoo

TRAINERS = ("pgd", "gd", "direct", "ico", "mlp")


def applies(trainer: str, problem) -> bool:
    """ICO needs the plant state and 2-step windows; every other trainer takes any problem."""
    if trainer == "ico":
        return problem.facts.has_state and problem.facts.horizon == 2
    return True


def method(trainer: str, *, num_inits: int, **kw):
    """A zoo method (Task -> FitResult) for one trainer; `kw` go to the trainer."""

    def run(t):
        common = dict(num_inits=num_inits, throw=False, **kw)
        if trainer == "pgd":
            return dj.fit_pgd(t.key, t.windows, t.qsr, n_state=t.n_state, **common)
        if trainer == "gd":
            return dj.fit_gd(t.key, t.windows, n_state=t.n_state, **common)
        if trainer == "direct":
            return dj.fit_direct(t.key, t.windows, t.qsr, n_state=t.n_state, **common)
        if trainer == "ico":
            return dj.fit_ico(t.key, t.windows, t.qsr, **common)
        if trainer == "mlp":
            return dj.fit_mlp(t.key, t.windows, **common)
        raise ValueError(f"`trainer` must be one of {TRAINERS}, got {trainer!r}.")

    return run


def run_full(trainer: str, problem, *, num_inits: int, max_steps: int, **kw):
    """One run without early stop (`atol = rtol = 0`), returning the last iterate where the
    trainer can return another (`keep="last"`): the FitResult and the zoo's report."""
    out = {}
    if trainer in ("pgd", "direct"):
        kw = dict(keep="last", **kw)

    def m(t):
        out["res"] = method(trainer, num_inits=num_inits, max_steps=max_steps, atol=0.0,
                            rtol=0.0, **kw)(t)
        return out["res"]

    rep = zoo.evaluate(problem, m)
    return out["res"], rep


def run_defaults(trainer: str, problem, *, num_inits: int, **kw):
    """One run with the trainer's defaults (its stopping rule and returned iterate), but for
    `kw` (a candidate default)."""
    out = {}

    def m(t):
        out["res"] = method(trainer, num_inits=num_inits, **kw)(t)
        return out["res"]

    rep = zoo.evaluate(problem, m)
    return out["res"], rep


def stop_steps(hist: np.ndarray, rtol: float) -> np.ndarray:
    """Per run, the step at which $|J_k - J_{k-1}| \\le$ `rtol` $|J_0|$ first holds (or the
    last recorded step), from a loss history `[inits, steps + 1]` run without early stop."""
    hist = np.asarray(hist, np.float64)
    out = np.empty(hist.shape[0], int)
    for i, h in enumerate(hist):
        h = h[np.isfinite(h)]
        d = np.abs(np.diff(h))
        hit = np.nonzero(d <= rtol * abs(h[0]))[0]
        out[i] = hit[0] + 1 if len(hit) else len(h) - 1
    return out
