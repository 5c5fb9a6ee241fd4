r"""The convex overbound SDP of one ICO iteration, assembled straight into Clarabel's format.

Host-side float64 numpy only. One `ICOProblem` per (windows, supply rate) holds the data and
the fixed sparsity pattern (shared read-only by all threads); one `ICOSolver` (`_ico_solver.py`) per
initialisation owns a Clarabel solver whose numbers are updated in place every iteration
(`solver.update(q=..., A=..., b=...)`).

## The SDP (two-step loss, paper Problem 17 / 18)

Write $\theta = (A, B, C, D)$, the current iterate $\theta_0$, the step $\delta\theta$ and,
per window $k$, $\zeta_k = (\hat x_{k,0}, \hat u_{k,0})$, targets $t_{k,0}, t_{k,1}$
($t = -u$), $z_k = A_0\hat x_{k,0} + B_0\hat u_{k,0}$, $\delta z_k = [\delta A\ \delta B]
\zeta_k$. The residuals (target minus prediction) are $r_k(\delta)$ (step 0, affine) and

$$e_k(\delta) = \bar e_k(\delta) - \delta C\,\delta z_k,\quad \bar e_k(\delta) = t_{k,1}
- C_0 z_k - D_0\hat u_{k,1} - C_0\delta z_k - \delta C z_k - \delta D\hat u_{k,1}.$$

Young's relation with $W = wI$ (the device of paper Lemmas 5-7) gives, for every $v$,
$-2v^\top\delta C\delta z \le w\,v^\top\delta C\delta C^\top v + \lVert\delta z\rVert^2/w$,
hence (maximise $2e^\top v - \lVert v\rVert^2 = \lVert e\rVert^2$ over $v$)

$$\lVert e\rVert^2 \le \bar e^\top (I - Y)^{-1}\bar e + \lVert\delta z\rVert^2/w
\quad\text{for any}\quad Y \succeq w\,\delta C\delta C^\top,\ Y \prec I.$$

This is the per-window LMI $[[-s, \bar e^\top, 0, \delta z^\top], [\bar e, -I, \delta C, 0],
[0, \delta C^\top, -W^{-1}, 0], [\delta z, 0, 0, -W]] \preceq 0$ after Schur complements
on its last two blocks, with the pieces lifted into a few small cones:

- one shared LMI $[[Y, \delta C], [\delta C^\top, \phi(w) I]] \succeq 0$ with
  $\phi(w) = 2/\tilde w - w/\tilde w^2 \le 1/w$ (the paper's overbound
  $W^{-1} \succeq 2\tilde W - \tilde W W\tilde W$ for the scalar weight);
- with $Y = yI$ ($y \ge w\lVert\delta C\rVert_2^2$, identical bound when $m = 1$), the
  rotated SOC $\lVert\bar e\rVert^2 \le \sigma (1 - y)$ for the stacked residual
  $\bar e = (\bar e_1, \dots, \bar e_N)$, compressed by a QR factorisation of its Jacobian to
  $\min(Nm, n_\theta) + 3$ rows (`window_cone="stacked"`, default; see `_ico_windows.stacked_pattern`);
  or the same bound window by window, $\lVert\bar e_k\rVert^2 \le \sigma_k (1 - y)$ (`"soc"`,
  the same optimum with $N$ cones; kept as a reference); or, with a full symmetric $Y$, the
  per-window LMI $[[\sigma_k, \bar e_k^\top], [\bar e_k, I - Y]] \succeq 0$ (`"psd"`;
  minimising over $Y$ recovers exactly that per-window LMI because every window's LMI
  is monotone in $Y$);
- $\sum_k\lVert\delta z_k\rVert^2/w = \lVert[\delta A\ \delta B]F\rVert_F^2/w \le \tau$ with
  $FF^\top = \sum_k\zeta_k\zeta_k^\top$: one rotated SOC whose size does not grow with $N$.

The program is

$$\min\ \frac{1}{N}\Bigl(\sum_k\lVert r_k(\delta)\rVert^2 + \tau + \sum_k\sigma_k\Bigr)
+ \frac{\mu}{2}\lVert\delta\theta\rVert^2 + \frac{\nu}{2}\lVert P - \tilde P\rVert^2$$

subject to the cones above and the convexified KYP LMI (`docs/concepts.md`; `ConvexifiedLMI`, paper
Corollary 1 + Remark 1) at $\theta_0 + \delta\theta$, in its congruence form
$\mathcal M \preceq -\varepsilon\,\mathrm{diag}(I, \tilde P^2)$ (i.e. the un-congruenced Schur
form $\preceq -\varepsilon I$, so the new iterate has the same margin at the next
linearisation point), and then balanced by the congruence
$\mathrm{diag}(\tilde P^{-1/2}, I, I, \tilde P^{-1/2})$, which keeps Clarabel accurate when
$P$ becomes ill-conditioned. The objective (without the proximal terms) overbounds the true
two-step loss $J(\theta_0 + \delta\theta)$ and equals $J(\theta_0)$ at $\delta = 0$ with
$Y = 0$, $\tau = 0$, $w = \tilde w$, $\sigma_k = \lVert\bar e_k(0)\rVert^2$ (or
$\sigma = \lVert\bar e(0)\rVert^2$). The step-0 term is
a plain quadratic with Hessian $I_m\otimes\sum_k\zeta_k\zeta_k^\top$: no per-window variables.

Variables: $x = (\delta\theta, P_{\text{triu}}, Y, w, \tau, \sigma)$ with one $\sigma$
(`"stacked"`) or $\sigma_{1..N}$ (no $P$ for ICO-NC). Cones in order: KYP PSD (ICO only),
the $\tau$ SOC, the $Y$ PSD (size $m + \hat n$), then the window cone(s). With the default
the SDP's size does not depend on $N$ at all. Only the numbers of $q$, $A$ and $b$ change between
iterations; the sparsity pattern is built once.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._lmi import ConvexifiedLMI, svec, svec_indices
from .._supply import QSR
from ._ico_windows import (
    _SQRT2,
    _svec_len,
    _svec_pos,
    stacked_factor,
    stacked_pattern,
    window_pattern,
)

WINDOW_CONES = ("stacked", "soc", "psd")


class ICOProblem:
    """Data and fixed sparsity of the ICO SDP for one data set (and one supply rate or None).

    **Arguments:** `x0` `[N, n]`, `uhat` `[N, 2, p]` (controller inputs $\\hat u = y$),
    `target` `[N, 2, m]` ($-u$), `qsr` (None for ICO-NC), `eps` (KYP margin), `prox` ($\\mu$),
    `reg` ($\\nu$).
    """

    def __init__(self, x0, uhat, target, qsr: QSR | None, *, eps=1e-6, prox=1e-4, reg=1e-6,
                 window_cone: str = "stacked"):
        x0, uhat, target = (np.asarray(a, np.float64) for a in (x0, uhat, target))
        N, n = x0.shape
        p, m = uhat.shape[2], target.shape[2]
        self.N, self.n, self.p, self.m = N, n, p, m
        self.x0, self.u0, self.u1 = x0, uhat[:, 0], uhat[:, 1]
        self.t0, self.t1 = target[:, 0], target[:, 1]
        self.c = 1.0 / N  # J = (1/N) sum over windows of both steps' errors (paper eq. 16)
        self.eps, self.prox, self.reg = float(eps), float(prox), float(reg)
        self.Nk = 0
        self.zeta = np.concatenate([x0, self.u0], axis=1)  # [N, n+p]
        G = self.zeta.T @ self.zeta
        lam, V = np.linalg.eigh(G)
        keep = lam > 1e-12 * max(1.0, lam.max())
        self.F = V[:, keep] * np.sqrt(lam[keep])  # G = F F^T, [n+p, r]
        r = self.F.shape[1]

        # -- variable layout ------------------------------------------------------------
        self.nA, self.nB, self.nC, self.nD = n * n, n * p, m * n, m * p
        self.ntheta = nth = self.nA + self.nB + self.nC + self.nD
        oA, oB, oC, oD = 0, self.nA, self.nA + self.nB, self.nA + self.nB + self.nC
        self.qsr = qsr
        self.lmi = ConvexifiedLMI(n, p, m, qsr) if qsr is not None else None
        nP = self.lmi.nP if qsr is not None else 0
        self.oP = nth
        self.oY = nth + nP
        if window_cone not in WINDOW_CONES:
            raise ValueError(
                f"`window_cone` must be one of {WINDOW_CONES}, got {window_cone!r}.")
        self.window_cone = window_cone
        stacked = window_cone == "stacked"
        soc = window_cone != "psd"  # Y = y I
        n_sig = 1 if stacked else N
        yi, yj = np.triu_indices(m)
        self.y_rows, self.y_cols = yi, yj
        nY = 1 if soc else len(yi)  # Y = y I, or a full symmetric Y
        self.ow = self.oY + nY
        self.otau = self.ow + 1
        self.osig = self.otau + 1
        self.nx = self.osig + n_sig
        colA = oA + np.arange(self.nA).reshape(n, n)
        colB = oB + np.arange(self.nB).reshape(n, p)
        colC = oC + np.arange(self.nC).reshape(m, n)
        colD = oD + np.arange(self.nD).reshape(m, p)
        colAB = np.concatenate([colA, colB], axis=1)  # [n, n+p]
        colCD = np.concatenate([colC, colD], axis=1)  # [m, n+p]
        colY = self.oY + np.arange(nY)
        wY = np.where(yi == yj, 1.0, _SQRT2)
        self._cols = dict(A=colA, B=colB, C=colC, D=colD)

        rows, cols = [], []  # COO pattern, block by block; values come in the same order
        row0 = 0
        cones, spec = [], []
        import clarabel

        # -- (a) convexified KYP LMI (ICO only) ------------------------------------------
        if qsr is not None:
            lmi = self.lmi
            self.Nk = lmi.N
            Lk = _svec_len(lmi.N)
            dense = np.ones((n, n)) + np.eye(n)  # generic P~: every possible nonzero present
            _, J, _ = self._kyp_blocks(dense)
            pattern = (lmi.svec(J) != 0) | (lmi.svec(lmi.J_fixed) != 0)  # [nx_lmi, Lk]
            kc, kr = np.nonzero(pattern)  # kc: lmi variable (same offset in x), kr: svec row
            self.kyp_var, self.kyp_row = kc, kr
            rows.append(row0 + kr)
            cols.append(kc)  # lmi variables (theta, P) sit at the same offsets in x
            self.kyp_rows0 = row0
            self.kyp_L = Lk
            self.eye_svec = lmi.svec(np.eye(lmi.N))
            row0 += Lk
            cones.append(clarabel.PSDTriangleConeT(lmi.N))
            spec.append(("psd", lmi.N))

        # -- (b) rotated SOC: ||2 vec([dA dB] F)||^2 + (w - tau)^2 <= (w + tau)^2 -----------
        self.soc_row0 = row0
        d_soc = 2 + n * r
        rows.append(row0 + np.array([0, 0, 1, 1]))
        cols.append(np.array([self.ow, self.otau, self.ow, self.otau]))
        # entry (i, l) of [dA dB] F: sum_j dAB[i, j] F[j, l]
        ii, ll, jj = np.meshgrid(np.arange(n), np.arange(r), np.arange(n + p), indexing="ij")
        rows.append(row0 + 2 + ii.ravel() * r + ll.ravel())
        cols.append(colAB[ii.ravel(), jj.ravel()])
        soc_vals = np.concatenate([[-1.0, -1.0, -1.0, 1.0], -2.0 * self.F[jj.ravel(), ll.ravel()]])
        row0 += d_soc
        cones.append(clarabel.SecondOrderConeT(d_soc))
        spec.append(("soc", d_soc))

        # -- (c) [[Y, dC], [dC^T, phi(w) I]] >= 0 ----------------------------------------
        self.Yrow0 = row0
        dY = m + n
        rY = row0 + (_svec_pos(np.arange(m), np.arange(m)) if soc else _svec_pos(yi, yj))
        colYb = np.full(m, colY[0]) if soc else colY
        wYb = np.ones(m) if soc else wY
        aa, jn = np.meshgrid(np.arange(m), np.arange(n), indexing="ij")
        rC = row0 + _svec_pos(aa.ravel(), m + jn.ravel())
        rW = row0 + _svec_pos(m + np.arange(n), m + np.arange(n))
        rows += [rY, rC, rW]
        cols += [colYb, colC[aa.ravel(), jn.ravel()], np.full(n, self.ow)]
        yblock_vals = np.concatenate([-wYb, np.full(m * n, -_SQRT2)])
        self.yw_rows = rW
        self.LY = _svec_len(dY)
        row0 += self.LY
        cones.append(clarabel.PSDTriangleConeT(dY))
        spec.append(("psd", dY))

        # -- (d) the windows' step-1 bound ------------------------------------------------
        self.win_row0 = row0
        if stacked:
            row0 = stacked_pattern(self, row0, rows, cols, cones, spec, colY[0])
        else:
            row0 = window_pattern(self, row0, rows, cols, cones, spec, colY, wY, soc)
        self.cone_spec = spec
        self.nrows = row0
        self.cones = cones

        # -- constant values and the COO -> CSC permutation ---------------------------------
        self._soc_vals, self._yblock_vals = soc_vals, yblock_vals
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        order = np.lexsort((rows, cols))
        rs, cs = rows[order], cols[order]
        if np.any((rs[1:] == rs[:-1]) & (cs[1:] == cs[:-1])):  # pragma: no cover - a bug guard
            raise AssertionError("duplicate entries in the ICO SDP pattern")
        self.order = order
        self.indices = rs.astype(np.int64)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(cs, minlength=self.nx))])
        self.nnz = len(rs)

        # -- objective: 1/2 x^T H x + q^T x + const ---------------------------------------
        H = sp.lil_matrix((self.nx, self.nx))
        Gc = 2 * self.c * G
        for a in range(m):  # step-0 residual: c * sum_k ||r_k + dCD zeta_k||^2
            idx = colCD[a]
            H[np.ix_(idx, idx)] = Gc
        H = H.tocsr()
        diag = np.zeros(self.nx)
        diag[:nth] = self.prox
        diag[self.oP:self.oY] = self.reg
        H = H + sp.diags(diag)
        self.H = sp.triu(H).tocsc()
        self._colCD = colCD
        self.q_fixed = np.zeros(self.nx)
        self.q_fixed[self.otau] = self.c
        self.q_fixed[self.osig:] = self.c
        self._svec_idx_kyp = svec_indices(self.Nk) if qsr is not None else None

    # -------------------------------------------------------------------------------------
    def theta(self, A, B, C, D) -> np.ndarray:
        return np.concatenate([np.asarray(M, np.float64).ravel() for M in (A, B, C, D)])

    def mats(self, theta):
        n, p, m = self.n, self.p, self.m
        o = np.cumsum([0, self.nA, self.nB, self.nC, self.nD])
        return (theta[o[0]:o[1]].reshape(n, n), theta[o[1]:o[2]].reshape(n, p),
                theta[o[2]:o[3]].reshape(m, n), theta[o[3]:o[4]].reshape(m, p))

    def loss(self, theta) -> float:
        """The true two-step loss $J$ (= `dj.imitation_loss` for $h = 2$), float64."""
        A, B, C, D = self.mats(theta)
        r0 = self.t0 - self.x0 @ C.T - self.u0 @ D.T
        z = self.x0 @ A.T + self.u0 @ B.T
        e1 = self.t1 - z @ C.T - self.u1 @ D.T
        return float(self.c * (np.sum(r0**2) + np.sum(e1**2)))

    BALANCE = True

    def _kyp_blocks(self, P_tilde):
        """`(M0, J, E)` of the convexified KYP LMI $M_0 + \\sum_k x_k J_k \\preceq -\\varepsilon E$.

        Balanced (see the module docstring) when `BALANCE` is True.
        """
        n = self.n
        P_tilde = np.asarray(P_tilde, np.float64)
        M0, J = self.lmi.blocks(P_tilde)
        E = np.eye(self.Nk)
        E[-n:, -n:] = P_tilde @ P_tilde
        if self.BALANCE:
            lam, V = np.linalg.eigh(P_tilde)
            Ph = (V / np.sqrt(lam)) @ V.T  # P~^{-1/2}
            T = np.eye(self.Nk)
            T[:n, :n] = Ph
            T[-n:, -n:] = Ph
            M0, E = T @ M0 @ T, T @ E @ T
            J = T @ J @ T  # broadcast over the variables (einsum here was 10x slower)
        return M0, J, E

    def kyp_margin(self, theta, P) -> float:
        """Margin $\\mu$ of δ = 0 at $\\tilde P = P$:
        $\\mathcal M \\preceq -\\mu\\,\\mathrm{diag}(I, P^2)$.

        Equivalently $-\\lambda_{\\max}$ of the un-congruenced Schur form of the KYP LMI.
        """
        P = np.asarray(P, np.float64)
        x = np.concatenate([theta, P[self.lmi.p_rows, self.lmi.p_cols]])
        T = np.eye(self.Nk)
        T[-self.n:, -self.n:] = np.linalg.inv(P)
        M = T @ self.lmi.evaluate(x, P) @ T
        return -float(np.linalg.eigvalsh((M + M.T) / 2)[-1])

    def data(self, theta0, P_tilde, w_tilde, eps=None):
        """Numbers of the SDP at this iterate: `(q, A_values_csc, b, const)`."""
        n, m, N = self.n, self.m, self.N
        A0, B0, C0, D0 = self.mats(theta0)
        vals, b = [], np.zeros(self.nrows)
        ps = self.p_scale(P_tilde)
        if self.qsr is not None:
            eps = self.eps if eps is None else eps
            M0, J, E = self._kyp_blocks(P_tilde)
            sJ = svec(J, self._svec_idx_kyp)  # [nx_lmi, Lk]
            sJ[self.ntheta:] *= ps  # the SDP's P variable is P / ps (see `p_scale`)
            vals.append(sJ[self.kyp_var, self.kyp_row])
            sl = slice(self.kyp_rows0, self.kyp_rows0 + self.kyp_L)
            b[sl] = (-svec(M0, self._svec_idx_kyp) - eps * svec(E, self._svec_idx_kyp)
                     - theta0 @ sJ[:self.ntheta])
        vals.append(self._soc_vals)
        vals.append(self._yblock_vals)
        vals.append(np.full(n, 1.0 / w_tilde**2))
        b[self.yw_rows] = 2.0 / w_tilde
        vals.append(self._win_fixed)
        z = self.x0 @ A0.T + self.u0 @ B0.T  # [N, n]
        ebar = self.t1 - z @ C0.T - self.u1 @ D0.T  # [N, m]
        if self.window_cone == "stacked":
            R, g, c = stacked_factor(self, C0, z, ebar)
            vals.append(2.0 * R[self._r_idx])
            b[self.win_row0:self.win_row0 + 2] = 1.0, -1.0
            b[self.g_rows] = 2.0 * g
            b[self.c_row] = 2.0 * c
        else:
            es = self._escale
            vals.append((es * C0[None, :, :, None] * self.x0[:, None, None, :]).ravel())
            vals.append((es * C0[None, :, :, None] * self.u0[:, None, None, :]).ravel())
            vals.append(np.broadcast_to(es * z[:, None, :], (N, m, n)).ravel())
            vals.append(np.broadcast_to(es * self.u1[:, None, :], (N, m, self.p)).ravel())
            b[self.win_row0:] = self._b_win
            b[self.e_rows] = self._escale * ebar
        vals = np.concatenate(vals)[self.order]
        # step-0: c * sum ||r0 - dCD zeta||^2, r0 = t0 - C0 x0 - D0 u0 (target minus prediction)
        r0 = self.t0 - self.x0 @ C0.T - self.u0 @ D0.T
        q = self.q_fixed.copy()
        q[self._colCD] = -2 * self.c * (r0.T @ self.zeta)
        if self.qsr is not None:
            q[self.oP:self.oY] = -self.reg * np.asarray(P_tilde)[self.lmi.p_rows,
                                                                   self.lmi.p_cols] / ps
        const = self.c * np.sum(r0**2)
        return q, vals, b, const, ps

    @staticmethod
    def p_scale(P_tilde) -> float:
        """The unit of the SDP's $P$ variable: $\\lambda_{\\max}(\\tilde P)$ (1 for ICO-NC).

        The SDP solves for $P/\\lambda_{\\max}(\\tilde P)$, which is of order one however
        small or large the certificate is (the projection of a large random controller
        can return $P\\sim10^{-6}$, and the solver then stalls on the badly scaled columns).
        The proximal term $\\frac\\nu2\\lVert P - \\tilde P\\rVert^2$ is measured in the same unit.
        """
        if P_tilde is None:
            return 1.0
        return float(np.linalg.eigvalsh(np.asarray(P_tilde, np.float64))[-1])

    def matrix(self, vals):
        return sp.csc_matrix((vals, self.indices, self.indptr), shape=(self.nrows, self.nx))
