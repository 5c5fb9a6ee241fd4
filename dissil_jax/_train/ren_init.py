"""`fit_ren(init=...)`: runs that start at given controllers instead of random draws.

A given controller is carried into the units the runs train in (the outputs' centre and
units and the states' units of `balance`, then the data scale $s$), and there mapped back
through the REN map (`_ren/inverse.py`): the runs then start exactly at it, and every step
stays certified as before. An LTI controller becomes a REN with `width` neurons that see
the state ($C_1$ drawn as the random starts draw their parameters, $\\mathcal N(0,
\\text{init\\_scale}^2)$ entries) but do not yet act on the output ($D_{21} = 0$): it
computes exactly what the LTI controller computes, and the gradient reaches $D_{21}$ at the
first step. (With both $C_1$ and $D_{21}$ zero the neurons would sit at a stationary
point and never move.)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._controller import LTIController
from .._direct_map import MARGIN
from .._progress import working
from .._rate_scale import rate_factor, scaled_rate
from .._ren.controller import RENController
from .._ren.inverse import ren_params_of
from .._ren.map import ren_map
from .._supply import QSR
from .._validate import warn_user
from ._units import Units
from .result import FitResult

# An LTI start's drawn neuron inputs C1 are shrunk by this factor, up to `_TRIES` times,
# until the REN has a certificate with the map's room; the last try has C1 = 0 (in the
# image whenever the LTI controller is).
_SHRINK, _TRIES = 0.25, 3

#: `fit_ren`'s default Adam step with `init`: on the problem zoo's tuning half, started at
#: `fit_direct`'s controllers, it gave the lowest geometric mean of the median final loss
#: and of the median held-out error among 0.1-0.001 (`benchmarks/bench_ren_init.py`).
WARM_LEARNING_RATE = 0.003

#: `fit_ren`'s margins with `init` and no `margin` given, tried in turn until every start
#: is in the map's reach.
INIT_MARGINS = (MARGIN, MARGIN / 10, MARGIN / 100)


def start_controllers(init, *, num_inits: int, n_state: int, width: int, n_in: int,
                      n_out: int, odd: bool, direct_input: bool, activation):
    """`init` as `(K, lti)`: a batch of `num_inits` controllers as nine float64 numpy
    arrays each `[num_inits, ...]` (an LTI controller as a width-`width` REN with idle
    neurons), and whether it was LTI; a `ValueError` naming `init` for anything
    `fit_ren` cannot start from."""
    init = _controllers(init)
    lti = isinstance(init, LTIController)
    if not lti and odd:
        raise ValueError("`init` cannot be a REN with `odd=True`: the runs train the REN "
                         "whose odd part is returned, which a REN does not determine. Pass "
                         "an LTI controller (its own odd part), or `odd=False`.")
    sizes = dict(n_state=(init.n_state, n_state), n_in=(init.n_in, n_in),
                 n_out=(init.n_out, n_out))
    if not lti:
        sizes["width"] = (init.width, width)
    for name, (got, want) in sizes.items():
        if got != want:
            raise ValueError(f"`init` has {name} {got}, but the runs need {want} (from "
                             "`windows`, `n_state` and `width`).")
    batch = init.batch_shape
    if batch not in ((), (num_inits,)):
        raise ValueError(f"`init` has batch shape {batch}: pass one controller, or "
                         f"`num_inits` ({num_inits}) of them.")
    if not lti and init.activation != activation:
        raise ValueError(f"`init` is a REN with activation {init.activation!r}, but the runs "
                         f"use {activation!r}: pass `activation=init.activation` to start "
                         "from the controller as it is.")
    if not lti and not direct_input and np.any(np.asarray(init.D12) != 0):
        raise ValueError("`init` has a nonzero `D12` (the neurons' direct input), which "
                         "the runs train only with `direct_input=True`.")
    K = RENController.from_lti(init, width) if lti else init
    mats = tuple(np.broadcast_to(np.asarray(M, np.float64), (num_inits,) + M.shape[-2:])
                 for M in K.matrices)
    return mats, lti


def balanced_controllers(K: tuple, units: Units, s: float) -> tuple:
    """Controllers (nine numpy arrays) in the runs' units: the inverse of
    `Units.controllers` (outputs moved by the centre $M$ and divided by $c$, states by
    $d$), then of `ren.to_user_units` (data scale $s$)."""
    A, B1, B2, C1, D11, D12, C2, D21, D22 = K
    if units.centre is not None:
        D22 = D22 + units.centre
    C2, D21, D22 = C2 / units.c, D21 / units.c, D22 / units.c
    if units.d is not None:
        d = units.d
        A = A * (1.0 / d)[:, None] * d[None, :]
        B1, B2 = B1 / d[:, None], B2 / d[:, None]
        C1, C2 = C1 * d[None, :], C2 * d[None, :]
    return A, B1 / s, B2, C1 * s, D11, D12 * s, C2, D21 / s, D22


def initial_params(init, key, qsr: QSR, units: Units, s2, *, num_inits: int, n_state: int,
                   width: int, n_in: int, n_out: int, init_scale: float, margins: tuple,
                   direct_input: bool, odd: bool, activation, dtype, progress: bool = False):
    """`(theta0, margin)`: the REN map's parameters (batched, `dtype`) at which `fit_ren`'s
    runs start, for the balanced rate `qsr` and the data scale `s2`, at the first of
    `margins` that reaches every start; a `ValueError` naming `init` when none does."""
    K, lti = start_controllers(init, num_inits=num_inits, n_state=n_state, width=width,
                               n_in=n_in, n_out=n_out, odd=odd, direct_input=direct_input,
                               activation=activation)
    K = balanced_controllers(K, units, float(s2) ** 0.5)
    rate = scaled_rate(qsr, rate_factor(qsr))  # the rate `solved_rate` trains in
    draws = [np.asarray(init_scale * jr.normal(k, (width, n_state)), np.float64)
             if lti and width else None for k in jr.split(key, num_inits)]
    tol = _EXACT if np.finfo(dtype).eps < 1e-10 else _EXACT_SINGLE
    reached = []  # (deviation, margin, parameters) at each margin that reaches every start
    for margin in margins:
        what = (f"mapping {num_inits} starts back through the REN map at margin {margin:g} "
                f"(an SDP each, of order {2 * n_state + width + n_in})")
        with working("fit_ren", what, progress):
            found, off = [], 0.0
            for i in range(num_inits):  # up to the first start out of reach
                Ki = [np.array(M[i]) for M in K]
                found.append(_start(Ki, draws[i], rate, margin, direct_input))
                if found[-1] is None:
                    break
                off = max(off, _deviation(found[-1], Ki, rate, margin, direct_input, dtype))
        if found[-1] is None:
            continue
        reached.append((off, margin, found))
        if off <= tol:  # else reached only approximately: try a smaller margin
            break
    if reached:
        off, margin, found = min(reached, key=lambda r: r[0])
        if off > tol:
            warn_user(f"`init` was reached only approximately (at `margin` {margin:g}, the "
                      f"closest of {len(reached)}): the REN map's value at the runs' start "
                      f"differs from the given controllers by up to {off:.1e} of their "
                      "largest entry, so the first loss is not the start's. The SDP that "
                      "maps a start back loses accuracy on ill-conditioned rates (gain "
                      "bounds of 1e-4 and below).")
        return jax.tree.map(lambda *a: jnp.asarray(np.stack(a), dtype), *found), margin
    bad = len(found) - 1
    where = f"`init[{bad}]`" if _controllers(init).batch_shape else "`init`"
    tried = ", ".join(f"{m:g}" for m in margins)
    raise ValueError(
        f"{where} is not in the set `fit_ren` trains in at `margin` {tried}: no certificate "
        "(P, Λ) leaves the REN map the room it needs there (for the supply rate in the runs' units). A "
        "controller on the edge of the set (trained by `fit_pgd` or `fit_ico`, or "
        "projected) may not be; pass a smaller `margin`, or another start.")


def _start(Ki: list, draw, rate: QSR, margin: float, direct_input: bool):
    """The parameters that map to the REN `Ki` (nine float64 matrices) at `margin`, or None
    when it is out of the map's reach. An LTI start's neuron inputs are `draw`, shrunk
    until the REN is in reach (the last try without them)."""
    for t in range(_TRIES + 1 if draw is not None else 1):
        if draw is not None:
            Ki[3] = draw * (_SHRINK**t if t < _TRIES else 0.0)
        got = ren_params_of(tuple(Ki), rate, margin, direct_input)
        # the SDP's δ is accurate to its tolerance: a δ this small below zero changes the
        # start by as little (Γ's eigenvalues are clipped at zero)
        if got is not None and got[1] >= -_REACH * margin:
            return got[0]
    return None


_REACH = 1e-3

# How far the map's value at a start may lie from the given controller, relative to its
# largest entry, before a smaller margin is tried: far above the SDP's and the map's
# round-off (about 1e-9 in float64), far below a visible change of the loss. In float32
# the map's own round-off is about 1e-6.
_EXACT, _EXACT_SINGLE = 1e-6, 1e-3


def _deviation(theta, Ki, rate: QSR, margin: float, direct_input: bool, dtype) -> float:
    """The largest entry of (the REN map at `theta`) minus `Ki`, over `Ki`'s largest entry,
    the map evaluated in the runs' `dtype`."""
    width = Ki[3].shape[0]
    K, _, _ = ren_map(jax.tree.map(lambda a: jnp.asarray(a, dtype), theta), rate, width,
                      "tanh", margin, direct_input)
    got = K.matrices
    size = max((float(np.abs(M).max()) for M in Ki if M.size), default=0.0)
    diff = max((float(np.abs(np.asarray(G, np.float64) - M).max())
                for G, M in zip(got, Ki) if M.size), default=0.0)
    return diff / size if size > 0 else diff


def _controllers(init):
    """The controllers of `init` (a controller or a `FitResult`), or a `ValueError`."""
    if isinstance(init, FitResult):
        init = init.controllers
    if not isinstance(init, (LTIController, RENController)):
        raise ValueError("`init` must be a `dj.LTIController`, a `dj.RENController` or a "
                         f"`FitResult` of one, got {type(init).__name__}.")
    return init


def init_controllers_order(init) -> int:
    """The order $\\hat n$ of `init`'s controllers (for windows that start at rest)."""
    return _controllers(init).n_state
