"""A tight gain bound (|Q| >> R): `fit_pgd` stalls far above `fit_direct` (documented limit).

The controller rate of a plant with a large H-infinity gain bounds the controller's gain by
a small gamma. The steepest first-order direction is the feedthrough D, so the projected
steps spend the bound on D and leave the dynamic part (C, B) almost no room: PGD stalls at
a point the projection keeps fixed, while `fit_direct` trains a much better certified
controller (`fit_pgd`'s docstring, "Tight gain bounds"; `docs/choosing.md`). This test pins
that documented gap and checks every returned controller with an independent float64 KYP
test.
"""

import jax
import jax.numpy as jnp
import numpy as np

import dissil_jax as dj


def _tight_gain_problem():
    """Two-state SISO plant with outputs x100, a state-feedback expert, 25 windows of h = 2."""
    A = np.array([[0.8, 0.2], [-0.1, 0.7]])
    B = np.array([[1.0], [0.5]])
    C = 100.0 * np.array([[1.0, -0.5]])
    K = np.array([[0.5, 0.3]])
    rng = np.random.default_rng(0)
    x0 = rng.standard_normal((25, 2))
    x1 = x0 @ A.T - (x0 @ K.T) @ B.T
    X = np.stack([x0, x1], 1)
    u = -X @ K.T + 0.02 * rng.standard_normal((25, 2, 1))
    z = np.exp(1j * np.linspace(0.0, np.pi, 4001))
    hinf = max(abs((C @ np.linalg.solve(zi * np.eye(2) - A, B))[0, 0]) for zi in z)
    windows = dj.Windows(jnp.asarray(x0), jnp.asarray(X @ C.T), jnp.asarray(u))
    qsr = dj.stabilising_qsr(dj.QSR.bounded_gain(1.01 * hinf, n_in=1, n_out=1))
    return windows, qsr


def _kyp_holds(A, B, C, D, P, Q, S, R):
    """Independent float64 check: P > 0 and the discrete KYP matrix (paper Lemma 2) < 0."""
    A, B, C, D, P, Q, S, R = (np.asarray(M, np.float64) for M in (A, B, C, D, P, Q, S, R))
    M11 = A.T @ P @ A - P - C.T @ Q @ C
    M12 = A.T @ P @ B - C.T @ S - C.T @ Q @ D
    M22 = B.T @ P @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R
    M = np.block([[M11, M12], [M12.T, M22]])
    return np.linalg.eigvalsh((M + M.T) / 2).max() < 0 and np.linalg.eigvalsh(P).min() > 0


def test_pgd_stalls_far_above_direct_on_a_tight_gain_bound():
    windows, qsr = _tight_gain_problem()
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    assert -Q[0, 0] > 1e4 * R[0, 0]  # the anisotropic rate of the audit (|Q| >> R)
    J0 = float(np.mean(np.sum(np.asarray(windows.u) ** 2, axis=(1, 2))))
    key = jax.random.PRNGKey(0)
    pgd = dj.fit_pgd(key, windows, qsr, num_inits=2, throw=False)
    direct = dj.fit_direct(key, windows, qsr, num_inits=2, throw=False)
    for res in (pgd, direct):
        assert np.all(np.asarray(res.certified))
        K = res.controllers
        for i in range(res.num_inits):
            assert _kyp_holds(K.A[i], K.B[i], K.C[i], K.D[i], res.P[i], Q, S, R)
    best_pgd, best_direct = float(np.min(pgd.final_loss)), float(np.min(direct.final_loss))
    # measured: PGD 0.29-0.30 (0.65 J0), fit_direct 0.005-0.01 (0.01-0.02 J0). If PGD ever
    # comes within 3x of fit_direct, update fit_pgd's "Tight gain bounds" and choosing.md.
    assert best_direct < 0.05 * J0
    assert best_pgd > 3.0 * best_direct
