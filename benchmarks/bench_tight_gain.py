"""Tight gain bounds (|Q| >> R): the certified trainers with and without `balance`.

The controller rate is `stabilising_qsr` of a plant's H-infinity bound (1.01 times it), a
gain bound far below the outputs' size when the plant's gain is large. The plants start at
a recorded state; their outputs are much larger than their states, so the states'
balancing (`balance=True`, docs "Units of the states") applies. Per plant and trainer:
the best of 8 runs' final loss over the zero controller's, J(0), with `balance=False`
and `balance=True` (the default), and the runs' outcomes.

Plants (SISO, an LQR expert u = -Kx + noise 0.02, 25 windows of two steps, x0 ~ N(0, I)):
- `two-state`: the plant of `tests/test_pgd_tight_gain.py` (outputs x 100);
- `drss4`: a python-control `drss` draw of order 4, outputs x 100 (seed 1);
- `drss8`: a `drss` draw of order 8 with its poles moved to radius 0.98 (lightly damped;
  seed 2), outputs as drawn;
- `resonant`: a two-state oscillator with poles at radius 0.995 and |C| = 1, whose large
  gain comes from the resonance, not from units (its states and outputs are of one size).

Usage: python benchmarks/bench_tight_gain.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import control  # noqa: E402
import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import state_ratios  # noqa: E402


def _hinf(A, B, C) -> float:
    z = np.exp(1j * np.linspace(0.0, np.pi, 4001))
    n = A.shape[0]
    return max(abs((C @ np.linalg.solve(zi * np.eye(n) - A, B))[0, 0]) for zi in z)


def _problem(A, B, C, seed):
    rng = np.random.default_rng(seed)
    K, _, _ = control.dlqr(A, B, C.T @ C / np.abs(C).max() ** 2, np.eye(1))
    n = A.shape[0]
    x0 = rng.standard_normal((25, n))
    u0 = -x0 @ K.T + 0.02 * rng.standard_normal((25, 1))
    x1 = x0 @ A.T + u0 @ B.T
    u1 = -x1 @ K.T + 0.02 * rng.standard_normal((25, 1))
    X, U = np.stack([x0, x1], 1), np.stack([u0, u1], 1)
    w = dj.Windows(x0, X @ C.T, U)
    qsr = dj.stabilising_qsr(dj.QSR.bounded_gain(1.01 * _hinf(A, B, C), n_in=1, n_out=1))
    return w, qsr


def problems():
    A = np.array([[0.8, 0.2], [-0.1, 0.7]])
    B = np.array([[1.0], [0.5]])
    yield "two-state", _problem(A, B, 100.0 * np.array([[1.0, -0.5]]), 0)
    s = control.drss(4, 1, 1, strictly_proper=True)  # seeded below, before each draw
    yield "drss4", _problem(s.A, s.B, 100.0 * s.C, 1)
    s = control.drss(8, 1, 1, strictly_proper=True)
    lam, V = np.linalg.eig(s.A)
    A8 = np.real(V @ np.diag(0.98 * lam / np.abs(lam)) @ np.linalg.inv(V))
    yield "drss8", _problem(A8, s.B, s.C, 2)
    # a large gain from a resonance, not from units: states and outputs of one size
    r, th = 0.995, 0.3
    A2 = r * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    yield "resonant", _problem(A2, np.array([[1.0], [0.0]]), np.array([[0.6, 0.8]]), 3)


def main():
    np.random.seed(0)  # python-control's drss draws from numpy's global generator
    fits = {"fit_direct": dj.fit_direct, "fit_pgd": dj.fit_pgd, "fit_ico": dj.fit_ico}
    print("| plant | rho | |Q|/R | trainer | balance=False | balance=True |")
    print("|---|---:|---:|---|---:|---:|")
    for name, (w, qsr) in problems():
        J0 = float(np.mean(np.sum(np.asarray(w.u) ** 2, axis=(1, 2))))
        rho = state_ratios(w)
        ratio = float(-np.asarray(qsr.Q)[0, 0] / np.asarray(qsr.R)[0, 0])
        for fname, fit in fits.items():
            cells = []
            for balance in (False, True):
                r = fit(jr.PRNGKey(0), w, qsr, num_inits=8, throw=False, balance=balance,
                        progress=False)
                ok = np.asarray(r.certified)
                best = float(np.min(np.where(ok, np.asarray(r.final_loss), np.inf))) / J0
                outcomes = sorted(set(r.result_names()))
                cells.append(f"{best:.3g} ({int(ok.sum())}/8 cert.; {', '.join(outcomes)})")
            print(f"| {name} | {rho.min():.2g}-{rho.max():.2g} | {ratio:.1e} | `{fname}` | "
                  f"{cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
