"""The window part of the ICO SDP: the bound on the step-1 residuals $\\bar e_k$.

Three interchangeable cone blocks (`blocks.ConeBlock`), chosen once by `window_cone`
(see the module docstring of `sdp.py` for the maths):

- `StackedWindows` (`"stacked"`): all windows in one QR-compressed rotated SOC;
- `SOCWindows` (`"soc"`): one rotated SOC $\\lVert\\bar e_k\\rVert^2 \\le \\sigma_k(1 - y)$
  per window;
- `PSDWindows` (`"psd"`): one LMI $[[\\sigma_k, \\bar e_k^\\top], [\\bar e_k, I - Y]]
  \\succeq 0$ per window, with a full symmetric $Y$.

Each class says which $Y$ it needs (`scalar_y`) and how many $\\sigma$ (`n_sigma`), so that
the `VariableLayout` is built for it.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from .blocks import ConeBlock
from .layout import SQRT2, TwoStepData, VariableLayout, svec_len, svec_pos


class StackedWindows(ConeBlock):
    r"""All windows in one rotated SOC, $\lVert\bar e\rVert^2 \le \sigma(1 - y)$.

    $\bar e = (\bar e_1, \dots, \bar e_N) = \bar e_0 - L\,\delta\theta$ is affine with
    $L \in \mathbb R^{Nm \times n_\theta}$. With a thin QR factorisation $L = QR$,
    $\lVert\bar e\rVert^2 = \lVert Q^\top\bar e_0 - R\,\delta\theta\rVert^2 + c^2$,
    $c = \lVert(I - QQ^\top)\bar e_0\rVert$, so the cone
    $\lVert(2(Q^\top\bar e_0 - R\delta\theta), 2c, \sigma - 1 + y)\rVert
    \le \sigma + 1 - y$ has $\min(Nm, n_\theta) + 3$ rows whatever $N$ is. Its optimum
    equals the per-window SOC form's ($\sum_k\sigma_k$ with $\sigma_k = \lVert\bar e_k
    \rVert^2/(1 - y)$); only the QR (`stacked_factor`), done in numpy every iteration, grows
    with $N$.
    """

    scalar_y = True

    @staticmethod
    def n_sigma(N: int) -> int:
        return 1

    def __init__(self, data: TwoStepData, layout: VariableLayout):
        import clarabel

        self.data = data
        nth = layout.ntheta
        self.r_e = r_e = min(data.N * data.m, nth)
        self.rows = r_e + 3
        self.cones = [clarabel.SecondOrderConeT(self.rows)]
        ri, cj = np.triu_indices(r_e, m=nth)  # R is upper trapezoidal
        self._r_idx = (ri, cj)
        osig, oy = layout.osig, layout.oY
        self._rows = np.concatenate([np.array([0, 1, 0, 1]), 2 + ri])
        self._cols = np.concatenate([np.array([osig, osig, oy, oy]), layout.col_theta[cj]])
        self._fixed = np.array([-1.0, -1.0, 1.0, -1.0])

    def fill(self, it):
        r_e = self.r_e
        R, g, c = stacked_factor(self.data, it.C, it.z, it.ebar)
        b = np.zeros(self.rows)
        b[0], b[1] = 1.0, -1.0
        b[2:2 + r_e] = 2.0 * g
        b[2 + r_e] = 2.0 * c
        return np.concatenate([self._fixed, 2.0 * R[self._r_idx]]), b


class _PerWindow(ConeBlock):
    """One cone of `width` rows per window; $\\bar e_k$ sits in its rows `e_pos`, times
    `escale`. Subclasses give the cone (`_cone`) and the entries of $\\sigma_k$, $Y$ and the
    constants (`_fixed_part`)."""

    scalar_y: bool
    escale: float

    @staticmethod
    def _cone(m: int) -> tuple[int, np.ndarray, Any]:
        """`(width, e_pos, cone)`: the cone of one window and where $\\bar e_k$ sits in it."""
        raise NotImplementedError

    @staticmethod
    def _fixed_part(base: np.ndarray, width: int, layout: VariableLayout
                    ) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray, np.ndarray]:
        """`(rows, cols, vals, b)` of the entries that do not change between iterations
        (`rows` and `cols` as lists of index arrays, one per group of entries)."""
        raise NotImplementedError

    @staticmethod
    def n_sigma(N: int) -> int:
        return N

    def __init__(self, data: TwoStepData, layout: VariableLayout):
        self.data = data
        N, n, p, m = data.N, data.n, data.p, data.m
        width, e_pos, cone = self._cone(m)
        self.rows, self.cones = N * width, [cone] * N
        base = np.arange(N) * width  # [N] first row of each window's cone
        self.e_rows = er = base[:, None] + e_pos[None, :]  # [N, m]
        rows, cols, self._fixed, b = self._fixed_part(base, width, layout)
        self._b = b.ravel()
        # ebar_a depends on dA[i, j] (C0[a, i] x0[k, j]), dB[i, j] (C0[a, i] u0[k, j]),
        # dC[a, j] (z[k, j]) and dD[a, j] (u1[k, j]).
        for col, shape in ((layout.colA[None, None], (N, m, n, n)),
                           (layout.colB[None, None], (N, m, n, p))):
            rows.append(np.broadcast_to(er[:, :, None, None], shape).ravel())
            cols.append(np.broadcast_to(col, shape).ravel())
        for col, shape in ((layout.colC[None], (N, m, n)), (layout.colD[None], (N, m, p))):
            rows.append(np.broadcast_to(er[:, :, None], shape).ravel())
            cols.append(np.broadcast_to(col, shape).ravel())
        self._rows, self._cols = np.concatenate(rows), np.concatenate(cols)

    def fill(self, it):
        d, es, C0 = self.data, self.escale, it.C
        N, m, n, p = d.N, d.m, d.n, d.p
        vals = np.concatenate([
            self._fixed,
            (es * C0[None, :, :, None] * d.x0[:, None, None, :]).ravel(),
            (es * C0[None, :, :, None] * d.u0[:, None, None, :]).ravel(),
            np.broadcast_to(es * it.z[:, None, :], (N, m, n)).ravel(),
            np.broadcast_to(es * d.u1[:, None, :], (N, m, p)).ravel(),
        ])
        b = self._b.copy()
        b[self.e_rows] = es * it.ebar
        return vals, b


class SOCWindows(_PerWindow):
    """Per window the rotated SOC $\\lVert\\bar e_k\\rVert^2 \\le \\sigma_k(1 - y)$, i.e.
    $\\lVert(2\\bar e_k, \\sigma_k - 1 + y)\\rVert \\le \\sigma_k + 1 - y$ ($Y = yI$)."""

    scalar_y = True
    escale = 2.0

    @staticmethod
    def _cone(m):
        import clarabel

        return m + 2, 2 + np.arange(m), clarabel.SecondOrderConeT(m + 2)

    @staticmethod
    def _fixed_part(base, width, layout):
        N = len(base)
        sig, y = layout.col_sig, np.full(N, layout.oY)
        vals = np.concatenate([-np.ones(2 * N), np.ones(N), -np.ones(N)])
        b = np.zeros((N, width))
        b[:, 0], b[:, 1] = 1.0, -1.0
        return [base, base + 1, base, base + 1], [sig, sig, y, y], vals, b


class PSDWindows(_PerWindow):
    """Per window the LMI $[[\\sigma_k, \\bar e_k^\\top], [\\bar e_k, I - Y]] \\succeq 0$
    with a full symmetric $Y$."""

    scalar_y = False
    escale = SQRT2

    @staticmethod
    def _cone(m):
        import clarabel

        return svec_len(1 + m), svec_pos(0, 1 + np.arange(m)), clarabel.PSDTriangleConeT(1 + m)

    @staticmethod
    def _fixed_part(base, width, layout):
        N, m = len(base), layout.m
        yi, yj, ycol, yw = layout.y_svec
        rows = [base, (base[:, None] + svec_pos(1 + yi, 1 + yj)[None]).ravel()]
        cols = [layout.col_sig, np.tile(ycol, N)]
        vals = np.concatenate([-np.ones(N), np.tile(yw, N)])
        b = np.zeros((N, width))
        b[:, svec_pos(1 + np.arange(m), 1 + np.arange(m))] = 1.0
        return rows, cols, vals, b


WINDOW_BLOCKS = {"stacked": StackedWindows, "soc": SOCWindows, "psd": PSDWindows}


def stacked_factor(data: TwoStepData, C0, z, ebar, chunk: int = 2048):
    r"""`(R, g, c)` of the stacked cone (see `StackedWindows`).

    The triangular factor of the augmented matrix $[L\ \bar e_0] = Q
    \bigl[\begin{smallmatrix} R & g\\ 0 & c\end{smallmatrix}\bigr]$ gives all three
    without forming $Q$, since $\bar e_0 - L\delta = [L\ \bar e_0](-\delta, 1)$. It is
    accumulated `chunk` windows at a time (memory $O(\text{chunk}\cdot m\cdot
    n_\theta)$, time linear in $N$). `data` is any `TwoStepData` (e.g. an `ICOProblem`).
    """
    N, m = data.N, data.m
    nth = (data.n + m) * (data.n + data.p)  # theta = (A, B, C, D)
    eye = np.eye(m)
    Raug = np.zeros((0, nth + 1))
    for k0 in range(0, N, chunk):
        sl = slice(k0, min(N, k0 + chunk))
        k = sl.stop - sl.start
        L = np.concatenate([  # rows (window, output a); columns theta = (A, B, C, D)
            (C0[None, :, :, None] * data.x0[sl, None, None, :]).reshape(k, m, -1),
            (C0[None, :, :, None] * data.u0[sl, None, None, :]).reshape(k, m, -1),
            (eye[None, :, :, None] * z[sl, None, None, :]).reshape(k, m, -1),
            (eye[None, :, :, None] * data.u1[sl, None, None, :]).reshape(k, m, -1),
            ebar[sl, :, None],
        ], axis=2).reshape(k * m, -1)
        # numpy's stub types every mode as `QRResult`; mode="r" returns the array R
        Raug = cast(np.ndarray, np.linalg.qr(np.concatenate([Raug, L]), mode="r"))
    r_e = min(N * m, nth)
    c = abs(Raug[r_e, nth]) if Raug.shape[0] > r_e else 0.0
    return Raug[:r_e, :nth], Raug[:r_e, nth], float(c)
