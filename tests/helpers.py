"""Small shared test utilities."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import dissil_jax as dj


def tree_allclose(a, b, rtol=1e-7, atol=1e-9):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(
        np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(la, lb)
    )


# -- tolerances from the numerics ------------------------------------------------------------
#
# A result that passed through an iterative solver is known only to the solver's stopping
# tolerance. Two computations of it that differ by round-off (a batched and a looped assembly,
# or another CPU's BLAS kernels, OPENBLAS_CORETYPE, which Clarabel and numpy use) can make the
# solver stop at another iterate, so they agree to the tolerance, not to round-off. An
# interior-point solve stopped at a duality gap `tol` of a problem whose objective has
# curvature mu lies within sqrt(2 tol / mu) of its optimum (strong convexity); the trainers
# normalise their data so that mu is of order one (the projection's distance has mu = 2), so
# one solve pins its result to ~sqrt(tol) relative. The steps between solves (a gradient
# step, the next projection, which is non-expansive) pass a difference on without amplifying
# it much, so k solves in a row agree to about k sqrt(tol).
#
# A real bug (a sign, a dropped term, a wrong step) moves results by far more; the mutations
# listed in the issue note were checked to fail the tests that use these allowances.

CLARABEL_TOL = 1e-8  # Clarabel's default tol_gap_abs/rel and tol_feas (the projection)


def through_solves(k: int, tol: float = CLARABEL_TOL) -> float:
    """Relative agreement of two results that each passed through `k` solves to `tol`."""
    return k * tol**0.5


def index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


# -- dissipativity from the definition -----------------------------------------------------
#
# Nothing below uses dissil_jax's KYP blocks (`_sdp/lmi.py`, `certify`) or `QSR.supply`: the
# storage decrease and the supply rate are evaluated by simulating one step,
#
#     f(x, u) = V(A x + B u) - V(x) - w(u, C x + D u),   V(x) = x'Px,
#     w(u, y) = y'Qy + 2 y'Su + u'Ru,
#
# and the matrix H of the quadratic form f(z) = z'Hz, z = (x, u), is recovered numerically
# by polarisation on basis vectors. K is dissipative with storage P iff P > 0 and H <= 0.


def _mats(K, qsr, P):
    A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    return A, B, C, D, Q, S, R, np.asarray(P, np.float64)


def supply_from_definition(Q, S, R, u, y):
    """w(u, y) = y'Qy + 2 y'Su + u'Ru for rows of `u` and `y` (no library code)."""
    return (np.einsum("ki,ij,kj->k", y, Q, y) + 2 * np.einsum("ki,ij,kj->k", y, S, u)
            + np.einsum("ki,ij,kj->k", u, R, u))


def dissipation_form(K, qsr, P, z):
    """f(z) = V(x+) - V(x) - w(u, y) for rows z = (x, u), by simulating one step of K."""
    A, B, C, D, Q, S, R, P = _mats(K, qsr, P)
    z = np.atleast_2d(np.asarray(z, np.float64))
    n = A.shape[0]
    x, u = z[:, :n], z[:, n:]
    x_next = x @ A.T + u @ B.T
    y = x @ C.T + u @ D.T
    V = lambda v: np.einsum("ki,ij,kj->k", v, P, v)
    return V(x_next) - V(x) - supply_from_definition(Q, S, R, u, y)


def dissipation_matrix(K, qsr, P):
    """The symmetric H with f(z) = z'Hz, by polarisation: H_ij = (f(e_i+e_j)-f(e_i)-f(e_j))/2."""
    k = K.A.shape[-1] + K.B.shape[-1]
    E = np.eye(k)
    diag = dissipation_form(K, qsr, P, E)
    i, j = np.triu_indices(k, 1)
    pairs = dissipation_form(K, qsr, P, E[i] + E[j])
    H = np.diag(diag)
    H[i, j] = H[j, i] = (pairs - diag[i] - diag[j]) / 2
    return H


def dissipation_scale(K, qsr, P):
    """|f(z)| <= scale * |z|^2: a bound on the size of every term of the form."""
    A, B, C, D, Q, S, R, P = _mats(K, qsr, P)
    nrm = lambda M: np.linalg.norm(M, 2) if M.size else 0.0
    AB, CD = nrm(np.hstack([A, B])), nrm(np.hstack([C, D]))
    return float(nrm(P) * (1 + AB**2) + nrm(Q) * CD**2 + 2 * nrm(S) * CD + nrm(R))


def dissipation_report(K, qsr, P, *, num_samples=4000, seed=0):
    """Worst relative values of the definition-based check (negative = dissipative).

    Returns a dict with `p_min` (lambda_min of the symmetrised P over ||P||), `worst` (max of
    f(z) / (scale |z|^2) over random z, the top eigenvectors of H and perturbations of them)
    and `lam_max` (lambda_max(H) / scale).
    """
    A, B, C, D, Q, S, R, P = _mats(K, qsr, P)
    assert A.ndim == 2, "one controller at a time"
    mats = (A, B, C, D, P)
    if not all(np.all(np.isfinite(M)) for M in mats):
        return dict(p_min=-np.inf, worst=np.inf, lam_max=np.inf)
    Ps = (P + P.T) / 2
    p_min = np.linalg.eigvalsh(Ps)[0] / max(np.linalg.norm(Ps, 2), 1e-300)
    scale = dissipation_scale(K, qsr, Ps)
    H = dissipation_matrix(K, qsr, Ps)
    lam, V = np.linalg.eigh(H)
    k = H.shape[0]
    rng = np.random.default_rng(seed)
    Z = rng.normal(size=(num_samples, k))
    Z[: num_samples // 2] *= 10.0 ** rng.uniform(-3, 3, size=(num_samples // 2, k))
    top = V[:, ::-1][:, : min(3, k)].T  # worst-case directions
    near = top[:1] + 1e-3 * rng.normal(size=(200, k))
    Z = np.vstack([Z, top, near])
    vals = dissipation_form(K, qsr, P, Z) / (scale * np.sum(Z**2, 1))
    return dict(p_min=float(p_min), worst=float(vals.max()), lam_max=float(lam[-1] / scale))


def _is_passivity(qsr):
    Q, S, R = (np.asarray(M) for M in (qsr.Q, qsr.S, qsr.R))
    return S.shape[0] == S.shape[1] and not Q.any() and not R.any() and np.array_equal(
        S, 0.5 * np.eye(S.shape[0]))


def in_storage_units(K, P):
    r"""`(K, P)` in the state coordinates $x = T\tilde x$, $T = \operatorname{diag}(P_{ii}^{-1/2})$,
    where the storage has a unit diagonal: the same dissipation inequality (exactly, in exact
    arithmetic), for checking realisations whose states have very different units, where
    a margin relative to the largest term says nothing about the small directions."""
    A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
    P = np.asarray(P, np.float64)
    t = 1.0 / np.sqrt(np.diag(P))
    return (dj.LTIController(A * t[None, :] / t[:, None], B / t[:, None], C * t[None, :], D),
            P * t[:, None] * t[None, :])


def dissipation_ok(K, qsr, P, rel_margin=1e-12, *, python_control=True):
    """True iff V(x) = x'Px certifies (Q,S,R)-dissipativity of K with a relative margin.

    Checks, from the definition only, P = P' > 0 (after explicit symmetrisation) and
    V(x+) - V(x) - w(u, y) <= -rel_margin * scale * (|x|^2 + |u|^2) on many random (x, u)
    and on the worst-case directions (top eigenvectors of the form's matrix). For the
    passivity supply rate it also asks python-control (`control.ispassive`).

    `scale` bounds every term of the form, so the float64 round-off of evaluating it is
    ~1e-15 * scale; the default margin is 1000x that. (Trained controllers sit close to the
    boundary: ICO's absolute LMI margin 1e-6 with a storage P ~ 1e4 is ~5e-11 relative.)
    """
    rep = dissipation_report(K, qsr, P)
    ok = rep["p_min"] > rel_margin and rep["worst"] <= -rel_margin
    ok = ok and rep["lam_max"] <= -rel_margin
    if ok and python_control and _is_passivity(qsr):
        import control

        A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
        ok = bool(control.ispassive(control.ss(A, B, C, D, True)))
    return bool(ok)


def loop_outputs(K, x0, y):
    """One window by a plain Python loop (float64 numpy): $\\hat y_k = C\\hat x_k + D y_k$,
    $\\hat x_{k+1} = A\\hat x_k + B y_k$ from `x0` (None: at rest, $\\hat x_0 = 0$)."""
    A, B, C, D = (np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))
    x = np.zeros(A.shape[0]) if x0 is None else np.asarray(x0, np.float64)
    out = []
    for yk in np.asarray(y, np.float64):
        out.append(C @ x + D @ yk)
        x = A @ x + B @ yk
    return np.array(out)


def loop_predict(K, windows):
    """Every window's outputs, shape (N, h, m), by plain Python loops (no vmap, no scan);
    windows without `x0` start the controller at rest."""
    x0s = [None] * windows.num_windows if windows.x0 is None else list(np.asarray(windows.x0))
    return np.stack([loop_outputs(K, x0, y) for x0, y in zip(x0s, np.asarray(windows.y))])


def loop_loss(K, windows) -> float:
    """The paper's eq. 16 by plain loops: $(1/N) \\sum_i \\sum_k \\|\\hat y_k + u_k\\|^2$."""
    err = loop_predict(K, windows) + np.asarray(windows.u, np.float64)
    return float(np.sum(err**2) / windows.num_windows)


def random_windows(key, N=10, h=2, n=1, p=1, m=1, gain=0.5, *, x0=None):
    """Random windows, y ~ N(0, I).

    With `gain`, the targets come from a known linear map, u = -gain * y (repeated or cut to
    m entries), so a good controller exists; with `gain=None`, u ~ N(0, I) independently of
    y. The controller state `x0` is drawn N(0, I) of width `n`, or taken as given, and
    `n=None` without `x0` gives windows at rest (`x0 = None`).
    """
    kx, ky, ku = jax.random.split(key, 3)
    if x0 is None and n is not None:
        x0 = jax.random.normal(kx, (N, n))
    y = jax.random.normal(ky, (N, h, p))
    if gain is None:
        u = jax.random.normal(ku, (N, h, m))
    else:
        u = -gain * (y[..., :m] if m <= p else jnp.tile(y, (1, 1, m))[..., :m])
    return dj.Windows(x0, y, u)


def as_float32(windows):
    """The same windows in float32 (a missing `x0` stays missing)."""
    return dj.Windows(*(None if a is None else jnp.asarray(a, jnp.float32)
                        for a in (windows.x0, windows.y, windows.u)))


# -- frequency responses (independent of python-control and of the KYP lemma) -------------

#: A grid of the unit circle's upper half, where a real system's response is determined.
OMEGAS = np.linspace(0.0, np.pi, 2001)


def freq_response(A, B, C, D, omegas=OMEGAS):
    """$G(e^{j\\omega}) = C (e^{j\\omega} I - A)^{-1} B + D$ on the grid, shape (W, m, p)."""
    A, B, C, D = (np.asarray(M, np.float64) for M in (A, B, C, D))
    eye = np.eye(A.shape[0])
    return np.stack([C @ np.linalg.solve(np.exp(1j * w) * eye - A, B) + D for w in omegas])


def frequency_supply_min(A, B, C, D, qsr, omegas=OMEGAS):
    """$\\min_\\omega \\lambda_{\\min}(G^H Q G + G^H S + S^T G + R)$: $\\ge 0$ iff the stable
    system G is (Q, S, R)-dissipative (frequency-domain KYP)."""
    G = freq_response(A, B, C, D, omegas)
    Q, S, R = (np.asarray(M, np.float64) for M in (qsr.Q, qsr.S, qsr.R))
    GH = np.conj(np.swapaxes(G, -1, -2))
    M = GH @ Q @ G + GH @ S + S.T @ G + R
    return float(np.linalg.eigvalsh((M + np.conj(np.swapaxes(M, -1, -2))) / 2)[:, 0].min())


def min_hermitian_part(A, B, C, D, omegas=OMEGAS):
    """$\\min_\\omega \\lambda_{\\min}((G + G^H)/2)$: $\\ge 0$ iff the stable square G is
    passive."""
    G = freq_response(A, B, C, D, omegas)
    He = (G + np.conj(np.swapaxes(G, -1, -2))) / 2
    return float(np.linalg.eigvalsh(He)[:, 0].min())


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


def exactly_dissipative(K, qsr, P) -> bool:
    """P > 0 and KYP(P) < 0 decided in exact rational arithmetic on the float64 entries
    (no rounding at all; no library code): Sylvester's criterion, every leading principal
    minor of P and of -KYP(P) positive, by fraction-exact elimination. Small controllers
    only (the fractions grow with the order)."""
    from fractions import Fraction

    F = lambda M: [[Fraction(float(v)) for v in row] for row in np.atleast_2d(
        np.asarray(M, np.float64))]
    A, B, C, D, Q, S, R, P = (F(M) for M in _mats(K, qsr, P))
    mul = lambda X, Y: [[sum(X[i][k] * Y[k][j] for k in range(len(Y))) for j in
                         range(len(Y[0]))] for i in range(len(X))]
    tr = lambda X: [list(r) for r in zip(*X)]
    add = lambda *Xs: [[sum(X[i][j] for X in Xs) for j in range(len(Xs[0][0]))]
                       for i in range(len(Xs[0]))]
    neg = lambda X: [[-v for v in r] for r in X]
    Ps = [[(P[i][j] + P[j][i]) / 2 for j in range(len(P))] for i in range(len(P))]
    M11 = add(mul(mul(tr(A), Ps), A), neg(Ps), neg(mul(mul(tr(C), Q), C)))
    M12 = add(mul(mul(tr(A), Ps), B), neg(mul(tr(C), add(S, mul(Q, D)))))
    M22 = add(mul(mul(tr(B), Ps), B), neg(mul(mul(tr(D), Q), D)), neg(mul(tr(D), S)),
              neg(mul(tr(S), D)), neg(R))
    M = [r1 + r2 for r1, r2 in zip(M11, M12)] + [r1 + r2 for r1, r2 in zip(tr(M12), M22)]

    def positive_definite(X):
        X = [list(r) for r in X]
        for k in range(len(X)):  # the k-th pivot is the ratio of leading minors k+1, k
            if X[k][k] <= 0:
                return False
            for i in range(k + 1, len(X)):
                f = X[i][k] / X[k][k]
                X[i] = [a - f * b for a, b in zip(X[i], X[k])]
        return True

    return positive_definite(Ps) and positive_definite(neg(M))


def random_ren_params(key, num, n, q, p, m, scale):
    """`num` parameters of the REN map (float64) with every entry random (X around I, E's
    skew part, the neurons' direct input), not only the trainer's initial draw."""
    from dissil_jax.internal import ren_map

    theta = ren_map.init_ren_params(key, num, n, q, p, m, scale, jnp.float64)
    leaves, tree = jax.tree.flatten(theta)
    keys = jr.split(jr.fold_in(key, 1), len(leaves))
    return jax.tree.unflatten(tree, [a + scale * jr.normal(k, a.shape, a.dtype)
                                     for a, k in zip(leaves, keys)])


#: Supply rates with Q <= 0 of every kind (m = p = 2), for the REN tests.
REN_RATES = {
    "strict": dj.QSR(-np.eye(2), 0.3 * np.eye(2), 2.0 * np.eye(2)),
    "passive": dj.QSR.passive(2),  # Q = 0
    "rank_deficient": dj.QSR(np.diag([-1.0, 0.0]), np.eye(2) / 2, 0 * np.eye(2)),
    "gain": dj.QSR.bounded_gain(1.5, n_in=2, n_out=2),
}
