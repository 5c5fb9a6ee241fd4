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
