"""PGD's step rules: the paper's decaying gradient step, the default step (Adam) of PGD and
plain GD, and the projection metric that matches a diagonally preconditioned optimiser."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optax

from .._data import Windows
from ._checks import check_n_state


def paper_rule(learning_rate, decay) -> optax.GradientTransformation:
    """The paper's step rule: gradient steps $\\eta_i = \\eta_0\\rho^{\\,i}$ ("an
    exponentially decaying learning rate", paper §4.2); `learning_rate` and `decay` may be
    traced (a vmapped sweep)."""
    # `count` is an int32 step counter: cast, so that strict dtype promotion holds too
    return optax.sgd(learning_rate=lambda count: learning_rate * decay ** jnp.asarray(
        count, jnp.result_type(decay)))


#: Smallest weight of the optimiser's metric relative to its largest, per controller: an
#: entry whose gradient has been (near) zero so far must not become free to move.
METRIC_FLOOR = 1e-3


def optimizer_metric(opt_state, K):
    """The projection metric that matches a diagonally preconditioned optimiser, or None.

    Adam, RMSProp, AdaBelief, Yogi, ... step by $-\\eta\\, m/\\sqrt{\\nu}$ per entry. A
    Euclidean projection of that step is biased: at a point of the boundary where the
    gradient is normal to the set, the preconditioned step has a component along the
    boundary, and the projected iterate drifts away from the constrained minimum. The
    projection in the metric $W = \\sqrt{\\nu}$ has the constrained minima as fixed points.
    `opt_state` is searched for a single second-moment field `nu` shaped like the
    controllers; weights below `METRIC_FLOOR` times the controller's largest are raised to
    it. Optimisers without one (SGD, momentum, the paper's rule) keep the Frobenius
    distance.
    """
    found = optax.tree_utils.tree_get_all_with_path(opt_state, "nu")
    if len(found) != 1 or jax.tree.structure(found[0][1]) != jax.tree.structure(K):
        return None
    W = jax.tree.map(jnp.sqrt, found[0][1])
    top = jnp.max(jnp.stack([jnp.max(w, axis=(-2, -1)) for w in jax.tree.leaves(W)]), axis=0)
    floor = jnp.where(top > 0, METRIC_FLOOR * top, 1.0)[:, None, None]
    return jax.tree.map(lambda w: jnp.maximum(w, floor), W)


#: The default step of `fit_pgd`, `pgd_run` and `fit_gd` when none of `optimizer`,
#: `learning_rate` and `decay` is given: Adam at this rate in the same normalised units (PGD
#: projects in Adam's metric), chosen on the tuning half of `dissil_jax.experiments.zoo`
#: (`benchmarks/bench_defaults.py`). For GD the paper's rule diverged in 138 of 144 runs;
#: for PGD Adam had a worst regret of 1.07 on the tuning half against the paper rule's 74.
ADAM_LEARNING_RATE = 0.1
#: One instance, so that the compiled runs (the optimiser is a static argument) are reused
#: across calls instead of retraced.
_ADAM = optax.adam(ADAM_LEARNING_RATE)


#: The width $w = \hat n + p$ up to which plain GD keeps `ADAM_LEARNING_RATE` (every problem
#: of the zoo and the paper's sizes are within it); see `gd_learning_rate`.
_GD_WIDTH = 9


def gd_learning_rate(n_state: int, n_in: int) -> float:
    """The default Adam step of plain GD (`fit_gd`, `pgd_run` with `qsr=None`) for a
    controller of order $\\hat n$ with $p$ inputs: $\\eta = 0.1\\min(1, 9/w)$, $w = \\hat n + p$.

    Why: Adam moves every entry by about $\\eta$ per step, so a step changes $A$ by about
    $\\eta\\,\\hat n$ in spectral norm; without a projection nothing pulls an iterate that
    left the stable controllers back, and the loss of a windowed rollout grows like
    $\\rho(A)^{2h}$. On the tuning problems (`benchmarks/bench_high_order.py --gd`, damped
    chains at $\\hat n$ = 6 to 48) the fixed step 0.1 ended the median run 0.39x and 305x its
    initial loss at $\\hat n = 48$ (worst 1.4e4x); with this rule every run ended below
    0.001x. The rule is `fit_direct`'s $1/w$ scaling of its step (`default_hyperparameters`),
    and it changes nothing for $w\\le9$.
    """
    return ADAM_LEARNING_RATE * min(1.0, _GD_WIDTH / (n_state + n_in))


#: The default initial scale of `fit_pgd`, `pgd_run` and, up to order `_GD_ORDER`, of
#: plain GD, chosen on the zoo: from N(0, 1) draws 150 Adam steps ended up to 80x (GD) and
#: 9x (PGD) above the runs from N(0, 0.3^2); scales that shrink with the order and the
#: window length, min(1, 1/sqrt(n)) and min(1, 1/sqrt(n (h - 1))), did worse than the
#: constant for PGD (worst tuning regret 9.8 and 3.7 against 1.07).
ADAM_INIT_SCALE = 0.3

#: The controller order up to which plain GD keeps `ADAM_INIT_SCALE` (every problem of the
#: zoo and the paper's sizes are within it); see `gd_init_scale`.
_GD_ORDER = 9


def gd_init_scale(n_state: int) -> float:
    """The default initial scale of plain GD (`fit_gd`, `pgd_run` with `qsr=None`) for a
    controller of order $\\hat n$: $\\sigma = 0.3\\min(1, 3/\\sqrt{\\hat n})$.

    Why: the eigenvalues of an $\\hat n\\times\\hat n$ matrix of i.i.d.
    $\\mathcal N(0,\\sigma^2)$ entries fill a disc of radius about $\\sigma\\sqrt{\\hat n}$,
    so the constant 0.3 draws unstable $\\hat A$ from $\\hat n\\approx 11$ on, and without a
    projection the first loss grows like $\\rho(\\hat A)^{2h}$ over windows of length $h$.
    This rule keeps the radius near 0.9. On the tuning problems (damped chains,
    $\\hat n$ = 24 and 48, `benchmarks/bench_high_order.py --gd-init`) the constant started the
    median run 230-6e4 times above the zero controller's loss and ended it 0.29-1.5 times
    that loss after 600 steps; this rule started it 1.1-1.5 times above and ended it
    0.0007-0.08 times. It changes nothing for $\\hat n\\le9$.
    """
    return ADAM_INIT_SCALE * min(1.0, (_GD_ORDER / n_state) ** 0.5)


def default_init_scale(init_scale, gd_windows=None, n_state=None):
    """`init_scale`, or when it is None the default: `ADAM_INIT_SCALE`, or for plain GD
    (pass its `windows` as `gd_windows`, and `n_state`) `gd_init_scale` of the order."""
    if init_scale is not None:
        return init_scale
    if isinstance(gd_windows, Windows):  # other input is refused by the argument checks
        return gd_init_scale(check_n_state(gd_windows, n_state, warn=False))
    return ADAM_INIT_SCALE


@functools.lru_cache(maxsize=64)
def _adam(learning_rate: float) -> optax.GradientTransformation:
    # one instance per rate, so that the compiled runs (the optimiser is static) are reused
    return _ADAM if learning_rate == ADAM_LEARNING_RATE else optax.adam(learning_rate)


def default_rule(optimizer, learning_rate, decay, gd_windows=None, n_state=None):
    """`optax.adam(ADAM_LEARNING_RATE)` when no step argument is given, else `optimizer`
    (None: the paper's rule with the given `learning_rate`/`decay`). For plain GD pass its
    `windows` as `gd_windows` (and `n_state`): the default Adam step then follows the
    width (`gd_learning_rate`)."""
    if optimizer is None and learning_rate is None and decay is None:
        if isinstance(gd_windows, Windows):  # other input is refused by the argument checks
            return _adam(gd_learning_rate(check_n_state(gd_windows, n_state, warn=False),
                                          gd_windows.n_in))
        return _ADAM
    return optimizer
