"""Shared type aliases (jaxtyping shape strings)."""

import numpy as np
from jaxtyping import Array, ArrayLike, Float

Scalar = Float[Array, ""]
RealLike = float | int | np.floating | Float[ArrayLike, ""]

__all__ = ["Array", "ArrayLike", "Float", "Scalar", "RealLike"]
