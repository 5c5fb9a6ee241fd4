"""Test-only views of an `ICOProblem`: the overbound's value, cone membership, a feasible point."""

import numpy as np
import scipy.sparse as sp

from dissil_jax._lmi import smat
from dissil_jax._train._ico_windows import _svec_len


def overbound(pb, x, theta0, P_tilde, w_tilde, eps=None):
    """The SDP objective at `x` without the proximal terms, and the cone slack `s = b - Ax`.

    Returns `(value, s)`; the overbound of $J(\\theta_0 + \\delta\\theta)$ when `s` is in
    the cones (see `cone_min`).
    """
    q, vals, b, const, _ = pb.data(theta0, P_tilde, w_tilde, eps)
    H = pb.H.copy().tolil()
    H.setdiag(H.diagonal() - np.concatenate(
        [np.full(pb.ntheta, pb.prox), np.full(pb.oY - pb.oP, pb.reg),
         np.zeros(pb.nx - pb.oY)]))
    Hs = H.tocsc()
    Hfull = Hs + sp.triu(Hs, 1).T
    q = q.copy()
    q[pb.oP:pb.oY] = 0.0
    value = 0.5 * x @ (Hfull @ x) + q @ x + const
    return float(value), b - pb.matrix(vals) @ x


def cone_min(pb, s) -> float:
    """The smallest cone 'eigenvalue' of the slack `s` (>= 0 iff `s` is in every cone)."""
    out, row = [], 0
    for kind, d in pb.cone_spec:
        if kind == "psd":
            L = _svec_len(d)
            out.append(np.linalg.eigvalsh(smat(s[row:row + L], d))[0])
            row += L
        else:
            out.append(s[row] - np.linalg.norm(s[row + 1:row + d]))
            row += d
    return float(min(out))


def feasible_point(pb, dtheta, w, P, theta0, w_tilde, P_tilde=None):
    """The cheapest feasible $(Y, \\tau, \\sigma)$ for a given step: tests of the bound."""
    m = pb.m
    dA, dB, dC, dD = pb.mats(dtheta)
    A0, B0, C0, D0 = pb.mats(theta0)
    phi = 2.0 / w_tilde - w / w_tilde**2
    if pb.window_cone != "psd":
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
    x = np.zeros(pb.nx)
    x[:pb.ntheta] = dtheta
    if pb.qsr is not None:
        x[pb.oP:pb.oY] = (np.asarray(P)[pb.lmi.p_rows, pb.lmi.p_cols]
                              / pb.p_scale(P if P_tilde is None else P_tilde))
    x[pb.oY:pb.ow] = Y[0, 0] if pb.window_cone != "psd" else Y[pb.y_rows, pb.y_cols]
    x[pb.ow], x[pb.otau] = w, tau
    if pb.window_cone == "stacked":
        sig = np.sum(sig, keepdims=True)
    x[pb.osig:] = sig * (1 + 1e-12) + 1e-15
    x[pb.otau] = tau * (1 + 1e-12) + 1e-15
    return x
