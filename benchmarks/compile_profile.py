"""Where a test run's time goes: XLA compilations per jitted function, as a pytest plugin.

JAX logs every backend compilation ("Finished XLA compilation of jit(f) in t sec") at
DEBUG level; this plugin sums them per function and writes one table per process
(each xdist worker) when it exits, by jitted function, by call site (the innermost
frame in `dissil_jax/` or `tests/` that led to the compilation) and by test. Subprocesses (examples, CLI runs) are not counted.

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
import sys

_TOTAL, _COUNT = collections.Counter(), collections.Counter()
_SITE_TOTAL, _SITE_COUNT = collections.Counter(), collections.Counter()
_TEST_TOTAL, _TEST_COUNT = collections.Counter(), collections.Counter()
_WRITTEN: list = []
_OURS = (os.sep + "dissil_jax" + os.sep, os.sep + "tests" + os.sep)


def _site():
    """The innermost frame of the library or the tests that led to this compilation."""
    frame = sys._getframe(1)
    while frame is not None:
        name = frame.f_code.co_filename
        if any(part in name for part in _OURS) and os.sep + ".venv" + os.sep not in name:
            short = name[name.rfind(os.sep, 0, name.rfind(os.sep)) + 1:]
            return f"{short}:{frame.f_lineno} ({frame.f_code.co_name})"
        frame = frame.f_back
    return "(elsewhere)"
_PATTERN = re.compile(r"Finished XLA compilation of (.*) in ([0-9.e+-]+) sec")


class _Handler(logging.Handler):
    def emit(self, record):
        match = _PATTERN.search(record.getMessage())
        if match:
            _TOTAL[match.group(1)] += float(match.group(2))
            _COUNT[match.group(1)] += 1
            site = _site()
            _SITE_TOTAL[site] += float(match.group(2))
            _SITE_COUNT[site] += 1
            test = os.environ.get("PYTEST_CURRENT_TEST", "(no test)").rsplit(" ", 1)[0]
            _TEST_TOTAL[test] += float(match.group(2))
            _TEST_COUNT[test] += 1


for _name in ("jax._src.dispatch", "jax._src.interpreters.pxla"):
    _logger = logging.getLogger(_name)
    _logger.setLevel(logging.DEBUG)
    _logger.addHandler(_Handler())


def pytest_unconfigure(config):
    """Write the table when pytest (or an xdist worker) finishes; atexit is the fallback
    for a process that is ended without it."""
    _write()


@atexit.register
def _write():
    if not _TOTAL or _WRITTEN:
        return
    _WRITTEN.append(True)
    with open(f"compile_profile.{os.getpid()}.txt", "w") as f:
        f.write(f"{sum(_TOTAL.values()):9.1f} {sum(_COUNT.values()):6d} (total)\n")
        for name, seconds in _TOTAL.most_common():
            f.write(f"{seconds:9.1f} {_COUNT[name]:6d} {name}\n")
        f.write("\n# by call site (the innermost frame in dissil_jax/ or tests/)\n")
        for name, seconds in _SITE_TOTAL.most_common():
            f.write(f"{seconds:9.1f} {_SITE_COUNT[name]:6d} {name}\n")
        f.write("\n# by test\n")
        for name, seconds in _TEST_TOTAL.most_common():
            f.write(f"{seconds:9.1f} {_TEST_COUNT[name]:6d} {name}\n")
