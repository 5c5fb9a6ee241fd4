"""Units in which [`certify_ren`][dissil_jax.certify_ren] solves its SDP: the neurons' and
the states', both chosen from the augmented system (`augmented_lti`), and mapped back
exactly or re-checked in the controller's own units."""

from __future__ import annotations

import numpy as np

from .._certify.coordinates import balanced_states, safe_norms, state_scale
from .._controller import LTIController

#: The coordinates `certify_ren` tries, in order, until a pair passes the float64 check:
#: `True` alternates the states' and the neurons' balancing, states first; `False`
#: balances the neurons once, then the states. Neither is always better. States in units
#: 2^100 from the neurons' defeat the second (the B1 column of the large state dominates
#: every neuron's effect, and Clarabel failed); on RENs trained for supply rates with
#: |Q| ~ 1e6 times R (`benchmarks/bench_ren.py --tight`) the first left 3 of 16 runs
#: uncertified where the second certified 2 of them.
COORDINATES = (True, False)


def coordinates(G: LTIController, q: int, states_first: bool):
    """`(d, ts)`: the neuron units (`neuron_scale`) and the states' (`state_scale`) of the
    augmented system `G` with `q` neurons, in the order `states_first` says (see
    `COORDINATES`)."""
    mats = lambda H: tuple(np.asarray(M, np.float64) for M in (H.A, H.B, H.C))
    if not states_first:
        d = neuron_scale(G, q)
        return d, state_scale(*mats(unit_multiplier(G, d)))
    d = np.ones(q)
    for _ in range(4):  # rounds
        ts = state_scale(*mats(unit_multiplier(G, d)))
        d, d_old = neuron_scale(LTIController(*balanced_states(*mats(G), ts), G.D), q), d
        if np.allclose(d, d_old, rtol=1e-3):
            break
    return d, ts


def neuron_scale(G: LTIController, q: int, sweeps: int = 30) -> np.ndarray:
    """Neuron units in which each neuron's input and effect have one size.

    In the units $\\tilde w = d^{1/2}w$, $\\tilde v = d^{1/2}v$ (`unit_multiplier` with
    $d$), neuron $i$'s column of $[B_1; D_{11}; D_{21}]$ (its effect on
    $(x^+, v, \\hat y)$) and its row of $[C_1\\ D_{11}\\ D_{12}]$ (its input) are balanced
    to equal 2-norms by a few damped sweeps (the $D_{11}$ entries couple the neurons, as in
    matrix balancing). A multiplier found there is $\\tilde\\Lambda = \\Lambda/d$, and the
    SDP is well scaled: a REN trained on data of size $s$ and returned in those units has
    $\\Lambda\\sim s^2$ against $P\\sim1$, which Clarabel failed on from $s = 10^3$."""
    d = np.ones(q)
    for _ in range(sweeps):
        Gd = unit_multiplier(G, d)
        B, C, D = (np.asarray(M, np.float64) for M in (Gd.B, Gd.C, Gd.D))
        out = safe_norms(np.concatenate([B[:, :q], D[:, :q]], 0), 0)
        inp = safe_norms(np.concatenate([C[:q], D[:q]], 1), 1)
        ok = (out > 0) & (inp > 0) & np.isfinite(out) & np.isfinite(inp)
        # damped; in logarithms, as the ratio may overflow
        step = np.exp2(np.where(ok, np.log2(np.where(ok, out, 1.0))
                                - np.log2(np.where(ok, inp, 1.0)), 0.0) / 2)
        if np.all(np.abs(np.log(step)) < 1e-3):
            break
        d = d * step
    return d


def unit_multiplier(G: LTIController, lam) -> LTIController:
    """The augmented system in neuron units where $\\Lambda = I$: $w = \\Lambda^{-1/2}\\tilde w$,
    $\\tilde v = \\Lambda^{1/2}v$. Its KYP matrix under `augmented_qsr(qsr, 1)` is
    $T^\\top M(P,\\Lambda)T$ with $T = \\operatorname{diag}(I, \\Lambda^{-1/2}, I)$, a congruence,
    so it is negative definite exactly when $M$ is."""
    q = lam.shape[-1]
    r = np.sqrt(lam)
    B, C, D = (np.array(M, np.float64) for M in (G.B, G.C, G.D))
    B[..., :, :q] /= r[..., None, :]
    C[..., :q, :] *= r[..., :, None]
    D[..., :q, :] *= r[..., :, None]
    D[..., :, :q] /= r[..., None, :]
    return LTIController(G.A, B, C, D)
