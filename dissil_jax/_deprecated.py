"""Names kept for one release (0.2) with a `DeprecationWarning`; see CHANGELOG.md."""

from __future__ import annotations

import enum
import warnings

import jax.numpy as jnp
import numpy as np

from . import _sdp


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
