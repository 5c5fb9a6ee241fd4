"""Sweeps past one device: `jax.shard_map` around a vmapped run.

`jax.pure_callback` outside `shard_map` is placed on one device (XLA's "maximal"
sharding), so a sweep that is merely `jit`-ed with sharded inputs gathers every shard's
projections to that device's host and scatters the results back. Inside `shard_map`, with
every mesh axis manual, each device calls its own copy of the callback with its local
batch, on its own host. [`sweep`][dissil_jax.sweep] is that recipe, with the mesh, the
input placement and uneven sweep sizes handled.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec


def _pad(x, pad: int):
    return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x


def sweep(fn, mesh: Mesh | None = None):
    """`jax.jit(jax.vmap(fn))`, with the swept axis split over the devices of `mesh`.

    Each device runs `fn` on its slice of the sweep: gradients and rollouts on the device,
    and the projection's SDPs on the CPU cores of the device's own host, through its own
    host callback (one per device and training step, with the device's local batch).
    Nothing is gathered to one device, and the results equal those of
    `jax.jit(jax.vmap(fn))`. On several hosts call `jax.distributed.initialize()` first and
    pass the same arguments on every process; the default mesh then spans all hosts. See
    [Scaling out](scaling.md).

    It is `jax.jit(jax.shard_map(jax.vmap(fn), mesh=mesh, in_specs=P(axes),
    out_specs=P(axes), check_vma=False))` over all mesh axes, applied to the arguments
    placed with `jax.device_put(args, NamedSharding(mesh, P(axes)))`. A sweep whose length
    is not a multiple of the number of devices is padded with copies of its last entry,
    whose results are dropped (the trimmed outputs are then replicated).

    **Arguments:**

    - `fn`: a function of one sweep point (e.g. a learning rate and a key) returning a
      pytree of arrays, as for `jax.vmap`; close over everything that is not swept.
      Every lane must be independent of the others (true of
      [`pgd_run`][dissil_jax.pgd_run] and [`project`][dissil_jax.project]).
    - `mesh`: the devices to split the sweep over; by default all devices (of all hosts),
      `jax.make_mesh((jax.device_count(),), ("sweep",))`. The sweep is split over the
      product of all its axes.

    **Returns:** a function of the swept arguments (every leaf with the same leading
    size), returning `fn`'s outputs with that leading axis, sharded over `mesh` (with
    its axes made `AxisType.Auto`).

    ```python
    run = lambda lr: dj.pgd_run(key, windows, qsr, learning_rate=lr, throw=False)
    res = dj.sweep(run)(jnp.logspace(-2, 0.5, 8))   # as jax.jit(jax.vmap(run))(lrs)
    ```
    """
    if mesh is None:
        mesh = jax.make_mesh((jax.device_count(),), ("sweep",))
    if not isinstance(mesh, Mesh):
        raise ValueError(f"`mesh` must be a `jax.sharding.Mesh`, got {type(mesh).__name__}.")
    # Auto axes: with Explicit ones (the default of `jax.make_mesh`) dropping the padding
    # of an uneven sweep would need an explicit output sharding.
    mesh = Mesh(mesh.devices, mesh.axis_names, axis_types=(AxisType.Auto,) * len(mesh.axis_names))
    spec = PartitionSpec(tuple(mesh.axis_names))
    # check_vma=False: a lane's loop carry may start invariant across devices (GD's initial
    # controllers depend on the closed-over key only) and become device-varying in the body,
    # which the varying-axes check rejects; the lanes never communicate, so nothing is lost.
    mapped = jax.jit(jax.shard_map(jax.vmap(fn), mesh=mesh, in_specs=spec, out_specs=spec,
                                   check_vma=False))

    @functools.wraps(fn)
    def run(*args, **kwargs):
        if kwargs:
            raise ValueError(
                "`dj.sweep` runs take the swept arguments by position only; got keyword "
                f"arguments {sorted(kwargs)}. Pass them by position, or close over them "
                "(e.g. `functools.partial`) when they are not swept.")
        leaves = jax.tree.leaves(args)
        if not leaves:
            raise ValueError("`dj.sweep` runs need at least one swept array argument; got none.")
        if any(isinstance(a, list | tuple) and a and all(np.ndim(x) == 0 for x in a)
               for a in args):
            raise ValueError(
                "a swept argument is a Python list or tuple of scalars, which JAX reads as "
                "a pytree of separate scalars, not as one axis: pass an array, e.g. "
                "`jnp.asarray([0.1, 0.3])`.")
        sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
        if sizes == {None}:
            raise ValueError("the swept arguments are scalars: a sweep needs a leading axis "
                             "of values, e.g. `jnp.asarray([0.1, 0.3])` for one value 0.1 "
                             "and another 0.3 (call the run directly for a single value).")
        if len(sizes) != 1 or None in sizes:
            raise ValueError("every leaf of the swept arguments must have the same leading "
                             f"(sweep) axis; got leading sizes {sorted(sizes, key=str)}. "
                             "Close over the arguments that are not swept.")
        size = sizes.pop()
        assert size is not None  # excluded just above
        pad = -size % mesh.size
        args = jax.device_put(jax.tree.map(lambda x: _pad(x, pad), args),
                              NamedSharding(mesh, spec))
        out = mapped(*args)
        return jax.tree.map(lambda x: x[:size], out) if pad else out

    return run
