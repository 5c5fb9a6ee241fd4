"""Host-side threading helpers shared by the SDP modules."""

from __future__ import annotations

import contextlib
import os
from concurrent.futures import ThreadPoolExecutor

_POOL: ThreadPoolExecutor | None = None
_CONTROLLER = None


@contextlib.contextmanager
def single_threaded_blas():
    """Limit BLAS to one thread: threaded BLAS slows Clarabel's small dense cones badly.

    The threadpoolctl controller is built once (building it scans the loaded libraries,
    about 2 ms, which would dominate a small projection).
    """
    global _CONTROLLER
    if _CONTROLLER is None:
        import clarabel  # noqa: F401  (load the solver's libraries before the scan)
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    with _CONTROLLER.limit(limits=1, user_api="blas"):
        yield


def pool() -> ThreadPoolExecutor:
    """A process-wide pool for batched host solves (Clarabel releases the GIL)."""
    global _POOL
    if _POOL is None:
        workers = int(os.environ.get("DISSIL_JAX_THREADS", os.cpu_count() or 1))
        _POOL = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="dissil-sdp")
    return _POOL


def num_workers() -> int:
    return pool()._max_workers  # noqa: SLF001
