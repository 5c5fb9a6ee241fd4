"""Supply rates far from unit size: solved divided by a power of two (trainers, `project`)."""

from __future__ import annotations

import functools

import numpy as np

from ._supply import QSR

#: Supply rates whose largest entry lies in [1/RATE_BAND, RATE_BAND] are used as given.
RATE_BAND = 64.0


@functools.lru_cache(maxsize=256)
def rate_factor(qsr: QSR) -> float:
    """The factor $\\kappa$ by which the trainers and `project` divide a supply rate.

    Dissipativity does not depend on the rate's scale ($w$ and $\\kappa w$ admit the same
    controllers, with storages $P$ and $\\kappa P$), but the numerics do: the LMI margin
    $\\varepsilon$, the solvers' tolerances and the direct map's $P\\approx I$ start are
    absolute. So a rate whose largest entry lies outside $[1/64, 64]$ is divided by
    $\\kappa = 2^{\\operatorname{round}(\\log_2\\sigma)}$, $\\sigma$ its size: the largest
    entry, or for $Q\\prec0$ the room $\\lambda_{\\min}(R - S^\\top Q^{-1}S)$ when that is
    smaller (a narrow cone far from zero has large entries and little room, and the margin
    must stay small against the room). The storage found is multiplied back; a power of
    two keeps both steps exact, so the float64 check sees the same matrix in both scales.
    1 for every other rate (all of the paper's and the zoo's).
    """
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    size = max(float(np.abs(M).max(initial=0.0)) for M in (Q, S, R))
    if not out_of_band(size):
        return 1.0
    if np.linalg.eigvalsh(Q)[-1] < 0:
        room = float(np.linalg.eigvalsh(R - S.T @ np.linalg.solve(Q, S))[0])
        if 0.0 < room < size:
            size = room
    return float(nearest_power_of_two(size))


def out_of_band(size):
    """Whether a rate of this size (its largest entry; vectorised) is solved divided by a
    power of two: nonzero and outside $[1/64, 64]$."""
    size = np.asarray(size, np.float64)
    return (size > 0) & ((size < 1.0 / RATE_BAND) | (size > RATE_BAND))


def nearest_power_of_two(size):
    """$2^{\\operatorname{round}(\\log_2 s)}$ for positive sizes $s$ (vectorised)."""
    return 2.0 ** np.clip(np.round(np.log2(size)), -500, 500)


def unit_scale(M) -> float:
    """The power of two $t$ that brings a block to unit size: $t^2\\max_{ij}|M_{ij}|$ within a
    factor 2 of 1 (1 for $M = 0$). Congruences by such factors (y = t_y y~, u = t_u u~)
    balance a supply rate's $Q$ and $R$ blocks exactly."""
    size = float(np.abs(np.asarray(M, np.float64)).max(initial=0.0))
    return 1.0 if size == 0.0 else float(nearest_power_of_two(size ** -0.5))


def balanced_blocks(qsr: QSR, cross: bool = False) -> tuple[float, float, QSR]:
    """`(t_y, t_u, rate)`: the powers of two `unit_scale(Q)`, `unit_scale(R)` and the rate
    in the output and input units $y = t_y\\tilde y$, $u = t_u\\tilde u$,
    $(t_y^2Q, t_yt_uS, t_u^2R)$: a congruence, so the same inertia and, for a controller
    $(A, Bt_u, C/t_y, Dt_u/t_y)$, the same dissipation inequality with the same storage.

    With `cross`, a zero $Q$ or $R$ block takes its unit from $S$ instead, so that
    $t_yt_u\\max|S_{ij}|$ is within a factor 2 of 1 (both from $S$ when both are zero): a
    degenerate cone ($Q = 0$) whose $S$ is tiny against $R$ has its whole static set
    below round-off otherwise."""
    t_y, t_u = unit_scale(qsr.Q), unit_scale(qsr.R)
    size = lambda M: float(np.abs(np.asarray(M, np.float64)).max(initial=0.0))
    s = size(qsr.S)
    if cross and s > 0.0 and (size(qsr.Q) == 0.0 or size(qsr.R) == 0.0):
        if size(qsr.Q) == 0.0 and size(qsr.R) == 0.0:
            t_y = t_u = unit_scale(qsr.S)
        elif size(qsr.Q) == 0.0:
            t_y = float(nearest_power_of_two(1.0 / (t_u * s)))
        else:
            t_u = float(nearest_power_of_two(1.0 / (t_y * s)))
    return t_y, t_u, QSR(t_y**2 * qsr.Q, t_y * t_u * qsr.S, t_u**2 * qsr.R)


def scaled_rate(qsr: QSR, k: float) -> QSR:
    """The supply rate $(Q, S, R)/\\kappa$ (`qsr` itself when $\\kappa = 1$)."""
    return qsr if k == 1.0 else QSR(qsr.Q / k, qsr.S / k, qsr.R / k)


@functools.lru_cache(maxsize=256)
def centring(qsr: QSR) -> tuple[np.ndarray, QSR] | None:
    """`(M, rate)`: the centre $M = Q^{-1}S$ of a narrow cone far from zero and the rate
    about it, $(Q, 0, R - S^\\top Q^{-1}S)$; None for every other rate.

    For $Q\\prec0$, with $\\hat y = \\hat y' - M\\hat u$ the supply is
    $w = \\hat y'^\\top Q\\hat y' + \\hat u^\\top(R - S^\\top Q^{-1}S)\\hat u$, so the
    controller $(A, B, C, D)$ is dissipative for $(Q, S, R)$ with storage $P$ exactly when
    $(A, B, C, D + M)$ is for the centred rate, with the same KYP matrix. The shift moves
    every controller by the same $M$, so a Euclidean projection commutes with it.

    A rate is centred when, along some input direction, its centre's term outweighs its
    room more than `RATE_BAND` times: $\\lambda_{\\max}(\\Pi^{-1/2}T\\Pi^{-1/2}) > 64$ with
    $T = -S^\\top Q^{-1}S\\succeq0$ and the room $\\Pi = R - S^\\top Q^{-1}S$ (a generalised
    eigenvalue). The LMI's input block near the centre, $R + S^\\top D + D^\\top S +
    D^\\top QD$, is then a difference of terms that many times its size along that
    direction (a cone $[a, a + 1]$: $4(a + \\frac12)^2$, four million at $a = 10^3$, where
    Clarabel reported the projection infeasible). The ratio does not change with the units
    of the outputs or the inputs, nor with the rate's size, so a wide cone in small units
    ($[0.5, 1.5]\\cdot10^{-3}$: 4) is left to the trainers' balancing of units. It is taken
    per direction: a cone $[0, 100]$ on one channel beside $[-1, 1]$ on another has a large
    term (2500) but as much room along it (ratio 1), and centring it moved the trainers'
    feedthrough 50 away from a start near the data; so did a $Q$ with one tiny eigenvalue
    ($-\\operatorname{diag}(1, 10^{-3})$), whose centre $Q^{-1}S$ runs away along it.
    """
    found = centre_of(qsr)
    if found is None or not found[2] > RATE_BAND:
        return None
    return found[0], found[1]


@functools.lru_cache(maxsize=256)
def centre_of(qsr: QSR) -> tuple[np.ndarray, QSR, float] | None:
    """`(M, rate, ratio)` of `centring` whatever the ratio: the centre $M = Q^{-1}S$, the
    rate about it and $\\lambda_{\\max}(\\Pi^{-1/2}T\\Pi^{-1/2})$; None unless
    $Q\\prec0$, $S\\ne0$ and the room $\\Pi\\succ0$."""
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    q = np.linalg.eigvalsh((Q + Q.T) / 2)
    if not q.size or q[-1] >= 0 or not np.any(S):
        return None
    M = np.linalg.solve(Q, S)
    term = -S.T @ M
    term = (term + term.T) / 2
    room = R + term
    room = (room + room.T) / 2
    try:
        L = np.linalg.cholesky(room)
    except np.linalg.LinAlgError:
        return None  # no room: no strictly dissipative static gain to centre on
    X = np.linalg.solve(L, np.linalg.solve(L, term).T)  # L^-1 T L^-T
    ratio = float(np.linalg.eigvalsh((X + X.T) / 2)[-1])
    return M, QSR(Q, np.zeros_like(S), room), ratio
