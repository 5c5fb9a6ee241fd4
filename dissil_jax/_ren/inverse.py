"""The REN direct map backwards: free parameters $\\theta$ with `ren_map(θ) = K`, for a REN
$K$ that has a certificate with room to spare (`fit_ren(init=...)` starts there).

`ren_map` builds a matrix $\\mathcal M\\succeq\\varepsilon I + \\mathcal C\\tilde\\Phi^{-1}
\\mathcal C^\\top$ over $(x, w, x^+)$ and reads the REN off its blocks (`map.py`). Choosing
$E = \\mathcal P = P$ and $Y = 0$ there, every block of $\\mathcal M$ is affine in the
certificate $(P, \\Lambda)$ of the given $K$:

$$\\mathcal M = \\begin{bmatrix} (1-\\varepsilon)P + C_2^\\top QC_2 & \\ast & \\ast\\\\
-\\Lambda C_1 + D_{21}^\\top QC_2 & 2(1-\\varepsilon)\\Lambda - \\Lambda D_{11} -
D_{11}^\\top\\Lambda + D_{21}^\\top QD_{21} & \\ast\\\\ PA & PB_1 & P\\end{bmatrix},\\qquad
\\mathcal C = \\begin{bmatrix} C_2^\\top T\\\\ D_{21}^\\top T - \\Lambda D_{12}\\\\
PB_2\\end{bmatrix},$$

with $T = S + QD_{22}$. So $K$ is in the map's image exactly when some $(P, \\Lambda)$
makes $\\Gamma = \\mathcal M - \\varepsilon I - \\mathcal C\\tilde\\Phi^{-1}\\mathcal C^\\top
\\succeq 0$, a linear matrix inequality (a Schur complement over $\\tilde\\Phi$), and then
$X = \\Gamma^{1/2}$. An SDP chooses the pair: the smallest $\\operatorname{tr}P +
\\operatorname{tr}\\Lambda$ with $\\Gamma\\succeq\\tfrac\\varepsilon2 I$, which keeps $X$ away
from singular and the storage near the size of the map's random starts ($P\\approx I$);
when there is no such pair, a second SDP finds the largest $\\delta$ with
$\\Gamma\\succeq\\delta I$ at $\\operatorname{tr}P + \\operatorname{tr}\\Lambda$ at most
1000 per row of $\\Gamma$ (negative: $K$ is out of the map's reach). The feedthrough's
parameter $W$ inverts the loop transformation of `_direct_map.output_map` at order 0 in
closed form.
"""

from __future__ import annotations

import warnings

import numpy as np

from .._direct_map import map_constants
from .._sdp import sdp as _sdp
from .._supply import QSR
from .map import RENParams, input_units


def feedthrough_params(D22: np.ndarray, qsr: QSR, margin: float) -> np.ndarray | None:
    """The `W` whose image under `output_map` at order 0 is `D22` (float64), or None when
    `D22` is outside its image ($\\Phi(D_{22})$ not above $\\varepsilon\\Phi_0$ there).

    The map is $D = D_0 + (1-\\varepsilon)Z(I - T_u^\\top Z)^{-1}G_\\Phi$ with
    $Z = WG_W^{-1}$, $G_W^\\top G_W = I + W^\\top NW$. With
    $\\Delta = (D - D_0)G_\\Phi^{-1}/(1-\\varepsilon)$: $Z = (I + \\Delta T_u^\\top)^{-1}
    \\Delta$, $H = I - Z^\\top NZ\\succ0$, and $W = ZG_W$ with $G_W$ the upper-triangular
    factor of $H^{-1} = G_WG_W^\\top$ (then $I + W^\\top NW = G_W^\\top G_W$, as the map
    computes it)."""
    D0, _, G_phi, T_u, N = map_constants(qsr, margin)
    m, p = D22.shape
    delta = np.linalg.solve(G_phi.T, (D22 - D0).T).T / (1.0 - margin)
    Z = np.linalg.solve(np.eye(m) + delta @ T_u.T, delta)
    H = np.eye(p) - Z.T @ N @ Z
    H = (H + H.T) / 2
    if not np.all(np.isfinite(H)) or np.linalg.eigvalsh(H)[0] <= 0.0:
        return None
    flip = np.eye(p)[::-1]
    G_W = flip @ np.linalg.cholesky(flip @ np.linalg.inv(H) @ flip) @ flip
    return Z @ G_W


def _blocks(K, qsr: QSR, margin: float, P, lam):
    """`(M, col)` of the module docstring for a pair `(P, lam)` of numpy arrays or cvxpy
    expressions (`lam` a vector of the neurons' multipliers)."""
    import cvxpy as cp

    A, B1, B2, C1, D11, D12, C2, D21, D22 = K
    Q, S = qsr.Q, qsr.S
    n, q = A.shape[0], C1.shape[0]
    T = S + Q @ D22
    expr = not isinstance(P, np.ndarray)
    Lam = (cp.diag(lam) if q else np.zeros((0, 0))) if expr else np.diag(lam)
    xx = (1.0 - margin) * P + C2.T @ Q @ C2
    if q:
        wx = -Lam @ C1 + D21.T @ Q @ C2
        ww = 2.0 * (1.0 - margin) * Lam - Lam @ D11 - D11.T @ Lam + D21.T @ Q @ D21
        xi = D21.T @ T - Lam @ D12
    else:
        wx, ww, xi = np.zeros((0, n)), np.zeros((0, 0)), np.zeros((0, B2.shape[1]))
    stack = cp.bmat if expr else np.block
    M = stack([[xx, wx.T, (P @ A).T], [wx, ww, (P @ B1).T], [P @ A, P @ B1, P]])
    col = stack([[C2.T @ T], [xi], [P @ B2]]) if expr else np.concatenate(
        [C2.T @ T, xi, P @ B2])
    return M, col


def _pair(K, qsr: QSR, margin: float, Phi_t):
    """The certificate `(P, lam)` of the module docstring and its $\\delta$ (one or two SDPs
    with cvxpy and Clarabel, BLAS single-threaded), or None when the solver fails."""
    import cvxpy as cp

    n, q = K[0].shape[0], K[3].shape[0]
    P = cp.Variable((n, n), symmetric=True)
    lam = cp.Variable(q) if q else np.zeros(0)
    M, col = _blocks(K, qsr, margin, P, lam)
    size = 2 * n + q

    def lmi(delta):
        big = cp.bmat([[M - (margin + delta) * np.eye(size), col], [col.T, Phi_t]])
        return (big + big.T) / 2 >> 0

    trace = cp.trace(P) + (cp.sum(lam) if q else 0.0)
    extra = [lam >= 0] if q else []
    value = lambda: (np.array(P.value), np.array(lam.value if q else np.zeros(0)).reshape(q))
    with _sdp.single_threaded_blas(), warnings.catch_warnings():
        # the pair is mapped forward by the caller, whose image is certified regardless
        warnings.filterwarnings("ignore", message="Solution may be inaccurate",
                                category=UserWarning)
        # the smallest storage that keeps half the map's room (one SDP for most starts)
        first = cp.Problem(cp.Minimize(trace), [lmi(margin / 2), *extra])
        try:
            first.solve(solver=cp.CLARABEL)
            if P.value is not None and first.status in _SOLVED:
                P_, lam_ = value()
                return (P_ + P_.T) / 2, lam_, margin / 2
        except cp.SolverError:
            pass
        # else the most room there is, at a bounded storage (negative: out of reach)
        delta = cp.Variable()
        second = cp.Problem(cp.Maximize(delta), [lmi(delta), delta <= margin / 2,
                                                 trace <= _TRACE * size, *extra])
        try:
            second.solve(solver=cp.CLARABEL)
        except cp.SolverError:
            return None
        if P.value is None or delta.value is None or second.status not in _SOLVED:
            return None
        P_, lam_ = value()
        return (P_ + P_.T) / 2, lam_, float(delta.value)


_SOLVED = ("optimal", "optimal_inaccurate")
# The second SDP's bound on tr P + tr Λ per row of Γ (the map starts at P ≈ I, Λ ≈ I/2).
_TRACE = 1e3


def ren_params_of(K, qsr: QSR, margin: float,
                  direct_input: bool) -> tuple[RENParams, float] | None:
    """`(θ, δ)`: parameters $\\theta$ (float64 numpy) with `ren_map(θ, qsr, width, ...,
    margin, direct_input)` $\\approx K$, and the least eigenvalue $\\delta$ of $\\Gamma$
    the SDP found; None for a $K$ the map cannot approach (a nonzero $D_{12}$ without
    `direct_input`, a feedthrough outside its image, or a failed solve).

    With $\\delta\\ge0$, $K$ is in the map's image and $\\theta$ maps to it up to the SDP's
    tolerance. With $\\delta<0$ it is not, and $\\Gamma$'s negative eigenvalues are
    clipped to zero: $\\theta$ then maps to a nearby REN, off by about $|\\delta|$ in
    $\\mathcal M$.

    `K` is one REN as a tuple of its nine matrices (float64 numpy), in the units and the
    rate (`qsr`, $Q\\preceq0$) of the map: the trainer's normalised units. The result is
    exact up to the SDP's tolerance ($\\Gamma$'s eigenvalues are clipped at zero)."""
    A, B1, B2, C1, D11, D12, C2, D21, D22 = K
    if not direct_input and np.any(D12 != 0):
        return None
    W = feedthrough_params(D22, qsr, margin)
    if W is None:
        return None
    Q, S, R = qsr.Q, qsr.S, qsr.R
    Phi0 = map_constants(qsr, margin)[1]
    Phi_t = R + S.T @ D22 + D22.T @ S + D22.T @ Q @ D22 - 0.5 * margin * Phi0
    Phi_t = (Phi_t + Phi_t.T) / 2
    if np.linalg.eigvalsh(Phi_t)[0] <= 0.0:
        return None
    pair = _pair(K, qsr, margin, Phi_t)
    if pair is None:
        return None
    P, lam, delta = pair
    if len(lam) and lam.min() <= 0.0:
        return None
    M, col = _blocks(K, qsr, margin, P, lam)
    gamma = M - margin * np.eye(M.shape[0]) - col @ np.linalg.solve(Phi_t, col.T)
    w, V = np.linalg.eigh((gamma + gamma.T) / 2)
    X = (V * np.sqrt(np.maximum(w, 0.0))) @ V.T
    units = input_units(qsr, margin)
    n, q = A.shape[0], C1.shape[0]
    theta = RENParams(X, np.zeros((n, n)), C2, D21, (P @ B2) / units, W,
                      (lam[:, None] * D12) / units if q else np.zeros((0, B2.shape[1])))
    return theta, delta
