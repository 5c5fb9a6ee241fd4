"""The arguments of [`certify`][dissil_jax.certify]: the controller's arrays and a given
storage, checked."""

from __future__ import annotations

import jax
import jax.core
import numpy as np

from .._controller import LTIController
from .._supply import QSR
from .._validate import real_array


def controller_arrays(K: LTIController, qsr: QSR):
    """`K`'s $(A, B, C, D)$ in float64 (numpy), after checking `K`, `qsr` and their sizes."""
    if not isinstance(K, LTIController):
        raise ValueError(f"`K` must be a `dj.LTIController`, got {type(K).__name__}.")
    if not isinstance(qsr, QSR):
        raise ValueError(f"`qsr` must be a `dj.QSR`, got {type(qsr).__name__}.")
    qsr.check_sizes(K.n_in, K.n_out)
    if any(isinstance(M, jax.core.Tracer) for M in (K.A, K.B, K.C, K.D)):
        raise ValueError("`certify` cannot run under `jax.jit` or `jax.vmap` (`K` is traced): "
                         "it checks the certificate in float64 on the host. Call it on the "
                         "result, outside the transformation (a batched `K` is certified "
                         "member by member).")
    return tuple(np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D))


# Asymmetry of a given storage tolerated as round-off, relative to its largest entry:
# a P computed in float32 (eps ~ 1.2e-7) and not symmetrised passes.
_SYMMETRY_RTOL = 1e-5


def storage_arg(name, P, batch, n, *, members: bool = False):
    """`P` checked (shape, finite, symmetric) and broadcast to the batch. With `members`, a
    batch's non-finite members pass (the caller judges them `non_finite`)."""
    P = real_array(name, P)
    if P.shape not in ((n, n), batch + (n, n)):
        expected = f"{n}x{n}" + (f" or {batch + (n, n)}" if batch else "")
        raise ValueError(f"`{name}` must be {expected}, got {P.shape}.")
    finite = np.all(np.isfinite(P), axis=(-2, -1))
    if not (np.all(finite) or (members and batch and P.ndim > 2)):
        raise ValueError(f"`{name}` contains NaN or inf.")
    if n:
        Pf = np.where(finite[..., None, None], P, 0.0)
        asym = np.max(np.abs(Pf - np.swapaxes(Pf, -1, -2)), axis=(-2, -1))
        size = np.max(np.abs(Pf), axis=(-2, -1))
        if np.any(asym > _SYMMETRY_RTOL * size):
            raise ValueError(
                f"`{name}` must be symmetric (the storage is V(x) = x'Px): max |P - P'| = "
                f"{np.max(asym):.3g} exceeds the round-off allowance {_SYMMETRY_RTOL:g} "
                "max |P|; pass (P + P.T) / 2 if the asymmetry is meant to be dropped.")
    return np.broadcast_to(P, batch + (n, n)) if batch else P
