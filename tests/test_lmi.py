"""The sparse assembly of the convexified KYP LMI against a dense construction written here."""

import jax
import numpy as np
import pytest
import scipy.sparse as sp
from helpers import dissipation_ok

import dissil_jax as dj
from dissil_jax.internal import ConvexifiedLMI, smat

pytestmark = pytest.mark.numerics  # re-run under other BLAS kernels (make test-kernels)

SUPPLIES = [
    ("passive", dj.QSR.passive(2)),
    ("bounded-gain-rect", dj.QSR.bounded_gain(0.7, n_in=3, n_out=2)),
    ("conic", dj.QSR.conic(-0.5, 2.0, dim=2)),
    ("nonlinear-paper", dj.QSR(-29.867, 3.556, 0.601)),
]


def _dense_M(A, B, C, D, P, P_tilde, S, R, L):
    """The convexified LMI written out block by block (no library code)."""
    n, p, r = A.shape[0], B.shape[1], L.shape[1]
    Z = np.zeros
    rows = [
        [-P, -C.T @ S, C.T @ L, A.T @ P_tilde],
        [-S.T @ C, -D.T @ S - S.T @ D - R, D.T @ L, B.T @ P_tilde],
        [L.T @ C, L.T @ D, -np.eye(r), Z((r, n))],
        [P_tilde @ A, P_tilde @ B, Z((n, r)), P - 2 * P_tilde],
    ]
    del p
    return np.block(rows)


def _unpack(x, n, p, m):
    """x = (vec A, vec B, vec C, vec D row-major, upper triangle of P row-major)."""
    sizes = np.cumsum([0, n * n, n * p, m * n, m * p])
    A, B, C, D = (x[sizes[i]:sizes[i + 1]].reshape(s)
                  for i, s in enumerate([(n, n), (n, p), (m, n), (m, p)]))
    P = np.zeros((n, n))
    P[np.triu_indices(n)] = x[sizes[4]:]
    return A, B, C, D, P + np.triu(P, 1).T


@pytest.mark.parametrize("name, qsr", SUPPLIES, ids=[s[0] for s in SUPPLIES])
def test_sparse_assembly_equals_the_dense_lmi(name, qsr):
    n, p, m = 3, qsr.n_in, qsr.n_out
    L = qsr.neg_q_factor()
    assert np.allclose(L @ L.T, -qsr.Q)
    lmi = ConvexifiedLMI(n, p, m, qsr)
    rng = np.random.default_rng(0)
    G = rng.normal(size=(n, n))
    P_tilde = G @ G.T + np.eye(n)
    nx = n * n + n * p + m * n + m * p + n * (n + 1) // 2
    assert lmi.nx == nx
    dense = lambda x: _dense_M(*_unpack(x, n, p, m), P_tilde, qsr.S, qsr.R, L)
    M0 = dense(np.zeros(nx))
    # the map is affine: unit steps give the Jacobian's columns exactly (up to round-off
    # of the entries, each a sum of at most n products of O(1) numbers)
    J = np.stack([dense(e) - M0 for e in np.eye(nx)])
    Jsp = lmi.jacobian(P_tilde).toarray()
    for k in range(nx):
        np.testing.assert_allclose(smat(Jsp[:, k], lmi.N), J[k], atol=1e-13, rtol=0)
    np.testing.assert_allclose(smat(lmi.offset(P_tilde), lmi.N), M0, atol=1e-13, rtol=0)
    x = rng.normal(size=nx)
    np.testing.assert_allclose(lmi.evaluate(x, P_tilde), dense(x), atol=1e-12, rtol=0)
    M0d, Jd = lmi.blocks(P_tilde)  # the dense view ICO uses
    np.testing.assert_allclose(Jd, J, atol=1e-13, rtol=0)
    np.testing.assert_allclose(M0d, M0, atol=1e-13, rtol=0)
    # no stored zeros except where a parameter may make them nonzero
    assert lmi.nnz == np.sum((Jsp != 0) | (lmi.jacobian(P_tilde + 1.0).toarray() != 0))


def test_batched_values_equal_a_loop():
    qsr = dj.QSR.passive(2)
    lmi = ConvexifiedLMI(4, 2, 2, qsr)
    rng = np.random.default_rng(1)
    Pt = rng.normal(size=(5, 4, 4))
    vals, off = lmi.values(Pt), lmi.offset(Pt)
    for i in range(5):
        assert np.array_equal(vals[i], lmi.values(Pt[i]))  # bit for bit, batch-independent
        assert np.array_equal(off[i], lmi.offset(Pt[i]))


def test_storage_grows_like_the_nonzeros():
    """Nothing stored is larger than a few times the LMI's own nonzeros (no dense tensors)."""
    qsr = dj.QSR.passive(2)
    for n in (8, 32):
        lmi = ConvexifiedLMI(n, 2, 2, qsr)
        # nonzeros: A^T P~ and B^T P~ (n per variable), P twice, C and D against S and L
        assert lmi.nnz <= n**3 + 2 * n * n + (n + 1) * n + 8 * (n + 2)
        stored = sum(v.nbytes for v in vars(lmi).values() if isinstance(v, np.ndarray))
        stored += sum(v.data.nbytes + v.indices.nbytes + v.indptr.nbytes
                      for v in vars(lmi).values() if sp.issparse(v))
        assert stored <= 64 * (lmi.nnz + lmi.L + lmi.nx)


def test_projection_at_order_16_is_certified(getkey):
    """A projection at n = 16, m = p = 2 (setup memory ~ nonzeros, not n^6)."""
    qsr = dj.QSR.passive(2)
    K = dj.LTIController.random(getkey(), 16, 2, 2, scale=1.0)
    Kp, P = dj.project(K, qsr, refine=1)
    assert dj.certify(Kp, qsr, P=P).holds
    assert dissipation_ok(Kp, qsr, P)
    assert jax.tree.all(jax.tree.map(lambda a: bool(np.all(np.isfinite(a))), Kp))
