"""Argument checks shared by the trainers (ValueErrors that name the argument)."""

from __future__ import annotations

import jax
import numpy as np

from .._data import Windows
from .._supply import QSR


def check_fit_args(windows, qsr, num_inits, max_steps, **nonnegative) -> None:
    """Validate the common trainer arguments; `nonnegative` are named hyperparameters.

    Traced hyperparameters (a vmapped sweep) are skipped: their values are not known here.
    """
    if not isinstance(windows, Windows):
        raise ValueError(f"`windows` must be a `dj.Windows`, got {type(windows).__name__}.")
    if qsr is not None:
        if not isinstance(qsr, QSR):
            raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
        qsr.check_sizes(windows.n_in, windows.n_out)
        qsr.neg_q_factor()  # ValueError naming `qsr.Q` for a Q with a positive eigenvalue
    if int(num_inits) != num_inits or num_inits < 1:
        raise ValueError(f"`num_inits` must be a positive integer, got {num_inits!r}.")
    if int(max_steps) != max_steps or max_steps < 0:
        raise ValueError(f"`max_steps` must be a non-negative integer, got {max_steps!r}.")
    for name, v in nonnegative.items():
        if isinstance(v, jax.core.Tracer):
            continue
        if not np.all(np.isfinite(v)) or np.any(np.asarray(v) < 0):
            raise ValueError(f"`{name}` must be finite and non-negative, got {v!r}.")
