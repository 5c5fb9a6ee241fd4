"""KYP blocks in float64 on the host: the exact dissipativity LMI and its convexified form.

Everything here is plain numpy; the SDP modules build on it.
"""

from __future__ import annotations

import numpy as np

from ._indefinite import QPlusTerm, split_q
from ._sdp import Layout
from ._supply import QSR


def _T(M):
    return np.swapaxes(M, -1, -2)


def kyp_matrix(A, B, C, D, qsr: QSR, P) -> np.ndarray:
    """The discrete KYP matrix of paper Lemma 2 (float64); $K$ is dissipative iff it is $\\preceq 0$.

    $$\\begin{bmatrix} A^\\top PA - P - C^\\top QC & A^\\top PB - C^\\top S - C^\\top QD \\\\
    \\ast & B^\\top PB - D^\\top QD - D^\\top S - S^\\top D - R\\end{bmatrix}$$

    Accepts stacks of controllers (leading batch axes on every matrix).
    """
    A, B, C, D, P = (np.asarray(M, np.float64) for M in (A, B, C, D, P))
    Q, S, R = qsr.Q, qsr.S, qsr.R
    PA, PB = P @ A, P @ B
    M11 = _T(A) @ PA - P - _T(C) @ Q @ C
    M12 = _T(A) @ PB - _T(C) @ (S + Q @ D)
    M22 = _T(B) @ PB - _T(D) @ Q @ D - _T(D) @ S - S.T @ D - R
    M = np.concatenate([np.concatenate([M11, M12], -1), np.concatenate([_T(M12), M22], -1)], -2)
    return (M + _T(M)) / 2


def _fro(M) -> np.ndarray:
    M = np.asarray(M, np.float64)
    return np.sqrt(np.sum(M * M, axis=(-2, -1)))


def kyp_scale(A, B, C, D, qsr: QSR, P):
    """A magnitude for relative tolerances on the KYP matrix (batched like the inputs).

    Built from Frobenius norms (upper bounds of spectral norms, cheap on the hot path), so
    the allowance it scales can only be stricter than one built from spectral norms.
    """
    nA, nB, nC, nD, nP = (_fro(M) for M in (A, B, C, D, P))
    q, s, r = (_fro(M) for M in (qsr.Q, qsr.S, qsr.R))
    return 1.0 + nP * (1 + (nA + nB) ** 2) + q * (nC + nD) ** 2 + 2 * s * (nC + nD) + r


# Relative round-off allowance for the float64 eigenvalue check of the KYP matrix.
VERIFY_RTOL = 1e-11


def kyp_margin(A, B, C, D, qsr: QSR, P):
    """$\\min(-\\lambda_{\\max}(\\mathrm{KYP}(P)), \\lambda_{\\min}(P))$ (batched like the inputs).

    Positive means certified (up to `VERIFY_RTOL` round-off, see `kyp_certified`).
    """
    P = np.asarray(P, np.float64)
    lam = np.linalg.eigvalsh(kyp_matrix(A, B, C, D, qsr, P))[..., -1]
    return np.minimum(-lam, np.linalg.eigvalsh((P + _T(P)) / 2)[..., 0])


def kyp_certified(A, B, C, D, qsr: QSR, P):
    """Exact float64 check: $P\\succ0$ and KYP$(P)\\prec 0$ beyond round-off (batched)."""
    mats = [np.asarray(M, np.float64) for M in (A, B, C, D, P)]
    finite = np.all([np.all(np.isfinite(M), axis=(-2, -1)) for M in mats], axis=0)
    safe = [np.where(finite[..., None, None], M, 0.0) for M in mats]
    ok = kyp_margin(*safe[:4], qsr, safe[4]) > VERIFY_RTOL * kyp_scale(*safe[:4], qsr, safe[4])
    ok = ok & finite
    return bool(ok) if np.ndim(ok) == 0 else ok


def svec_indices(N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, cols and weights of Clarabel's svec: upper triangle, column-major, off-diag x sqrt2."""
    cols, rows = [], []
    for j in range(N):
        for i in range(j + 1):
            rows.append(i)
            cols.append(j)
    rows, cols = np.array(rows), np.array(cols)
    w = np.where(rows == cols, 1.0, np.sqrt(2.0))
    return rows, cols, w


def svec(M: np.ndarray, idx=None) -> np.ndarray:
    """Clarabel's scaled vectorisation of symmetric `M` (works on stacks `[..., N, N]`)."""
    rows, cols, w = idx if idx is not None else svec_indices(M.shape[-1])
    return M[..., rows, cols] * w


def smat(v: np.ndarray, N: int) -> np.ndarray:
    """Inverse of `svec`."""
    rows, cols, w = svec_indices(N)
    M = np.zeros((N, N))
    M[rows, cols] = v / w
    M[cols, rows] = v / w
    return M


class ConvexifiedLMI:
    """The convexified KYP LMI (paper Corollary 1 + Remark 1, factored form; `docs/concepts.md`).

    For $-Q = LL^\\top$ and a fixed $\\tilde P\\succ0$, the matrix

    $$\\mathcal M = \\begin{bmatrix} -P & -C^\\top S & C^\\top L & A^\\top\\tilde P \\\\
    \\ast & -D^\\top S - S^\\top D - R & D^\\top L & B^\\top \\tilde P \\\\
    \\ast & \\ast & -I_r & 0 \\\\ \\ast & \\ast & \\ast & P - 2\\tilde P\\end{bmatrix}$$

    is affine in $x = (\\operatorname{vec}A, \\operatorname{vec}B, \\operatorname{vec}C,
    \\operatorname{vec}D, P)$ and $\\mathcal M\\preceq0$ implies the exact KYP LMI (it is the
    congruence by $\\operatorname{diag}(I,I,I,\\tilde P)$ of the Schur form with
    $-P^{-1}$ overbounded by $-2\\tilde P^{-1} + \\tilde P^{-1}P\\tilde P^{-1}$).

    This class precomputes, for fixed sizes and supply rate, the affine map
    $x\\mapsto\\operatorname{svec}(\\mathcal M)$ as a constant part plus a part linear in
    $\\tilde P$, so that $\\tilde P$ can be changed by updating numbers only.

    Variable order: the host layer's `Layout` (`vec` row-major for A, B, C, D, then the
    upper-triangular entries of P row-major, with $P = \\sum_k p_k E_k$).

    For an indefinite $Q = Q_+ - Q_-$, $L$ factors $Q_-$ and the concave $-H^\\top Q_+H$
    ($H = [C\\ D]$) is replaced by its linearisation around a point $H_0$ (`qplus`, a
    `QPlusTerm`; `H0` arguments), which adds to the $(x, u)$ block a constant and a part
    affine in $(C, D)$; then the matrix also depends on $H_0$ and is exact at $H = H_0$.
    """

    def __init__(self, n: int, p: int, m: int, qsr: QSR):
        qsr.check_sizes(p, m)
        L, L_plus = split_q(qsr.Q)
        r = L.shape[1]
        self.n, self.p, self.m, self.r = n, p, m, r
        self.N = N = 2 * n + p + r
        i0, i1, i2, i3 = 0, n, n + p, n + p + r  # block offsets: x, u, L-block, P~-block
        self.layout = lay = Layout(n, p, m)
        self.nA, self.nB, self.nC, self.nD = lay.nA, lay.nB, lay.nC, lay.nD
        self.ntheta, self.nP, self.nx = lay.ntheta, lay.nP, lay.nx
        iu, ju = self.p_rows, self.p_cols = lay.p_rows, lay.p_cols
        S, R = qsr.S, qsr.R

        # Constant part of M (without the -2P~ term) and the linear maps.
        M0 = np.zeros((N, N))
        M0[i1:i2, i1:i2] = -R
        M0[i2:i3, i2:i3] = -np.eye(r)
        self.M0 = M0
        # Jacobian of the P~-independent part: [nx, N, N]
        J = np.zeros((self.nx, N, N))
        k = 0
        k += self.nA + self.nB  # A and B columns depend on P~ (filled in `jacobian`)
        for a in range(m):  # C[a, b]
            for b in range(n):
                E = np.zeros((N, N))
                # -C^T S block (x, u): (C^T S)[b, :] = S[a, :]
                E[i0 + b, i1:i2] -= S[a, :]
                E[i0 + b, i2:i3] += L[a, :]
                J[k] = E + E.T
                k += 1
        for a in range(m):  # D[a, b]
            for b in range(p):
                E = np.zeros((N, N))
                # -(D^T S + S^T D): d/dD[a,b] of D^T S is e_b S[a,:]
                E[i1 + b, i1:i2] -= S[a, :]
                E[i1 + b, i2:i3] += L[a, :]
                J[k] = E + E.T
                k += 1
        for a, b in zip(iu, ju):  # P[a, b] (symmetric basis)
            E = np.zeros((N, N))
            E[i0 + a, i0 + b] -= 1.0
            E[i3 + a, i3 + b] += 1.0
            if a != b:
                E[i0 + b, i0 + a] -= 1.0
                E[i3 + b, i3 + a] += 1.0
            J[k] = E
            k += 1
        self.J_fixed = J
        # Linear-in-P~ part for the A and B columns: d/dA[a,b] of (P~ A) at rows i3+:, col i0+b
        # equals P~[:, a]; put it in the (x-block col, P~-block row) position and symmetrise.
        G = np.zeros((self.nA + self.nB, n, n, N, N))  # [var, P~ row, P~ col, N, N]
        k = 0
        for a in range(n):
            for b in range(n):
                for c in range(n):  # entry (i3 + c, i0 + b) += P~[c, a]
                    G[k, c, a, i3 + c, i0 + b] += 1.0
                    G[k, c, a, i0 + b, i3 + c] += 1.0
                k += 1
        for a in range(n):
            for b in range(p):
                for c in range(n):
                    G[k, c, a, i3 + c, i1 + b] += 1.0
                    G[k, c, a, i1 + b, i3 + c] += 1.0
                k += 1
        self.G = G
        self._svec_idx = svec_indices(N)
        oC = self.nA + self.nB
        self.qplus = (QPlusTerm(n, p, m, L_plus, oC, oC + self.nC) if L_plus.shape[1] else None)

    def blocks(self, P_tilde: np.ndarray, H0=None) -> tuple[np.ndarray, np.ndarray]:
        """Return `(M0, J)` with $\\mathcal M(x) = M_0 + \\sum_k x_k J_k$ at this $\\tilde P$
        (and, for an indefinite $Q$, at the linearisation point `H0 = (C0, D0)`)."""
        P_tilde = np.asarray(P_tilde, np.float64)
        i3 = self.N - self.n
        M0 = self.M0.copy()
        M0[i3:, i3:] = -2 * P_tilde
        J = self.J_fixed.copy()
        J[: self.nA + self.nB] = np.einsum("kcaij,ca->kij", self.G, P_tilde)
        if self.qplus is not None:
            if H0 is None:
                raise ValueError("an indefinite `qsr.Q` needs the linearisation point `H0`.")
            dM0, dJ = self.qplus.dense(*H0, self.N)
            M0 += dM0
            J[self.qplus.var] += dJ
        return M0, J

    def evaluate(self, x: np.ndarray, P_tilde: np.ndarray, H0=None) -> np.ndarray:
        """$\\mathcal M(x)$ at a given $\\tilde P$ (and $H_0$; dense, for checks)."""
        M0, J = self.blocks(P_tilde, H0)
        return M0 + np.tensordot(x, J, axes=1)

    def pack(self, A, B, C, D, P=None) -> np.ndarray:
        """Stack a controller (and optionally P) into the variable vector x (`Layout.pack`)."""
        return self.layout.pack(A, B, C, D, P)

    def unpack(self, x: np.ndarray):
        """Inverse of `pack`: returns `(A, B, C, D, P)`."""
        return self.layout.unpack(x)

    def svec(self, M: np.ndarray) -> np.ndarray:
        return svec(M, self._svec_idx)
