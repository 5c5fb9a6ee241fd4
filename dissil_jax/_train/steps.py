"""PGD's step rules: the paper's decaying gradient step, and the projection metric that
matches a diagonally preconditioned optimiser (Adam)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax


def paper_rule(learning_rate, decay) -> optax.GradientTransformation:
    """The paper's step rule: gradient steps $\\eta_i = \\eta_0\\rho^{\\,i}$ ("an
    exponentially decaying learning rate", paper §4.2); `learning_rate` and `decay` may be
    traced (a vmapped sweep)."""
    return optax.sgd(learning_rate=lambda count: learning_rate * decay**count)


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
