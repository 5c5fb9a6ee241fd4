r"""The convex overbound SDP of one ICO iteration, assembled straight into Clarabel's format.

Host-side float64 numpy only. One `ICOProblem` per (windows, supply rate) holds the data and
the fixed sparsity pattern (shared read-only by all threads); one `ICOSolver` (`solver.py`) per
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
  $W^{-1} \succeq 2\tilde W - \tilde W W\tilde W$ for the scalar weight), balanced by
  the congruence $\mathrm{diag}(I, \tilde w^{1/2}I)$ (`YoungLMI`);
- with $Y = yI$ ($y \ge w\lVert\delta C\rVert_2^2$, identical bound when $m = 1$), the
  rotated SOC $\lVert\bar e\rVert^2 \le \sigma (1 - y)$ for the stacked residual
  $\bar e = (\bar e_1, \dots, \bar e_N)$, compressed by a QR factorisation of its Jacobian to
  $\min(Nm, n_\theta) + 3$ rows (`window_cone="stacked"`, default; see `windows.StackedWindows`);
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

Variables (`layout.VariableLayout`): $x = (\delta\theta, P_{\text{triu}}, Y, w, \tau,
\sigma)$ with one $\sigma$ (`"stacked"`) or $\sigma_{1..N}$ (no $P$ for ICO-NC). Cone blocks
in order (`blocks.py`, `windows.py`): KYP PSD (`KYPBlock`, ICO only), the $\tau$ SOC
(`DeltaZCone`), the $Y$ PSD of size $m + \hat n$ (`YoungLMI`), then the window cone(s)
(`StackedWindows`, `SOCWindows` or `PSDWindows`, chosen once by `window_cone`). With the
default the SDP's size does not depend on $N$ at all. Only the numbers of $q$, $A$ and $b$
change between iterations; the sparsity pattern is built once, block by block.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..._sdp.lmi import ConvexifiedLMI
from ..._supply import QSR
from .blocks import ConeBlock, DeltaZCone, Iterate, KYPBlock, YoungLMI
from .layout import TwoStepData, VariableLayout
from .windows import WINDOW_BLOCKS

WINDOW_CONES = tuple(WINDOW_BLOCKS)


def _layout_alias(name):
    return property(lambda self: getattr(self.layout, name), doc=f"`layout.{name}`.")


class ICOProblem(TwoStepData):
    """Data and fixed sparsity of the ICO SDP for one data set (and one supply rate or None).

    **Arguments:** `x0` `[N, n]`, `uhat` `[N, 2, p]` (controller inputs $\\hat u = y$),
    `target` `[N, 2, m]` ($-u$), `qsr` (None for ICO-NC), `eps` (KYP margin), `prox` ($\\mu$),
    `reg` ($\\nu$), `window_cone` (one of `WINDOW_CONES`).

    The windows (`TwoStepData`), the variable vector (`layout`, a `VariableLayout`) and the
    cone blocks (`blocks`: `kyp` (None for ICO-NC), a `DeltaZCone`, a `YoungLMI` and
    `window_block`), stacked into Clarabel's CSC format once (`indices`, `indptr`, `order`).
    """

    ntheta = _layout_alias("ntheta")
    oP = _layout_alias("oP")
    oY = _layout_alias("oY")
    ow = _layout_alias("ow")
    otau = _layout_alias("otau")
    osig = _layout_alias("osig")
    nx = _layout_alias("nx")

    def __init__(self, x0, uhat, target, qsr: QSR | None, *, eps=1e-6, prox=1e-4, reg=1e-6,
                 window_cone: str = "stacked"):
        super().__init__(x0, uhat, target)
        self.qsr = qsr
        self.eps, self.prox, self.reg = float(eps), float(prox), float(reg)
        self.lmi = ConvexifiedLMI(self.n, self.p, self.m, qsr) if qsr is not None else None
        if window_cone not in WINDOW_BLOCKS:
            raise ValueError(
                f"`window_cone` must be one of {WINDOW_CONES}, got {window_cone!r}.")
        self.window_cone = window_cone
        windows = WINDOW_BLOCKS[window_cone]
        self.layout = lay = VariableLayout(
            self.n, self.p, self.m, nP=0 if self.lmi is None else self.lmi.nP,
            scalar_y=windows.scalar_y, n_sig=windows.n_sigma(self.N))
        self.kyp = None if self.lmi is None else KYPBlock(self.lmi, lay, self.reg)
        self.window_block = windows(self, lay)
        self.blocks: list[ConeBlock] = [
            blk for blk in (self.kyp, DeltaZCone(self, lay), YoungLMI(lay), self.window_block)
            if blk is not None]
        self._assemble()
        self.H = self.hessian(self.prox)
        self.q_fixed = np.zeros(lay.nx)
        self.q_fixed[lay.otau] = self.c  # (1/N) (tau + sum_k sigma_k)
        self.q_fixed[lay.col_sig] = self.c

    def _assemble(self):
        """Stack the blocks' patterns: the cones, `nrows` and the COO -> CSC permutation."""
        rows, cols, self.cones = [], [], []
        row0 = 0
        for blk in self.blocks:
            r, c = blk.pattern()
            rows.append(row0 + r)
            cols.append(c)
            self.cones += blk.cones
            row0 += blk.rows
        self.nrows = row0
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        order = np.lexsort((rows, cols))
        rs, cs = rows[order], cols[order]
        if np.any((rs[1:] == rs[:-1]) & (cs[1:] == cs[:-1])):  # pragma: no cover - a bug guard
            raise AssertionError("duplicate entries in the ICO SDP pattern")
        self.order = order
        self.indices = rs.astype(np.int64)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(cs, minlength=self.nx))])
        self.nnz = len(rs)

    def hessian(self, prox: float):
        """Upper triangle of $H$ in the objective $\\frac12 x^\\top Hx + q^\\top x + $ const,
        with the proximal weight $\\mu$ = `prox` (`self.H` has `self.prox`; a larger one is
        the shorter step of `step.step_with_fallbacks`)."""
        lay = self.layout
        H = sp.lil_matrix((lay.nx, lay.nx))
        Gc = 2 * self.c * self.G
        for a in range(self.m):  # step-0 residual: c * sum_k ||r_k + dCD zeta_k||^2
            idx = lay.colCD[a]
            H[np.ix_(idx, idx)] = Gc
        H = H.tocsr()
        diag = np.zeros(lay.nx)
        diag[:lay.ntheta] = prox
        diag[lay.colP] = self.reg
        H = H + sp.diags(diag)
        return sp.triu(H).tocsc()

    # -------------------------------------------------------------------------------------
    def theta(self, A, B, C, D) -> np.ndarray:
        return self.layout.theta(A, B, C, D)

    def mats(self, theta):
        return self.layout.mats(theta)

    def loss(self, theta) -> float:
        """The true two-step loss $J$ (= `dj.imitation_loss` for $h = 2$), float64."""
        r0, _, e1 = self.residuals(*self.mats(theta))
        return float(self.c * (np.sum(r0**2) + np.sum(e1**2)))

    def kyp_margin(self, theta, P) -> float:
        """Margin $\\mu$ of δ = 0 at $\\tilde P = P$ (`KYPBlock.margin`; ICO only)."""
        if self.kyp is None:
            raise ValueError("ICO-NC (`qsr` None) has no KYP constraint.")
        return self.kyp.margin(theta, P)

    def data(self, theta0, P_tilde, w_tilde, eps=None, rel=0.0):
        """Numbers of the SDP at this iterate, with the KYP margin `eps` $+$ `rel`
        $\\operatorname{tr}P$: `(q, A_values_csc, b, const, p_scale)`."""
        mats = self.mats(theta0)
        r0, z, ebar = self.residuals(*mats)
        it = Iterate(theta0, *mats, P_tilde, w_tilde, self.eps if eps is None else eps,
                     self.p_scale(P_tilde), z, ebar, float(rel))
        vals, b = zip(*(blk.fill(it) for blk in self.blocks))
        # step-0: c * sum ||r0 - dCD zeta||^2, r0 = t0 - C0 x0 - D0 u0 (target minus prediction)
        q = self.q_fixed.copy()
        q[self.layout.colCD] = -2 * self.c * (r0.T @ self.zeta)
        for blk in self.blocks:
            cols, qb = blk.objective(it)
            q[cols] = qb
        const = self.c * np.sum(r0**2)
        return q, np.concatenate(vals)[self.order], np.concatenate(b), const, it.ps

    @staticmethod
    def p_scale(P_tilde):
        """The unit of the SDP's $P$ variable: $\\tilde P^{1/2}$ (1 for ICO-NC).

        The SDP solves for $X = \\tilde P^{-1/2}P\\tilde P^{-1/2}$, which is near $I$ however
        small, large or ill-conditioned the certificate is (the projection of a large random
        controller can return $P\\sim10^{-6}$; near the edge of the dissipative set $P$'s
        condition number grows past $10^4$, and Clarabel then stopped on `NumericalError`
        when it solved for $P$ itself). The proximal term $\\frac\\nu2\\lVert X - I\\rVert^2$
        is measured in the same unit ($\\nu$ = `reg` = $10^{-6}$: smaller weights left $P$,
        and so the next step, determined only to the solver's tolerance, and broke the
        runs' agreement under a change of the data's units, `tests/test_units.py`).
        """
        if P_tilde is None:
            return 1.0
        lam, V = np.linalg.eigh(np.asarray(P_tilde, np.float64))
        return (V * np.sqrt(lam)) @ V.T

    def matrix(self, vals):
        return sp.csc_matrix((vals, self.indices, self.indptr), shape=(self.nrows, self.nx))
