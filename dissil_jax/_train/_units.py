"""Balancing the units of the controller's output against its input's, and of its initial
states against its input's (`fit_*`).

The trainers divide the windows by one data scale $s$ (`_scale.py`), which makes them
invariant when $x_0$, $y$ and $u$ change units *together*. The controller's input
$\\hat u = y$ and output $\\hat y = -u$ often have units of their own (a velocity in, a
force out), and then the ratio of their sizes

$$r = \\sqrt{\\frac{\\frac1N\\sum_i\\sum_k\\lVert u^{(i)}_k\\rVert^2}
{\\frac1N\\sum_i\\bigl(\\lVert x^{(i)}_0\\rVert^2 + \\sum_k\\lVert y^{(i)}_k\\rVert^2\\bigr)}}$$

sets the size of the best controller's $C$ and $D$ in the normalised units: $O(r)$.
Adam moves each entry by about its step, and the initial draws are of order one, so the
defaults were chosen for $r$ of order one. On realisable tuning problems
(`benchmarks/bench_units.py --curve`), the median final losses at $r\\approx50$ were up
to 46 times the best for $0.4\\le r\\le3.3$, and at $r\\approx1/20$ up to 23 times.

**The balancing.** When $r$ lies outside `BAND` $= [1/5, 5]$, the `fit_*` trainers take
$c = 2^{\\operatorname{round}(\\log_2 r)}$ and train on the windows $(x_0, y, u/c)$ with the
supply rate $(c^2Q, cS, R)$; the controller $(A, B, C, D)$ found there is returned as
$(A, B, cC, cD)$ with the same storage $P$, and losses as $c^2$ times theirs. For a REN
the outputs' matrices $C_2, D_{21}, D_{22}$ are multiplied by $c$; $P$ and $\\Lambda$ stay.
The two problems are the same problem: with $\\hat y = c\\hat y_b$,

$$\\hat y^\\top Q\\hat y + 2\\hat y^\\top S\\hat u + \\hat u^\\top R\\hat u =
\\hat y_b^\\top(c^2Q)\\hat y_b + 2\\hat y_b^\\top(cS)\\hat u + \\hat u^\\top R\\hat u,$$

so the dissipation inequality, its storage and its margin are unchanged. Since $c$ is a
power of two, every product with it is exact in floating point: the float64 check of the
returned controller in the user's units sees bit for bit the matrix it passed in the
balanced units, and `certified` carries over.

Inside the band nothing changes: every problem of the zoo has $0.22\\le r\\le 2.4$, and
their results stay bit for bit those of the defaults' tuning. (The paper's examples have
$r$ = 0.011-0.23; the reproduction passes `balance=False`.) The jittable cores (`pgd_run`, `direct_run`, `dj.sweep`) do not balance:
their windows may be traced.

**The states.** The same single scale $s$ also assumes that the initial states $\\hat x_0$
are of the outputs' size $y$. They need not be: a plant whose output is $y = 100x$, or
states in mm beside outputs in m, leaves $\\hat x_0/s$ tiny, the best controller's $C$ of
size 100 in the normalised units, and the runs learn next to nothing (a new user's trial:
the median final loss 0.91 of the zero controller's, against $6\\cdot10^{-5}$ in matching
units, every run certified and no warning). With

$$\\rho_i = \\frac{\\operatorname{rms}_{\\text{windows}}\\,\\hat x_{0,i}}
{\\operatorname{rms}_{\\text{windows, steps, outputs}}\\,y},$$

the trainers take $d_i = 2^{\\operatorname{round}(\\log_2\\rho_i)}$ for every state with
$\\rho_i < 1/5$ (`STATE_BAND`; $d_i = 1$ for the others), and train on the initial states
$\\hat x_{0,i}/d_i$. That is a change of the controller's state coordinates, $\\hat x =
D\\hat x_b$ with $D = \\operatorname{diag}(d)$, which every controller allows: the one
found, $(A_b, B_b, C_b, D_b)$ with storage $P_b$, is returned as $(DA_bD^{-1}, DB_b,
C_bD^{-1}, D_b)$ with storage $D^{-1}P_bD^{-1}$ (a REN: $A$, $B_1$, $B_2$ times $D$ on the
left, $A$, $C_1$, $C_2$ times $D^{-1}$ on the right, $\\Lambda$ unchanged), and the losses
are unchanged. Its dissipation matrix is the balanced one under the congruence
$\\operatorname{diag}(D^{-1}, I)$, exact in floating point; the float64 check is repeated in
the user's units all the same (`unbalance`). $d$ is chosen first, and $c$ on the windows
with $\\hat x_0/d$.

Only the small side is balanced. States far smaller than the outputs are what a plant
measured in large units gives ($y = 100x$), and there the runs fail without it (above;
`fit_pgd`'s stall on tight gain bounds was this). States far *larger* than the outputs
are measured both ways: when they are a change of units of a problem in balance, scaling
them back helped (`fit_direct` lost up to 120 times at $\\rho\\approx60$ without it), but on
plants with small output matrices ($\\rho\\approx140$) it changed nothing, and on an
audit's windows that start far from rest, in the expert's own coordinates
($\\rho\\approx30$), it cost PGD 140 times: the data cannot tell the two apart, so
they are left as they are. When states more than 16 times the outputs' size come with
runs that ended above a tenth of the zero controller's loss, the trainers warn, naming the
power of two to divide $\\hat x_0$ by if the states are in small units
(`large_states_hint`). Every problem of the zoo and the paper's examples have
$0.23\\le\\rho_i\\le3.8$ (`benchmarks/bench_units.py --states`): unchanged.
"""

from __future__ import annotations

from typing import NamedTuple, overload

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .. import _outcome
from .._data import Windows
from .._rate_scale import centring, nearest_power_of_two
from .._ren.certify import certified_batch
from .._ren.controller import RENController
from .._sdp.lmi import kyp_certified
from .._supply import QSR
from .._validate import check_flag, warn_user
from .result import raise_if_failed

#: The ratios r of output to input size that the trainers take as they are.
BAND = (0.2, 5.0)

#: The ratios rho_i of a state's size to the outputs' that the trainers take as they are:
#: only states far smaller than the outputs are rescaled (module docstring).
STATE_BAND = (0.2, float("inf"))

#: A hint is warned when some rho_i exceeds the first and the runs' median final loss the
#: second fraction of the zero controller's (`large_states_hint`).
LARGE_STATES = (16.0, 0.1)


def _power(a) -> float:
    """Mean over windows of the summed squares of `a` (`[N, ...]`), in float64."""
    a = np.asarray(a, np.float64)
    return float(np.mean(np.sum(a.reshape(a.shape[0], -1) ** 2, axis=1))) if a.size else 0.0


def output_ratio(windows: Windows) -> float:
    """$r$ of the module docstring, or NaN when the outputs or the inputs are all zero."""
    inputs = _power(windows.y) + (0.0 if windows.x0 is None else _power(windows.x0))
    outputs = _power(windows.u)
    if not (inputs > 0.0 and outputs > 0.0 and np.isfinite(inputs * outputs)):
        return float("nan")
    return float(np.sqrt(outputs / inputs))


def output_factor(windows: Windows) -> float:
    """The factor $c$ of the module docstring: 1 when $r$ is in `BAND` (or undefined), else
    the power of two nearest to $r$ (in $\\log_2$)."""
    r = output_ratio(windows)
    if not np.isfinite(r) or BAND[0] <= r <= BAND[1]:
        return 1.0
    return float(nearest_power_of_two(r))


def state_ratios(windows: Windows) -> np.ndarray:
    """$\\rho_i$ of the module docstring, per state (NaN where a state or every output is
    zero; empty for windows at rest)."""
    if windows.x0 is None:
        return np.zeros(0)
    x0, y = (np.asarray(a, np.float64) for a in (windows.x0, windows.y))
    ry = np.sqrt(np.mean(y**2)) if y.size else 0.0
    rx = np.sqrt(np.mean(x0**2, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = rx / ry
    return np.where((rx > 0) & np.isfinite(rho), rho, np.nan)


def state_factors(windows: Windows) -> np.ndarray | None:
    """The factors $d_i$ of the module docstring, or None when every $\\rho_i$ is in
    `STATE_BAND` (or undefined)."""
    rho = state_ratios(windows)
    out = np.isfinite(rho) & ((rho < STATE_BAND[0]) | (rho > STATE_BAND[1]))
    if not out.any():
        return None
    return np.where(out, nearest_power_of_two(np.where(out, rho, 1.0)), 1.0)


class Units(NamedTuple):
    """The changes of units of a `fit_*` call: the outputs divided by `c`, the initial
    states' components by `d` (None: unchanged), both powers of two, after the outputs
    were moved by the rate's centre, $\\hat y + M\\hat u$ (`centre` $= M$; None: not
    moved)."""

    c: float = 1.0
    d: np.ndarray | None = None
    centre: np.ndarray | None = None
    #: `(max rho_i, the zero controller's loss)` when some state is `LARGE_STATES[0]` times
    #: the outputs' size, for `large_states_hint`; None otherwise.
    hint: tuple[float, float] | None = None

    @property
    def none(self) -> bool:
        """No change of units."""
        return self.c == 1.0 and self.d is None and self.centre is None

    def controllers(self, K):
        """Controllers (LTI or REN, batched or not) of the balanced problem in the user's
        units: $\\hat x = D\\hat x_b$ and $\\hat y = c\\,\\hat y_b - M\\hat u$ (the
        feedthrough $D$, a REN's $D_{22}$, less $M$)."""
        if self.d is not None:
            d = self._d(K.n_state)
            names = (("A", "B1", "B2", "C1", "C2") if isinstance(K, RENController)
                     else ("A", "B", "C"))
            rows, cols = d[:, None], 1.0 / d[None, :]
            scale = {"A": rows * cols, "B": rows, "B1": rows, "B2": rows, "C": cols,
                     "C1": cols, "C2": cols}
            K = eqx.tree_at(lambda k: tuple(getattr(k, n) for n in names), K,
                            tuple(_times(getattr(K, n), scale[n]) for n in names))
        if self.c != 1.0:
            names = ("C2", "D21", "D22") if isinstance(K, RENController) else ("C", "D")
            K = eqx.tree_at(lambda k: tuple(getattr(k, n) for n in names), K,
                            tuple(self.c * getattr(K, n) for n in names))
        if self.centre is not None:
            name = "D22" if isinstance(K, RENController) else "D"
            D = getattr(K, name)
            K = eqx.tree_at(lambda k: getattr(k, name), K,
                            D - jnp.asarray(self.centre, D.dtype))
        return K

    def storages(self, P):
        """Storages of the balanced problem in the user's units: $D^{-1}P_bD^{-1}$."""
        if self.d is None or P is None:
            return P
        d = self._d(P.shape[-1])
        with np.errstate(over="ignore"):  # an overflow is reported by `unbalance`
            return _times(P, 1.0 / (d[:, None] * d[None, :]))

    def _d(self, n: int) -> np.ndarray:
        # an odd REN (`fit_ren(odd=True)`) has two copies of the state: (x, -x)
        assert self.d is not None and n % self.d.size == 0
        return np.tile(self.d, n // self.d.size)


def _times(M, factors: np.ndarray):
    """`M` times `factors` (broadcast over its last two axes), in `M`'s dtype: powers of
    two, so exact."""
    return M * jnp.asarray(factors, M.dtype) if isinstance(M, jax.Array) else M * factors


def balancing_units(windows: Windows, balance, qsr: QSR | None = None) -> Units:
    """The `Units` of the module docstring when `balance` is True (the rate's centre $M$
    first, then the states' factors $d$ of the windows with $u - yM^\\top$, then $c$ of
    those with $\\hat x_0/d$), none when False; a `ValueError`
    naming `balance` for anything else, or for traced windows (`fit_gd` under `jax.jit` or
    `jax.vmap` over the windows): the factors are powers of two chosen from the data on
    the host."""
    if not check_flag("balance", balance):
        return Units()
    if any(isinstance(a, jax.core.Tracer) for a in (windows.x0, windows.y, windows.u)):
        raise ValueError("`balance=True` chooses the outputs' units from the data on the host, "
                         "which traced `windows` (a trainer under `jax.jit` or `jax.vmap` over "
                         "its windows) do not allow: pass `balance=False` there.")
    rho, zero = state_ratios(windows), _power(windows.u)  # zero: the zero controller's loss
    top = float(np.nanmax(rho)) if np.isfinite(rho).any() else 0.0
    hint = (top, zero) if top > LARGE_STATES[0] and zero > 0 else None
    found = None if qsr is None else centring(qsr)
    centre = None if found is None else found[0]
    windows = _divided(windows, Units(centre=centre))
    d = state_factors(windows)
    return Units(output_factor(_divided(windows, Units(1.0, d))), d, centre, hint)


def _divided(windows: Windows, units: Units) -> Windows:
    """The windows $(\\hat x_0/d, y, (u - yM^\\top)/c)$ (exact but for the centre's
    products)."""
    if units.centre is not None:
        u = windows.u - windows.y @ jnp.asarray(units.centre.T, windows.y.dtype)
        windows = Windows(windows.x0, windows.y, u)
    x0 = windows.x0
    if units.d is not None:  # (d is only chosen for windows that start at a state)
        assert x0 is not None
        x0 = x0 / jnp.asarray(units.d, x0.dtype)
    return Windows(x0, windows.y, windows.u / units.c if units.c != 1.0 else windows.u)


@overload
def balance(windows: Windows, qsr: QSR, units: Units) -> tuple[Windows, QSR]: ...
@overload
def balance(windows: Windows, qsr: None, units: Units) -> tuple[Windows, None]: ...
def balance(windows: Windows, qsr: QSR | None, units: Units) -> tuple[Windows, QSR | None]:
    """The windows $(\\hat x_0/d, y, u/c)$ and the supply rate $(c^2Q, cS, R)$ (None stays
    None)."""
    if units.none:
        return windows, qsr
    c = units.c
    if qsr is not None and units.centre is not None:
        found = centring(qsr)
        assert found is not None  # `balancing_units` found it for this rate
        qsr = found[1]
    if qsr is not None and c != 1.0:
        qsr = QSR(c * c * qsr.Q, c * qsr.S, qsr.R)
    return _divided(windows, units), qsr


def large_states_hint(res, units: Units) -> None:
    """Warn when the runs ended at a median loss above `LARGE_STATES[1]` of the zero
    controller's and some initial state is more than `LARGE_STATES[0]` times the outputs'
    size (`Units.hint`): the one case `balance` leaves alone (module docstring) that made
    the runs fail. On a realisable 2x2 problem of order 4 (passive), `fit_direct` ended at
    0.0025-0.0058 of the zero controller's loss in matching units and at 0.06-0.26, 0.55-0.56
    and 0.65 with the states 16, 64 and 256 times larger (same data, states in smaller
    units)."""
    if units.hint is None or isinstance(res.final_loss, jax.core.Tracer):
        return
    rho, zero = units.hint
    ratio = float(np.median(np.asarray(res.final_loss, np.float64))) / zero
    if not ratio > LARGE_STATES[1]:
        return
    k = nearest_power_of_two(rho)
    warn_user(
        f"the runs ended at a median loss {ratio:.2g} times the zero controller's, and the "
        f"windows' initial states are up to {rho:.3g} times the outputs' size (root mean "
        f"square). Training is slow when the states are much larger than the outputs (states "
        f"in small units): on a test problem, 16 and 64 times larger states left the loss "
        f"20-230 times higher than in matching units. `balance` rescales states that are far "
        f"smaller than the outputs but leaves large ones, since windows that start far from "
        f"rest look the same. If the states are in small units, train on `x0 / {k:g}` "
        f"instead (the controller then starts at x̂0 = x0 / {k:g}).")


def unbalance(res, units: Units, qsr: QSR | None = None, throw: bool = False):
    """`_unbalance`, then `large_states_hint`."""
    res = _unbalance(res, units, qsr, throw)
    large_states_hint(res, units)
    return res


def _unbalance(res, units: Units, qsr: QSR | None = None, throw: bool = False):
    """A `FitResult` (LTI or REN controllers) of the balanced problem in the user's units:
    controllers by `Units.controllers`, storages by `Units.storages` (a REN's multiplier
    unchanged), losses times $c^2$.

    With the states' units changed or the outputs centred, `certified` is checked again
    against the user's `qsr` (float64; the same matrix up to exact scalings by powers of
    two and the centre's rounding, so the verdict agrees except at round-off), and a pair
    that fails it becomes `not_certified` (raised with `throw`)."""
    if units.none:
        return res
    c = units.c
    res = eqx.tree_at(lambda r: (r.controllers, r.loss_history, r.final_loss), res,
                      (units.controllers(res.controllers), res.loss_history * c**2,
                       res.final_loss * c**2))
    if (units.d is None and units.centre is None) or res.P is None:
        return res
    res = eqx.tree_at(lambda r: r.P, res, units.storages(res.P))
    if qsr is None or res.certified is None:
        return res
    K = res.controllers
    if isinstance(K, RENController):
        ok = certified_batch(K, qsr, np.asarray(res.P, np.float64),
                             np.asarray(res.multiplier, np.float64))
    else:
        ok = kyp_certified(K.A, K.B, K.C, K.D, qsr, res.P)
    lost = np.asarray(res.certified) & ~np.asarray(ok)
    if not lost.any():
        return res
    P = np.asarray(res.P)
    overflow = lost & ~np.isfinite(P.reshape(P.shape[0], -1)).all(1)
    if throw and overflow.any() and units.d is not None:
        raise ValueError(
            f"{int(overflow.sum())} of {lost.size} certified runs have storages that overflow "
            f"{P.dtype} in your units: some states are about {1 / units.d.min():.0e} times "
            "smaller than the outputs, and the storage of the balanced problem, P, becomes "
            "D^-1 P D^-1 (`balance`, docs: Units of the states). Train in float64 "
            "(`JAX_ENABLE_X64=1`) or put those states in units nearer the outputs'.")
    codes = np.where(lost, _outcome.code("not_certified"), _outcome.codes(res.result))
    res = eqx.tree_at(lambda r: (r.certified, r.result), res,
                      (jnp.asarray(~lost & np.asarray(res.certified)),
                       _outcome.item(np.asarray(codes, np.int32))))
    return raise_if_failed(res) if throw else res
