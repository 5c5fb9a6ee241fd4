"""Experts on the edge of the dissipative set: `fit_direct` against `fit_pgd` and `fit_ico`.

`fit_direct`'s map keeps every controller a margin inside the set, KYP(P) <= -eps
diag(P, Phi0) with Phi0 the input block at its feedthrough centre, and its contractions
flatten near the edge; the projection-based trainers reach the edge itself. Three
problems whose best controller lies on the edge (found by a new-user audit), order 2, 8
initialisations, float64; per cell the best final loss, with the zero controller's for
scale:

1. a gain bound of 1 and the static expert y = u, on the bound;
2. passivity (m = p = 2) and the lossless static expert D = [[0, 1], [-1, 0]];
3. the cone [10, 1000] and `realisable_windows` (an expert projected onto the cone from a
   draw near zero, so on its edge nearest zero).

Two-step windows from a random state, 50 of them. `fit_direct` with its defaults, and
with `margin=1e-4` and `max_steps=5000`.

Usage: python benchmarks/bench_edge_experts.py
"""

from __future__ import annotations

import jax
import jax.random as jr
import numpy as np

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments.data import realisable_windows  # noqa: E402


def static_windows(D, n=2, num_windows=50, seed=0):
    """Two-step windows of the static expert y_hat = D u_hat from random states."""
    D = np.asarray(D, np.float64)
    kx, ky = jr.split(jr.PRNGKey(seed))
    y = jr.normal(ky, (num_windows, 2, D.shape[1]))
    return dj.Windows(jr.normal(kx, (num_windows, n)), y, -np.einsum("ij,nkj->nki", D, y))


def main():
    cone = dj.QSR.conic(10.0, 1000.0, dim=1)
    cases = [
        ("gain bound 1, expert on the bound", dj.QSR.bounded_gain(1.0, n_in=1, n_out=1),
         static_windows([[1.0]])),
        ("passive, lossless expert", dj.QSR.passive(2), static_windows([[0.0, 1.0], [-1.0, 0.0]])),
        ("cone [10, 1000], realisable", cone,
         realisable_windows(jr.PRNGKey(0), cone, n_state=2, num_windows=50, noise=0.01)[0]),
    ]
    runs = [("fit_direct", dj.fit_direct, {}),
            ("fit_direct, margin 1e-4, 5000 steps", dj.fit_direct,
             {"margin": 1e-4, "max_steps": 5000}),
            ("fit_pgd", dj.fit_pgd, {}), ("fit_ico", dj.fit_ico, {})]
    print("| problem | zero controller | " + " | ".join(r[0] for r in runs) + " |")
    print("|---|---:|" + "---:|" * len(runs))
    for name, qsr, w in cases:
        zero = float(np.mean(np.sum(np.asarray(w.u) ** 2, axis=(1, 2))))
        cells = []
        for _, fit, kw in runs:
            extra = {} if fit is dj.fit_ico else {"n_state": 2}
            res = fit(jr.PRNGKey(1), w, qsr, progress=False, **extra, **kw)
            assert bool(np.all(res.certified))
            cells.append(f"{float(np.min(res.final_loss)):.2g}")
        print(f"| {name} | {zero:.2g} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
