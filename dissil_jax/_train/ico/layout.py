"""What the ICO SDP is built from: the two-step windows (`TwoStepData`) and the layout of its
variable vector (`VariableLayout`). Host-side float64 numpy only; see `sdp.py` for the maths.
"""

from __future__ import annotations

import numpy as np

from ..._sdp.sdp import Layout

SQRT2 = np.sqrt(2.0)


def svec_pos(i, j):
    """Clarabel svec position of entry (i, j) with i <= j (upper triangle, column-major)."""
    return j * (j + 1) // 2 + i


def svec_len(d):
    """Length of the svec of a `d` x `d` symmetric matrix."""
    return d * (d + 1) // 2


class TwoStepData:
    """The demonstration windows in float64 and the quantities of the two-step loss.

    **Arguments:** `x0` `[N, n]`, `uhat` `[N, 2, p]` (controller inputs $\\hat u = y$),
    `target` `[N, 2, m]` ($-u$).
    """

    def __init__(self, x0, uhat, target):
        x0, uhat, target = (np.asarray(a, np.float64) for a in (x0, uhat, target))
        self.N, self.n = x0.shape
        self.p, self.m = uhat.shape[2], target.shape[2]
        self.x0, self.u0, self.u1 = x0, uhat[:, 0], uhat[:, 1]
        self.t0, self.t1 = target[:, 0], target[:, 1]
        self.c = 1.0 / self.N  # J = (1/N) sum over windows of both steps' errors (paper eq. 16)
        self.zeta = np.concatenate([x0, self.u0], axis=1)  # [N, n+p]
        self.G = self.zeta.T @ self.zeta  # sum_k zeta_k zeta_k^T
        lam, V = np.linalg.eigh(self.G)
        keep = lam > 1e-12 * max(1.0, lam.max())
        self.F = V[:, keep] * np.sqrt(lam[keep])  # G = F F^T, [n+p, r]

    def residuals(self, A, B, C, D):
        """`(r0, z, ebar)`: the step-0 residual, $z = A\\hat x_0 + B\\hat u_0$ and the step-1
        residual (targets minus predictions, `[N, m]`, `[N, n]`, `[N, m]`)."""
        r0 = self.t0 - self.x0 @ C.T - self.u0 @ D.T
        z = self.x0 @ A.T + self.u0 @ B.T
        ebar = self.t1 - z @ C.T - self.u1 @ D.T
        return r0, z, ebar


class VariableLayout(Layout):
    """The SDP's variable vector $x = (\\delta\\theta, P_{\\text{triu}}, Y, w, \\tau, \\sigma)$.

    $\\delta\\theta = (\\delta A, \\delta B, \\delta C, \\delta D)$, each `vec` row-major; then
    the `nP` upper-triangular entries of $P$ (row-major, as `ConvexifiedLMI`; `nP = 0` for
    ICO-NC), so the KYP LMI's variables are the first `ntheta + nP` columns of $x$; then $Y$
    (one scalar $y$ with $Y = yI$ when `scalar_y`, else its upper triangle), the Young weight
    $w$, $\\tau$ and `n_sig` values $\\sigma$. `o*` are offsets, `col*` the columns of each
    matrix entry.
    """

    def __init__(self, n: int, p: int, m: int, *, nP: int, scalar_y: bool, n_sig: int):
        super().__init__(n, p, m)  # theta = (vec A, vec B, vec C, vec D) and P's triangle
        self.oP, self.nP = self.ntheta, nP
        self.oY = self.oP + nP
        self.scalar_y = scalar_y
        self.y_rows, self.y_cols = np.triu_indices(m)
        self.nY = 1 if scalar_y else len(self.y_rows)
        self.ow = self.oY + self.nY
        self.otau = self.ow + 1
        self.osig, self.n_sig = self.otau + 1, n_sig
        self.nx = self.osig + n_sig

        o = self._offsets
        self.col_theta = np.arange(self.ntheta)
        self.colA = o[0] + np.arange(self.nA).reshape(n, n)
        self.colB = o[1] + np.arange(self.nB).reshape(n, p)
        self.colC = o[2] + np.arange(self.nC).reshape(m, n)
        self.colD = o[3] + np.arange(self.nD).reshape(m, p)
        self.colAB = np.concatenate([self.colA, self.colB], axis=1)  # [n, n+p]
        self.colCD = np.concatenate([self.colC, self.colD], axis=1)  # [m, n+p]
        self.colP = self.oP + np.arange(nP)
        self.colY = self.oY + np.arange(self.nY)
        self.col_sig = self.osig + np.arange(n_sig)
        # Y's entries in a svec: rows, cols, column of x and svec weight of each.
        if scalar_y:
            d = np.arange(m)
            self.y_svec = (d, d, np.full(m, self.oY), np.ones(m))
        else:
            yi, yj = self.y_rows, self.y_cols
            self.y_svec = (yi, yj, self.colY, np.where(yi == yj, 1.0, SQRT2))

    def theta(self, A, B, C, D) -> np.ndarray:
        """$\\theta$ of a controller (float64)."""
        return self.pack(A, B, C, D)
