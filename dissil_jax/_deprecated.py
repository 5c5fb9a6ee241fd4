"""Names kept for one release (0.2) with a `DeprecationWarning`; see CHANGELOG.md."""

from __future__ import annotations

import enum
import functools
import warnings

import jax.numpy as jnp
import numpy as np

from . import _sdp


def positional_options(call: str, names: tuple[str, ...], new_form: str, *, leading: int = 1):
    """Decorator: accept the 0.1 call with `names` positional (after `leading` positional
    arguments), mapping them onto the keyword-only parameters with a DeprecationWarning."""

    def decorate(fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            head, extra = args[:leading], args[leading:]
            if extra:
                if len(extra) > len(names):
                    raise TypeError(f"{call}() takes {leading} positional argument(s) and "
                                    f"keyword-only {', '.join(names)}; got {len(args)}.")
                for name, value in zip(names, extra):
                    if name in kwargs:
                        raise TypeError(f"{call}() got multiple values for `{name}`.")
                    kwargs[name] = value
                warnings.warn(f"passing {', '.join(f'`{n}`' for n in names)} of `{call}` "
                              f"positionally is deprecated; call `{new_form}`. The positional "
                              "form will be removed in 0.3.0.", DeprecationWarning, stacklevel=2)
            return fn(*head, **kwargs)

        return wrapper

    return decorate


class Status(enum.IntEnum):
    """Deprecated: the projection's outcome codes of 0.1. Use [`Outcome`][dissil_jax.Outcome]."""

    SOLVED = 0
    UNCHANGED = 1
    SKIPPED = 2
    INFEASIBLE = 3
    SOLVER_FAILED = 4
    NOT_CERTIFIED = 5


# Outcome code -> Status code (trainer-only outcomes never come out of a projection).
_TO_STATUS = np.full(len(_sdp.NAMES), int(Status.SOLVER_FAILED), np.int32)
for _s in Status:
    _TO_STATUS[_sdp.code(_s.name.lower())] = int(_s)


def project_with_status(K, qsr, P_ref=None, active=True, *, eps: float = 1e-6,
                        reg: float = 1e-6, refine: int = 3):
    """Deprecated: use `dj.project(K, qsr, P_ref, throw=False, active=active)`.

    **Returns:** `(K_proj, P, status)` with `status` an int32 `Status` code, as in 0.1.
    """
    from ._projection import project

    warnings.warn("`dj.project_with_status` is deprecated and will be removed in 0.3; use "
                  "`dj.project(..., throw=False)` and its `.result`.", DeprecationWarning,
                  stacklevel=2)
    proj = project(K, qsr, P_ref, throw=False, active=active, eps=eps, reg=reg, refine=refine)
    return proj[0], proj[1], jnp.asarray(_TO_STATUS)[proj.result._value]


def module_getattr(name: str):
    """`dissil_jax.__getattr__`: deprecated module attributes."""
    if name == "Status":
        warnings.warn("`dj.Status` is deprecated and will be removed in 0.3; use `dj.Outcome`.",
                      DeprecationWarning, stacklevel=3)
        return Status
    raise AttributeError(f"module 'dissil_jax' has no attribute {name!r}")
