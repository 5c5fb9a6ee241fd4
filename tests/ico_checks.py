"""Test-only views of an `ICOProblem`: the overbound's value, cone membership, a feasible point."""

import clarabel
import numpy as np
import scipy.sparse as sp

from dissil_jax.internal import smat, svec_len


def overbound(pb, x, theta0, P_tilde, w_tilde, eps=None):
    """The SDP objective at `x` without the proximal terms, and the cone slack `s = b - Ax`.

    Returns `(value, s)`; the overbound of $J(\\theta_0 + \\delta\\theta)$ when `s` is in
    the cones (see `cone_min`).
    """
    lay = pb.layout
    q, vals, b, const, _ = pb.data(theta0, P_tilde, w_tilde, eps)
    prox_diag = np.zeros(lay.nx)
    prox_diag[:lay.ntheta] = pb.prox
    prox_diag[lay.colP] = pb.reg
    H = pb.H.copy().tolil()
    H.setdiag(H.diagonal() - prox_diag)
    Hs = H.tocsc()
    Hfull = Hs + sp.triu(Hs, 1).T
    q = q.copy()
    q[lay.colP] = 0.0
    value = 0.5 * x @ (Hfull @ x) + q @ x + const
    return float(value), b - pb.matrix(vals) @ x


def cone_spec(pb):
    """`[(kind, size)]` of the SDP's cones in order, kind "psd" or "soc"."""
    return [("psd" if isinstance(c, clarabel.PSDTriangleConeT) else "soc", c.dim)
            for c in pb.cones]


def cone_min(pb, s) -> float:
    """The smallest cone 'eigenvalue' of the slack `s` (>= 0 iff `s` is in every cone)."""
    out, row = [], 0
    for kind, d in cone_spec(pb):
        if kind == "psd":
            L = svec_len(d)
            out.append(np.linalg.eigvalsh(smat(s[row:row + L], d))[0])
            row += L
        else:
            out.append(s[row] - np.linalg.norm(s[row + 1:row + d]))
            row += d
    return float(min(out))


def feasible_point(pb, dtheta, w, P, theta0, w_tilde, P_tilde=None):
    """The cheapest feasible $(Y, \\tau, \\sigma)$ for a given step: tests of the bound."""
    m, lay = pb.m, pb.layout
    dA, dB, dC, dD = pb.mats(dtheta)
    A0, B0, C0, D0 = pb.mats(theta0)
    phi = 2.0 / w_tilde - w / w_tilde**2
    if lay.scalar_y:
        Y = np.linalg.norm(dC, 2) ** 2 / phi * np.eye(m)
    else:
        Y = dC @ dC.T / phi
    dz = pb.x0 @ dA.T + pb.u0 @ dB.T
    z = pb.x0 @ A0.T + pb.u0 @ B0.T
    ebar = (pb.t1 - z @ C0.T - pb.u1 @ D0.T - dz @ C0.T - z @ dC.T - pb.u1 @ dD.T)
    if not (phi > 0 and np.linalg.eigvalsh(np.eye(m) - Y)[0] > 0):
        raise ValueError("this step is outside the SDP's domain: I - Y must be > 0.")
    sig = np.einsum("ka,ka->k", ebar, np.linalg.solve(np.eye(m) - Y, ebar.T).T)
    tau = np.sum(dz**2) / w
    x = np.zeros(lay.nx)
    x[lay.col_theta] = dtheta
    if pb.qsr is not None:
        # the SDP's P variable is X = Ph^{-1} P Ph^{-1}, Ph = P~^{1/2} (`ICOProblem.p_scale`)
        Ph_inv = np.linalg.inv(pb.p_scale(P if P_tilde is None else P_tilde))
        x[lay.colP] = (Ph_inv @ np.asarray(P) @ Ph_inv)[pb.lmi.p_rows, pb.lmi.p_cols]
    x[lay.colY] = Y[0, 0] if lay.scalar_y else Y[lay.y_rows, lay.y_cols]
    if lay.n_sig == 1:  # one sigma for all windows ("stacked")
        sig = np.sum(sig, keepdims=True)
    x[lay.col_sig] = sig * (1 + 1e-12) + 1e-15
    x[lay.ow] = w
    x[lay.otau] = tau * (1 + 1e-12) + 1e-15
    return x
