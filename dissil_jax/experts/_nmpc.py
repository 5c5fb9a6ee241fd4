"""The nonlinear benchmark's expert: single-shooting NMPC solved by Newton in JAX (paper §5.2)."""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._linalg import spd_solve
from .._validate import check_int

# Step sizes tried in parallel by the backtracking line search (vectorised, so the
# Newton loop stays one `while_loop` under vmap).
_LINE_SEARCH_STEPS = 16
_ARMIJO = 1e-4


class NMPCSolution(NamedTuple):
    """One solved NMPC problem: inputs `u` `[H, m]`, `cost`, final `grad_norm`, `iterations`."""

    u: Float[Array, "H m"]
    cost: Float[Array, ""]
    grad_norm: Float[Array, ""]
    iterations: Int[Array, ""]


class NMPCExpert(eqx.Module):
    """Nonlinear MPC by single shooting and damped Newton, jit- and vmap-friendly (paper §5.2).

    At state $x_0$ it solves, over $u_0..u_{H-1}$ (no input bounds),

    $$\\min_u\\ \\sum_{i=0}^{H-1}\\left(q\\,x_i^\\top x_i + r\\,u_i^\\top u_i\\right)
    + q_T\\,x_H^\\top x_H, \\qquad x_{i+1} = f(x_i, u_i),$$

    with $f$ the plant's noise-free `step`, and applies $u_0$. The paper's expert is
    $H = 11$, $q = 2$, $r = 1$, $q_T = 2$ (the $i = 0$ stage term is a constant).

    Newton: gradient and Hessian by autodiff of the shooting cost, solved by Cholesky
    after a tiny shift (`hess_floor` times $\\lVert H\\rVert_F$); where the Hessian is not
    positive definite (the cost is nonconvex through $\\sin$) it is shifted by
    $\\lVert H\\rVert_F$, which gives a descent direction; a backtracking Armijo line search over
    $1, \\tfrac12, \\ldots$ evaluates all candidates at once. It stops when
    $\\lVert\\nabla J\\rVert \\le$ `gtol` $(1 + |J|)$ or after `max_iter` iterations.

    Closed loop: `init(x0)` gives the carry (zeros, a cold start) and `__call__(x, carry)`
    returns $u_0$ and the shifted solution $(u_1, \\ldots, u_{H-1}, 0)$ as the next warm
    start. Unbatched; vmap for batches.

    **Arguments:** `plant` (a module with `step(x, u)`, e.g. `dj.SectorPlant`), `horizon`
    $H$, weights `q`, `r`, `q_terminal`, `max_iter`, `gtol` (None: $10^{-10}$ in float64,
    $10^{-5}$ in float32), `hess_floor`.
    """

    plant: Any
    horizon: int = eqx.field(static=True, default=11)
    q: float = eqx.field(static=True, default=2.0)
    r: float = eqx.field(static=True, default=1.0)
    q_terminal: float = eqx.field(static=True, default=2.0)
    max_iter: int = eqx.field(static=True, default=50)
    gtol: float | None = eqx.field(static=True, default=None)
    hess_floor: float = eqx.field(static=True, default=1e-8)

    def __check_init__(self):
        if not hasattr(self.plant, "step"):
            raise ValueError(f"`plant` must have a `step(x, u)` method, got {type(self.plant)}.")
        check_int("horizon", self.horizon)
        check_int("max_iter", self.max_iter)
        if self.r <= 0:
            raise ValueError(f"`r` must be positive (it makes the problem well posed), got {self.r}.")
        if self.q < 0 or self.q_terminal < 0:
            raise ValueError("`q` and `q_terminal` must be non-negative.")

    @property
    def n_in(self) -> int:
        return self.plant.n_in

    def cost(self, u: Float[Array, "H m"], x0: Float[Array, " n"]) -> Float[Array, ""]:
        """The single-shooting cost $J(u; x_0)$."""

        def step(x, ui):
            return self.plant.step(x, ui), self.q * x @ x + self.r * ui @ ui

        xH, stage = jax.lax.scan(step, x0, u)
        return jnp.sum(stage) + self.q_terminal * xH @ xH

    def solve(self, x0: Float[Array, " n"], u_init: Float[Array, "H m"] | None = None
              ) -> NMPCSolution:
        """Solve the NMPC problem at `x0` from the initial guess `u_init` (zeros if None)."""
        H, m = self.horizon, self.n_in
        if u_init is None:
            u_init = jnp.zeros((H, m), x0.dtype)
        dtype = jnp.result_type(x0, u_init)
        gtol = self.gtol
        if gtol is None:
            gtol = 1e-10 if dtype == jnp.float64 else 1e-5
        J = lambda v: self.cost(v.reshape(H, m), x0)
        grad = jax.grad(J)
        hess = jax.hessian(J)
        steps = 0.5 ** jnp.arange(_LINE_SEARCH_STEPS, dtype=dtype)

        def cond(state):
            v, it, Jv, g, stuck = state
            return (it < self.max_iter) & (jnp.linalg.norm(g) > gtol * (1 + jnp.abs(Jv))) & ~stuck

        def body(state):
            v, it, Jv, g, _ = state
            Hv = hess(v)
            Hv = (Hv + Hv.T) / 2
            # Cholesky is ~10x cheaper than eigh for a batch of small matrices; when the
            # Hessian is not positive definite (the cost is nonconvex through sin), shift it
            # by its Frobenius norm, which makes it positive definite: a descent direction.
            eye = jnp.eye(Hv.shape[0], dtype=dtype)
            shift = self.hess_floor * jnp.maximum(jnp.linalg.norm(Hv), 1.0)
            d = -spd_solve(Hv + shift * eye, g)
            bad = ~jnp.all(jnp.isfinite(d))
            d = jnp.where(bad, -spd_solve(Hv + (jnp.linalg.norm(Hv) + shift) * eye, g), d)
            cand = v[None] + steps[:, None] * d[None]
            Jc = jax.vmap(J)(cand)
            # Near the optimum the predicted decrease falls below the round-off of J;
            # allow that much slack or full Newton steps get rejected on rounding noise.
            slack = 16 * jnp.finfo(dtype).eps * (1 + jnp.abs(Jv))
            ok = Jc <= Jv + _ARMIJO * steps * (g @ d) + slack
            i = jnp.argmax(ok)
            accepted = ok[i]
            v_new = jnp.where(accepted, cand[i], v)
            J_new = jnp.where(accepted, Jc[i], Jv)
            return v_new, it + 1, J_new, grad(v_new), ~accepted

        v0 = u_init.reshape(-1).astype(dtype)
        state = (v0, jnp.array(0), J(v0), grad(v0), jnp.array(False))
        v, it, Jv, g, _ = jax.lax.while_loop(cond, body, state)
        return NMPCSolution(v.reshape(H, m), Jv, jnp.linalg.norm(g), it)

    def init(self, x0: Float[Array, " n"]) -> Float[Array, "H m"]:
        """Cold-start carry: a zero input sequence."""
        return jnp.zeros((self.horizon, self.n_in), x0.dtype)

    def __call__(self, x: Float[Array, " n"], carry: Float[Array, "H m"]
                 ) -> tuple[Float[Array, " m"], Float[Array, "H m"]]:
        """Apply $u_0$ of the solution at `x`; return it and the shifted warm start."""
        sol = self.solve(x, carry)
        shifted = jnp.concatenate([sol.u[1:], jnp.zeros_like(sol.u[:1])], axis=0)
        return sol.u[0], shifted


def nmpc_expert(plant=None, horizon: int = 11, q: float = 2.0, r: float = 1.0,
                q_terminal: float = 2.0, **kwargs) -> NMPCExpert:
    """The paper's NMPC expert (§5.2): horizon 11, stage cost $2x^2 + u^2$, terminal $2x_{11}^2$.

    `plant` defaults to `dj.systems.paper_nonlinear_plant()`; other keyword arguments go
    to [`NMPCExpert`][dissil_jax.experts.NMPCExpert].
    """
    if plant is None:
        from ..systems import paper_nonlinear_plant

        plant = paper_nonlinear_plant()
    return NMPCExpert(plant, horizon, float(q), float(r), float(q_terminal), **kwargs)
