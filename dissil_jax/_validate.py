"""Argument checks shared across the package (a leaf module: it imports nothing from it)."""

from __future__ import annotations

import functools
import sys
import threading
import warnings
from typing import Any, cast

import jax
import jax.core
import jax.numpy as jnp
import numpy as np


def has_non_finite(x) -> bool:
    """True if concrete `x` has a NaN or inf entry; False for a tracer (it cannot be read).

    In numpy: an eager `jnp.all(jnp.isfinite(x))` compiles a reduction for every new shape,
    which made argument checks cost compilations.
    """
    if isinstance(x, jax.core.Tracer):
        return False
    return not np.isfinite(np.asarray(x)).all()


def check_flag(name: str, value) -> bool:
    """`value` as a `bool` (Python or numpy), or a `ValueError` naming `name`: a string such
    as `"no"` is truthy, so accepting anything would read it as True."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"`{name}` must be True or False, got {value!r}.")
    return bool(value)


def check_int(name: str, value, *, minimum: int = 1) -> int:
    """`value` as an `int`, or a `ValueError` naming `name`.

    Accepts Python and numpy integers and integral floats (`3.0`) of at least `minimum`
    (1: "a positive integer", 0: "a non-negative integer"); rejects bools, arrays and
    anything else.
    """
    kind = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
    if minimum == 0:
        kind = "a non-negative integer"
    try:
        ok = (not isinstance(value, bool) and np.ndim(value) == 0 and int(value) == value
              and value >= minimum)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        if isinstance(value, jax.core.Tracer):
            raise ValueError(f"`{name}` must be {kind} known when tracing (it sets array "
                             "shapes or loop lengths), got a traced value: pass it as a "
                             "static argument (`jax.jit(..., static_argnames=...)`) or close "
                             "over it.")
        raise ValueError(f"`{name}` must be {kind}, got {value!r}.")
    return int(value)


def real_scalar(value) -> float:
    """`value` as a `float` if it is one real number (Python or numpy, not a bool, string,
    complex number or array), else NaN."""
    try:
        real = (not isinstance(value, bool | str | complex | np.complexfloating)
                and np.ndim(value) == 0 and np.isrealobj(value))
        return float(cast(Any, value)) if real else np.nan
    except (TypeError, ValueError):
        return np.nan


def check_real(name: str, value, what: str = "a finite real number") -> float:
    """`value` as a finite `float` (`real_scalar`), or a ValueError naming `name`."""
    v = real_scalar(value)
    if not np.isfinite(v):
        raise ValueError(f"`{name}` must be {what}, got {value!r}.")
    return v


def real_array(name: str, value) -> np.ndarray:
    """`value` as a float64 numpy array, or a ValueError naming `name` when it is not an
    array of real numbers (complex values, whose imaginary part numpy would drop with only a
    warning, strings, bools, objects)."""
    if isinstance(value, jax.core.Tracer):
        raise ValueError(f"`{name}` is traced (inside `jax.jit`, `jax.vmap` or `jax.grad`), "
                         "but it is read on the host in float64 here: call this on concrete "
                         "arrays, outside the transformation.")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.dtype.kind not in "fiu":
        got = f"dtype {arr.dtype}" if arr is not None else type(value).__name__
        raise ValueError(f"`{name}` must be an array of real numbers, got {got}.")
    return arr.astype(np.float64)


def check_positive(name: str, value, *, zero: bool = False) -> float:
    """A finite positive (with `zero`, non-negative) real number, or a ValueError naming it."""
    v = real_scalar(value)
    if not (np.isfinite(v) and (v > 0 or (zero and v == 0))):
        kind = "non-negative" if zero else "positive"
        raise ValueError(f"`{name}` must be a finite {kind} number, got {value!r}.")
    return v


def check_tolerance(name: str, value) -> float:
    """A relative tolerance: a finite non-negative real number, or a ValueError naming it."""
    v = real_scalar(value)
    if not (np.isfinite(v) and v >= 0):
        raise ValueError(f"`{name}` must be a finite non-negative number, got {value!r}.")
    return v


def check_abcd(A, B, C, D, *, what: str = "") -> None:
    """The shapes of a state-space quadruple $(A, B, C, D)$ with shared leading batch axes;
    a `ValueError` naming the first wrong matrix (as `` `{what}B` ``) otherwise."""
    batch = A.shape[:-2]
    n, m, p = A.shape[-1], B.shape[-1], C.shape[-2]
    expected = {"A": (n, n), "B": (n, m), "C": (p, n), "D": (p, m)}
    for name, M in zip("ABCD", (A, B, C, D)):
        if M.shape[:-2] != batch or M.shape[-2:] != expected[name]:
            raise ValueError(
                f"`{what}{name}` has shape {M.shape}; with A {A.shape}, B {B.shape}, "
                f"C {C.shape} it must be {batch + expected[name]}.")


def check_precision(name: str, dtype) -> None:
    """A `ValueError` naming `name` for a half-precision float dtype (float16, bfloat16):
    the certificates and the SDPs need float32 at least (bfloat16 is not even a numpy
    float, and float16's round-off of 1e-3 swamps every LMI margin)."""
    if jnp.issubdtype(dtype, jnp.floating) and jnp.finfo(dtype).bits < 32:
        raise ValueError(f"`{name}` has dtype {dtype}; pass float32 or float64 (e.g. "
                         f"`{name}.astype(np.float32)`): half precision is too coarse for "
                         "the certificates.")


def warn_user(message: str) -> None:
    """`warnings.warn(message)`, attributed to the first caller outside this package (the
    user's line), however deep inside the library it is raised."""
    frame, level = sys._getframe(0), 1
    while frame is not None and frame.f_globals.get("__name__", "").startswith("dissil_jax"):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, stacklevel=level)


def check_callback_dtype(dtype, fn: str) -> None:
    """Refuse 64-bit data for host callbacks (`jax.pure_callback`) inside a compiled loop
    when float64 is enabled only on this thread (`with jax.enable_x64(True):`, a
    thread-local setting): in a loop the callbacks run on XLA's threads, where JAX casts
    their float64 results to float32 and then fails on the declared dtype, deep inside the
    compiled run (a single `dj.project` call runs its callback on the calling thread)."""
    if np.dtype(dtype).itemsize < 8:
        return
    seen = []  # the setting a thread without a local one sees: the global one
    thread = threading.Thread(target=lambda: seen.append(bool(jax.config.jax_enable_x64)))
    thread.start()
    thread.join()
    if not seen[0]:
        raise ValueError(
            f"`{fn}` projects inside its compiled training loop through host callbacks, "
            "which run on XLA's threads, and `jax.enable_x64(True)` sets float64 for the "
            f"calling thread only: the {np.dtype(dtype).name} projections would come back "
            "as float32. Enable float64 for the whole process "
            "(`jax.config.update(\"jax_enable_x64\", True)` or the environment variable "
            "JAX_ENABLE_X64=1), or pass float32 data.")


def check_key(key) -> None:
    """A JAX PRNG key (raw `uint32` or typed), or a `ValueError` naming `key`; traced keys
    (a vmapped sweep over keys) pass."""
    if isinstance(key, jax.core.Tracer):
        return
    dtype = getattr(key, "dtype", None)
    typed = dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key)
    # a raw key is `uint32[2]` (threefry) or `uint32[4]` (rbg); leading batch axes are not
    # one key
    raw = (dtype is not None and not typed and np.dtype(dtype) == np.uint32
           and np.ndim(key) == 1 and np.shape(key)[0] in (2, 4))
    if not (typed or raw):
        raise ValueError(f"`key` must be a JAX PRNG key such as `jax.random.PRNGKey(0)` or "
                         f"`jax.random.key(0)`, got {key!r}.")


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def no_derivative(name: str, x):
    """`x` unchanged; differentiating through it raises a ValueError naming `name`, a
    function solved on the host (JAX's own error, "Pure callbacks do not support JVP",
    names neither the function nor a way out)."""
    return x


@no_derivative.defjvp
def _no_derivative_jvp(name, primals, tangents):
    raise ValueError(
        f"`{name}` has no derivative: its SDP is solved on the host (Clarabel, or the "
        "first-order path's float64 check), which JAX cannot differentiate. For derivatives "
        "of a certified training run with respect to its hyperparameters use `dj.direct_run` "
        "in forward mode (`jax.jacfwd`); to pass through a projection without one, apply "
        "`jax.lax.stop_gradient` to its input.")
