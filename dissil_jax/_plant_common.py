"""What the plant supply-rate tools share: reading a plant, solving an SDP, error hints."""

from __future__ import annotations

import numpy as np

from ._sdp.sdp import single_threaded_blas
from ._validate import check_abcd

_SOLVER_OPTS = dict(tol_gap_abs=1e-9, tol_gap_rel=1e-9, tol_feas=1e-9, max_iter=400)


def abcd(plant, what: str = "plant"):
    """`(A, B, C, D)` (float64, 2-d) from a plant/controller module, StateSpace or 4-tuple."""
    if isinstance(plant, (tuple, list)):
        if len(plant) != 4:
            raise ValueError(f"`{what}` as a tuple must be (A, B, C, D), got {len(plant)} items.")
        mats = plant
    elif all(hasattr(plant, k) for k in "ABCD"):
        mats = (plant.A, plant.B, plant.C, plant.D)
    else:
        raise ValueError(f"`{what}` must have matrices A, B, C, D (e.g. `dj.LinearPlant`), "
                         f"got {type(plant).__name__}.")
    out = []
    for name, M in zip("ABCD", mats):
        M = np.asarray(M, np.float64)
        if M.ndim == 0:
            M = M.reshape(1, 1)
        if M.ndim != 2:
            raise ValueError(f"`{what}.{name}` must be a matrix (one plant, no batch axis), "
                             f"got shape {M.shape}.")
        if not np.all(np.isfinite(M)):
            raise ValueError(f"`{what}.{name}` contains NaN or inf.")
        out.append(M)
    A, B, C, D = out
    check_abcd(A, B, C, D, what=f"{what}.")
    if getattr(plant, "dt", None) == 0:
        raise ValueError(f"`{what}` is a continuous-time system; discretise it first.")
    return A, B, C, D


def with_state(A, B, C, D):
    """A static plant ($n = 0$, $y = Du$) with one decoupled, unobservable state
    $x^+ = 0$ added: the same operator $u\\mapsto y$, but cvxpy cannot build the SDPs with
    a 0x0 storage."""
    if A.shape[0]:
        return A, B, C, D
    return np.zeros((1, 1)), np.zeros((1, B.shape[1])), np.zeros((C.shape[0], 1)), D


def solve(prob, what: str, A) -> None:
    """Solve `prob` (the `what` SDP of a plant with matrix `A`); a `ValueError` otherwise."""
    import warnings

    import cvxpy as cp

    with single_threaded_blas(), warnings.catch_warnings():
        # An inaccurate solution is checked by `certify` afterwards (`_backed_off`).
        warnings.filterwarnings("ignore", message="Solution may be inaccurate",
                                category=UserWarning)
        try:
            prob.solve(solver=cp.CLARABEL, **_SOLVER_OPTS)
            status = prob.status
        except cp.SolverError as err:  # an unbounded or infeasible problem can end so
            status = f"failed ({err})"
    if status not in ("optimal", "optimal_inaccurate"):
        ended = "failed" if status.startswith("failed") else f"is {status}"
        raise SolverFailure(f"the {what} SDP {ended} in Clarabel. {hint(what, A)}")


class SolverFailure(ValueError):
    """A plant SDP, or the strict certificate of its result, failed (`solve`,
    `_plant_qsr._backed_off`): for a stable plant, worth one more try in a balanced
    realisation (`balanced_realisation`)."""


def balanced_realisation(A, B, C, D):
    """The balanced realisation $(T^{-1}AT, T^{-1}B, CT, D)$ of a stable, minimal plant
    (controllability and observability Gramians both equal to the diagonal of its Hankel
    singular values; the square-root method), or None when there is none (unstable, or not
    minimal to working precision).

    A supply rate is a property of the plant's input-output map, so it can be computed on
    any realisation. A lightly damped plant sampled fast and written in companion form
    (`control.tf2ss`, then `control.c2d`: two modes with damping 0.02 at 100 samples a
    second) has states of very different sizes along non-diagonal directions, and
    Clarabel failed on its cone SDP; the balanced realisation of the same plant solved."""
    import scipy.linalg as sla

    if A.shape[0] == 0 or radius(A) >= 1:
        return None
    try:
        Wc = sla.solve_discrete_lyapunov(A, B @ B.T)
        Wo = sla.solve_discrete_lyapunov(A.T, C.T @ C)
        Lc = np.linalg.cholesky((Wc + Wc.T) / 2)
        Lo = np.linalg.cholesky((Wo + Wo.T) / 2)
        U, hsv, Vt = np.linalg.svd(Lo.T @ Lc)
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not (np.all(np.isfinite(hsv)) and hsv[-1] > 1e-12 * hsv[0]):
        return None
    root = hsv ** -0.5
    T = Lc @ Vt.T * root[None, :]
    Ti = root[:, None] * U.T @ Lo.T
    return Ti @ A @ T, Ti @ B, C @ T, D


def value(x) -> np.ndarray:
    """The value of a cvxpy variable or expression after `solve` (which raises unless the
    problem was solved, so the value is set)."""
    value = x.value
    assert value is not None
    return np.asarray(value)


def radius(A) -> float:
    """The spectral radius of `A` (0 without state)."""
    return float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0


def hint(what: str, A) -> str:
    """Why the `what` SDP or its certificate may fail for a plant with matrix `A`."""
    if what == "Lemma 8":
        return ("The plant may admit no such supply rate: Lemma 8 needs a storage with "
                "2(A'PA + alpha^2 tau I) < P, so the linear part must contract strongly "
                "(||A||^2 + alpha^2 < 1/2 suffices): check `A` and `alpha`, or describe the "
                "plant by another supply rate.")
    rad = radius(A)
    if rad >= 1 and "output" in what:
        return (f"The plant `A` is not stable (spectral radius {rad:.4g} >= 1): an unstable "
                "plant can only have a negative output passivity index, through its "
                "feedthrough `D` (a strictly proper one has none), and the SDP found none; "
                "check that the plant is discrete-time, or stabilise it first.")
    if rad >= 1:
        return (f"The plant `A` is not stable (spectral radius {rad:.4g} >= 1): a storage "
                f"of this rate must decrease along the plant's free motion, so a strict "
                f"certificate of a {what} needs a stable plant (a marginally stable one has "
                "at most a lossless storage); stabilise it first, and check that it is "
                "discrete-time.")
    if what == "cone":
        return (f"The plant `A` is stable (spectral radius {rad:.4g} < 1), so a cone "
                "exists and the solver failed on the numbers, in the realisation given and "
                "in its balanced realisation (if it has one: a non-minimal plant has none). "
                "Remove the plant's uncontrollable or unobservable modes "
                "(`control.minreal`), or scale its input and output.")
    return (f"The plant `A` is stable (spectral radius {rad:.4g} < 1), so the plant "
            f"itself has no such {what}: it is not passive enough (e.g. a strictly proper "
            "plant that is not passive has no output passivity index); `dj.lti_cone_qsr` "
            "describes any stable plant.")


def sym(M):
    return (M + M.T) / 2
