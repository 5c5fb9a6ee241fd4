"""Cones away from zero: the trainers with and without solving about the rate's centre.

A cone rate ([a, b]: Q = -I, S = (a + b)/2 I, R = -ab I) admits the feedthroughs near
(a + b)/2; far from zero its entries are large against its room (b - a)^2/4. The library
solves such a rate about its centre when its centre's term -S'Q^-1 S exceeds 64 times its
room along some direction (`dissil_jax.internal.rate_scale.centring`; the trainers under `balance=True`, the
projection always). Per cell: the median final loss over 4 initialisations, solved as
given ("plain": `centring` switched off in the trainers and the projection, as before)
and about the centre ("centred": forced, whatever the ratio), both on the same windows in
the same run, with every trainer's defaults, and which of the two the library picks; runs
that raised are shown as their error. Every returned controller is certified (the
trainers' own float64 check). "ratio" is `centring`'s criterion, the term -S'Q^-1 S over the room
lambda_min(R - S'Q^-1 S) (4 (a + 1/2)^2 for [a, a + 1]).

Data: `expert_windows` (a projected random expert of order 3 whose feedthrough lies
anywhere in the cone, 20 windows of length 10, output noise 0.01), so the expert's own
loss is about 1e-3.

1. `--tuning` (chose the threshold 64): cones [a, a + 1], a = 1, 3, 10 (ratios 9, 49,
   441), seeds 1 and 2.
2. `--held-out` (reported, not used to choose): [5, 6] and [300, 301] (seed 3), the wider
   cone [20, 24] (ratio 121), and the 2x2 cone [50, 50.5] (seed 4).

Usage: python benchmarks/bench_far_cones.py [--tuning] [--held-out]
"""

from __future__ import annotations

import argparse
import contextlib

import jax
import jax.random as jr
import numpy as np

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.internal import rate_scale  # noqa: E402

_MODULES = ("dissil_jax._train._units", "dissil_jax._projection.rows",
            "dissil_jax._projection.admm_rate")


@contextlib.contextmanager
def centring_as(fn):
    """`centring` replaced by `fn` in the trainers and the projection."""
    import sys

    saved = [getattr(sys.modules[m], "centring") for m in _MODULES]
    for m in _MODULES:
        setattr(sys.modules[m], "centring", fn)
    try:
        yield
    finally:
        for m, f in zip(_MODULES, saved):
            setattr(sys.modules[m], "centring", f)


def forced(qsr):
    """The centring of every rate with Q < 0 and S != 0, whatever its ratio."""
    return rate_scale.centre_of(qsr)[:2]


def ratio(qsr) -> float:
    """`centring`'s criterion: the largest generalised eigenvalue of the term
    T = -S'Q^-1 S against the room R - S'Q^-1 S (scalar for these diagonal cones)."""
    return rate_scale.centre_of(qsr)[2]


def expert_windows(seed, qsr, a, b, n=3, num_windows=20, horizon=10, noise=0.01):
    """Windows of an expert whose feedthrough lies anywhere in the cone: a random order-3
    controller (entries N(0, 1)) with a + (b - a) v, v ~ U(0, 1), added to D, projected
    onto the rate; x0 and y ~ N(0, 1), u = -expert + noise (as `realisable_windows`, whose
    projection of a draw near zero puts every expert on the cone's edge nearest zero,
    where the plain projection also puts the initial controllers)."""
    kK, kv, kx, ky, kn = jr.split(jr.PRNGKey(seed), 5)
    p = qsr.n_in
    K = dj.LTIController.random(kK, n, p, p, scale=1.0)
    K = dj.LTIController(K.A, K.B, K.C, K.D + (a + (b - a) * jr.uniform(kv)) * np.eye(p))
    K, _ = dj.project(K, qsr)
    x0 = jr.normal(kx, (num_windows, n))
    y = jr.normal(ky, (num_windows, horizon, p))
    u = -jax.vmap(lambda x, yk: dj.rollout(K, x, yk))(x0, y)
    return dj.Windows(x0, y, u + noise * jr.normal(kn, u.shape))


def _median(trainer, w, qsr):
    try:
        res = getattr(dj, f"fit_{trainer}")(jr.PRNGKey(0), w, qsr, n_state=3, num_inits=4,
                                            progress=False)
    except ValueError as e:
        return f"error: {str(e)[:40]}"
    assert bool(np.all(res.certified))
    return f"{float(np.median(np.asarray(res.final_loss))):.3g}"


def table(title, cases):
    print(f"\n{title}\n")
    print("| cone | dim | seed | ratio | trainer | plain | centred | library |")
    print("|---|---:|---:|---:|---|---:|---:|---|")
    for a, b, dim, seed in cases:
        qsr = dj.QSR.conic(a, b, dim=dim)
        w = expert_windows(seed, qsr, a, b)
        for trainer in ("direct", "pgd"):
            with centring_as(lambda qsr: None):
                before = _median(trainer, w, qsr)
            with centring_as(forced):
                after = _median(trainer, w, qsr)
            choice = "centred" if rate_scale.centring(qsr) is not None else "plain"
            print(f"| [{a:g}, {b:g}] | {dim} | {seed} | {ratio(qsr):.0f} | {trainer} | "
                  f"{before} | {after} | {choice} |", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tuning", action="store_true")
    ap.add_argument("--held-out", action="store_true")
    args = ap.parse_args()
    if args.tuning:
        table("Tuning: cones [a, a + 1]", [(a, a + 1.0, 1, s) for a in (1.0, 3.0, 10.0)
                                           for s in (1, 2)])
    if args.held_out:
        table("Held out", [(5.0, 6.0, 1, 3), (300.0, 301.0, 1, 3), (20.0, 24.0, 1, 3),
                           (50.0, 50.5, 2, 4)])


if __name__ == "__main__":
    main()
