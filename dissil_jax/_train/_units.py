"""Balancing the units of the controller's output against those of its input (`fit_*`).

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
"""

from __future__ import annotations

from typing import overload

import equinox as eqx
import jax
import jax.core
import numpy as np

from .._data import Windows
from .._supply import QSR
from .._validate import check_flag

#: The ratios r of output to input size that the trainers take as they are.
BAND = (0.2, 5.0)

# 2**±500: c**2 and the scaled data stay finite in float64 for any finite windows.
_MAX_EXPONENT = 500


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
    return float(2.0 ** np.clip(np.round(np.log2(r)), -_MAX_EXPONENT, _MAX_EXPONENT))


def balance_factor(windows: Windows, balance) -> float:
    """`output_factor(windows)` when `balance` is True, 1 when False; a `ValueError`
    naming `balance` for anything else, or for traced windows (`fit_gd` under `jax.jit` or
    `jax.vmap` over the windows): the factor is a power of two chosen from the data on the
    host."""
    if not check_flag("balance", balance):
        return 1.0
    if any(isinstance(a, jax.core.Tracer) for a in (windows.x0, windows.y, windows.u)):
        raise ValueError("`balance=True` chooses the outputs' units from the data on the host, "
                         "which traced `windows` (a trainer under `jax.jit` or `jax.vmap` over "
                         "its windows) do not allow: pass `balance=False` there.")
    return output_factor(windows)


@overload
def balance(windows: Windows, qsr: QSR, c: float) -> tuple[Windows, QSR]: ...
@overload
def balance(windows: Windows, qsr: None, c: float) -> tuple[Windows, None]: ...
def balance(windows: Windows, qsr: QSR | None, c: float) -> tuple[Windows, QSR | None]:
    """The windows $(x_0, y, u/c)$ and the supply rate $(c^2Q, cS, R)$ (None stays None)."""
    if c == 1.0:
        return windows, qsr
    balanced = Windows(windows.x0, windows.y, windows.u / c)
    if qsr is not None:
        qsr = QSR(c * c * qsr.Q, c * qsr.S, qsr.R)
    return balanced, qsr


def unbalance(res, c: float):
    """A `FitResult` (LTI or REN controllers) of the balanced problem in the user's units:
    the controllers' output matrices times $c$, losses times $c^2$; storages unchanged."""
    if c == 1.0:
        return res
    K = res.controllers
    names = ("C2", "D21", "D22") if hasattr(K, "D22") else ("C", "D")
    K = eqx.tree_at(lambda k: tuple(getattr(k, n) for n in names), K,
                    tuple(c * getattr(K, n) for n in names))
    return eqx.tree_at(lambda r: (r.controllers, r.loss_history, r.final_loss), res,
                       (K, res.loss_history * c**2, res.final_loss * c**2))
