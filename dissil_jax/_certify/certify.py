"""Exact dissipativity certificates (paper Lemma 2) on the host: cheap candidates, then an SDP."""

from __future__ import annotations

import math

import equinox as eqx
import numpy as np

from .. import _outcome
from .._controller import LTIController
from .._outcome import Outcome
from .._progress import working
from .._rate_scale import balanced_blocks
from .._sdp.lmi import VERIFY_RTOL, kyp_bound_holds, kyp_margin, kyp_matrix, kyp_scale
from .._supply import QSR
from .._validate import check_flag, check_tolerance
from . import coordinates as _coordinates, fast as _certify_fast, sdp as _certify_sdp
from .args import controller_arrays, storage_arg
from .coordinates import (
    balanced_states,
    check_storage_range,
    state_scale,
    unbalanced_storage,
)


class Certificate(eqx.Module):
    """The outcome of [`certify`][dissil_jax.certify].

    - `result`: the [`Outcome`][dissil_jax.Outcome]: `solved` iff `P` is positive definite
      and the KYP matrix at `P` is negative definite beyond float64 round-off (an
      eigenvalue check, independent of the solver); `not_certified` when that check fails,
      `infeasible` or `solver_failed` when the SDP found no storage.
    - `holds` (read-only): `result == Outcome.solved`, as a `bool` (a bool array when
      batched).
    - `P`: the storage matrix ($V(x) = x^\\top P x$), float64; all NaN when no storage
      was found (`infeasible` or `solver_failed`), so that batched fields stack.
    - `margin`: $\\min(-\\lambda_{\\max}(\\mathrm{KYP}(P)), \\lambda_{\\min}(P))$ in the
      given coordinates. Negative when no certificate was found, but also, by round-off
      (e.g. -1e-10), for some certified controllers with badly scaled states: `holds` then
      rests on the componentwise bound of the diagonally scaled KYP matrix. Filter on
      `holds`, not on the sign of `margin`.
    - `source`: where `P` came from: `"given"` (supplied), `"hint"`, `"cached"` (a recent
      projection's), `"riccati"`, `"static"` (a controller without state, $\\hat n = 0$:
      `P` is 0x0), or the SDP solver's status (`"optimal"`, ..., prefixed `"rebalanced: "`
      when solved in states balanced by an approximate storage); or, with
      `result` `infeasible` and `P` all NaN, the cheap disproof that skipped the SDP
      (`"disproved: ..."`); see
      [`certify`][dissil_jax.certify]. (Called `status` before; that name remains a
      read-only alias.)

    For one controller `P` is an $\\hat n\\times\\hat n$ array, `margin` a `float` and
    `source` a `str`; `message` (a property) says what `result` means and what to do.
    For a controller with leading batch axes `batch` every field has
    those axes in front: `result` (shape `batch`), `P` (`[*batch, n, n]`), `margin`
    (float64) and `source` (a numpy string array); member `i` is the certificate `certify`
    returns for the `i`-th controller.
    """

    result: Outcome
    P: np.ndarray
    margin: float | np.ndarray
    source: str | np.ndarray = "given"

    @property
    def holds(self) -> bool | np.ndarray:
        """`result == Outcome.solved`: a `bool`, or a boolean array when batched."""
        ok = np.asarray(self.result == Outcome.solved)
        return bool(ok) if ok.ndim == 0 else ok

    def result_names(self) -> str | list:
        """`result` decoded into `Outcome` names: a `str`, nested lists when batched."""
        return _outcome.names(self.result)

    @property
    def status(self) -> str | np.ndarray:
        """The former name of `source`."""
        return self.source

    @property
    def message(self) -> str | list:
        """What `result` means for `certify` (and what to do about it), as a sentence; a
        nested list of them when batched. The `Outcome` item's own sentence also serves the
        projection and the trainers, whose arguments (`eps`, `P_ref`) `certify` lacks."""
        codes = np.asarray(_outcome.codes(self.result))
        sources = np.broadcast_to(np.asarray(self.source, dtype=object), codes.shape)
        vtext = np.vectorize(_message, otypes=[object])
        return _message(codes, self.source) if codes.ndim == 0 else vtext(codes,
                                                                          sources).tolist()


_DISPROOF = "disproved: "


def _message(code, source) -> str:
    """The sentence of `Certificate.message` for one controller."""
    if str(source) == _NON_FINITE_SOURCE:
        return ("the controller, or the storage given for it, has NaN or inf entries (a "
                "sweep's lane that ended `non_finite`, say): nothing to certify")
    if str(source).startswith(_DISPROOF):
        return ("no storage exists: a necessary condition for dissipativity fails ("
                f"{str(source)[len(_DISPROOF):]}), so the controller is not strictly "
                "dissipative for `qsr`; the SDP was skipped and `P` is NaN. `dj.project` "
                "finds the nearest controller that is")
    if _outcome.NAMES[int(code)] == "not_certified" and str(source) in _INACCURATE:
        return (f"undecided: the SDP solver stopped at `{source}` and found no storage that "
                "passes the exact float64 KYP check (nor in states balanced by an "
                "approximate storage, where one was found). That does not show that none "
                "exists: the controller may well be dissipative. Pass a storage known to "
                "prove it as `P` or `hint` (a trainer's `res.P[i]`, a projection's), or "
                "certify a better conditioned realisation (a change of state coordinates)")
    return _outcome.message(_outcome.NAMES[int(code)], caller="certify")


#: SDP statuses whose storage is only approximate: a failed check then decides nothing.
_INACCURATE = ("optimal_inaccurate", "max_iterations")


def _outcome_of_sdp(status: str) -> Outcome:
    """The SDP's status string as an `Outcome` (no storage was found)."""
    return getattr(Outcome, "infeasible" if status.startswith("infeasible") else "solver_failed")


def certify(K: LTIController, qsr: QSR, *, P=None, rtol: float = VERIFY_RTOL, hint=None,
            max_margin: bool = False, progress: bool = True) -> Certificate:
    """Certify $(Q,S,R)$-dissipativity of `K` by the discrete KYP lemma (paper Lemma 2).

    A storage $P$ proves the certificate when an eigenvalue computation finds $P\\succ0$ and
    $\\mathrm{KYP}(P)\\prec0$ beyond round-off: the re-checked margin
    $\\min(-\\lambda_{\\max}(\\mathrm{KYP}(P)), \\lambda_{\\min}(P))$ must exceed `rtol`
    times a bound on the size of the KYP terms, so nearly lossless systems with margins of
    order $10^{-7}$ are still decided correctly; at the default `rtol`, a realisation far
    from balanced (a storage with eigenvalues $10^1$ and $10^7$, say), whose terms' size
    swamps its margin, is also proved by componentwise round-off bounds
    (`internal.kyp_bound_holds`). The storage is found by, in order, until
    one proves it:

    1. `hint`, if given (`source` `"hint"`);
    2. the storage of a recent [`project`][dissil_jax.project] that returned exactly this
       controller (`"cached"`);
    3. a Riccati storage: the stabilising solution of the discrete Riccati equation of the
       KYP inequality tightened by $\\delta$, for a few decreasing $\\delta$ (`"riccati"`;
       $O(\\hat n^3)$, milliseconds at $\\hat n = 64$);
    4. the maximum-margin SDP, solved in float64 by Clarabel (independently of the
       projection code),

    $$\\max_{P,\\,t}\\ t \\quad\\text{s.t.}\\quad \\mathrm{KYP}(P) \\preceq -tI,\\quad P\\succeq tI,
    \\quad t\\le 1$$

    (`source` is the solver's: `"optimal"`, `"optimal_inaccurate"`, `"infeasible"`, ...).
    Margins are absolute; $t\\le1$ normalises the certificate (the LMI is not homogeneous in
    $P$ because of the fixed $Q,S,R$). Steps 1-3 skip the SDP but return a storage with a
    smaller margin; `max_margin=True` always solves the SDP. Steps 3 and 4 run on the
    realisation with its states rescaled by powers of two (`state_scale`: each state's
    effect and what drives it of one size) and map the storage back exactly. When step 4's
    storage fails the check (and the SDP did not prove infeasibility), the SDP is solved
    again in states in which the best approximate storage found is the identity, a
    non-diagonal similarity (`source` `"rebalanced: optimal"`, ...); its storage, mapped
    back, is checked in the given coordinates. The verdict is always on the controller as
    given.

    Before step 4 (its stability part before step 1), a cheap disproof is tried: every certified controller has
    $\\Phi(z) = G^HQG + G^HS + S^\\top G + R\\succ0$ on the unit circle and at $z=\\infty$
    ($G$ its transfer function; the storage terms cancel along
    $x = (zI-A)^{-1}Bu$), and a Schur-stable $A$ when $Q\\preceq0$. A violation far beyond
    round-off (on a grid of 257 frequencies) returns `infeasible` at once, with `P` all
    NaN and `source` starting `"disproved: "` and saying which (as does `message`); the
    SDP, which costs seconds from $\\hat n\\approx 24$ on and minutes at $\\hat n = 48$
    for a controller that is not dissipative, is then skipped. A controller that is not dissipative but passes these
    necessary conditions still goes to the SDP.

    A controller with leading batch axes is certified member by member; with `P` given the
    eigenvalue check is vectorised over the batch.

    **Static controllers** ($\\hat n = 0$, $\\hat y = D\\hat u$) have no storage: `P` is
    0x0 and the KYP matrix is its input block alone, $-\\Phi(D)$ with
    $\\Phi(D) = R + S^\\top D + D^\\top S + D^\\top QD$, so the certificate holds iff
    $\\Phi(D)\\succ0$ beyond round-off (`source` `"static"`); otherwise `result` is
    `infeasible` (no storage can help). No SDP is solved.

    **Arguments:**

    - `K`: an `LTIController`, possibly with leading batch axes.
    - `qsr`: the supply rate; `qsr.S` must be `K.n_out x K.n_in`.
    - `P`: optional storage matrix to check instead of searching: `[n, n]` (the
      same for every member) or `[*K.batch_shape, n, n]`, symmetric up to round-off
      (a relative asymmetry above 1e-5 raises a ValueError); `source` is `"given"`.
    - `rtol`: relative round-off allowance of the final eigenvalue check (called `tol`
      before). Above the default it asks for more margin than round-off, and only the
      relative test decides.
    - `hint`: optional storage to try first, shaped like `P`.
    - `max_margin`: skip steps 1-3 and return the maximum-margin storage.
    - `progress`: when the search takes more than 10 s (an SDP at a high order: about
      11 minutes at $\\hat n = 64$), a line on standard error every 10 s says so (default
      True).

    **Returns:** a [`Certificate`][dissil_jax.Certificate]; batched like `K`.

    ```python
    cert = dj.certify(Ks, qsr)   # Ks.batch_shape == (8,)
    cert.holds.shape, cert.P.shape, cert.source[0]   # (8,), (8, n, n), 'riccati'
    ```
    """
    A, B, C, D = controller_arrays(K, qsr)
    batch, n = K.batch_shape, K.n_state
    tol = check_tolerance("rtol", rtol)
    max_margin = check_flag("max_margin", max_margin)
    progress = check_flag("progress", progress)
    bad = ~np.all([np.all(np.isfinite(M), axis=(-2, -1)) for M in (A, B, C, D)], axis=0)
    if not batch and bad:
        raise ValueError("`K` contains NaN or inf: no certificate can hold for it (a batch's "
                         "non-finite members, such as a sweep's `non_finite` lanes, are "
                         "judged `non_finite` one by one).")
    if P is not None:
        P = storage_arg("P", P, batch, n, members=True)
        bad = bad | ~np.all(np.isfinite(P), axis=(-2, -1))
        if np.any(bad):  # judged on placeholders, then marked
            A, B, C, D = (np.where(bad[..., None, None], 0.0, M) for M in (A, B, C, D))
            P = np.where(bad[..., None, None], np.eye(n), P)
        return _non_finite(_verdict(A, B, C, D, qsr, P, tol, "given"), bad)
    if hint is not None:
        hint = storage_arg("hint", hint, batch, n)
    what = (f"searching a storage for {math.prod(batch)} controllers" if batch else
            "searching a storage for a controller") + f" of order {n}"
    with working("certify", what, progress):
        if not batch:
            return _search(A, B, C, D, qsr, tol, hint, max_margin)
        certs = [_search(A[i], B[i], C[i], D[i], qsr, tol,
                         None if hint is None else hint[i], max_margin)
                 if not bad[i] else _non_finite_member(n) for i in np.ndindex(*batch)]
    stack = lambda name, dtype: np.array([getattr(c, name) for c in certs], dtype).reshape(
        batch + ((n, n) if name == "P" else ()))
    codes = np.array([_outcome.codes(c.result) for c in certs], np.int32).reshape(batch)
    return Certificate(_outcome.item(codes), stack("P", np.float64),
                       stack("margin", np.float64), stack("source", str))


#: `source` of a batch member with NaN or inf entries (in `K`, or in a given `P`).
_NON_FINITE_SOURCE = "non-finite"


def _non_finite_member(n: int) -> Certificate:
    return Certificate(Outcome.non_finite, np.full((n, n), np.nan), -np.inf,
                       _NON_FINITE_SOURCE)


def _non_finite(cert: Certificate, bad) -> Certificate:
    """`cert` with the members `bad` marked `non_finite` (P NaN, margin -inf)."""
    if not np.any(bad):
        return cert
    codes = np.where(bad, _outcome.code("non_finite"), _outcome.codes(cert.result))
    return Certificate(_outcome.item(codes), np.where(bad[..., None, None], np.nan, cert.P),
                       np.where(bad, -np.inf, cert.margin),
                       np.where(bad, _NON_FINITE_SOURCE, cert.source))


def _candidates(A, B, C, D, qsr, hint, t):
    """Cheap storages to check before the SDP, with their `status` (`fast.py`); the
    Riccati storages are found in the balanced units `t` (`state_scale`)."""
    if hint is not None:
        yield hint, "hint"
    P = _certify_fast.cached(A, B, C, D, qsr)
    if P is not None:
        yield P, "cached"
    for P in _certify_fast.riccati(*balanced_states(A, B, C, t), D, qsr):
        yield unbalanced_storage(P, t), "riccati"


#: Blocks of the supply rate whose sizes differ by more than 2**12 are also searched with
#: the controller's input and output in balanced units (`_io_scale`).
_IO_BAND = 12


def _io_scale(qsr: QSR) -> tuple[float, float, QSR] | None:
    """`balanced_blocks(qsr)` when the sizes of $Q$ and $R$ differ by more than $2^{12}$;
    else None."""
    t_y, t_u, balanced = balanced_blocks(qsr)
    return (t_y, t_u, balanced) if abs(np.log2(t_y / t_u)) > _IO_BAND / 2 else None


def _search(A, B, C, D, qsr: QSR, tol, hint, max_margin) -> Certificate:
    """One (unbatched) controller: `_search_units`, and when that finds no certificate for
    a rate whose $Q$ and $R$ blocks differ in size by more than $2^{12}$, the same search
    with the controller's output and input in units $\\hat y = t_y\\tilde y$,
    $\\hat u = t_u\\tilde u$ that balance them, $(A, Bt_u, C/t_y, Dt_u/t_y)$ against
    $(t_y^2Q, t_yt_uS, t_u^2R)$: the same dissipation inequality with the same storage.

    A controller with gain $1.25\\cdot10^{6}$ against a gain bound 1 % above it ($Q = -1$,
    $R\\approx1.6\\cdot10^{12}$) was refused (`not_certified`, `solver_failed` from
    $10^7$): the KYP matrix's terms of size $10^{12}$ swamped margins of size 1. Its storage,
    found in balanced units, passes the check in the given ones. The verdict is always on
    the controller as given.

    When both fail (and the SDP did not prove infeasibility), the SDP is re-solved in states
    balanced by the best approximate storage (`coordinates.py`: a non-diagonal similarity,
    which `state_scale` cannot give), and the storage mapped back is checked in the given
    coordinates."""
    cert = _search_units(A, B, C, D, qsr, tol, hint, max_margin)
    if cert.holds or str(cert.source).startswith("disproved"):
        return cert
    io, found = _io_scale(qsr), [cert.P]
    units = [(A, B, C, D, qsr)]
    if io is not None:
        t_y, t_u, balanced = io
        units.append((A, B * t_u, C / t_y, D * (t_u / t_y), balanced))
        other = _search_units(*units[1], tol, None, max_margin)
        if np.all(np.isfinite(other.P)):
            retry = _verdict(A, B, C, D, qsr, other.P, tol, other.source)
            if retry.holds:
                return retry
            found.append(other.P)
    if A.shape[0] == 0 or cert.source == "infeasible":  # static, or a proof of infeasibility
        return cert
    units = [(*u, state_scale(*u[:3])) for u in units]

    def check(P, source):
        return _verdict(A, B, C, D, qsr, P, tol, source)

    return _coordinates.search(A, B, C, D, qsr, found, io, units, check) or cert


def _search_units(A, B, C, D, qsr: QSR, tol, hint, max_margin) -> Certificate:
    """One (unbatched) controller in the given input and output units: the first candidate
    that proves it, else the SDP."""
    n = A.shape[0]
    if n == 0:
        return _static(A, B, C, D, qsr, tol)
    t = state_scale(A, B, C)
    check_storage_range(t)
    reason = _certify_fast.unstable(A, qsr)
    if not max_margin and reason is None:
        for P, status in _candidates(A, B, C, D, qsr, hint, t):
            cert = _verdict(A, B, C, D, qsr, P, tol, status)
            if cert.holds:
                return cert
    reason = reason or _certify_fast.disproof(A, B, C, D, qsr)
    if reason is not None:
        return Certificate(Outcome.infeasible, np.full((n, n), np.nan), -np.inf, reason)
    return _solve(A, B, C, D, qsr, tol, t)


def _solve(A, B, C, D, qsr: QSR, tol, t) -> Certificate:
    """The KYP SDP for one (unbatched) controller, solved in the balanced units `t`, then
    the eigenvalue verdict in the controller's own."""
    n = A.shape[0]
    try:
        P, status = _certify_sdp.solve(*balanced_states(A, B, C, t), D, qsr)
        P = None if P is None else unbalanced_storage(P, t)
    except Exception as e:  # pragma: no cover - depends on solver internals
        return Certificate(Outcome.solver_failed, np.full((n, n), np.nan), -np.inf,
                           f"solver error: {e}")
    if P is None:
        return Certificate(_outcome_of_sdp(status), np.full((n, n), np.nan), -np.inf, status)
    return _verdict(A, B, C, D, qsr, P, tol, status)


def _static(A, B, C, D, qsr: QSR, tol) -> Certificate:
    """A static controller ($\\hat n = 0$): no storage to search, so the check at the 0x0
    $P$ decides. The KYP matrix is then its input block alone, $-\\Phi(D)$ with
    $\\Phi(D) = R + S^\\top D + D^\\top S + D^\\top QD$ (see `kyp_matrix`): certified iff
    $\\Phi(D)\\succ0$ beyond round-off, and otherwise no storage exists (`infeasible`)."""
    cert = _verdict(A, B, C, D, qsr, np.zeros((0, 0)), tol, "static")
    if cert.holds:
        return cert
    return Certificate(Outcome.infeasible, cert.P, cert.margin,
                       "static: the controller has no state and Phi(D) = R + S'D + D'S + "
                       "D'QD is not positive definite beyond round-off")


def _margin(A, B, C, D, qsr, P):
    """`kyp_margin`, also for $\\hat n = 0$: the empty $P\\succ0$ holds vacuously, so the
    margin is $-\\lambda_{\\max}$ of the KYP matrix alone."""
    if np.shape(P)[-1] == 0:
        return -np.linalg.eigvalsh(kyp_matrix(A, B, C, D, qsr, P))[..., -1]
    return kyp_margin(A, B, C, D, qsr, P)


def _verdict(A, B, C, D, qsr, P, tol, status) -> Certificate:
    """The eigenvalue check, vectorised over leading batch axes (scalars when unbatched)."""
    margin = _margin(A, B, C, D, qsr, P)
    holds = margin > tol * kyp_scale(A, B, C, D, qsr, P)
    if tol <= VERIFY_RTOL and not np.all(holds):
        # an unbalanced realisation: componentwise round-off bounds (a larger `rtol` asks
        # for more margin than round-off, which only the relative test measures)
        holds = holds | kyp_bound_holds(A, B, C, D, qsr.Q, qsr.S, qsr.R, P)
    codes = np.where(holds, _outcome.code("solved"), _outcome.code("not_certified"))
    if np.ndim(margin) == 0:
        return Certificate(_outcome.item(codes), P, float(margin), status)
    return Certificate(_outcome.item(codes), np.array(P), np.asarray(margin, np.float64),
                       np.full(np.shape(margin), status))


__all__ = ["Certificate", "certify", "kyp_matrix"]
