"""KYP blocks in float64 on the host: the exact dissipativity LMI and its convexified form.

Everything here is plain numpy; the SDP modules build on it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from .._rate_scale import rate_factor
from .._supply import QSR
from .._validate import real_array
from .indefinite import split_q
from .sdp import Layout


def _T(M):
    return np.swapaxes(M, -1, -2)


def kyp_matrix(A, B, C, D, qsr: QSR, P) -> np.ndarray:
    """The discrete KYP matrix of paper Lemma 2 (float64); $K$ is dissipative iff it is $\\preceq 0$.

    $$\\begin{bmatrix} A^\\top PA - P - C^\\top QC & A^\\top PB - C^\\top S - C^\\top QD \\\\
    \\ast & B^\\top PB - D^\\top QD - D^\\top S - S^\\top D - R\\end{bmatrix}$$

    Accepts stacks of controllers (leading batch axes on every matrix). Each matrix must hold
    real numbers (a complex `P` is refused, not cast).
    """
    A, B, C, D, P = (real_array(name, M) for name, M in zip("ABCDP", (A, B, C, D, P)))
    return kyp_matrix_of(A, B, C, D, qsr.Q, qsr.S, qsr.R, P)


def kyp_matrix_of(A, B, C, D, Q, S, R, P) -> np.ndarray:
    """`kyp_matrix` with the rate's matrices given as arrays, which may carry batch axes too
    (a rate per controller, as a REN's multiplier makes it)."""
    A, B, C, D, P, Q, S, R = (np.asarray(M, np.float64) for M in (A, B, C, D, P, Q, S, R))
    PA, PB = P @ A, P @ B
    M11 = _T(A) @ PA - P - _T(C) @ Q @ C
    M12 = _T(A) @ PB - _T(C) @ (S + Q @ D)
    M22 = _T(B) @ PB - _T(D) @ Q @ D - _T(D) @ S - _T(S) @ D - R
    M = np.concatenate([np.concatenate([M11, M12], -1), np.concatenate([_T(M12), M22], -1)], -2)
    return (M + _T(M)) / 2


def _fro(M) -> np.ndarray:
    M = np.asarray(M, np.float64)
    return np.sqrt(np.sum(M * M, axis=(-2, -1)))


def kyp_scale(A, B, C, D, qsr: QSR, P):
    """A magnitude for relative tolerances on the KYP matrix (batched like the inputs).

    Built from Frobenius norms (upper bounds of spectral norms, cheap on the hot path), so
    the allowance it scales can only be stricter than one built from spectral norms. Its
    floor is the rate's size $\\kappa$ (`rate_factor`: 1 for rates of ordinary size), so
    that multiplying the rate and $P$ by a power of two changes no verdict.
    """
    return kyp_scale_of(A, B, C, D, qsr.Q, qsr.S, qsr.R, P, rate_factor(qsr))


def kyp_scale_of(A, B, C, D, Q, S, R, P, factor):
    """`kyp_scale` with the rate's matrices as (possibly batched) arrays and its
    `rate_factor` given (batched like them, or a number)."""
    # Terms beyond float64 (states 2^600 from the neurons) overflow to inf, and a zero
    # rate block times one to NaN: either way no relative allowance, and the caller's
    # componentwise bound (`kyp_bound_holds`) decides.
    with np.errstate(over="ignore", invalid="ignore"):
        nA, nB, nC, nD, nP = (_fro(M) for M in (A, B, C, D, P))
        q, s, r = (_fro(M) for M in (Q, S, R))
        scale = (factor + nP * (1 + (nA + nB) ** 2) + q * (nC + nD) ** 2 + 2 * s * (nC + nD)
                 + r)
    return np.where(np.isnan(scale), np.inf, scale)


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
    """Exact float64 check: $P\\succ0$ and KYP$(P)\\prec 0$ beyond round-off (batched):
    the relative allowance `VERIFY_RTOL` of `kyp_scale`, or else `kyp_bound_holds`."""
    mats = [np.asarray(M, np.float64) for M in (A, B, C, D, P)]
    finite = np.all([np.all(np.isfinite(M), axis=(-2, -1)) for M in mats], axis=0)
    safe = [np.where(finite[..., None, None], M, 0.0) for M in mats]
    A, B, C, D, P = safe
    ok = kyp_margin(A, B, C, D, qsr, P) > VERIFY_RTOL * kyp_scale(A, B, C, D, qsr, P)
    if not np.all(ok):
        ok = ok | kyp_bound_holds(A, B, C, D, qsr.Q, qsr.S, qsr.R, P)
    ok = ok & finite
    return bool(ok) if np.ndim(ok) == 0 else ok


def kyp_bound_holds(A, B, C, D, Q, S, R, P) -> np.ndarray:
    """A float64 proof of $P\\succ0$ and KYP$(P)\\prec0$ from componentwise round-off
    bounds, in Jacobi-scaled form (batched like the inputs; rate matrices as arrays).

    Computing KYP$(P)$ in floating point makes each entry wrong by at most
    $\\gamma\\,|M|_{ij}$, where $|M|$ is the same sum of products taken with absolute values
    ($|A|^\\top|P||A| + |P| + |C|^\\top|Q||C|$ in the first block, and so on) and
    $\\gamma\\approx(k+2)\\epsilon$ for inner dimensions up to $k$ (we allow twice that).
    For any positive diagonal $\\Delta$, $\\Delta M\\Delta\\prec0$ exactly when $M\\prec0$,
    so the test is $\\lambda_{\\max}(\\Delta\\tilde M\\Delta) + \\gamma\\lVert\\Delta|M|\\Delta
    \\rVert_F + c N\\epsilon\\lVert\\Delta\\tilde M\\Delta\\rVert_F < 0$ (the last term for the
    eigenvalue solver's own backward error), with $\\Delta = \\operatorname{diag}(|\\tilde
    M_{ii}|^{-1/2})$, or failing that $\\Delta = I$, and likewise $\\lambda_{\\min}$ of the
    scaled $P$. The scaled test certifies realisations that are far from balanced (a
    storage with eigenvalues $10^1$ and $10^7$, state matrices with entries of 30 whose
    products cancel), where an allowance relative to the norms of the factors
    (`kyp_scale`) exceeds the margin by orders of magnitude. The unscaled one proves
    matrices with a tiny diagonal entry whose $|M|$ is large: a narrow cone far from zero
    ($[10^3, 10^3 + 1]$) has an input block of $10^{-6}$ computed from terms of $10^6$, an
    error of $10^{-9}$ that scaling by $10^{3}$ on each side magnifies to $10^{-3}$ of a
    unit diagonal.
    """
    A, B, C, D, P, Q, S, R = (np.asarray(M, np.float64) for M in (A, B, C, D, P, Q, S, R))
    eps = np.finfo(np.float64).eps
    M = kyp_matrix_of(A, B, C, D, Q, S, R, P)
    aA, aB, aC, aD, aP, aQ, aS, aR = (np.abs(X) for X in (A, B, C, D, P, Q, S, R))
    M11 = _T(aA) @ aP @ aA + aP + _T(aC) @ aQ @ aC
    M12 = _T(aA) @ aP @ aB + _T(aC) @ (aS + aQ @ aD)
    M22 = _T(aB) @ aP @ aB + _T(aD) @ aQ @ aD + _T(aD) @ aS + _T(aS) @ aD + aR
    Mabs = np.concatenate([np.concatenate([M11, M12], -1),
                           np.concatenate([_T(M12), M22], -1)], -2)
    N, n = M.shape[-1], P.shape[-1]
    gamma = 2.0 * (max(N, Q.shape[-1]) + 4) * eps

    def scaled(X, ref):
        diag = np.abs(np.diagonal(ref, axis1=-2, axis2=-1))
        d = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
        return d[..., :, None] * X * d[..., None, :]

    fro = lambda X: np.sqrt(np.sum(X * X, axis=(-2, -1)))

    def negative(Ms, Mabs_s):
        err = gamma * fro(Mabs_s) + (8 * N + 2) * eps * fro(Ms)
        return np.linalg.eigvalsh(Ms)[..., -1] + err < 0

    ok = negative(scaled(M, M), scaled(Mabs, M))
    if not np.all(ok):  # Delta = I: for a tiny diagonal entry whose |M| is large
        ok = ok | negative(M, Mabs)
    if n:
        Psym = (P + _T(P)) / 2
        Ps = scaled(Psym, Psym)
        ok &= np.linalg.eigvalsh(Ps)[..., 0] - (8 * n + 2) * eps * fro(Ps) > 0
    return ok


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


def svec_pos(i, j):
    """Position of entry $(i, j)$ in Clarabel's svec (either triangle; arrays broadcast)."""
    i, j = np.minimum(i, j), np.maximum(i, j)
    return j * (j + 1) // 2 + i


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

    The affine map $x\\mapsto\\operatorname{svec}(\\mathcal M) = m_0(\\tilde P) + J(\\tilde P)x$
    is stored sparsely, straight in Clarabel's format: the sparsity of $J$ is fixed
    (`indices`, `indptr`, CSC, `nnz` entries, column $k$ = svec of
    $\\partial\\mathcal M/\\partial x_k$), and its numbers are a constant part plus a part
    linear in the linearisation point's parameters (today the entries of $\\tilde P$):
    the column of $A_{ab}$ holds $\\tilde P_{ca}$ at entry $(b, \\tilde P\\text{-block } c)$,
    so a new $\\tilde P$ only changes numbers ([`values`][], [`offset`][]). Memory and
    time grow like the LMI's nonzeros ($\\hat n^3$ from $A^\\top\\tilde P$).

    Variable order: the host layer's `Layout` (`vec` row-major for A, B, C, D, then the
    upper-triangular entries of P row-major, with $P = \\sum_k p_k E_k$).

    For an indefinite $Q = Q_+ - Q_-$, $L$ factors $Q_-$ and the concave $-H^\\top Q_+H$
    ($H = [C\\ D]$) is replaced by its linearisation around a point $H_0$
    (`docs/concepts.md`, *Indefinite Q*): with $W = H_0^\\top Q_+$ the $(x, u)$ block gains
    $G - WH - H^\\top W^\\top$, $G = WH_0$, i.e. the column of $H_{aj}$ holds $-W_{ia}$ at
    entry $(i, j)$ ($-2W_{ja}$ on the diagonal) and $m_0$ holds $G$. $W$ and $G$ join $\\tilde P$ as parameters (`indefinite`, the
    `H0 = (C0, D0)` arguments), so a new $H_0$ also only changes numbers.
    """

    def __init__(self, n: int, p: int, m: int, qsr: QSR):
        qsr.check_sizes(p, m)
        L, L_plus = split_q(qsr.Q)
        self.Q_plus = L_plus @ L_plus.T
        self.indefinite = L_plus.shape[1] > 0
        r = L.shape[1]
        self.n, self.p, self.m, self.r = n, p, m, r
        self.N = N = 2 * n + p + r
        self.L = N * (N + 1) // 2  # svec length
        i1, i2, i3 = n, n + p, n + p + r  # block offsets: u, L-block, P~-block (x at 0)
        self.layout = lay = Layout(n, p, m)
        self.nA, self.nB, self.nC, self.nD = lay.nA, lay.nB, lay.nC, lay.nD
        self.ntheta, self.nP, self.nx = lay.ntheta, lay.nP, lay.nx
        self.p_rows, self.p_cols = lay.p_rows, lay.p_cols
        kx = n + p  # the (x, u) block, indexed like the columns of H = [C D]
        # the linearisation point: P~ row-major, then (indefinite Q only) W = H0' Q+ [kx, m]
        # and G = H0' Q+ H0 [kx, kx], row-major
        self.n_params = n * n + (kx * m + kx * kx if self.indefinite else 0)
        S, R = np.asarray(qsr.S, np.float64), np.asarray(qsr.R, np.float64)
        oC, oD, oP = lay.nA + lay.nB, lay.nA + lay.nB + lay.nC, lay.ntheta
        # Every entry is a symmetric pair M[i, j] = M[j, i]: (i, j, variable, constant,
        # parameter index or -1, parameter weight). Constant zeros are left out.
        ent = []

        def add(i: ArrayLike, j: ArrayLike, var: ArrayLike, const: ArrayLike = 0.0,
                param: ArrayLike = -1, weight: ArrayLike = 0.0) -> None:
            i, j, var, const, param, weight = np.broadcast_arrays(
                np.asarray(i), np.asarray(j), np.asarray(var), np.asarray(const, np.float64),
                np.asarray(param), np.asarray(weight, np.float64))
            ent.append(tuple(np.ravel(v) for v in (i, j, var, const, param, weight)))

        a, b, c = np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij")
        add(b, i3 + c, a * n + b, param=c * n + a, weight=1.0)  # A[a,b]: (A^T P~)[b, c]
        a, b, c = np.meshgrid(np.arange(n), np.arange(p), np.arange(n), indexing="ij")
        add(i1 + b, i3 + c, lay.nA + a * p + b, param=c * n + a, weight=1.0)  # B^T P~
        a, b, j = np.meshgrid(np.arange(m), np.arange(n), np.arange(p), indexing="ij")
        add(b, i1 + j, oC + a * n + b, const=-S[a, j])  # -C^T S
        a, b, l_ = np.meshgrid(np.arange(m), np.arange(n), np.arange(r), indexing="ij")
        add(b, i2 + l_, oC + a * n + b, const=L[a, l_])  # C^T L
        # -(D^T S + S^T D): d/dD[a,b] is -(e_b S[a,:] + S[a,:]^T e_b^T), twice on the diagonal
        a, b, j = np.meshgrid(np.arange(m), np.arange(p), np.arange(p), indexing="ij")
        add(i1 + b, i1 + j, oD + a * p + b, const=-S[a, j] * np.where(j == b, 2.0, 1.0))
        a, b, l_ = np.meshgrid(np.arange(m), np.arange(p), np.arange(r), indexing="ij")
        add(i1 + b, i2 + l_, oD + a * p + b, const=L[a, l_])  # D^T L
        if self.indefinite:  # -(W' H + H' W): the column of H[a, j] holds -W[i, a] at (i, j)
            a, j, i = np.meshgrid(np.arange(m), np.arange(kx), np.arange(kx), indexing="ij")
            var = np.where(j < n, oC + a * n + j, oD + a * p + j - n)
            add(i, j, var, param=n * n + i * m + a, weight=np.where(i == j, -2.0, -1.0))
        k = oP + np.arange(self.nP)
        add(self.p_rows, self.p_cols, k, const=-1.0)  # -P
        add(i3 + self.p_rows, i3 + self.p_cols, k, const=1.0)  # +P in the P~ block
        i, j, var, const, param, weight = (np.concatenate(v) for v in zip(*ent))
        keep = (const != 0) | (param >= 0)
        i, j, var, const, param, weight = (v[keep] for v in (i, j, var, const, param, weight))
        rows = svec_pos(i, j)
        w = np.where(i == j, 1.0, np.sqrt(2.0))  # svec weight
        # The pattern in CSC order; duplicates (i, j, var) are summed.
        order = np.lexsort((rows, var))
        rows, var, const, param, weight, w = (v[order] for v in (rows, var, const, param,
                                                                   weight, w))
        new = np.ones(len(rows), bool)
        new[1:] = (rows[1:] != rows[:-1]) | (var[1:] != var[:-1])
        slot = np.cumsum(new) - 1
        self.nnz = int(slot[-1] + 1) if len(slot) else 0
        self.indices = rows[new].astype(np.int64)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(var[new],
                                                                minlength=self.nx))])
        self.vals0 = np.zeros(self.nnz)
        np.add.at(self.vals0, slot, w * const)
        dep = param >= 0
        self.vals_map = sp.csr_matrix((w[dep] * weight[dep], (slot[dep], param[dep])),
                                      shape=(self.nnz, self.n_params))
        # m0 = svec(M(0)): -R, -I_r and -2 P~ (the last one linear in the parameters).
        iu, ju = np.triu_indices(p)
        wr = np.where(iu == ju, 1.0, np.sqrt(2.0))
        self.offset0 = np.zeros(self.L)
        self.offset0[svec_pos(i1 + iu, i1 + ju)] = -R[iu, ju] * wr
        self.offset0[svec_pos(i2 + np.arange(r), i2 + np.arange(r))] = -1.0
        cu, du = np.triu_indices(n)
        wp = np.where(cu == du, 1.0, np.sqrt(2.0))
        o_rows, o_cols, o_vals = svec_pos(i3 + cu, i3 + du), cu * n + du, -2.0 * wp
        if self.indefinite:  # + G = H0' Q+ H0 in the (x, u) block
            gi, gj = np.triu_indices(kx)
            o_rows = np.concatenate([o_rows, svec_pos(gi, gj)])
            o_cols = np.concatenate([o_cols, n * n + kx * m + gi * kx + gj])
            o_vals = np.concatenate([o_vals, np.where(gi == gj, 1.0, np.sqrt(2.0))])
        self.offset_map = sp.csr_matrix((o_vals, (o_rows, o_cols)),
                                        shape=(self.L, self.n_params))
        self.svec_eye = np.zeros(self.L)
        self.svec_eye[svec_pos(np.arange(N), np.arange(N))] = 1.0

    def params(self, P_tilde, H0=None) -> np.ndarray:
        """The linearisation point's parameters, `[..., n_params]` (batched like `P_tilde`);
        `H0 = (C0, D0)` is required for an indefinite $Q$ (ignored otherwise)."""
        P_tilde = np.asarray(P_tilde, np.float64)
        batch = P_tilde.shape[:-2]
        par = P_tilde.reshape(batch + (self.n * self.n,))
        if not self.indefinite:
            return par
        if H0 is None:
            raise ValueError("an indefinite `qsr.Q` needs the linearisation point `H0`.")
        H = np.concatenate([np.broadcast_to(np.asarray(M, np.float64), batch + np.shape(M)[-2:])
                            for M in H0], -1)  # [..., m, n + p]
        # einsum (not BLAS) so that a row's numbers do not depend on the batch size
        W = np.einsum("...ai,ak->...ik", H, self.Q_plus)
        G = np.einsum("...ia,...aj->...ij", W, H)
        return np.concatenate([par, W.reshape(batch + (-1,)), G.reshape(batch + (-1,))], -1)

    def values(self, P_tilde, H0=None) -> np.ndarray:
        """The `nnz` numbers of $J(\\tilde P)$ in CSC order, `[..., nnz]` (batched)."""
        par = self.params(P_tilde, H0)
        flat = par.reshape(-1, self.n_params)
        # a sparse product computes each row on its own: a row's numbers do not depend on
        # the batch size (BLAS would change them at ~1e-16)
        out = self.vals0 + (self.vals_map @ flat.T).T
        return out.reshape(par.shape[:-1] + (self.nnz,))

    def offset(self, P_tilde, H0=None) -> np.ndarray:
        """$m_0(\\tilde P) = \\operatorname{svec}\\mathcal M(0)$, `[..., L]` (batched)."""
        par = self.params(P_tilde, H0)
        flat = par.reshape(-1, self.n_params)
        out = self.offset0 + (self.offset_map @ flat.T).T
        return out.reshape(par.shape[:-1] + (self.L,))

    def jacobian(self, P_tilde, H0=None) -> sp.csc_matrix:
        """$J(\\tilde P)$ as a `[L, nx]` CSC matrix (one $\\tilde P$)."""
        return sp.csc_matrix((self.values(P_tilde, H0), self.indices, self.indptr),
                             shape=(self.L, self.nx))

    def evaluate(self, x: np.ndarray, P_tilde: np.ndarray, H0=None) -> np.ndarray:
        """$\\mathcal M(x)$ at a given $\\tilde P$ (and $H_0$; dense `[N, N]`, for checks)."""
        return smat(self.offset(P_tilde, H0) + self.jacobian(P_tilde, H0) @ np.asarray(x),
                    self.N)

    def blocks(self, P_tilde: np.ndarray, H0=None) -> tuple[np.ndarray, np.ndarray]:
        """Dense `(M0, J)` with $\\mathcal M(x) = M_0 + \\sum_k x_k J_k$ (`J` is `[nx, N, N]`:
        memory $\\sim\\hat n^4$, for moderate sizes only)."""
        rows, cols, w = svec_indices(self.N)
        M0 = np.zeros((self.N, self.N))
        M0[rows, cols] = self.offset(P_tilde, H0) / w
        M0[cols, rows] = M0[rows, cols]
        var = np.repeat(np.arange(self.nx), np.diff(self.indptr))
        v = self.values(P_tilde, H0) / w[self.indices]
        J = np.zeros((self.nx, self.N, self.N))
        J[var, rows[self.indices], cols[self.indices]] = v
        J[var, cols[self.indices], rows[self.indices]] = v
        return M0, J

    def svec(self, M: np.ndarray) -> np.ndarray:
        return svec(M, svec_indices(self.N))


def cast(x, dtype) -> np.ndarray:
    """Round to `dtype` and back to float64, so a check sees exactly what is returned."""
    return np.asarray(x, np.float64).astype(dtype).astype(np.float64)


def certified(A, B, C, D, qsr: QSR, P) -> np.ndarray:
    """The exact float64 KYP check of a batch of (controller, $P$) pairs, as a bool array.

    $P\\succ 0$ and KYP$(P)\\prec 0$ beyond round-off (paper Lemma 2), evaluated for the
    whole batch at once with stacked eigenvalue computations.
    """
    return np.asarray(kyp_certified(A, B, C, D, qsr, P), bool)
