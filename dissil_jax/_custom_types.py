"""Shared type aliases (jaxtyping shape strings)."""

from typing import Union

import numpy as np
from jaxtyping import Array, ArrayLike, Float

Scalar = Float[Array, ""]
RealLike = Union[float, int, np.floating, Float[ArrayLike, ""]]

__all__ = ["Array", "ArrayLike", "Float", "Scalar", "RealLike"]
