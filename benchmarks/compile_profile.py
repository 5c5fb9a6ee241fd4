"""Where a test run's time goes: XLA compilations per jitted function, as a pytest plugin.

JAX logs every backend compilation ("Finished XLA compilation of jit(f) in t sec") at
DEBUG level; this plugin sums them per function and writes one table per process
(each xdist worker) when it exits. Subprocesses (examples, CLI runs) are not counted.

```
PYTHONPATH=benchmarks .venv/bin/python -m pytest -p compile_profile -n 2 -m "not slow" tests
cat compile_profile.*.txt     # seconds, compilations, function; most expensive first
```

Use a fresh `JAX_COMPILATION_CACHE_DIR` (or none): a persistent-cache hit is logged as a
compilation too, in the time of the read.
"""

import atexit
import collections
import logging
import os
import re

_TOTAL, _COUNT = collections.Counter(), collections.Counter()
_PATTERN = re.compile(r"Finished XLA compilation of (.*) in ([0-9.e+-]+) sec")


class _Handler(logging.Handler):
    def emit(self, record):
        match = _PATTERN.search(record.getMessage())
        if match:
            _TOTAL[match.group(1)] += float(match.group(2))
            _COUNT[match.group(1)] += 1


for _name in ("jax._src.dispatch", "jax._src.interpreters.pxla"):
    _logger = logging.getLogger(_name)
    _logger.setLevel(logging.DEBUG)
    _logger.addHandler(_Handler())


@atexit.register
def _write():
    if not _TOTAL:
        return
    with open(f"compile_profile.{os.getpid()}.txt", "w") as f:
        f.write(f"{sum(_TOTAL.values()):9.1f} {sum(_COUNT.values()):6d} (total)\n")
        for name, seconds in _TOTAL.most_common():
            f.write(f"{seconds:9.1f} {_COUNT[name]:6d} {name}\n")
