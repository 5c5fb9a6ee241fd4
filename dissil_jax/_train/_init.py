"""The trainers' random initialisation (paper Alg. 1 and 2, "Random Initialization")."""

from __future__ import annotations

import jax
import jax.random as jr

from .._controller import LTIController
from .._data import Windows

#: The paper's standard deviation of the initial entries: it draws "each matrix element from
#: a normal distribution" (paper §4.1), i.e. N(0, 1), and then projects the draw onto the
#: dissipative set (PGD, ICO). The default of `fit_ico_nc` only; the certified trainers'
#: defaults are smaller, measured on the zoo's tuning half (`ICO_INIT_SCALE`,
#: `ADAM_INIT_SCALE`), and the reproduction passes N(0, 1) explicitly.
INIT_SCALE = 1.0


def init_controllers(key, num_inits: int, windows: Windows, scale, dtype=None, *,
                     n_state: int | None = None) -> LTIController:
    """`num_inits` controllers with i.i.d. $\\mathcal N(0, \\text{scale}^2)$ entries (batched).

    One key per initialisation, so initialisation $i$ is the same for every trainer given the
    same `key`. `scale` may be traced (a vmapped sweep over initialisation scales).

    **Arguments:** the PRNG `key`, `num_inits`, the `windows` (for $p$, $m$ and the default
    order), `scale`, an optional `dtype` (default: that of `windows.y`) and the controller
    order `n_state` (default `windows.n_state`; required when `windows.x0` is None, see
    `check_n_state`).

    **Returns:** an `LTIController` with batch shape `[num_inits]`.
    """
    n = windows.n_state if n_state is None else n_state
    if n is None:
        raise ValueError("`n_state` is required when `windows.x0` is None (the windows start "
                         "at rest, so they do not fix the controller order).")
    p, m = windows.n_in, windows.n_out
    dtype = dtype or windows.y.dtype
    K = jax.vmap(lambda k: LTIController.random(k, n, p, m, scale=1.0, dtype=dtype))(
        jr.split(key, num_inits))
    return jax.tree.map(lambda M: scale * M, K)
