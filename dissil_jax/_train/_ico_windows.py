"""The window part of the ICO SDP: its sparsity pattern and per-iteration numbers.

Each function reads and sets attributes of an `ICOProblem` (`pb`); see the module docstring
of `_ico_sdp` for the maths of the three variants (`"stacked"`, `"soc"`, `"psd"`).
"""

from __future__ import annotations

import numpy as np

_SQRT2 = np.sqrt(2.0)


def _svec_pos(i, j):
    """Clarabel svec position of entry (i, j) with i <= j (upper triangle, column-major)."""
    return j * (j + 1) // 2 + i


def _svec_len(d):
    return d * (d + 1) // 2


def window_pattern(pb, row0, rows, cols, cones, spec, colY, wY, soc):
    """Per window: psd $[[\\sigma_k, \\bar e_k^\\top], [\\bar e_k, I - Y]] \\succeq 0$, or
    ($Y = yI$) the rotated SOC $\\lVert\\bar e_k\\rVert^2 \\le \\sigma_k(1 - y)$, i.e.
    $\\lVert(2\\bar e_k, \\sigma_k - 1 + y)\\rVert \\le \\sigma_k + 1 - y$."""
    import clarabel

    N, n, p, m = pb.N, pb.n, pb.p, pb.m
    colA, colB, colC, colD = (pb._cols[k] for k in "ABCD")
    yi, yj = pb.y_rows, pb.y_cols
    Lw = m + 2 if soc else _svec_len(1 + m)
    pb.Lw = Lw
    kk = np.arange(N)
    base = row0 + kk * Lw  # [N]
    e_pos = 2 + np.arange(m) if soc else _svec_pos(0, 1 + np.arange(m))  # [m]
    pb.e_rows = base[:, None] + e_pos[None, :]  # [N, m]
    pb._escale = 2.0 if soc else _SQRT2
    b_win = np.zeros((N, Lw))
    if soc:
        rows += [base, base + 1, base, base + 1]
        cols += [pb.osig + kk, pb.osig + kk, np.full(N, colY[0]), np.full(N, colY[0])]
        win_fixed = np.concatenate([-np.ones(2 * N), np.ones(N), -np.ones(N)])
        b_win[:, 0], b_win[:, 1] = 1.0, -1.0
    else:
        rows.append(base)
        cols.append(pb.osig + kk)
        rows.append((base[:, None] + _svec_pos(1 + yi, 1 + yj)[None]).ravel())
        cols.append(np.tile(colY, N))
        win_fixed = np.concatenate([-np.ones(N), np.tile(wY, N)])
        b_win[:, _svec_pos(1 + np.arange(m), 1 + np.arange(m))] = 1.0
    pb._b_win = b_win.ravel()
    pb._win_fixed = win_fixed
    # ebar_a depends on dA[i, j] (C0[a, i] x0[k, j]), dB[i, j] (C0[a, i] u0[k, j]),
    # dC[a, j] (z[k, j]) and dD[a, j] (u1[k, j]).
    er = pb.e_rows
    rows.append(np.broadcast_to(er[:, :, None, None], (N, m, n, n)).ravel())
    cols.append(np.broadcast_to(colA[None, None], (N, m, n, n)).ravel())
    rows.append(np.broadcast_to(er[:, :, None, None], (N, m, n, p)).ravel())
    cols.append(np.broadcast_to(colB[None, None], (N, m, n, p)).ravel())
    rows.append(np.broadcast_to(er[:, :, None], (N, m, n)).ravel())
    cols.append(np.broadcast_to(colC[None], (N, m, n)).ravel())
    rows.append(np.broadcast_to(er[:, :, None], (N, m, p)).ravel())
    cols.append(np.broadcast_to(colD[None], (N, m, p)).ravel())
    row0 += N * Lw
    if soc:
        cones += [clarabel.SecondOrderConeT(Lw)] * N
        spec += [("soc", Lw)] * N
    else:
        cones += [clarabel.PSDTriangleConeT(1 + m)] * N
        spec += [("psd", 1 + m)] * N
    return row0


def stacked_pattern(pb, row0, rows, cols, cones, spec, col_y):
    r"""All windows in one rotated SOC, $\lVert\bar e\rVert^2 \le \sigma(1 - y)$.

    $\bar e = (\bar e_1, \dots, \bar e_N) = \bar e_0 - L\,\delta\theta$ is affine with
    $L \in \mathbb R^{Nm \times n_\theta}$. With a thin QR factorisation $L = QR$,
    $\lVert\bar e\rVert^2 = \lVert Q^\top\bar e_0 - R\,\delta\theta\rVert^2 + c^2$,
    $c = \lVert(I - QQ^\top)\bar e_0\rVert$, so the cone
    $\lVert(2(Q^\top\bar e_0 - R\delta\theta), 2c, \sigma - 1 + y)\rVert
    \le \sigma + 1 - y$ has $\min(Nm, n_\theta) + 3$ rows whatever $N$ is. Its optimum
    equals the per-window SOC form's ($\sum_k\sigma_k$ with $\sigma_k = \lVert\bar e_k
    \rVert^2/(1 - y)$); only the QR, done in numpy every iteration, grows with $N$.
    """
    import clarabel

    nth = pb.ntheta
    pb.r_e = r_e = min(pb.N * pb.m, nth)
    Lw = r_e + 3
    rows += [row0 + np.array([0, 1, 0, 1])]
    cols += [np.array([pb.osig, pb.osig, col_y, col_y])]
    pb._win_fixed = np.array([-1.0, -1.0, 1.0, -1.0])
    ri, cj = np.triu_indices(r_e, m=nth)  # R is upper trapezoidal
    pb._r_idx = (ri, cj)
    rows.append(row0 + 2 + ri)
    cols.append(cj)  # theta sits at columns 0..n_theta-1 of x
    pb.g_rows = row0 + 2 + np.arange(r_e)
    pb.c_row = row0 + 2 + r_e
    cones.append(clarabel.SecondOrderConeT(Lw))
    spec.append(("soc", Lw))
    return row0 + Lw


def stacked_factor(pb, C0, z, ebar, chunk: int = 2048):
    r"""`(R, g, c)` of the stacked cone (see `_stacked_pattern`).

    The triangular factor of the augmented matrix $[L\ \bar e_0] = Q
    \bigl[\begin{smallmatrix} R & g\\ 0 & c\end{smallmatrix}\bigr]$ gives all three
    without forming $Q$, since $\bar e_0 - L\delta = [L\ \bar e_0](-\delta, 1)$. It is
    accumulated `chunk` windows at a time (memory $O(\text{chunk}\cdot m\cdot
    n_\theta)$, time linear in $N$).
    """
    N, m, nth = pb.N, pb.m, pb.ntheta
    eye = np.eye(m)
    Raug = np.zeros((0, nth + 1))
    for k0 in range(0, N, chunk):
        sl = slice(k0, min(N, k0 + chunk))
        k = sl.stop - sl.start
        L = np.concatenate([  # rows (window, output a); columns theta = (A, B, C, D)
            (C0[None, :, :, None] * pb.x0[sl, None, None, :]).reshape(k, m, -1),
            (C0[None, :, :, None] * pb.u0[sl, None, None, :]).reshape(k, m, -1),
            (eye[None, :, :, None] * z[sl, None, None, :]).reshape(k, m, -1),
            (eye[None, :, :, None] * pb.u1[sl, None, None, :]).reshape(k, m, -1),
            ebar[sl, :, None],
        ], axis=2).reshape(k * m, -1)
        Raug = np.linalg.qr(np.concatenate([Raug, L]), mode="r")
    r_e = pb.r_e
    c = abs(Raug[r_e, nth]) if Raug.shape[0] > r_e else 0.0
    return Raug[:r_e, :nth], Raug[:r_e, nth], float(c)
