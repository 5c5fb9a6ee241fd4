"""The activation of a REN: the known names, and the screen of a user's callable (slope
restricted in $[0, 1]$ with $\\sigma(0) = 0$, the sector condition the certificate uses)."""

from __future__ import annotations

import weakref
from collections.abc import Callable

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

#: The activations known to be slope-restricted in $[0, 1]$ with $\sigma(0) = 0$.
ACTIVATIONS: dict[str, Callable] = {"relu": jax.nn.relu, "tanh": jnp.tanh}

# The screen of a user-supplied activation: difference quotients on this grid, symmetric
# about 0: logarithmic from 1e-6 to 1e6, and a uniform step of 1/256 up to 16, where the
# trainers' normalised data live (a 123-point grid let a spike between two of its points
# through, an audit's σ(1.12) = 6.12). Exact binary fractions, so float32 keeps them apart.
_POSITIVE = np.unique(np.concatenate([np.float32(np.logspace(-6, 6, 1201)),
                                      np.arange(1, 16 * 256 + 1) / 256.0]))
_GRID = np.concatenate([-_POSITIVE[::-1], [0.0], _POSITIVE])
# Round-off allowance of the screen, in units of the evaluation's machine epsilon per
# rounded value: each quotient (s(a) - s(b)) / (a - b) is allowed 8 eps (|s(a)| + |s(b)|)
# / |a - b|, room for a correctly rounded s and a few ulps of a library's tanh.
_ULPS = 8.0


def check_activation(activation, rescreen: bool = False) -> str | Callable:
    """`activation` if it is a known name or passes the sector screen, else a ValueError.

    A name from `ACTIVATIONS` is accepted as is. A callable is evaluated on a grid of
    about 10,000 points in $[-10^6, 10^6]$ (logarithmic, and a uniform step of $1/256$ in
    $[-16, 16]$): it must give $\\sigma(0) = 0$ and difference quotients of neighbouring
    points in $[0, 1]$. The screen can refuse but not
    prove: the certificate assumes the slope restriction everywhere, so a callable is the
    caller's promise, checked where it is cheap to check. A callable that passed is
    remembered (controllers built inside a trace cannot screen), unless `rescreen`.
    """
    if isinstance(activation, str):
        if activation not in ACTIVATIONS:
            raise ValueError(f"`activation` must be one of {sorted(ACTIVATIONS)} or a callable "
                             f"slope-restricted in [0, 1] with sigma(0) = 0, got {activation!r}.")
        return activation
    if not callable(activation):
        raise ValueError(f"`activation` must be a name or a callable, got {activation!r}.")
    if _holds_arrays(activation):
        raise ValueError(
            "`activation` is an equinox Module holding JAX arrays. The activation is a static "
            "(compile-time) part of the controller, so its constants must be Python numbers: "
            "declare them `eqx.field(static=True)` with float values, or close over floats.")
    try:  # a static field of the controller: JAX hashes it to key its compilations
        hash(activation)
    except TypeError:
        raise ValueError(
            "`activation` must be hashable: it is a static (compile-time) part of the "
            "controller, and JAX keys its compiled rollouts and training by it. A class "
            "that defines `__eq__` needs a `__hash__` too (e.g. a frozen dataclass).") from None
    if _passed(activation) and not rescreen:
        return activation
    # Trainers build controllers inside their compiled, differentiated loops, where the
    # screen cannot run: `fit_ren` screens first, eagerly, and this remembers the result.
    try:
        with jax.ensure_compile_time_eval():
            grid = jnp.asarray(_GRID)  # float32 without x64: the points it rounds to are used
            out = jax.vmap(activation)(grid)
            dtype = jnp.result_type(out)
            vals = np.asarray(out, np.float64)
            points = np.asarray(grid, np.float64)
    except _NOT_TRACEABLE as err:
        if _under_jit():
            raise ValueError(
                "`activation` (a callable) could not be screened inside this JAX "
                "transformation: it closes over traced values, or it is not a JAX function "
                "(NumPy's or `math`'s). Close over Python numbers only, and screen it once "
                "outside any transformation before a RENController is built inside one: "
                "build one RENController with it eagerly first (`dj.fit_ren` does this)."
            ) from None
        raise ValueError(
            "`activation` must be a JAX function applied elementwise (it runs on traced "
            "arrays inside the compiled rollouts and training loop): NumPy and `math` "
            "functions such as `np.tanh` or `math.tanh` cannot run there. Use `jnp.tanh`, "
            f"`jax.nn.relu`, or the names 'tanh'/'relu'. ({type(err).__name__} when applied "
            "under `jax.vmap`.)") from None
    except Exception as err:
        raise ValueError(
            "`activation` must take one array and return an array of its shape; applying it "
            f"under `jax.vmap` raised {type(err).__name__}: {err}") from None
    if vals.shape != _GRID.shape or not np.all(np.isfinite(vals)):
        raise ValueError("`activation` must map scalars to finite scalars elementwise.")
    # Round-off allowance per quotient, in the evaluation's precision (float32 without x64):
    # a slope of 1 + 1e-2 in float32 is refused, as in float64.
    eps = float(jnp.finfo(dtype).eps) if jnp.issubdtype(dtype, jnp.floating) else 0.0
    step = np.diff(points)
    slopes = np.diff(vals) / step
    tol = _ULPS * eps * (np.abs(vals[1:]) + np.abs(vals[:-1])) / step
    mid = len(_GRID) // 2
    zero = vals[mid]
    zero_tol = _ULPS * eps * max(abs(vals[mid - 1]), abs(vals[mid + 1]))
    if abs(zero) > zero_tol or np.any(slopes < -tol) or np.any(slopes > 1 + tol):
        raise ValueError(
            "`activation` is not slope-restricted in [0, 1] with sigma(0) = 0 (found sigma(0) "
            f"= {zero:.3g}, difference quotients in [{slopes.min():.6g}, {slopes.max():.6g}] "
            "on a grid in [-1e6, 1e6]); the certificate's sector condition w (v - w) >= 0 "
            "needs it. Rescale it (e.g. sigma(v)/L for slopes in [0, L]) or use 'relu'/'tanh'.")
    _remember(activation)
    return activation


# What a callable that is not JAX-traceable raises on a tracer (NumPy's and `math`'s
# functions call `__array__`, `float` or `bool` on it).
_NOT_TRACEABLE = (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError,
                  jax.errors.TracerBoolConversionError, jax.errors.TracerIntegerConversionError)


def _under_jit() -> bool:
    """Whether the caller is being traced by `jax.jit` (new arrays are then tracers)."""
    return isinstance(jnp.zeros(()) + 0, jax.core.Tracer)


def _holds_arrays(fn) -> bool:
    """An equinox Module with JAX array leaves (which cannot be a static field)."""
    return isinstance(fn, eqx.Module) and bool(jax.tree.leaves(eqx.filter(fn, eqx.is_array)))


# Callables that passed the screen (weakly held; by id for those that take no weak ref).
_SCREENED: weakref.WeakSet = weakref.WeakSet()
_SCREENED_IDS: dict[int, Callable] = {}


def _passed(fn) -> bool:
    try:
        return fn in _SCREENED
    except TypeError:
        return _SCREENED_IDS.get(id(fn)) is fn


def _remember(fn) -> None:
    try:
        _SCREENED.add(fn)
    except TypeError:
        _SCREENED_IDS[id(fn)] = fn
