"""The dissipativity certificate of a REN controller: a storage $P$ and a diagonal sector
multiplier $\\Lambda$ (S-procedure), found by an SDP and checked by eigenvalues in float64."""

from __future__ import annotations

import itertools
import math
import warnings

import equinox as eqx
import jax
import jax.core
import numpy as np

from .._certify.args import storage_arg
from .._certify.certify import _io_scale
from .._certify.coordinates import (
    balanced_states,
    check_storage_range,
    unbalanced_storage,
)
from .._controller import LTIController
from .._progress import working
from .._rate_scale import nearest_power_of_two, out_of_band, rate_factor
from .._sdp import sdp as _sdp
from .._sdp.lmi import (
    VERIFY_RTOL,
    kyp_bound_holds,
    kyp_margin,
    kyp_matrix,
    kyp_matrix_of,
    kyp_scale,
    kyp_scale_of,
)
from .._supply import QSR
from .._validate import check_flag, check_tolerance, real_array
from .controller import RENController
from .units import COORDINATES, coordinates, unit_multiplier


class RENCertificate(eqx.Module):
    """The outcome of [`certify_ren`][dissil_jax.certify_ren].

    - `holds`: True iff $P\\succ0$, $\\Lambda\\succ0$ and the REN's dissipation matrix
      $M(P,\\Lambda)\\prec0$ beyond float64 round-off (an eigenvalue check).
    - `P`: the storage ($V(x) = x^\\top Px$), float64.
    - `multiplier`: the diagonal of $\\Lambda$ (`[q]`).
    - `margin`: $\\min(-\\lambda_{\\max}(M), \\lambda_{\\min}(P), \\min_i\\Lambda_{ii})$,
      computed in float64 from $M$ as given. With multipliers far larger than $P$ it
      carries their round-off and can read slightly below zero while `holds` is True
      (the verdict allows for round-off and also checks the congruent form with unit
      multipliers): a REN audit saw -0.009 where the exact margin was +0.003.
    - `status`: `"given"` or the SDP solver's status; `message` says what the verdict
      means.

    For a batch of controllers each field gains the batch axes in front (numpy arrays).
    """

    holds: bool | np.ndarray
    P: np.ndarray
    multiplier: np.ndarray
    margin: float | np.ndarray
    status: str | np.ndarray = "given"

    @property
    def message(self) -> str | list:
        """What the verdict means, as a sentence (a nested list of them when batched), as
        [`Certificate.message`][dissil_jax.Certificate] says it for `certify`."""
        holds = np.asarray(self.holds, bool)
        status = np.broadcast_to(np.asarray(self.status, dtype=object), holds.shape)
        text = np.vectorize(_ren_message, otypes=[object])(holds, status)
        return str(text[()]) if holds.ndim == 0 else text.tolist()


def _ren_message(holds, status) -> str:
    """`RENCertificate.message` for one controller."""
    if holds:
        return ("certified: the storage P and the multiplier prove the REN's dissipation "
                "inequality beyond float64 round-off")
    if status == "given":
        return ("the given (P, multiplier) does not prove the certificate beyond float64 "
                "round-off; call `dj.certify_ren` without them to search by SDP")
    if str(status).startswith("infeasible"):
        return ("no storage and diagonal multiplier satisfy the REN certificate (the solver "
                f"reported `{status}`): the controller is not certifiably dissipative by this "
                "sector certificate, which is sufficient, not necessary (an unstable or "
                "too-high-gain linear part fails it for every activation)")
    return (f"undecided: the SDP solver stopped at `{status}` and its storage does not pass "
            "the float64 check; that does not show that none exists (an ill-conditioned "
            "storage may be beyond float64: pass a known pair as `P` and `multiplier`)")


def augmented_lti(K: RENController) -> LTIController:
    """The REN's linear part as one LTI system from $(w, \\hat u)$ to $(v, \\hat y)$:

    $$\\left[\\begin{array}{c|cc} A & B_1 & B_2\\\\ \\hline C_1 & D_{11} & D_{12}\\\\
    C_2 & D_{21} & D_{22}\\end{array}\\right]$$ (float64, batch axes kept)."""
    A, B1, B2, C1, D11, D12, C2, D21, D22 = (np.asarray(M, np.float64) for M in K.matrices)
    cat = np.concatenate
    return LTIController(A, cat([B1, B2], -1), cat([C1, C2], -2),
                         cat([cat([D11, D12], -1), cat([D21, D22], -1)], -2))


def augmented_qsr(qsr: QSR, multiplier) -> QSR:
    """The supply rate of the augmented system that turns the REN certificate into a KYP
    inequality (paper Lemma 2) of `augmented_lti`:

    $$s_\\Lambda\\bigl((w,\\hat u),(v,\\hat y)\\bigr) = s(\\hat u,\\hat y) - 2w^\\top\\Lambda(v - w),
    \\quad Q_\\Lambda = \\begin{bmatrix}0&0\\\\0&Q\\end{bmatrix},\\
    S_\\Lambda = \\begin{bmatrix}-\\Lambda&0\\\\0&S\\end{bmatrix},\\
    R_\\Lambda = \\begin{bmatrix}2\\Lambda&0\\\\0&R\\end{bmatrix}.$$

    $Q_\\Lambda\\preceq0$ whenever $Q\\preceq0$."""
    lam = np.asarray(multiplier, np.float64)
    q, m, p = lam.shape[-1], qsr.n_out, qsr.n_in
    L = np.diag(lam)
    Q = np.block([[np.zeros((q, q)), np.zeros((q, m))], [np.zeros((m, q)), qsr.Q]])
    S = np.block([[-L, np.zeros((q, p))], [np.zeros((m, q)), qsr.S]])
    R = np.block([[2 * L, np.zeros((q, p))], [np.zeros((p, q)), qsr.R]])
    return QSR(Q, S, R)


def ren_lmi(K: RENController, qsr: QSR, P, multiplier) -> np.ndarray:
    """The REN's dissipation matrix $M(P,\\Lambda)$ in float64 (one controller).

    $\\xi^\\top M\\xi = V(x^+) - V(x) - s(\\hat u,\\hat y) + 2w^\\top\\Lambda(v - w)$ for
    $\\xi = (x, w, \\hat u)$, with $v$ and $\\hat y$ the linear part's outputs at $\\xi$ and
    $V(x) = x^\\top Px$. If $M\\preceq0$, every trajectory of the REN satisfies
    $V(x_{k+1}) - V(x_k)\\le s(\\hat u_k,\\hat y_k)$, because $w = \\sigma(v)$ makes
    $w^\\top\\Lambda(v - w)\\ge0$ for a diagonal $\\Lambda\\succeq0$.
    """
    G = augmented_lti(K)
    return kyp_matrix(G.A, G.B, G.C, G.D, augmented_qsr(qsr, multiplier), P)


def _check_args(K, qsr):
    if not isinstance(K, RENController):
        raise ValueError(f"`K` must be a `dj.RENController`, got {type(K).__name__}.")
    if not isinstance(qsr, QSR):
        raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
    qsr.check_sizes(K.n_in, K.n_out)
    if any(isinstance(M, jax.core.Tracer) for M in jax.tree.leaves(K)):
        raise ValueError("`certify_ren` cannot run under `jax.jit` or `jax.vmap` (`K` is "
                         "traced): it checks the certificate in float64 on the host. Call it "
                         "on the result, outside the transformation (a batched `K` is "
                         "certified member by member).")
    # The layer uses tril(D11, -1) only; a traced or edited D11 may carry more, and the
    # certificate of the full matrix would be of another system than the one that runs.
    D11 = np.asarray(K.D11)
    if D11.shape[-1] and np.any(np.triu(D11) != 0):
        raise ValueError("`K.D11` must be strictly lower triangular (the explicit layer uses "
                         "only the part below the diagonal, so a certificate of the whole "
                         "matrix would be of another system); pass jnp.tril(D11, -1).")


def _augmented_arrays(qsr: QSR, lam):
    """`augmented_qsr` for a batch of multipliers `lam` (`[*batch, q]`): its $(Q, S, R)$ as
    batched arrays and its `rate_factor` per member."""
    lam = np.asarray(lam, np.float64)
    batch, q, m, p = lam.shape[:-1], lam.shape[-1], qsr.n_out, qsr.n_in
    if q == 0:  # the rate itself
        return qsr.Q, qsr.S, qsr.R, rate_factor(qsr)
    L = lam[..., :, None] * np.eye(q)
    Q = np.zeros(batch + (q + m, q + m))
    Q[..., q:, q:] = qsr.Q
    S = np.zeros(batch + (q + m, q + p))
    S[..., :q, :q], S[..., q:, q:] = -L, qsr.S
    R = np.zeros(batch + (q + p, q + p))
    R[..., :q, :q], R[..., q:, q:] = 2 * L, qsr.R
    # `rate_factor` of each augmented rate: Q is singular (its neuron block is zero), so the
    # size is the largest entry, 2 max(lam) or the rate's own
    size = np.maximum(max(np.abs(M).max(initial=0.0) for M in (qsr.Q, qsr.S, qsr.R)),
                      2 * np.abs(lam).max(-1))
    scaled = out_of_band(size)
    return Q, S, R, np.where(scaled, nearest_power_of_two(np.where(scaled, size, 1.0)), 1.0)


def _margin_and_holds(G: LTIController, qsr: QSR, P, lam, tol):
    """Margin and verdict of the eigenvalue check for (augmented systems, P, Λ), batched
    over leading axes (numpy arrays of the batch's shape).

    The verdict accepts the check of $M(P,\\Lambda)$ itself or of its congruent form with a
    unit multiplier (`_unit_multiplier`): each is a float64 eigenvalue test with its own
    round-off allowance. The second matters when $\\Lambda$ is far from the size of $P$
    (neurons in other units than the state, e.g. a REN trained on large data and returned
    in the user's units, with $\\Lambda\\sim10^7$ and $P\\sim10$): the allowance, which grows
    with the largest term, then swamps the first test's margin.
    """
    P, lam = np.asarray(P, np.float64), np.asarray(lam, np.float64)
    A, B, C, D = (np.asarray(M, np.float64) for M in (G.A, G.B, G.C, G.D))
    finite = np.all([np.all(np.isfinite(M), axis=(-2, -1)) for M in (A, B, C, D, P)], axis=0) \
        & np.all(np.isfinite(lam), axis=-1)
    # non-finite members are judged on zeros (and refused below), so the others still batch
    zero = lambda M, k: np.where(finite[(...,) + (None,) * k], M, 0.0)
    A, B, C, D, P = (zero(M, 2) for M in (A, B, C, D, P))
    lam = zero(lam, 1)
    Q, S, R, factor = _augmented_arrays(qsr, lam)
    M = kyp_matrix_of(A, B, C, D, Q, S, R, P)
    margin = np.minimum(np.minimum(-np.linalg.eigvalsh(M)[..., -1],
                                   np.linalg.eigvalsh(P)[..., 0]), lam.min(-1, initial=np.inf))
    holds = finite & (margin > tol * kyp_scale_of(A, B, C, D, Q, S, R, P, factor))
    positive = (lam.shape[-1] == 0) | np.all(lam > 0, axis=-1)
    if tol <= VERIFY_RTOL and not np.all(holds | ~finite | ~positive):
        # componentwise round-off bounds (as `certify`: not when `tol` asks for more)
        holds |= finite & positive & kyp_bound_holds(A, B, C, D, Q, S, R, P)
    retry = finite & ~holds & (lam.shape[-1] > 0) & positive
    if np.any(retry):
        unit = unit_multiplier(LTIController(A, B, C, D), np.where(retry[..., None], lam, 1.0))
        umats = (unit.A, unit.B, unit.C, unit.D)
        uaug = augmented_qsr(qsr, np.ones(lam.shape[-1]))
        holds |= retry & (kyp_margin(*umats, uaug, P) > tol * kyp_scale(*umats, uaug, P))
    return np.where(finite, margin, -np.inf), holds


def _solve(G: LTIController, qsr: QSR, q: int, d, ts):
    """$\\max t$ s.t. $M(P,\\Lambda)\\preceq -tI$, $P\\succeq tI$, $\\Lambda\\succeq tI$,
    $t\\le1$, in the neuron units `d` and the state units `ts` (`units.coordinates`),
    with cvxpy and Clarabel (BLAS single-threaded); returns `(P, λ, status)` in the
    controller's own units."""
    import cvxpy as cp

    check_storage_range(ts)
    G = unit_multiplier(G, d)
    A, B, C, D = (np.asarray(M, np.float64) for M in (G.A, G.B, G.C, G.D))
    A, B, C = balanced_states(A, B, C, ts)
    n = B.shape[0]
    k = n + B.shape[1]
    P = cp.Variable((n, n), symmetric=True)
    lam = cp.Variable(q)
    t = cp.Variable()
    F = np.concatenate([A, B], 1)
    # The constant supply part and the sector part are linear in Λ: build them from the
    # augmented supply rate's KYP matrix with unit multipliers, one neuron at a time.
    K0 = kyp_matrix(np.zeros((n, n)), np.zeros_like(B), C, D, augmented_qsr(qsr, np.zeros(q)),
                    np.zeros((n, n)))
    M = F.T @ P @ F + K0
    E = np.zeros((n, k))
    E[:, :n] = np.eye(n)
    M = M - E.T @ P @ E
    for i in range(q):
        e = np.zeros(q)
        e[i] = 1.0
        Ki = kyp_matrix(np.zeros((n, n)), np.zeros_like(B), C, D, augmented_qsr(qsr, e),
                        np.zeros((n, n))) - K0
        M = M + lam[i] * Ki
    cons = [(M + M.T) / 2 << -t * np.eye(k), P >> t * np.eye(n), t <= 1]
    if q:
        cons.append(lam >= t)
    prob = cp.Problem(cp.Maximize(t), cons)
    with _sdp.single_threaded_blas(), warnings.catch_warnings():
        # The status is returned, and the verdict is the float64 check of the pair anyway.
        warnings.filterwarnings("ignore", message="Solution may be inaccurate",
                                category=UserWarning)
        try:
            prob.solve(solver=cp.CLARABEL)
        except cp.SolverError as err:
            return None, None, f"solver_error: {err}"
    if P.value is None:
        return None, None, str(prob.status)
    status = str(prob.status)
    # Solved to optimality with t* clearly below 0 (beyond the solver's tolerances, ~1e-8
    # on these unit-size data): no pair with M < 0, P > 0, Λ > 0 exists, since any would
    # give t* >= min(its margins, 1) > 0.
    if status == "optimal" and t.value is not None and t.value < -_DISPROOF * max(
            1.0, float(np.abs(K0).max(initial=0.0))):
        status = f"infeasible (solved to optimality at t* = {float(t.value):.3g} < 0)"
    return (unbalanced_storage(np.asarray(P.value), ts),
            d * np.asarray(lam.value if q else np.zeros(0)).reshape(q), status)


def _io_units(G: LTIController, qsr: QSR, q: int):
    """`(G, qsr)` as given, then, for a rate whose $Q$ and $R$ differ in size by more than
    $2^{12}$ (`dj.certify`'s `_io_scale`), the augmented system in the units
    $\\hat y = t_y\\tilde y$, $\\hat u = t_u\\tilde u$ that balance them: the columns
    of $\\hat u$ times $t_u$, the rows of $\\hat y$ divided by $t_y$, against
    $(t_y^2Q, t_yt_uS, t_u^2R)$. The same inequality with the same $(P, \\Lambda)$, exactly
    (powers of two). A gain bound of $10^{-5}$ ($R = 10^{-10}$ beside $Q = -1$) left the
    SDP's margin below Clarabel's tolerance, and `certify_ren` undecided on RENs whose
    trainer's pair passes the check."""
    yield G, qsr
    found = _io_scale(qsr)
    if found is None:
        return
    t_y, t_u, rate = found
    cols = np.concatenate([np.ones(q), np.full(qsr.n_in, t_u)])
    rows = np.concatenate([np.ones(q), np.full(qsr.n_out, 1.0 / t_y)])
    yield LTIController(G.A, G.B * cols, G.C * rows[:, None],
                        G.D * rows[:, None] * cols), rate


# The optimum t* below which an SDP solved to optimality disproves the certificate (the
# solver's own tolerances are ~1e-8 relative).
_DISPROOF = 1e-6


def certify_ren(K: RENController, qsr: QSR, *, P=None, multiplier=None,
                tol: float = VERIFY_RTOL, progress: bool = True) -> RENCertificate:
    """Certify $(Q,S,R)$-dissipativity of a REN controller with a storage and a sector
    multiplier (S-procedure).

    $$M(P,\\Lambda) = \\begin{bmatrix}A&B_1&B_2\\end{bmatrix}^\\top P
    \\begin{bmatrix}A&B_1&B_2\\end{bmatrix} - \\operatorname{diag}(P,0,0)
    - (\\text{supply}) + (\\text{sector}) \\prec 0,\\quad P\\succ0,\\ \\Lambda\\succ0$$

    where $\\xi^\\top M\\xi = V(x^+) - V(x) - s(\\hat u,\\hat y) + 2w^\\top\\Lambda(v-w)$
    for all $\\xi = (x,w,\\hat u)$ (`ren_lmi`). Since
    $w_i = \\sigma(v_i)$ with $\\sigma$ slope-restricted in $[0,1]$ and $\\sigma(0)=0$ gives
    $w_i(v_i - w_i)\\ge0$, it implies $V(x_{k+1}) - V(x_k)\\le s(\\hat u_k,\\hat y_k)$ along
    every trajectory: the REN is $(Q,S,R)$-dissipative with storage $V$. $M$ is linear in
    $(P,\\Lambda)$.

    Without `P` and `multiplier`, solves $\\max t$ s.t. $M\\preceq-tI$, $P\\succeq tI$,
    $\\Lambda\\succeq tI$, $t\\le1$ (cvxpy with Clarabel), in balanced coordinates of the
    states and neurons, and, for a rate whose $Q$ and $R$ differ in size by more than
    $2^{12}$ (a gain bound of $10^{-5}$: $R = 10^{-10}$), also with the input and output in
    units that balance them, as [`certify`][dissil_jax.certify] does; the verdict is always
    the float64 eigenvalue check of the returned pair in the units given, independent of
    the solver. With both given, only the eigenvalue check runs.

    **Cost.** The check of a given pair takes milliseconds at any size; the SDP grows
    steeply with the order $n$ and width $q$. Measured for one REN with 2 inputs and outputs
    (Clarabel, BLAS single-threaded, a shared 2-core machine): about 1 s at $(n, q)$ =
    (16, 16), 3 s at (32, 16), 3 min at (64, 4), 6 min at (48, 16), and more than 15 min at
    (64, 16). A trained REN comes with its pair (`res.P`, `res.multiplier`): check that
    instead where an independent solve is not the point.

    **Arguments:** the controller `K` (leading batch axes allowed), the supply rate `qsr`,
    optionally `P` (`[*batch, n, n]`) and `multiplier` (the diagonal of $\\Lambda$,
    `[*batch, q]`), the relative round-off allowance `tol`, and `progress` (default True:
    when the SDPs take more than 10 s, a line on standard error every 10 s says so).

    **Returns:** a [`RENCertificate`][dissil_jax.RENCertificate].
    """
    _check_args(K, qsr)
    tol = check_tolerance("tol", tol)
    if (P is None) != (multiplier is None):
        raise ValueError("pass both `P` and `multiplier` (an eigenvalue check of a given "
                         "certificate) or neither (solve for one).")
    batch, n, q = K.batch_shape, K.n_state, K.width
    G = augmented_lti(K)
    if P is not None:
        # shape, finiteness and symmetry as in `dj.certify`
        P = np.broadcast_to(storage_arg("P", P, batch, n), batch + (n, n))
        lam = real_array("multiplier", multiplier)  # the diagonal of Lambda
        if not np.all(np.isfinite(lam)):
            raise ValueError("`multiplier` contains NaN or inf.")
        if lam.shape not in ((q,), batch + (q,)):
            raise ValueError(f"`multiplier` must be {batch + (q,)} (the diagonal of Lambda), "
                             f"got {lam.shape}.")
        lam = np.broadcast_to(lam, batch + (q,))
    status = np.full(batch, "given", dtype=object)
    progress = check_flag("progress", progress)
    if P is None:  # one SDP per controller
        P, lam = np.full(batch + (n, n), np.nan), np.full(batch + (q,), np.nan)
        what = (f"solving {math.prod(batch)} SDPs" if batch else "solving the SDP") + \
            f" for a storage of order {n} and {q} multipliers"
        with working("certify_ren", what, progress):
            for idx in np.ndindex(*batch):
                Gi = LTIController(*(M[idx] for M in (G.A, G.B, G.C, G.D)))
                # the coordinates of `units.COORDINATES` until a pair passes the check;
                # else the first pair found (and its status), else the first failure's
                tried, found, proved = [], [], False
                for (Gu, rate), states_first in itertools.product(_io_units(Gi, qsr, q),
                                                                  COORDINATES):
                    d, ts = coordinates(Gu, q, states_first)
                    if any(r is rate and np.array_equal(d, e) and np.array_equal(ts, f)
                           for r, e, f in tried):
                        continue
                    tried.append((rate, d, ts))
                    found.append(_solve(Gu, rate, q, d, ts))
                    Pi, li, _ = found[-1]
                    # the verdict is on the controller and the rate as given
                    proved = Pi is not None and bool(_margin_and_holds(Gi, qsr, Pi, li, tol)[1])
                    if proved:
                        break
                Pi, li, status[idx] = found[-1] if proved else next(
                    (f for f in found if f[0] is not None), found[0])
                if Pi is not None:
                    P[idx], lam[idx] = Pi, li
    Ps, lams = np.array(P, np.float64), np.array(lam, np.float64)
    margin, holds = _margin_and_holds(G, qsr, Ps, lams, tol)  # one batched check
    if not batch:
        return RENCertificate(bool(holds), Ps, lams, float(margin), str(status[()]))
    return RENCertificate(holds, Ps, lams, margin, status.astype(str))


def certified_batch(K: RENController, qsr: QSR, P, multiplier) -> np.ndarray:
    """The eigenvalue check of a batch of `(K, P, Λ)` as a bool array (the trainers' end
    check)."""
    return np.asarray(certify_ren(K, qsr, P=P, multiplier=multiplier).holds, bool)
