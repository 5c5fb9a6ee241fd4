"""The closed-loop QSR theorem (paper Theorem 1) and the controller-supply recipe built on
it, for the supply rates of `_supply.py`."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, cast

import equinox as eqx
import numpy as np
import scipy.optimize

from ._outcome import Outcome
from ._supply import QSR, _as_matrix


class ClosedLoopCertificate(eqx.Module):
    """What [`closed_loop_certificate`][dissil_jax.closed_loop_certificate] returns.

    - `result`: the [`Outcome`][dissil_jax.Outcome], `solved` when Theorem 1's condition
      holds, `no_multiplier` when no $\\alpha$ tried satisfies it;
    - `alpha`: the best multiplier found (the one minimising $\\lambda_{\\max}$);
    - `holds` (read-only): `result == Outcome.solved`, a `bool`;
    - `message` (read-only): what `result` means here, as a sentence.

    It unpacks like the pair `(holds, alpha)`.
    """

    result: Outcome
    alpha: float

    @property
    def holds(self) -> bool:
        """`result == Outcome.solved`: Theorem 1's condition holds at `alpha`."""
        return bool(self.result == Outcome.solved)

    @property
    def message(self) -> str:
        """What `result` means for Theorem 1 (the `Outcome` item's own sentence is the
        projection's and the certificates')."""
        if self.holds:
            return (f"Theorem 1 holds: M(alpha) is negative definite at alpha = "
                    f"{self.alpha:.6g} beyond round-off (a float64 eigenvalue check), so the "
                    "loop is l2-stable")
        return ("no multiplier found: lambda_max(M(alpha)) is not negative for any alpha "
                f"scanned (least at alpha = {self.alpha:.6g}); the two supply rates do not "
                "certify the loop, which may still be stable")

    def __iter__(self) -> Iterator[Any]:
        return iter((self.holds, self.alpha))


def _theorem1_matrix(plant: QSR, ctrl: QSR, alpha: float) -> np.ndarray:
    return np.block(
        [
            [plant.Q + alpha * ctrl.R, -plant.S + alpha * ctrl.S.T],
            [(-plant.S + alpha * ctrl.S.T).T, plant.R + alpha * ctrl.Q],
        ]
    )


def _check_interconnection(plant_qsr: QSR, controller_qsr: QSR) -> None:
    if not isinstance(plant_qsr, QSR) or not isinstance(controller_qsr, QSR):
        raise ValueError("`plant_qsr` and `controller_qsr` must be `dj.QSR` instances.")
    # plant: u in R^m -> y in R^p, so plant S is p x m; controller maps R^p -> R^m.
    if controller_qsr.S.shape != plant_qsr.S.T.shape:
        raise ValueError(
            f"`controller_qsr` has S of shape {controller_qsr.S.shape} but the plant's S is "
            f"{plant_qsr.S.shape}; the controller's input is the plant's output, so its S "
            f"must be {plant_qsr.S.T.shape}."
        )


def closed_loop_certificate(plant_qsr: QSR, controller_qsr: QSR) -> ClosedLoopCertificate:
    """Decide the QSR input-output stability theorem (paper Theorem 1) for a feedback pair.

    The negative-feedback loop $u_1 = r_1 - y_2$, $u_2 = r_2 + y_1$ of a
    $(Q_1,S_1,R_1)$-dissipative plant and a $(Q_2,S_2,R_2)$-dissipative controller is
    $\\ell_2$-stable if some $\\alpha>0$ gives

    $$M(\\alpha) = \\begin{bmatrix} Q_1 + \\alpha R_2 & -S_1 + \\alpha S_2^\\top \\\\
    \\ast & R_1 + \\alpha Q_2 \\end{bmatrix} \\prec 0.$$

    $\\lambda_{\\max}(M(\\alpha))$ is convex in $\\alpha$, so it is minimised by a
    log-spaced scan over $\\alpha\\in\\alpha_0[10^{-8}, 10^{8}]$ followed by Brent
    refinement, where $\\alpha_0$ is the ratio of the two rates' sizes (largest entries),
    the scale at which their terms in $M(\\alpha)$ compare: a rate and its multiples admit
    the same systems, so the answer must not depend on their scales (with the scan fixed at
    $[10^{-8}, 10^8]$, a plant rate of size 1 against a controller rate of size $10^{11}$
    found no multiplier where $\\alpha = 10^{-11}$ works).

    **Arguments:**

    - `plant_qsr`: the plant's supply rate (input $u\\in\\mathbb{R}^m$, output $y\\in\\mathbb{R}^p$).
    - `controller_qsr`: the controller's supply rate (input $y$, output $\\hat y\\in\\mathbb{R}^m$).

    **Returns:** a [`ClosedLoopCertificate`][dissil_jax.ClosedLoopCertificate] (`result`,
    `alpha`, `holds`); `alpha` is the best multiplier found (the one minimising
    $\\lambda_{\\max}$), returned even when the condition fails.
    """
    _check_interconnection(plant_qsr, controller_qsr)
    f = lambda la: np.linalg.eigvalsh(_theorem1_matrix(plant_qsr, controller_qsr, 10**la))[-1]
    size = lambda q: max(float(np.abs(M).max(initial=0.0)) for M in (q.Q, q.S, q.R))
    s1, s2 = size(plant_qsr), size(controller_qsr)
    centre = np.log10(s1 / s2) if s1 > 0 and s2 > 0 else 0.0
    grid = centre + np.linspace(-8, 8, 321)
    vals = np.array([f(g) for g in grid])
    i = int(np.argmin(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best_la, best = grid[i], vals[i]
    if hi > lo:
        # scipy types the result as `object`; it is an `OptimizeResult`
        res = cast(scipy.optimize.OptimizeResult,
                   scipy.optimize.minimize_scalar(f, bounds=(lo, hi), method="bounded",
                                                  options={"xatol": 1e-10}))
        if res.fun < best:
            best_la, best = res.x, res.fun
        # Brent stops at about sqrt(eps) relative in log(alpha), wider than the feasible
        # window of a pair at the edge (gain bounds 2 and 0.5 - 1e-9: alpha in (4, 4 +
        # 1.6e-8)); lambda_max is convex in alpha itself, so scipy's golden-section search
        # there, with a relative tolerance near float64's, resolves it
        g = lambda a: np.linalg.eigvalsh(_theorem1_matrix(plant_qsr, controller_qsr, a))[-1]
        res = cast(scipy.optimize.OptimizeResult, scipy.optimize.minimize_scalar(
            g, bracket=(10**lo, 10**hi), method="golden", options={"xtol": 1e-15}))
        if res.x > 0 and res.fun < best:
            best_la, best = float(np.log10(res.x)), float(res.fun)
    scale = 1.0 + np.abs(_theorem1_matrix(plant_qsr, controller_qsr, 10**best_la)).max()
    holds = bool(best < -1e-12 * scale)
    return ClosedLoopCertificate(Outcome.solved if holds else Outcome.no_multiplier,
                                 float(10**best_la))


def stabilising_qsr(plant_qsr: QSR, *, alpha: float = 1.0, margins=(1e-2, 1e-2)) -> QSR:
    """A controller supply rate that Theorem 1 pairs with `plant_qsr` (the recipe of `docs/concepts.md`, *The closed-loop theorem*).

    $$S_2 = S_1^\\top/\\alpha,\\quad R_2 = -(Q_1 + M_1)/\\alpha,\\quad Q_2 = -(R_1 + M_2)/\\alpha,$$

    so that $M(\\alpha) = \\operatorname{diag}(-M_1, -M_2) \\prec 0$ for $M_1, M_2 \\succ 0$.
    The paper's nonlinear example ($\\alpha=1$, margins $0.399$, $0.534$) maps the plant
    $(-1, 3.556, 29.333)$ to the controller $(-29.867, 3.556, 0.601)$.

    **Arguments:**

    - `plant_qsr`: the plant's supply rate.
    - `alpha`: the multiplier $\\alpha>0$.
    - `margins`: `(M1, M2)`, positive scalars or positive definite matrices of the plant's
      output and input sizes.

    `alpha` and `margins` are keyword-only.

    **Returns:** the controller's `QSR`.
    """
    if not isinstance(plant_qsr, QSR):
        raise ValueError("`plant_qsr` must be a `dj.QSR`.")
    a = np.asarray(alpha)
    if a.ndim != 0 or a.dtype.kind not in "iuf" or not np.isfinite(a) or a <= 0:
        raise ValueError(f"`alpha` must be positive and finite, got {alpha!r}.")
    try:
        M1, M2 = margins
    except (TypeError, ValueError):
        raise ValueError("`margins` must be a pair (M1, M2).") from None
    p, m = plant_qsr.S.shape
    mats = []
    for name, M, d in (("margins[0]", M1, p), ("margins[1]", M2, m)):
        M = np.asarray(M)
        if M.dtype.kind not in "iuf" or not np.all(np.isfinite(M)):
            raise ValueError(f"`{name}` must be a positive scalar or matrix of real numbers, "
                             f"got {M!r}.")
        M = M.astype(np.float64)
        M = M * np.eye(d) if M.ndim == 0 else _as_matrix(name, M, (d, d))
        if not np.allclose(M, M.T):
            raise ValueError(f"`{name}` must be symmetric (a quadratic form's matrix); "
                             f"pass ({name} + {name}.T) / 2.")
        if np.linalg.eigvalsh(M).min() <= 0:
            raise ValueError(f"`{name}` must be positive (definite), got eigenvalues "
                             f"{np.linalg.eigvalsh(M)}.")
        mats.append(M)
    M1, M2 = mats
    return QSR(
        Q=-(plant_qsr.R + M2) / alpha,
        S=plant_qsr.S.T / alpha,
        R=-(plant_qsr.Q + M1) / alpha,
    )
