"""The steps of projected gradient descent (and of GD) for the driver loop (`_iterate.py`)."""

from __future__ import annotations

from typing import Any, cast

import jax
import jax.numpy as jnp
import optax

from .. import _outcome
from .._controller import LTIController
from .._data import Windows
from .._projection import first_order as _first_order
from .._projection.handle import RateHandle
from .._projection.project import project, project_first_order_warm
from .._rollout import imitation_loss
from .._supply import QSR
from ._checks import finite_lanes
from ._iterate import Method
from .steps import optimizer_metric

_CONVERGED, _NON_FINITE = (_outcome.code(n) for n in ("converged", "non_finite"))

_batched_loss = jax.vmap(jax.value_and_grad(imitation_loss), in_axes=(0, None))


class PGDSteps(Method):
    """Projected gradient steps (GD when `qsr` is None) for the driver loop (`_iterate.py`).

    Each initialisation has its own optimiser state (the optimiser is vmapped over the
    batch, so a transformation such as `optax.clip_by_global_norm` never couples two
    runs); the state carries across steps and each update is followed by the projection
    (projected Adam, projected SGD, ...). Runs whose initial projection failed take no
    step.
    """

    K0: Any
    P0: Any
    code0: Any
    windows: Windows
    opt: optax.GradientTransformation
    qsr: QSR | RateHandle | None  # a handle: the rate by reference (`trainer_rate`)
    eps: float
    method: str
    warm: bool  # the first-order projection, warm-started from the previous step's ADMM state
    weighted: bool  # the optimiser has a metric (`optimizer_metric`), so the projection too

    @property
    def keep_non_finite(self) -> bool:  # GD returns its diverged iterate
        return self.qsr is None

    def init(self):
        pending = (self.K0, self.P0, jax.vmap(self.opt.init)(self.K0))
        if self.warm:  # one cold ADMM state per initialisation
            assert self.qsr is not None  # `warm` is the first-order projection's
            n, qsr, dtype = self.K0.n_state, self.qsr, self.K0.A.dtype
            cold = jax.vmap(lambda K: _first_order.cold_state(
                n, qsr, dtype, (K.A, K.B, K.C, K.D) if self.weighted else None))(self.K0)
            pending += (cold,)
        return pending, self.code0

    def evaluate(self, pending):
        K, P, opt_state, *warm = pending
        loss, grads = _batched_loss(K, self.windows)
        return (K, P, opt_state, grads, *warm), loss

    def update(self, state, active):
        K, P, opt_state, grads, *warm = state
        updates, opt_state = jax.vmap(self.opt.update)(grads, opt_state, K)
        # optax types its result as a generic pytree; it has K's structure
        K_new, P_new = cast(LTIController, optax.apply_updates(K, updates)), P
        # a non-finite step (e.g. a NaN step size of a vmapped sweep) ends its run as such,
        # before its projection could report it as the solver's failure
        finite = finite_lanes(K_new)
        code = jnp.where(finite, _CONVERGED, _NON_FINITE).astype(jnp.int32)
        if self.qsr is not None:
            active = active & finite
            # An indefinite Q's positive part is linearised at the certified iterate (K_ref),
            # once per step (refine=1; the next step re-linearises). No effect for Q <= 0.
            metric = optimizer_metric(opt_state, K_new)
            if self.warm:
                proj, warm[0] = project_first_order_warm(K_new, self.qsr, P, warm[0],
                                                         active=active, eps=self.eps,
                                                         metric=metric)
            else:  # (`project` takes a `RateHandle` for a `QSR`: `trainer_rate`)
                proj = project(K_new, cast(QSR, self.qsr), P, throw=False, active=active,
                               eps=self.eps, metric=metric, K_ref=K, refine=1,
                               method=self.method)
            codes = _outcome.codes(proj.result)
            code = jnp.where(_outcome.failed(codes), codes, code)
            K_new, P_new = proj
        return (K_new, P_new, opt_state, *warm), code
