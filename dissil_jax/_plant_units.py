"""Units in which the plant SDPs are solved: state and output scaled by powers of two.

A plant's supply rate does not depend on its units, but Clarabel's tolerances (about
$10^{-9}$, absolute) and the back-off's floor do: the paper's plant with its input and
output in units $10^3$ times larger (gains near $10^{-6}$) got a Lemma 8 rate whose
matrix was negative by more than the rate itself, and a realisation with $B = 10^6$,
$C = 10^{-6}$ of a strictly passive plant got an input passivity index of 0. Each SDP
therefore runs on the realisation

$$\\hat A = T^{-1}AT,\\quad \\hat B = T^{-1}B,\\quad \\hat C = CT/g,\\quad \\hat D = D/g,$$

with $x = Tz$ ($T$ diagonal) and $\\hat y = y/g$: $T$ balances the states (the LTI tools:
each state separately, as [`certify`][dissil_jax.certify] does; Lemma 8, whose bound
$P\\preceq\\tau I$ is not invariant under a diagonal $T$, by one common factor) and $g$
brings the gain to about 1. A rate $(\\hat Q, \\hat S, \\hat R)$ with storage $\\hat P$ of
the scaled plant is, multiplied by any $k > 0$, the rate
$(k\\hat Q/g^2,\\ k\\hat S/g,\\ k\\hat R)$ with storage $kT^{-\\top}\\hat PT^{-1}$ of the
plant as given; every factor is a power of two, so the map is exact in floating point.
"""

from __future__ import annotations

import numpy as np

from ._certify.coordinates import state_scale
from ._supply import QSR


def _pow2(x: float) -> float:
    """The power of two nearest `x` (> 0, finite); 1 otherwise."""
    return float(2.0 ** np.round(np.log2(x))) if np.isfinite(x) and x > 0 else 1.0


class PlantUnits:
    """The scaling of one plant: `t` (the diagonal of $T$) and `g` (powers of two)."""

    def __init__(self, A, B, C, D, *, per_state: bool = True):
        n = A.shape[0]
        t = state_scale(A, B, C) if per_state and n else np.ones(n)
        Bt, Ct = B / t[:, None], C * t[None, :]
        nb, nc, nd = (float(np.linalg.norm(M, 2)) if M.size else 0.0 for M in (Bt, Ct, D))
        self.g = _pow2(max(nd, nb * nc))
        # one more common state factor: |B^| about |C^| after the output's scaling
        self.t = t * _pow2(np.sqrt(nb / (nc / self.g)) if nb > 0 and nc > 0 else 1.0)

    def plant(self, A, B, C, D):
        """The scaled realisation $(\\hat A, \\hat B, \\hat C, \\hat D)$."""
        t = self.t
        return A * t[None, :] / t[:, None], B / t[:, None], C * t[None, :] / self.g, D / self.g

    def rate(self, qsr: QSR, k: float) -> QSR:
        """The scaled plant's rate as the plant's, times `k` (a power of two: `g` for rates
        with $S = \\tfrac12I$, `g**2` for cones, so that their forms are kept)."""
        g = self.g
        return QSR(qsr.Q * (k / g**2), qsr.S * (k / g), qsr.R * k)

    def storage(self, P, k: float):
        """The scaled plant's storage as the plant's ($x = Tz$), times `k` (as `rate`)."""
        return k * P / np.outer(self.t, self.t)
