"""What `dj.project` returns: the pair `(controller, P)` with its `Outcome`s, a JAX pytree."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import _sdp
from ._controller import LTIController
from ._sdp import Outcome


class Projection(tuple):
    """What [`project`][dissil_jax.project] returns: the pair `(controller, P)`, plus `result`.

    It unpacks like a pair (`K, P = dj.project(K, qsr)`) and indexes like one
    (`dj.project(K, qsr)[0]`); `result` is the [`Outcome`][dissil_jax.Outcome] of each
    projection (batched like `K`). It is a JAX pytree, so it can be returned from `jax.jit`.
    """

    def __new__(cls, controller, P, result):
        self = super().__new__(cls, (controller, P))
        self.result = result
        return self

    @property
    def controller(self) -> LTIController:
        return self[0]

    @property
    def P(self):
        return self[1]

    def __repr__(self):
        return f"Projection(controller={self[0]!r}, P={self[1]!r}, result={self.result!r})"


jax.tree_util.register_pytree_node(
    Projection, lambda p: ((p[0], p[1], p.result), None),
    lambda _, children: Projection(*children))


def raise_on_failure(P, codes):
    """`throw=True`: a ValueError eagerly, an `EquinoxRuntimeError` under `jit`."""
    if not isinstance(codes, jax.core.Tracer):
        codes = np.asarray(codes)
        bad = codes[_sdp.failed(codes)]
        if bad.size:
            raise ValueError(f"dj.project: {Outcome[_sdp.item(bad.max())]}")
        return P
    worst = _sdp.item(jnp.max(jnp.where(_sdp.failed(codes), codes, -1)))
    return worst.error_if(P, jnp.any(_sdp.failed(codes)))
