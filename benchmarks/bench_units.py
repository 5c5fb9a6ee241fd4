"""Outputs in units of their own: the trainers with and without `balance`.

The demonstrations' outputs u are put in other units (u -> a u, the controller's rate
(Q, S, R) -> (Q/a², S/a, R), the same controllers), so that the ratio r of the outputs'
size to the inputs' (`dissil_jax.internal.output_ratio`) moves away from one. Per cell:
the median final loss over 8 initialisations divided by a², i.e. in the base problem's
units, with `balance=False` (one scale for every signal, as before) and `balance=True`
(the default). Every certified trainer's controllers are checked (`certified`).

1. `--curve` (tuning; chose the default and showed where the unbalanced runs degrade):
   realisable problems (`realisable_windows`, order 4, 40 windows of length 4, noise
   0.1), passivity (seeds 0, 1) and a cone (seed 0); a from 1/32 to 32.
2. `--held-out` (reported, not used to choose): the zoo's held-out problems with Q <= 0,
   outputs scaled by a = 1/32 and 32.
3. `--rate`: a supply rate multiplied by c (the same controllers, storages times c): a
   gain bound of 1 (m = p = 2), 50 windows from a certified order-2 expert, 4
   initialisations, every certified trainer's defaults; the best run's loss over the zero
   controller's, with the rate used as given (`RATE_BAND` = inf, as before) and divided by
   a power of two (the default).
4. `--paper`: the paper's examples as they are (the reproduction's windows, initial
   segments, N = 25; their outputs are 4-90x smaller than their inputs) with every
   trainer's defaults.
5. `--states`: initial states in units of their own (x0 -> a x0: the same controllers in
   the state coordinates x = a x_b, storages P/a²), so that the ratio rho of the states'
   size to the outputs' (`dissil_jax.internal.state_ratios`) moves away from one; the
   `--curve` problems (tuning: chose `STATE_BAND`), then the zoo's held-out problems
   with x0 scaled by 1/64 and 64 (reported), and the range of rho over the zoo and the
   paper's examples. Cells as in 1, with the states' balancing off and on. Then what
   balancing the large side too would do, on plants and on an expert's own coordinates.

Usage: python benchmarks/bench_units.py [--curve] [--held-out] [--rate] [--paper] [--states]
"""

from __future__ import annotations

import argparse

import jax
import jax.random as jr
import numpy as np

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import realisable_windows, zoo  # noqa: E402
from dissil_jax.internal import (  # noqa: E402
    is_indefinite,
    output_ratio,
    rate_scale,
    state_ratios,
    units,
)

TRAINERS = {
    "fit_direct": lambda w, q, b, **kw: dj.fit_direct(jr.PRNGKey(7), w, q, balance=b,
                                                      throw=False, **kw),
    "fit_pgd": lambda w, q, b, **kw: dj.fit_pgd(jr.PRNGKey(7), w, q, balance=b, throw=False,
                                                **kw),
    "fit_gd": lambda w, q, b, **kw: dj.fit_gd(jr.PRNGKey(7), w, balance=b, throw=False, **kw),
}


def _rescaled(w: dj.Windows, q: dj.QSR, a: float):
    return dj.Windows(w.x0, w.y, a * w.u), dj.QSR(q.Q / a**2, q.S / a, q.R)


def _cell(name, w, q, a, balance, **kw) -> str:
    res = TRAINERS[name](w, q, balance, **kw)
    med = float(np.median(np.asarray(res.final_loss))) / a**2
    if res.certified is not None and not bool(np.all(res.certified)):
        return f"{med:.3g} ({np.mean(np.asarray(res.certified)):.0%} cert.)"
    return f"{med:.3g}"


def curve():
    scales = (1 / 32, 1 / 8, 1 / 4, 1 / 2, 1.0, 2.0, 4.0, 8.0, 32.0)
    rates = (("passive", dj.QSR.passive(2), 0), ("passive", dj.QSR.passive(2), 1),
             ("cone", dj.QSR(-np.eye(2), 0.5 * np.eye(2), 0.3 * np.eye(2)), 0))
    for label, q0, seed in rates:
        w0, _ = realisable_windows(jr.PRNGKey(seed), q0, n_state=4, num_windows=40,
                                   horizon=4, noise=0.1)
        ws = [_rescaled(w0, q0, a) for a in scales]
        print(f"\n{label}, seed {seed}: median final loss / a² (balance=False; "
              "balance=True where it changes the run)")
        print("| trainer | " + " | ".join(f"r = {output_ratio(w):.2g}" for w, _ in ws) + " |")
        print("|---|" + "---:|" * len(ws))
        for name in TRAINERS:
            cells = []
            for a, (w, q) in zip(scales, ws):
                off = _cell(name, w, q, a, False)
                r = output_ratio(w)
                cells.append(off if 0.2 <= r <= 5 else f"{off}; {_cell(name, w, q, a, True)}")
            print(f"| `{name}` | " + " | ".join(cells) + " |", flush=True)


def held_out():
    print("| problem | a | r | trainer | base (a = 1) | balance=False | balance=True |")
    print("|---|---:|---:|---|---:|---:|---:|")
    for pname in zoo.HELD_OUT:
        prob = zoo.problem(pname)
        if is_indefinite(prob.qsr):
            continue
        kw = dict(n_state=prob.n_state)
        for name in ("fit_direct", "fit_pgd"):
            base = _cell(name, prob.train, prob.qsr, 1.0, True, **kw)
            for a in (1 / 32, 32.0):
                w, q = _rescaled(prob.train, prob.qsr, a)
                print(f"| {pname} | {a:g} | {output_ratio(w):.2g} | `{name}` | {base} | "
                      f"{_cell(name, w, q, a, False, **kw)} | "
                      f"{_cell(name, w, q, a, True, **kw)} |", flush=True)


def rate():
    base = dj.QSR.bounded_gain(1.0, n_in=2, n_out=2)
    K = dj.LTIController.random(jr.PRNGKey(0), 2, 2, 2, scale=0.5)
    K, _ = dj.project(K, base)  # a certified expert
    rng = np.random.default_rng(1)
    x0, y = rng.standard_normal((50, 2)), rng.standard_normal((50, 2, 2))
    A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
    u = -np.stack([x0 @ C.T + y[:, 0] @ D.T,
                   (x0 @ A.T + y[:, 0] @ B.T) @ C.T + y[:, 1] @ D.T], 1)
    w = dj.Windows(x0, y, u)
    zero = float(np.mean(np.sum(u**2, axis=(1, 2))))
    fits = {"fit_direct": dj.fit_direct, "fit_pgd": dj.fit_pgd, "fit_ico": dj.fit_ico,
            "fit_ren": lambda k, w, q, **kw: dj.fit_ren(k, w, q, width=4, **kw)}
    print("| c | trainer | rate as given | rate divided by a power of two |")
    print("|---:|---|---:|---:|")
    band = rate_scale.RATE_BAND
    for c in (1e-6, 1.0, 1e6):
        q = dj.QSR(c * base.Q, c * base.S, c * base.R)
        for name, fit in fits.items():
            cells = []
            for rb in (float("inf"), band):
                rate_scale.RATE_BAND = rb
                jax.clear_caches()  # the factor is read when a trainer is traced
                try:
                    r = fit(jr.PRNGKey(0), w, q, num_inits=4, throw=False)
                    best = float(np.nanmin(np.where(np.asarray(r.certified),
                                                    np.asarray(r.final_loss), np.nan)))
                    cells.append(f"{best / zero:.3g} ({sorted(set(r.result_names()))})")
                except Exception as e:  # noqa: BLE001 -- a raising trainer is a result here
                    cells.append(f"{type(e).__name__}")
                finally:
                    rate_scale.RATE_BAND = band
                    jax.clear_caches()
            print(f"| {c:g} | `{name}` | {cells[0]} | {cells[1]} |", flush=True)


def _no_state_band(fn):
    """Run `fn()` with the states' balancing off (`STATE_BAND` wide open)."""
    band = units.STATE_BAND
    units.STATE_BAND = (0.0, float("inf"))
    try:
        return fn()
    finally:
        units.STATE_BAND = band


def _state_cells(name, w, q, band=None, **kw) -> str:
    """Off; on (with the default `STATE_BAND`, or `band` for the measurement of another)."""
    off = _no_state_band(lambda: _cell(name, w, q, 1.0, True, **kw))
    default = units.STATE_BAND
    units.STATE_BAND = band or default
    try:
        if units.state_factors(w) is None:
            return off
        return f"{off}; {_cell(name, w, q, 1.0, True, **kw)}"
    finally:
        units.STATE_BAND = default


def _natural(seed: int, scale: float):
    """An expert in its own coordinates (O(1) matrices, gain 0.7, random inputs), windows
    starting at `scale` N(0, I): states far from the outputs' size by where they start,
    not by their units (a new-user audit's data)."""
    rng = np.random.default_rng(seed)
    n = p = m = 2
    A = rng.standard_normal((n, n))
    A *= 0.8 / np.abs(np.linalg.eigvals(A)).max()
    B, C, D = (rng.standard_normal(s) for s in ((n, p), (m, n), (m, p)))
    z = np.exp(1j * np.linspace(0.0, np.pi, 400))
    g = max(np.linalg.norm(C @ np.linalg.solve(zi * np.eye(n) - A, B) + D, 2) for zi in z)
    C, D = 0.7 * C / g, 0.7 * D / g
    x0, y = scale * rng.standard_normal((40, n)), rng.standard_normal((40, 5, p))
    u, x = np.zeros((40, 5, m)), x0.copy()
    for k in range(5):
        u[:, k] = -(x @ C.T + y[:, k] @ D.T) + 0.05 * rng.standard_normal((40, m))
        x = x @ A.T + y[:, k] @ B.T
    return dj.Windows(x0, y, u), dj.QSR.bounded_gain(1.0, n_in=p, n_out=m)


def _plant(C, seed: int, A=None, B=None):
    """SISO plant windows (an LQR expert, 25 windows of two steps) with output matrix C."""
    from bench_tight_gain import _problem

    A = np.array([[0.8, 0.2], [-0.1, 0.7]]) if A is None else A
    B = np.array([[1.0], [0.5]]) if B is None else B
    return _problem(A, B, C, seed)[0], dj.QSR.passive(1)


def both_sides():
    """What balancing the large side too would do (the two-sided band [1/5, 5]), on data
    whose natural coordinates are the given ones: plants with small or large output
    matrices, and an expert's windows that start far from rest."""
    import control

    np.random.seed(0)  # python-control's drss draws from numpy's global generator
    s = control.drss(4, 1, 1, strictly_proper=True)
    c2 = np.array([[1.0, -0.5]])
    cases = [("plant, 2 states, C x 0.01", _plant(0.01 * c2, 0)),
             ("plant, 2 states, C x 100", _plant(100.0 * c2, 0)),
             ("plant, drss order 4, C x 0.01", _plant(0.01 * s.C, 1, s.A, s.B)),
             ("plant, drss order 4, C as drawn", _plant(s.C, 1, s.A, s.B))]
    cases += [(f"expert's coordinates, start x {a:g}, seed {k}", _natural(k, a))
              for k in (1, 2) for a in (30.0, 0.01)]
    print("\n| data | rho | trainer | off; on (both sides balanced) |\n|---|---:|---|---:|")
    for label, (w, q) in cases:
        for name in TRAINERS:
            if name == "fit_gd" and label.startswith("plant"):
                continue
            print(f"| {label} | {_rho(w)} | `{name}` | "
                  f"{_state_cells(name, w, q, band=(0.2, 5.0))} |", flush=True)


def _rho(w) -> str:
    rho = state_ratios(w)
    return f"{np.nanmin(rho):.2g}-{np.nanmax(rho):.2g}"


def states():
    scales = (1 / 64, 1 / 16, 1 / 4, 1 / 2, 1.0, 4.0, 16.0, 64.0)
    rates = (("passive", dj.QSR.passive(2), 0), ("passive", dj.QSR.passive(2), 1),
             ("cone", dj.QSR(-np.eye(2), 0.5 * np.eye(2), 0.3 * np.eye(2)), 0))
    for label, q, seed in rates:
        w0, _ = realisable_windows(jr.PRNGKey(seed), q, n_state=4, num_windows=40,
                                   horizon=4, noise=0.1)
        ws = [dj.Windows(a * w0.x0, w0.y, w0.u) for a in scales]
        print(f"\n{label}, seed {seed}: median final loss (states' balancing off; on, "
              "where it changes the run)")
        print("| trainer | " + " | ".join(f"rho = {_rho(w)}" for w in ws) + " |")
        print("|---|" + "---:|" * len(ws))
        for name in TRAINERS:
            cells = [_state_cells(name, w, q) for w in ws]
            print(f"| `{name}` | " + " | ".join(cells) + " |", flush=True)
    print("\n| problem | a | rho | trainer | base (a = 1) | off; on |")
    print("|---|---:|---:|---|---:|---:|")
    for pname in zoo.HELD_OUT:
        prob = zoo.problem(pname)
        w0 = prob.train
        if w0.x0 is None or is_indefinite(prob.qsr):
            continue
        kw = dict(n_state=prob.n_state)
        for name in ("fit_direct", "fit_pgd"):
            base = _cell(name, w0, prob.qsr, 1.0, True, **kw)
            for a in (1 / 64, 64.0):
                w = dj.Windows(a * w0.x0, w0.y, w0.u)
                print(f"| {pname} | {a:g} | {_rho(w)} | `{name}` | {base} | "
                      f"{_state_cells(name, w, prob.qsr, **kw)} |", flush=True)
    from dissil_jax.experiments.protocol import example_spec, training_data

    print("\n| problem | rho |\n|---|---:|")
    for pname in zoo.TUNING + zoo.HELD_OUT:
        w = zoo.problem(pname).train
        print(f"| {pname} | {'at rest' if w.x0 is None else _rho(w)} |")
    for ex in ("linear", "nonlinear"):
        for data in ("initial", "sliding"):
            w = training_data(example_spec(ex), 0, 0, data, 25)[2]
            print(f"| {ex}, {data} | {_rho(w)} |", flush=True)


def paper():
    from dissil_jax.experiments.protocol import example_spec, training_data

    print("| example | plant | r | trainer | balance=False | balance=True |")
    print("|---|---:|---:|---|---:|---:|")
    for ex, plants in (("linear", (0, 1, 2)), ("nonlinear", (0,))):
        spec = example_spec(ex)
        for i in plants:
            w = training_data(spec, i, 0, "initial", 25)[2]
            for name in ("fit_direct", "fit_pgd", "fit_gd"):
                print(f"| {ex} | {i} | {output_ratio(w):.2g} | `{name}` | "
                      f"{_cell(name, w, spec.qsr, 1.0, False)} | "
                      f"{_cell(name, w, spec.qsr, 1.0, True)} |", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--curve", action="store_true")
    ap.add_argument("--held-out", action="store_true")
    ap.add_argument("--rate", action="store_true")
    ap.add_argument("--paper", action="store_true")
    ap.add_argument("--states", action="store_true")
    a = ap.parse_args()
    if a.curve:
        curve()
    if a.held_out:
        held_out()
    if a.rate:
        rate()
    if a.paper:
        paper()
    if a.states:
        states()
        both_sides()
