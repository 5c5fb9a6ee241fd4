"""Argument checks of `dj.project` (ValueErrors that name the argument and the fix)."""

from __future__ import annotations

import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .._controller import LTIController
from .._rate_scale import rate_factor, scaled_rate
from .._sdp.indefinite import check_feasible, schur_complement
from .._supply import QSR
from .._validate import check_int, check_positive, real_array


def check_qsr(K: LTIController, qsr: QSR) -> None:
    if not isinstance(K, LTIController):
        raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__}.")
    if not isinstance(qsr, QSR):
        raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
    if K.n_state == 0:
        raise ValueError(
            "`K` has no state (`K.n_state` = 0, a static controller y = D u): `dj.project` "
            "needs an order of at least 1 (its convexified KYP LMI linearises around a storage "
            "P, which a static controller lacks). Certify a static gain with `dj.certify` (the "
            "test is then Phi(D) = R + S'D + D'S + D'QD > 0), or project an order-1 "
            "controller.")
    qsr.check_sizes(K.n_in, K.n_out)
    check_feasible(qsr)  # some static D is strictly dissipative


def solved_room(qsr: QSR) -> float | None:
    """$\\lambda_{\\min}(R - S^\\top Q^{-1}S)$ of the rate as the projection solves it
    (divided by `rate_factor`), the most room any feedthrough has there, in which the LMI
    margin `eps` must fit; None for $Q$ not negative definite (no such bound)."""
    found = schur_complement(scaled_rate(qsr, rate_factor(qsr)), 1e-12)
    return None if found is None else float(np.linalg.eigvalsh(found[0])[0])


def check_eps_room(qsr: QSR, eps) -> None:
    """Refuse an LMI margin `eps` that no controller can meet, naming `eps`.

    The KYP LMI with margin $\\varepsilon$ asks $\\Phi(D) - B^\\top PB\\succeq\\varepsilon I$ in
    its input block, $\\Phi(D) = R + S^\\top D + D^\\top S + D^\\top QD$. For $Q\\prec0$,
    $\\Phi(D) = R - S^\\top Q^{-1}S + (D + Q^{-1}S)^\\top Q(D + Q^{-1}S)\\preceq
    R - S^\\top Q^{-1}S$, so when $\\lambda_{\\min}(R - S^\\top Q^{-1}S)\\le\\varepsilon$ the
    set is empty whatever the solver does (e.g. a gain bound $\\gamma = 10^{-4}$ has room
    $\\gamma^2 = 10^{-8}$, below the default $\\varepsilon = 10^{-6}$). Other rates are left to
    the solver (their room can be unbounded). A rate outside $[1/64, 64]$ in size is
    solved divided by a power of two (`rate_factor`), and `eps` is its margin there.
    """
    if isinstance(eps, jax.core.Tracer) or isinstance(qsr.Q, jax.core.Tracer):
        return
    room = solved_room(qsr)
    if room is not None and 0 < room <= float(eps):
        raise ValueError(
            f"`eps` = {float(eps):.3g} is not below the supply rate's room: every feedthrough "
            f"has R + S'D + D'S + D'QD <= R - S'Q^-1 S, whose smallest eigenvalue is "
            f"{room:.3g}, so no controller meets the KYP LMI with this margin. Pass a much "
            f"smaller `eps` (e.g. {room * 1e-4:.1g}), or express the signals in units where "
            "Q, S and R are of similar size."
            + (" With room this close to float64's round-off, a projection may succeed "
               "but a trainer's iterates rarely pass the exact check; `dj.fit_direct`, "
               "whose `margin` is relative to the room, trains such rates."
               if room < 1e-8 else ""))


def check_k_ref(K: LTIController, K_ref) -> None:
    if K_ref is None:
        return
    if not isinstance(K_ref, LTIController):
        raise ValueError(f"`K_ref` must be a `dj.LTIController`, got {type(K_ref).__name__}.")
    for name in "ABCD":
        if getattr(K_ref, name).shape != getattr(K, name).shape:
            raise ValueError(f"`K_ref.{name}` must have the shape {getattr(K, name).shape} of "
                             f"`K.{name}`, got {getattr(K_ref, name).shape}.")


def check_metric(K: LTIController, metric) -> None:
    if metric is None:
        return
    if not isinstance(metric, LTIController):
        raise ValueError(f"`metric` must be a `dj.LTIController` of weights, got "
                         f"{type(metric).__name__}.")
    for name in "ABCD":
        W, M = getattr(metric, name), getattr(K, name)
        if W.shape != M.shape:
            raise ValueError(f"`metric.{name}` must have the shape {M.shape} of `K.{name}`, "
                             f"got {W.shape}.")
        if not isinstance(W, jax.core.Tracer) and not np.all(np.isfinite(W) & (W > 0)):
            raise ValueError(f"`metric.{name}` must be positive and finite.")


def check_options(K: LTIController, P_ref, active, eps, reg, refine, metric=None) -> None:
    check_metric(K, metric)
    check_positive("eps", eps)
    check_positive("reg", reg, zero=True)
    check_int("refine", refine, minimum=0)
    try:
        boolean = jnp.result_type(active) == jnp.bool_
    except TypeError:  # e.g. a string, which would read as True
        boolean = False
    if not boolean:
        raise ValueError(f"`active` must be bool (a scalar or an array), got {active!r}.")
    if jnp.shape(active) not in ((), K.batch_shape):
        raise ValueError(f"`active` must be a bool scalar or have the batch shape "
                         f"{K.batch_shape} of `K`, got shape {jnp.shape(active)}.")
    if P_ref is None:
        return
    n, shape = K.n_state, np.shape(P_ref)
    if shape not in ((n, n), K.batch_shape + (n, n)):
        raise ValueError(
            f"`P_ref` must be {n}x{n} (the controller's order), got {shape}." if not K.batch_shape
            else f"`P_ref` must be {n}x{n} (shared by the batch) or "
                 f"{K.batch_shape + (n, n)} (one per controller), got {shape}.")
    if isinstance(P_ref, jax.core.Tracer):
        if jnp.iscomplexobj(P_ref):
            raise ValueError("`P_ref` must be an array of real numbers, got complex values.")
        return
    P = real_array("P_ref", P_ref)
    sym = (P + np.swapaxes(P, -1, -2)) / 2
    if not np.all(np.isfinite(P)):
        raise ValueError("`P_ref` contains NaN or inf.")
    if not np.allclose(P, sym, rtol=1e-6, atol=1e-12 * max(1.0, np.abs(P).max(initial=0.0))):
        raise ValueError("`P_ref` must be symmetric.")
    if P.size and np.linalg.eigvalsh(sym)[..., 0].min() <= 0:
        raise ValueError("`P_ref` must be positive definite.")
