"""A plant's supply in the frequency domain: why no strict certificate of a rate exists."""

from __future__ import annotations

import numpy as np

from ._supply import QSR


def _least(G, qsr: QSR) -> float:
    """$\\lambda_{\\min}$ of the supply $\\Pi = G^*QG + G^*S + S^\\top G + R$ at a response $G$."""
    Pi = G.conj().T @ qsr.Q @ G + G.conj().T @ qsr.S + qsr.S.T @ G + qsr.R
    return float(np.linalg.eigvalsh((Pi + Pi.conj().T) / 2)[0])


def vanishing_supply(A, B, C, D, qsr: QSR, points: int = 256) -> str | None:
    """Why backing off a rate's index cannot help, when its supply vanishes somewhere.

    A strict certificate of $(Q,S,R)$ for the plant $G(z) = C(zI - A)^{-1}B + D$ needs the
    supply $\\Pi(z) = G^*QG + G^*S + S^\\top G + R\\succ0$ on $|z| = 1$, and its input
    block needs $\\Pi$ at the feedthrough $G = D$ positive too ($\\Phi(D)\\succ B^\\top PB$).
    Where the response vanishes, a rate with $R = 0$ has $\\Pi = 0$ whatever its index:
    for a plant without feedthrough ($D = 0$), or a Tustin-discretised one at $z = -1$.

    **Returns:** a sentence for the error message, or None when $\\Pi$ is positive at the
    feedthrough and on a grid of `points` frequencies in $[0, \\pi]$.
    """
    scale = 1.0 + max(np.abs(M).max(initial=0.0) for M in (qsr.Q, qsr.S, qsr.R))
    n = A.shape[0]
    least = [(_least(np.asarray(D, complex), qsr), "the feedthrough D (high frequency)")]
    for w in np.linspace(0.0, np.pi, points):
        G = D + (C @ np.linalg.solve(np.exp(1j * w) * np.eye(n) - A, B) if n else 0.0)
        where = "z = 1" if w == 0 else "z = -1" if w == np.pi else f"the angle {w:.3g} rad"
        least.append((_least(G, qsr), where))
    worst, where = min(least, key=lambda t: t[0])
    if worst > 1e-9 * scale:
        return None
    return (f"The rate's supply on the plant's response is not positive at {where} (least "
            f"eigenvalue {worst:.3g}), so no index of this kind gives a strict certificate: "
            "with R = 0 the supply vanishes where the response does (a plant without "
            "feedthrough, D = 0; a Tustin-discretised plant at z = -1). "
            "`dj.input_passivity_qsr` or `dj.lti_cone_qsr` describe such plants.")
