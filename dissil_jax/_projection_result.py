"""What `dj.project` returns: the pair `(controller, P)` with its `Outcome`s, a JAX pytree."""

from __future__ import annotations

import jax

from ._controller import LTIController


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
