"""Small shared test utilities."""

import jax
import jax.numpy as jnp
import numpy as np

import dissil_jax as dj


def tree_allclose(a, b, rtol=1e-7, atol=1e-9):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(
        np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(la, lb)
    )


def index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def independent_kyp_ok(K, qsr, P):
    """Exact float64 KYP check written out independently of dissil_jax._lmi."""
    A, B, C, D, P = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D, P))
    Q, S, R = qsr.Q, qsr.S, qsr.R
    M11 = A.T @ P @ A - P - C.T @ Q @ C
    M12 = A.T @ P @ B - C.T @ S - C.T @ Q @ D
    M22 = B.T @ P @ B - D.T @ Q @ D - D.T @ S - S.T @ D - R
    M = np.block([[M11, M12], [M12.T, M22]])
    return np.linalg.eigvalsh((M + M.T) / 2).max() < 0 and np.linalg.eigvalsh(P).min() > 0


def random_windows(key, N=10, h=2, n=1, p=1, m=1, gain=0.5):
    """Windows from a known linear map so a good controller exists: u = -gain * y."""
    k1, k2 = jax.random.split(key)
    x0 = jax.random.normal(k1, (N, n))
    y = jax.random.normal(k2, (N, h, p))
    u = -gain * y[..., :m] if m <= p else -gain * jnp.tile(y, (1, 1, m))[..., :m]
    return dj.Windows(x0, y, u)


def expert_windows(seed, n, p, m, N=12, noise=0.05):
    """Two-step windows of a random (generally not dissipative) LTI expert plus noise."""
    rng = np.random.default_rng(seed)
    Ae = 0.5 * rng.normal(size=(n, n)) / np.sqrt(n)
    Be, Ce, De = rng.normal(size=(n, p)), rng.normal(size=(m, n)), rng.normal(size=(m, p))
    x0, y = rng.normal(size=(N, n)), rng.normal(size=(N, 2, p))
    t0 = x0 @ Ce.T + y[:, 0] @ De.T
    t1 = (x0 @ Ae.T + y[:, 0] @ Be.T) @ Ce.T + y[:, 1] @ De.T
    target = np.stack([t0, t1], 1) + noise * rng.normal(size=(N, 2, m))
    return dj.Windows(x0, y, -target)
