"""Projected gradient descent (paper Alg. 2) and its unconstrained baseline (GD)."""

from __future__ import annotations

import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._data import Windows
from .._lmi import kyp_certified
from .._projection import MESSAGES, Status, project_with_status
from .._rollout import imitation_loss
from .._supply import QSR
from ._checks import check_fit_args
from ._init import INIT_SCALE, init_controllers
from .result import FitResult, stop_code

_CONVERGED, _MAX_STEPS, _NON_FINITE, _SOLVER_FAILED = (
    stop_code(r) for r in ("converged", "max_steps", "non_finite", "solver_failed"))

# Incremented each time the training loop is traced (tests assert no retracing).
TRACE_COUNT = {"pgd_loop": 0}

_batched_loss = jax.vmap(jax.value_and_grad(imitation_loss), in_axes=(0, None))


def _mats(K):
    return K.A, K.B, K.C, K.D


def _where(mask, new, old):
    """Per-initialisation select on pytrees whose leaves have the init axis first."""
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b),
        new, old,
    )


def _loop(K0, P0, ok0, windows, learning_rate, decay, *, qsr, max_steps, tol, eps):
    """The jit-compatible training loop over a batch of initialisations.

    Pure: vmappable over (learning_rate, decay) and over the initial controllers.
    """
    TRACE_COUNT["pgd_loop"] += 1
    num_inits = K0.A.shape[0]
    schedule = lambda count: learning_rate * decay**count
    opt = optax.sgd(learning_rate=schedule)
    loss0, _ = _batched_loss(K0, windows)
    hist = jnp.full((num_inits, max_steps + 1), jnp.nan, loss0.dtype).at[:, 0].set(loss0)
    carry = dict(
        step=jnp.zeros((), jnp.int32), K=K0, P=P0, opt=opt.init(K0), loss=loss0, hist=hist,
        done=~ok0, steps=jnp.zeros(num_inits, jnp.int32), ok=ok0,
        reason=jnp.where(ok0, _MAX_STEPS, _SOLVER_FAILED).astype(jnp.int32),
    )

    def cond(c):
        return (c["step"] < max_steps) & jnp.any(~c["done"])

    def body(c):
        active = ~c["done"]
        _, grads = _batched_loss(c["K"], windows)
        updates, opt_state = opt.update(grads, c["opt"], c["K"])
        K_tilde = optax.apply_updates(c["K"], updates)
        if qsr is None:
            K_new, P_new, failed = K_tilde, c["P"], jnp.zeros(num_inits, bool)
        else:
            K_new, P_new, status = project_with_status(K_tilde, qsr, c["P"], active, eps=eps)
            failed = status >= int(Status.INFEASIBLE)
            # A failed solve never yields an uncertified controller: keep the last iterate.
            K_new = _where(failed, c["K"], K_new)
            P_new = jnp.where(failed[:, None, None], c["P"], P_new)
        K_new = _where(active, K_new, c["K"])
        P_new = P_new if qsr is None else jnp.where(active[:, None, None], P_new, c["P"])
        loss_new, _ = _batched_loss(K_new, windows)
        loss_new = jnp.where(active, loss_new, c["loss"])
        small = jnp.abs(loss_new - c["loss"]) < tol
        finite = jnp.isfinite(loss_new)
        stop = active & (small | failed | ~finite)
        code = jnp.where(failed, _SOLVER_FAILED, jnp.where(finite, _CONVERGED, _NON_FINITE))
        hist = c["hist"].at[:, c["step"] + 1].set(jnp.where(active, loss_new, jnp.nan))
        return dict(
            step=c["step"] + 1, K=K_new, P=P_new, opt=opt_state, loss=loss_new, hist=hist,
            done=c["done"] | stop,
            steps=c["steps"] + active.astype(jnp.int32), ok=c["ok"] & ~(active & failed),
            reason=jnp.where(stop, code, c["reason"]).astype(jnp.int32),
        )

    c = jax.lax.while_loop(cond, body, carry)
    # A run converged iff it stopped on |dJ| < tol with a finite loss and no failed solve.
    return (c["K"], c["P"], c["hist"], c["loss"], c["reason"] == _CONVERGED, c["steps"],
            c["ok"], c["reason"])


def pgd_run(
    key, windows: Windows, qsr: QSR | None, *, learning_rate=1e-3, decay=0.99,
    init_scale=INIT_SCALE, num_inits: int = 8, max_steps: int = 150, tol: float = 1e-3,
    eps: float = 1e-6,
) -> FitResult:
    """The pure, traceable PGD run behind [`fit_pgd`][dissil_jax.fit_pgd].

    Unlike `fit_pgd` it is safe to `jax.vmap`/`jax.jit` over `key`, `learning_rate`,
    `decay` and `init_scale` (a hyperparameter sweep); `qsr` must be closed over.
    `qsr=None` gives plain gradient descent. `wall_time` is NaN and `certified` comes from
    the projection's own float64 check (a failed initial projection leaves that
    initialisation with `certified=False` and zero steps).

    ```python
    lrs = jnp.logspace(-4, -2, 5)
    sweep = jax.jit(jax.vmap(lambda lr: dj.pgd_run(key, windows, qsr, learning_rate=lr)))
    res = sweep(lrs)            # every field gains a leading axis of size 5
    ```
    """
    check_fit_args(windows, qsr, num_inits, max_steps, learning_rate=learning_rate, decay=decay,
                   tol=tol, init_scale=init_scale)
    K0 = init_controllers(key, num_inits, windows, init_scale)
    if qsr is None:
        P0, ok0 = None, jnp.ones(num_inits, bool)
    else:
        K0, P0, status = project_with_status(K0, qsr, None, eps=eps)
        ok0 = status < int(Status.INFEASIBLE)
    K, P, hist, loss, converged, steps, ok, reason = _loop(
        K0, P0, ok0, windows, learning_rate, decay, qsr=qsr, max_steps=max_steps, tol=tol,
        eps=eps,
    )
    return FitResult(
        controllers=K, P=P, certified=None if qsr is None else ok, loss_history=hist,
        final_loss=loss, converged=converged, steps=steps,
        wall_time=jnp.asarray(jnp.nan, hist.dtype), stop_reason=reason,
    )


_COMPILED: dict = {}


def _compiled_loop(qsr, max_steps, tol, eps):
    key = (None if qsr is None else (qsr.Q.tobytes(), qsr.S.tobytes(), qsr.R.tobytes(),
                                     qsr.S.shape), max_steps, float(tol), float(eps))
    fn = _COMPILED.get(key)
    if fn is None:
        fn = _COMPILED[key] = jax.jit(partial(_loop, qsr=qsr, max_steps=max_steps, tol=tol,
                                              eps=eps))
    return fn


def _fit(key, windows, qsr, *, num_inits, max_steps, learning_rate, decay, tol, init_scale,
         eps):
    check_fit_args(windows, qsr, num_inits, max_steps, learning_rate=learning_rate, decay=decay,
                   tol=tol, init_scale=init_scale)
    start = time.perf_counter()
    K0 = init_controllers(key, num_inits, windows, init_scale)
    if qsr is None:
        P0 = None
    else:
        K0, P0, status = project_with_status(K0, qsr, None, eps=eps)
        worst = int(np.max(np.asarray(status)))
        if worst >= Status.INFEASIBLE:
            raise ValueError(f"initial projection failed: {MESSAGES[Status(worst)]}")
    ok0 = jnp.ones(num_inits, bool)
    loop = _compiled_loop(qsr, int(max_steps), tol, eps)
    dtype = windows.y.dtype
    K, P, hist, loss, converged, steps, ok, reason = loop(
        K0, P0, ok0, windows, jnp.asarray(learning_rate, dtype), jnp.asarray(decay, dtype)
    )
    jax.block_until_ready(hist)
    certified = None
    if qsr is not None:
        # Independent exact check in float64 of every returned (controller, P) pair.
        mats = [np.asarray(M) for M in _mats(K)]
        Pn = np.asarray(P)
        certified = jnp.asarray([kyp_certified(*(M[i] for M in mats), qsr, Pn[i])
                                 for i in range(num_inits)])
        if not bool(jnp.all(certified)):  # pragma: no cover - guarded by the projection
            raise RuntimeError("internal error: a trained controller failed its KYP check")
    wall = time.perf_counter() - start
    return FitResult(K, P, certified, hist, loss, converged, steps, jnp.asarray(wall), reason)


def fit_pgd(
    key, windows: Windows, qsr: QSR, *, num_inits: int = 8, max_steps: int = 150,
    learning_rate: float = 1e-3, decay: float = 0.99, tol: float = 1e-3,
    init_scale: float = INIT_SCALE, eps: float = 1e-6,
) -> FitResult:
    """Learn $(Q,S,R)$-dissipative controllers by projected gradient descent (paper Alg. 2).

    For each of `num_inits` random initialisations $K_0$ (entries
    $\\mathcal N(0,\\sigma^2)$, $\\sigma=$ `init_scale`, then projected), iterate

    $$\\tilde K_{i} = K_i - \\eta_i\\nabla J(K_i),\\qquad
    K_{i+1} = \\Pi_{\\tilde P = P_i}(\\tilde K_i), \\qquad \\eta_i = \\eta_0\\,\\rho^{\\,i},$$

    with $J$ the imitation MSE ([`imitation_loss`][dissil_jax.imitation_loss]) and
    $\\Pi$ the projection of paper eq. 13 ([`project`][dissil_jax.project]) linearised at
    the previous iterate's $P$, until $|J(K_{i+1}) - J(K_i)| <$ `tol` or `max_steps`.
    All initialisations run in one compiled `lax.while_loop`; each step sends the whole
    batch to the host once, where Clarabel solves it on a thread pool.

    **Arguments:**

    - `key`: PRNG key for the initialisations.
    - `windows`: the demonstrations ([`Windows`][dissil_jax.Windows]); the controller has
      `windows.n_state` states.
    - `qsr`: the controller's supply rate ($Q\\preceq0$).
    - `num_inits`, `max_steps` (paper: 150), `tol` (paper: 1e-3 linear, 1e-5 nonlinear;
      `0.0` runs every step), `learning_rate` $\\eta_0$, `decay` $\\rho$, `init_scale`
      $\\sigma$ (default 1: the paper's N(0, 1) draw, see below), `eps` (LMI strictness
      margin).

    **Initialisation.** The paper draws "each matrix element from a normal distribution"
    and projects the draw (paper §4.1); `init_scale=1.0` is that N(0, 1). A small scale
    starts every run near the zero controller, which is already dissipative, so the
    constraint would rarely bind.

    **Returns:** a [`FitResult`][dissil_jax.FitResult]; every controller carries a `P`
    that passes the exact float64 KYP check (`certified`).
    """
    if qsr is None:
        raise ValueError("`qsr` is required for PGD; use `dj.fit_gd` for the unconstrained run.")
    return _fit(key, windows, qsr, num_inits=num_inits, max_steps=max_steps,
                learning_rate=learning_rate, decay=decay, tol=tol, init_scale=init_scale,
                eps=eps)


def fit_gd(
    key, windows: Windows, *, num_inits: int = 8, max_steps: int = 150,
    learning_rate: float = 1e-3, decay: float = 0.99, tol: float = 1e-3,
    init_scale: float = INIT_SCALE,
) -> FitResult:
    """Plain gradient descent on the imitation loss: [`fit_pgd`][dissil_jax.fit_pgd] without $\\Pi$.

    The paper's unconstrained baseline; no stability guarantee (`P` and `certified` are
    None). Same arguments and defaults as `fit_pgd`.
    """
    return _fit(key, windows, None, num_inits=num_inits, max_steps=max_steps,
                learning_rate=learning_rate, decay=decay, tol=tol, init_scale=init_scale,
                eps=0.0)


