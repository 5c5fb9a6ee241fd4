"""How a computation ended: the [`Outcome`][dissil_jax.Outcome] enumeration and its codes.

A leaf module (it imports nothing from the package). Host code (Clarabel callbacks, numpy
loops) and jitted loops carry outcomes as int32 *codes*, this module's own numbering
`code(name)`; results carry `Outcome` items. The two meet only here, through equinox's
public enumeration interface: items are built with `Outcome.where` and read back with `==`,
so nothing depends on how equinox stores an item.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class Outcome(eqx.Enumeration):
    """How a projection, a certificate, an SDP step or a training run ended.

    Every result type has it in its `result` field. Projections report `solved`,
    `unchanged`, `skipped` or one of the three failures (`infeasible`, `solver_failed`,
    `not_certified`); trainers report why each run stopped: `converged`, `max_steps`,
    `stalled` (ICO found no further certified step), `non_finite`, or the failure that
    ended it; certificates report `solved` when the
    certificate holds. A failure never comes with an uncertified controller: the
    projection returns its (flagged) target, the certified trainers their best certified iterate.
    """

    converged = "converged: |ΔJ| < atol + rtol |J_0|"
    max_steps = "stopped at max_steps"
    non_finite = (
        "the loss became NaN or infinite: the steps were too large for this problem, or "
        "float32 arithmetic did not suffice for it; pass a smaller "
        "`learning_rate` (or an `optimizer` with a bounded step, such as `optax.adam`) or a "
        "smaller `init_scale`, or, if the data are float32, train in float64 "
        "(`jax.config.update(\"jax_enable_x64\", True)` and float64 windows)"
    )
    solver_failed = (
        "Clarabel failed to solve the SDP (max iterations or numerical trouble), usually for "
        "a target far outside the dissipative set (entries of 1e5 and more); to a trainer "
        "pass a smaller `init_scale` or step, or a larger `eps`; a single `project` call "
        "with Q <= 0 solves such targets with `method=\"first_order\"` (ADMM, the same "
        "float64 check) (`certify`: see `Certificate.message`)"
    )
    loss_increased = "ICO's float64 re-evaluation found the loss increased; the step was refused"
    not_certified = (
        "the exact float64 KYP check failed. In a projection or a certified trainer the "
        "solver's point failed it even after the safeguards (an enlarged margin in a "
        "projection, shorter steps in ICO; no controller is returned without a "
        "certificate): pass a larger `eps` (`margin` in `fit_direct` and `fit_ren`). In "
        "`certify` (which has no `eps`) the storage P does not prove the certificate beyond "
        "round-off: see `Certificate.message`"
    )
    solved = "solved and verified by the exact float64 check"
    unchanged = "the target was already certified by P_ref and is returned as is"
    skipped = "inactive (e.g. a converged trainer lane); returned as is"
    infeasible = (
        "the SDP is infeasible: in a projection or a trainer, `qsr` admits no strictly "
        "dissipative controller of these sizes near the reference P with the LMI margin "
        "`eps`. Check the supply rate (e.g. R and S signs), pass a different `P_ref`, or a "
        "smaller `eps` when the rate's terms are small (a gain bound of 1e-4 has R = 1e-8, "
        "below the default eps = 1e-6), or express the signals in units where Q, S and R "
        "are of similar size. In `certify`: no storage exists, the controller is not "
        "strictly dissipative for `qsr` (`source` says whether the SDP or a cheap necessary "
        "condition, 'disproved: ...', decided)."
    )
    stalled = (
        "no further certified step: ICO's step failed the exact float64 check even when "
        "shortened, and the run stopped at its last certified iterate (near the edge of the "
        "dissipative set, or in float32, where rounding the step can take it out); a "
        "larger `eps` leaves more room"
    )
    no_multiplier = (
        "no multiplier alpha > 0 makes the matrix of the QSR stability theorem (paper "
        "Theorem 1) negative definite: the loop is not certified"
    )


#: The item names in code order: `NAMES[code(name)] == name`.
NAMES: tuple[str, ...] = (
    "converged", "max_steps", "non_finite", "solver_failed", "loss_increased",
    "not_certified", "solved", "unchanged", "skipped", "infeasible", "no_multiplier",
    "stalled")
if len(Outcome) != len(NAMES) or not all(isinstance(getattr(Outcome, n), Outcome) for n in NAMES):
    raise ImportError("`_outcome.NAMES` must list every `Outcome` item once.")
_ITEMS = tuple(getattr(Outcome, n) for n in NAMES)
_FAILURES = ("infeasible", "solver_failed", "not_certified")
#: The trainers' normal ends; anything else is a failure for `throw=True`.
FINE = ("converged", "max_steps", "stalled")


def code(name: str) -> int:
    """The int32 code of the `Outcome` item called `name`."""
    return NAMES.index(name)


def item(codes) -> Outcome:
    """Integer codes (any shape, numpy or JAX, traced or not) as an `Outcome` item."""
    codes = jnp.asarray(codes, jnp.int32)

    def one(c):
        out = _ITEMS[0]
        for i in range(1, len(_ITEMS)):
            out = Outcome.where(c == i, _ITEMS[i], out)
        return out

    for _ in range(codes.ndim):  # `Outcome.where` takes a scalar predicate
        one = jax.vmap(one)
    return one(codes)


def codes(outcome):
    """The integer codes of an `Outcome` item (batched like it); integer input passes through.

    A JAX array when `outcome` is an item, so it may be traced.
    """
    if not isinstance(outcome, Outcome):
        return outcome
    out = jnp.zeros(jnp.shape(outcome == _ITEMS[0]), jnp.int32)
    for i, it in enumerate(_ITEMS):
        out = jnp.where(outcome == it, i, out)
    return out


def names(outcome) -> list | str:
    """An `Outcome` item (or codes) decoded into item names (nested lists when batched)."""
    found = np.asarray(NAMES, dtype=object)[np.asarray(codes(outcome))]
    return found.tolist() if isinstance(found, np.ndarray) else str(found)


def is_in(codes_, names_) -> np.ndarray | jax.Array:
    """Elementwise: is the code one of `names_`? (numpy or JAX codes)"""
    out = codes_ == code(names_[0])
    for n in names_[1:]:
        out = out | (codes_ == code(n))
    return out


def failed(codes_):
    """Elementwise: is this code one of the SDP failures? (numpy or JAX codes)"""
    return is_in(codes_, _FAILURES)


def worst(codes_, bad) -> Outcome:
    """The item of the highest code where `bad` (traceable), for `error_if`."""
    return item(jnp.max(jnp.where(bad, codes_, -1)))


#: What an outcome of ICO's runs means where the projection's advice does not apply: its
#: step SDP holds the windows' data, and has no `init_scale`.
_ICO_MESSAGES = {
    "solver_failed": (
        "Clarabel failed to solve ICO's SDP (max iterations or numerical trouble). Its data "
        "are the windows themselves: windows in which one signal is negligible beside the "
        "others (plant outputs y near zero beside the states and inputs: a dead sensor) "
        "leave it degenerate. Check the data, pass a larger `eps`, or train with `dj.fit_pgd` or "
        "`dj.fit_direct`, which solve no SDP of the data"),
}

#: What an outcome of [`certify`][dissil_jax.certify] means, for the items it returns. An
#: `Outcome` item has one sentence whoever returns it; these replace the advice of the
#: projection and the trainers (`eps`, `init_scale`, `P_ref`), arguments `certify` lacks.
_CERTIFY_MESSAGES = {
    "solved": "certified: P is positive definite and the KYP matrix at P negative definite "
              "beyond float64 round-off",
    "not_certified": (
        "the exact float64 KYP check failed at the storage P: min(-lambda_max(KYP(P)), "
        "lambda_min(P)) is not above the round-off allowance `rtol` times the size of the KYP "
        "terms. With `P` given, that P does not prove the certificate (omit it to search); "
        "otherwise the best storage found (the maximum-margin SDP's, solved to the solver's "
        "tolerance, also in states balanced by an approximate storage) does not, so the "
        "controller is at best marginally dissipative for `qsr` (its margin is of the order "
        "of round-off): loosen the supply rate slightly, or move the controller inside the "
        "dissipative set with `dj.project`"),
    "infeasible": (
        "no storage exists: the controller is not strictly dissipative for `qsr` (the SDP is "
        "infeasible, or a necessary condition fails: `source` says which); `dj.project` "
        "finds the nearest controller that is"),
    "solver_failed": (
        "Clarabel failed to solve the certificate's SDP (max iterations or numerical "
        "trouble; `source` holds its status): the certificate is undecided. A better "
        "conditioned realisation of the controller (a change of state coordinates, which "
        "preserves dissipativity, e.g. a balanced one) may help"),
}


def message(name: str, caller: str | None = None) -> str:
    """The sentence of the item called `name`: the item's own, or with `caller="certify"`
    what it means for [`certify`][dissil_jax.certify] (whose arguments differ from those
    the projection's and trainers' advice names), with `caller="ico"` for ICO's step SDP."""
    if caller == "certify" and name in _CERTIFY_MESSAGES:
        return _CERTIFY_MESSAGES[name]
    if caller == "ico" and name in _ICO_MESSAGES:
        return _ICO_MESSAGES[name]
    if caller not in (None, "certify", "ico"):
        raise ValueError(f"`caller` must be None, 'certify' or 'ico', got {caller!r}.")
    return Outcome[getattr(Outcome, name)]
