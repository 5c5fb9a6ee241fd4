"""What `dj.project` returns: the pair `(controller, P)` with its `Outcome`s, a JAX pytree."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import equinox as eqx
import jax
import jax.core
import numpy as np
from jaxtyping import Array, Float

from .. import _outcome
from .._controller import LTIController
from .._outcome import Outcome


class Projection(eqx.Module):
    """What [`project`][dissil_jax.project] returns: `controller`, `P` and `result`.

    It unpacks like the pair `(controller, P)` (`K, P = dj.project(K, qsr)`) and indexes
    like one (`dj.project(K, qsr)[0]`); `result` is the [`Outcome`][dissil_jax.Outcome] of
    each projection (batched like `K`). An `eqx.Module`, so it can be returned from
    `jax.jit`.
    """

    controller: LTIController
    P: Float[Array, "*batch n n"]
    result: Outcome

    def __iter__(self) -> Iterator[Any]:
        return iter((self.controller, self.P))

    def __len__(self) -> int:
        return 2

    def __getitem__(self, i: int) -> Any:
        return (self.controller, self.P)[i]

    def result_names(self) -> str | list:
        """`result` decoded into `Outcome` names (`'solved'`, `'unchanged'`, ...): a `str`
        for one projection, nested lists when batched (`dj.Outcome[result]` gives the
        item's message instead, and only for a single item)."""
        return _outcome.names(self.result)


def raise_on_failure(P, codes):
    """`throw=True`: a ValueError eagerly; under `jax.jit` a `JaxRuntimeError` (an
    `EquinoxRuntimeError` under `eqx.filter_jit`)."""
    bad = _outcome.failed(codes)
    if not isinstance(codes, jax.core.Tracer):
        codes = np.asarray(codes)
        bad = codes[_outcome.failed(codes)]
        if bad.size:
            raise ValueError(f"dj.project: {_outcome.message(_outcome.NAMES[int(bad.max())])}")
        return P
    return _outcome.worst(codes, bad).error_if(P, bad.any())
