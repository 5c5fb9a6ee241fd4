"""State coordinates in which [`certify`][dissil_jax.certify] searches for a storage.

A change of state coordinates $x = Tz$ leaves the dissipation inequality as it is: the
realisation $(T^{-1}AT,\\ T^{-1}B,\\ CT,\\ D)$ with storage $P_z$ has the KYP matrix

$$\\mathrm{KYP}_x(P_x) = \\begin{bmatrix}T^{-\\top}&0\\\\0&I\\end{bmatrix}
\\mathrm{KYP}_z(P_z)\\begin{bmatrix}T^{-1}&0\\\\0&I\\end{bmatrix},\\qquad
P_x = T^{-\\top}P_zT^{-1},$$

a congruence, so a storage found in $z$ is one of the controller as given. Two choices:

- **Diagonal, powers of two** (`state_scale`), for every search: each state in units of
  one size; the storage maps back exactly.
- **Balanced by an approximate storage** (`search`), when that search fails. A realisation
  whose storage is ill-conditioned along directions that are not the state axes
  (eigenvalues from $10^{-2}$ to $10^{6}$ along rotated directions, $A$ with entries of 90
  and spectral radius 0.96) defeats the diagonal scaling: Clarabel stopped at
  `optimal_inaccurate` with an indefinite $P$ although a storage with margin $10^{-3}$
  exists. With an approximate storage $\\hat P = V\\Lambda V^\\top\\succ0$ and
  $T = V\\Lambda^{-1/2}$ ($T^\\top\\hat PT = I$), the SDP is well posed in $z$ (its
  margin measured in turn as in `certify`, in the verdict's diagonal units and in $z$:
  `METRICS`), and its storage maps back as $P_x = V\\Lambda^{1/2}P_z\\Lambda^{1/2}
  V^\\top$. That map is not exact in floating point, which is why `certify` re-checks
  $P_x$ in the given coordinates with its float64 eigenvalue check; nothing here decides a
  verdict.

  The approximate storages, best first (by the margin $\\min(-\\lambda_{\\max}
  (\\mathrm{KYP}(P)), \\lambda_{\\min}(P))$ in the given coordinates), are the positive
  definite ones among those the search already found (the SDP's, the Riccati storages of
  `fast.riccati` in the given and the balanced input/output units), then, when $Q\\prec0$,
  the observability Gramian $W = \\sum_k A^{\\top k}(-C^\\top QC)A^k$, a lower bound of
  every storage ($P - A^\\top PA\\succ -C^\\top QC$ from the KYP matrix's first block).
"""

from __future__ import annotations

import warnings

import numpy as np

from .._sdp.lmi import kyp_margin, kyp_matrix
from .._supply import QSR
from .._validate import warn_user
from . import fast as _certify_fast, sdp as _certify_sdp

#: At most this many SDPs are re-solved (the best approximate storage with each of
#: `METRICS`), so a controller that is not dissipative costs a bounded number of extra
#: solves.
MAX_SOLVES = 3
#: A reference storage must be this well conditioned for its square root to be usable.
_MAX_COND = 1e14


def state_scale(A, B, C, sweeps: int = 30) -> np.ndarray:
    """Powers of two $t$ that balance the state: in $x = \\operatorname{diag}(t)z$ each
    state's effect (its column of $A$ off the diagonal and of $C$) and what drives it (its
    row of $A$ and of $B$) have about one size (damped sweeps, as Osborne's balancing).

    A realisation whose states are in very different units (a similarity by
    $\\operatorname{diag}(10^{-3}, 1, 10^3)$, or $B = 10^6$, $C = 10^{-6}$) left the Riccati
    storages and the SDP without a certificate (`insufficient_progress`,
    `numerical_error`); the storage search runs in balanced units and maps the storage back
    (powers of two: exactly).
    """
    d = np.ones(A.shape[0])
    for _ in range(sweeps):
        Ab = A * d[None, :] / d[:, None]
        off = Ab - np.diag(np.diag(Ab))
        col = safe_norms(np.concatenate([off, C * d[None, :]], 0), 0)
        row = safe_norms(np.concatenate([off, B / d[:, None]], 1), 1)
        ok = (col > 0) & (row > 0) & np.isfinite(col) & np.isfinite(row)
        # in logarithms: the ratio itself overflows for states 2^600 apart
        step = 2.0 ** np.round(np.where(ok, np.log2(np.where(ok, row, 1.0))
                                        - np.log2(np.where(ok, col, 1.0)), 0.0) / 2)
        if np.all(step == 1.0):
            break
        d = d * step
    return d


def safe_norms(M, axis: int) -> np.ndarray:
    """2-norms along `axis`, scaled before squaring so that entries beyond
    $\\sqrt{\\text{max}}$ (states in units $2^{\\pm600}$ apart) do not overflow to inf."""
    top = np.max(np.abs(M), axis=axis, keepdims=True, initial=0.0)
    unit = np.where((top > 0) & np.isfinite(top), top, 1.0)
    return np.squeeze(unit, axis) * np.sqrt(((M / unit) ** 2).sum(axis))


def balanced_states(A, B, C, t):
    """The realisation in the states $z$ with $x = \\operatorname{diag}(t)z$."""
    return A * t[None, :] / t[:, None], B / t[:, None], C * t[None, :]


def unbalanced_storage(P, t):
    """A storage of the balanced realisation in the original states."""
    with np.errstate(over="ignore", under="ignore"):  # `check_storage_range` warns of it
        return P / (t[:, None] * t[None, :])


def check_storage_range(t) -> None:
    """Warn when the states' balancing units `t` are so far apart that a storage in the
    given coordinates leaves float64's range (its entries scale like $1/(t_it_j)$): no
    certificate can then be checked in them."""
    span = float(np.max(np.abs(np.log2(t)), initial=0.0))
    if 2 * span > _STORAGE_RANGE:
        warn_user(f"The controller's states are in units up to 2^{span:.0f} away from those "
                  "of its inputs and outputs: a storage in these coordinates has entries beyond float64's "
                  "range, so the certificate's check cannot succeed in them. Rescale the "
                  "states (x = Tz, T diagonal) to units of one size and certify that "
                  "realisation.")


#: log2 of the factor 1/(t_i t_j) beyond which a unit-size storage leaves float64's range
#: (2^1023 is its largest power of two).
_STORAGE_RANGE = 1000.0


def _positive_definite(P) -> bool:
    if P is None or not np.all(np.isfinite(P)):
        return False
    lam = np.linalg.eigvalsh((P + P.T) / 2)
    return bool(lam[0] > 0 and lam[-1] < _MAX_COND * lam[0])


def gramian(A, C, qsr: QSR):
    """$W = \\sum_k A^{\\top k}(-C^\\top QC)A^k$ when $Q\\prec0$ and $A$ is Schur stable
    (a lower bound of every storage), else None."""
    from scipy.linalg import solve_discrete_lyapunov

    Q = np.asarray(qsr.Q, np.float64)
    if Q.size == 0 or np.linalg.eigvalsh(Q)[-1] >= 0:
        return None
    if np.abs(np.linalg.eigvals(A)).max(initial=0.0) >= 1.0:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        W = solve_discrete_lyapunov(A.T, -C.T @ Q @ C)
    return (W + W.T) / 2


def references(A, B, C, D, qsr: QSR, found, units) -> list:
    """Positive definite approximate storages to balance on, best first (module docstring).

    `found`: storages the search returned (NaN ones are skipped); `units`: the realisations
    `(A, B, C, D, qsr)` in which to compute Riccati storages, each with its `state_scale`
    `t` (the storage maps back by `P / (t t')`, exactly)."""
    cands = [np.asarray(P, np.float64) for P in found if P is not None]
    for a, b, c, d, q, t in units:
        for P in _certify_fast.riccati(*balanced_states(a, b, c, t), d, q):
            cands.append(unbalanced_storage(P, t))
    cands = [(P + P.T) / 2 for P in cands if _positive_definite(P)]
    cands.sort(key=lambda P: -float(kyp_margin(A, B, C, D, qsr, P)))
    W = gramian(A, C, qsr)
    if _positive_definite(W):
        cands.append(W)
    return cands


#: The margins the re-solved SDP maximises, in the order tried: `"given"`, the certify
#: SDP's own ($\mathrm{KYP}(P_x)\preceq -tI$, $P_x\succeq tI$, so the same optimum,
#: only better posed); `"jacobi"`, relative to the diagonals of $\mathrm{KYP}(\hat P)$ and
#: $\hat P$ (the units of the verdict's componentwise check, `kyp_bound_holds`);
#: `"balanced"`, the identity in the balanced states ($P_z\succeq tI$).
METRICS = ("given", "jacobi", "balanced")


def _weights(A, B, C, D, qsr: QSR, P_ref, T, metric):
    """`(W1, W2)` of `sdp.solve` in the balanced states for a margin `metric`: a margin
    $-tW$ in the given states is $-tS^\\top WS$ in the balanced ones, $S = \\mathrm{diag}(T, I)$."""
    n, p = B.shape
    if metric == "balanced":
        return np.eye(n + p), np.eye(n)
    if metric == "given":
        W1, W2 = np.eye(n + p), np.eye(n)
    else:
        d1 = np.abs(np.diagonal(kyp_matrix(A, B, C, D, qsr, P_ref)))
        d2 = np.abs(np.diagonal(P_ref))
        W1, W2 = (np.diag(np.maximum(d, 1e-12 * d.max(initial=0.0)) + (d.max(initial=0.0) == 0))
                  for d in (d1, d2))
    S = np.eye(n + p)
    S[:n, :n] = T
    return S.T @ W1 @ S, T.T @ W2 @ T


def solve(A, B, C, D, qsr: QSR, P_ref, io=None, metric="balanced"):
    """The certificate SDP in the states that make `P_ref` the identity, its margin measured
    by `metric` (`METRICS`); returns `(P in the given states or None, status)`. With
    `io = (t_y, t_u, rate)` the SDP is posed in those input and output units (the same
    storage)."""
    lam, V = np.linalg.eigh(P_ref)
    T, Ti = V / np.sqrt(lam), (V * np.sqrt(lam)).T
    W = _weights(A, B, C, D, qsr, P_ref, T, metric)
    Az, Bz, Cz, Dz, q = Ti @ A @ T, Ti @ B, C @ T, D, qsr
    if io is not None:
        t_y, t_u, q = io
        Bz, Cz, Dz = Bz * t_u, Cz / t_y, Dz * (t_u / t_y)
        # the same inequality in the units of `io`: the input rows and columns scale by t_u
        s = np.concatenate([np.ones(len(Az)), np.full(Bz.shape[1], t_u)])
        W = (W[0] * s[:, None] * s[None, :], W[1]) if metric != "balanced" else W
    Pz, status = _certify_sdp.solve(Az, Bz, Cz, Dz, q, W)
    if Pz is None:
        return None, status
    P = Ti.T @ Pz @ Ti
    return (P + P.T) / 2, status


def search(A, B, C, D, qsr: QSR, found, io, units, check):
    """Up to `MAX_SOLVES` SDPs in states balanced by the best approximate storages
    (`references`), with the margins of `METRICS` in turn; returns the first certificate
    `check(P, source)` proves (`source` `"rebalanced: <solver status>"`), else None.

    `found`: the storages of the failed search; `io`: `(t_y, t_u, rate)` or None (the
    SDP's input and output units); `units`: as in `references`."""
    tries = [(P, m) for P in references(A, B, C, D, qsr, found, units) for m in METRICS]
    for P_ref, metric in tries[:MAX_SOLVES]:
        P, status = solve(A, B, C, D, qsr, P_ref, io, metric)
        if P is None:
            continue
        cert = check(P, f"rebalanced: {status}")
        if cert.holds:
            return cert
    return None
