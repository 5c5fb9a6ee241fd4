"""The paper's linear benchmark: random passive chains of unit masses (paper §5.1)."""

from __future__ import annotations

from typing import cast

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import PRNGKeyArray

from .._validate import check_int
from ._plants import LinearPlant


class MassSpringChain(eqx.Module):
    """A sampled mass-spring-damper chain: the discrete plant and its continuous model.

    - `plant`: the discretised [`LinearPlant`][dissil_jax.LinearPlant] (zero-order hold by
      default, which keeps $D = \\varphi I$).
    - `Ac`, `Bc`, `Cc`, `Dc`: the continuous-time matrices (float64 numpy), used by the
      LQR expert (paper §5.1 designs it from the continuous Riccati equation).
    - `k`, `c`: spring and damper coefficients $k_1..k_n$, $c_1..c_n$; `phi`: the
      feedthrough $\\varphi$ ($D_c = \\varphi I$); `dt`: the sampling time.
    """

    plant: LinearPlant
    Ac: np.ndarray
    Bc: np.ndarray
    Cc: np.ndarray
    Dc: np.ndarray
    k: np.ndarray
    c: np.ndarray
    phi: float
    dt: float


def chain_matrices(k, c, phi: float):
    """Continuous-time $(A, B, C, D)$ of the chain wall–$(k_1,c_1)$–$m_1$–…–$m_n$ (unit masses).

    State $x = (q_1..q_n, v_1..v_n)$ (positions, then velocities); input: one force per mass;
    output $y = v + \\varphi F$. With the stiffness and damping matrices $K$, $C_d$
    (tridiagonal, spring $i$ joins mass $i-1$, or the wall for $i=1$, to mass $i$):

    $$A = \\begin{bmatrix}0 & I\\\\ -K & -C_d\\end{bmatrix},\\quad
    B = \\begin{bmatrix}0\\\\ I\\end{bmatrix},\\quad C = \\begin{bmatrix}0 & I\\end{bmatrix},
    \\quad D = \\varphi I.$$
    """
    k, c = np.asarray(k, np.float64), np.asarray(c, np.float64)
    n = k.shape[0]

    def laplacian(g):
        L = np.diag(g + np.append(g[1:], 0.0))
        L -= np.diag(g[1:], 1) + np.diag(g[1:], -1)
        return L

    Z, I = np.zeros((n, n)), np.eye(n)
    A = np.block([[Z, I], [-laplacian(k), -laplacian(c)]])
    B = np.vstack([Z, I])
    C = np.hstack([Z, I])
    D = float(phi) * I
    return A, B, C, D


def mass_spring_chain(
    key: PRNGKeyArray,
    n_masses: int = 3,
    dt: float = 0.1,
    *,
    k_range: tuple[float, float] = (1.0, 5.0),
    c_range: tuple[float, float] = (1.0, 10.0),
    phi_range: tuple[float, float] = (0.05, 1.0),
    method: str = "zoh",
    check_passive: bool = True,
) -> MassSpringChain:
    """Sample one of the paper's passive mass-spring-damper chains (paper §5.1).

    Springs $k_i\\sim U[1,5]$, dampers $c_i\\sim U[1,10]$, feedthrough
    $\\varphi\\sim U[0.05,1]$; see [`chain_matrices`][dissil_jax.systems.chain_matrices]
    for the model. The continuous plant is discretised by python-control
    (`sys.sample(dt, method)`). The default zero-order hold keeps the state at the samples
    and the feedthrough $D = \\varphi I$ that the paper states ("The feedthrough matrix was
    designed as $\\phi I$", paper §5.1). It is passive when $\\varphi$ exceeds about $dt/2$
    (at $z = -1$ a unit mass contributes $-dt/2$ to the frequency response), which every
    draw of $\\varphi\\sim U[0.05, 1]$ does at $dt = 0.1$; `check_passive` certifies each
    draw. Tustin (`method="bilinear"`) also preserves passivity but adds
    $\\tfrac12 C B_d$ to $D$.

    **Arguments:**

    - `key`: a JAX PRNG key (for an integer seed `s`, `jax.random.PRNGKey(s)`).
    - `n_masses`: number of masses $n$ (state size $2n$, $n$ inputs, $n$ outputs).
    - `dt`: sampling time.
    - `k_range`, `c_range`, `phi_range`: the uniform sampling intervals.
    - `method`: python-control discretisation method.
    - `check_passive`: certify the discrete plant passive with
      [`certify`][dissil_jax.certify] (the KYP SDP of paper Lemma 2 with $Q=0$,
      $S=\\tfrac12 I$, $R=0$, applied to the plant $u\\mapsto y$) and raise if it is not.

    **Returns:** a [`MassSpringChain`][dissil_jax.systems.MassSpringChain].

    ```python
    chain = dj.systems.mass_spring_chain(jax.random.PRNGKey(0))
    expert = dj.experts.lqr_expert(chain.Ac, chain.Bc, chain.Cc)
    ```
    """
    import control

    n_masses = check_int("n_masses", n_masses)
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"`dt` must be a positive sampling time, got {dt!r}.")
    for name, (lo, hi) in (("k_range", k_range), ("c_range", c_range), ("phi_range", phi_range)):
        if not (np.isfinite(lo) and np.isfinite(hi)) or not 0 < lo <= hi:
            raise ValueError(f"`{name}` must be an interval 0 < lo <= hi, got {(lo, hi)}.")
    if isinstance(key, (int, np.integer)):
        raise ValueError(f"`key` must be a JAX PRNG key, got the integer {key!r}; pass "
                         f"`jax.random.PRNGKey({key!r})` (the same chain as the seed gave).")
    kk, kc, kp = jr.split(key, 3)
    # Draw in float32-independent fashion: uniform [0,1) then scale in float64 on the host.
    k = k_range[0] + (k_range[1] - k_range[0]) * np.asarray(jr.uniform(kk, (n_masses,)), np.float64)
    c = c_range[0] + (c_range[1] - c_range[0]) * np.asarray(jr.uniform(kc, (n_masses,)), np.float64)
    phi = phi_range[0] + (phi_range[1] - phi_range[0]) * float(jr.uniform(kp, ()))
    Ac, Bc, Cc, Dc = chain_matrices(k, c, phi)
    # python-control types `ss` as returning any I/O system; from matrices it is a StateSpace
    sysd = cast(control.StateSpace, control.ss(Ac, Bc, Cc, Dc)).sample(dt, method=method)
    plant = LinearPlant(*(jnp.asarray(np.asarray(M, np.float64)) for M in (sysd.A, sysd.B, sysd.C,
                                                                           sysd.D)))
    if check_passive:
        from .._certify.certify import certify
        from .._controller import LTIController
        from .._supply import QSR

        cert = certify(LTIController(*plant.matrices()), QSR.passive(n_masses))
        if not cert.holds:
            raise ValueError(
                f"the discretised chain (`method`={method!r}, `dt`={dt}) is not certified "
                f"passive (margin {cert.margin:.3g}, solver {cert.status}); a zero-order hold "
                "needs `phi_range` above about `dt`/2, or use `method='bilinear'`."
            )
    return MassSpringChain(plant, Ac, Bc, Cc, Dc, k, c, float(phi), float(dt))
