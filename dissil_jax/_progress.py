"""Progress reports of long runs: training, printed from inside the compiled loop, and
long host work such as a certificate's SDP at a high order.

A trainer's loop is one `lax.while_loop`, silent until it returns. With `progress=True`
(the trainers' default) the loop calls back to the host every `every(max_steps)` steps;
the host prints nothing during the first `DELAY` seconds, so short runs stay silent, and
then one line at most every `INTERVAL` seconds, on standard error:

    fit_ren: compiled and started after 11 s, 100 runs of at most 600 steps
    fit_ren: step 240 of at most 600, 61 of 100 runs training, lowest loss 3.1e-03, 14 s

(ICO's host loops give the steps of their slowest and furthest running runs, "steps
12-150".) Before the loop's first call back and after its last, a trainer may work for
minutes without a step to report (compiling the loop, a first projection at a high order,
the float64 check of every result); a heartbeat thread then says what it is doing, at the
same delay and interval:

    fit_pgd: compiling the training loop and preparing the runs, 20 s
    fit_pgd: checking every result's certificate in float64, 130 s

The compiled loop receives a traced token (`reporting`), so calls with another reporter
reuse the compiled run; token 0 reports nothing. ICO's runs are host loops on worker
threads; they report through `HostProgress`.
"""

from __future__ import annotations

import contextlib
import itertools
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

#: Seconds of training before the first report (shorter runs print nothing).
DELAY = 10.0
#: Seconds between reports.
INTERVAL = 10.0

_LOCK = threading.Lock()
_REPORTERS: dict[int, _Reporter] = {}
_IDS = itertools.count(1)


def every(max_steps: int) -> int:
    """How many steps apart the loop calls back: about 100 calls per run at most."""
    return max(1, int(max_steps) // 100)


class _Reporter:
    def __init__(self, name: str, max_steps: int, scale: float = 1.0, lanes: int = 0):
        self.name, self.max_steps, self.scale = name, int(max_steps), float(scale)
        self.start = time.perf_counter()
        self.last = -float("inf")
        # a loop vmapped by its caller (the MLP) calls back once per lane, in order
        self.lanes, self.parts = int(lanes), []
        # what the run does while the loop has no step to report (None: it is stepping)
        self.phase: str | None = "compiling the training loop and preparing the runs"
        self.lock = threading.Lock()  # the loop's call backs against the heartbeat thread

    def heartbeat(self) -> None:
        """A line saying what the run does, when it has reported nothing for a while."""
        with self.lock:
            self._heartbeat()

    def _heartbeat(self) -> None:
        now = time.perf_counter()
        if (self.phase is None or now - self.start < DELAY
                or now - self.last < INTERVAL):
            return
        self.last = now
        print(f"{self.name}: {self.phase}, {now - self.start:.0f} s", file=sys.stderr,
              flush=True)

    def __call__(self, k, loss, done):
        with self.lock:
            self._report(k, loss, done)

    def _report(self, k, loss, done):
        loss = self.scale * np.asarray(loss, np.float64).ravel()
        done = np.asarray(done).ravel()
        if loss.size < self.lanes:  # one lane of a vmapped loop: gather the step's lanes
            self.parts.append((loss, done))
            if sum(part[0].size for part in self.parts) < self.lanes:
                return
            loss, done = (np.concatenate(a) for a in zip(*self.parts))
            self.parts = []
        now = time.perf_counter()
        first, self.phase = self.phase is not None and np.ndim(k) == 0, None
        # the loop's first call back is reported even right after a heartbeat's line
        if now - self.start < DELAY or (now - self.last < INTERVAL and not first):
            return
        self.last = now
        finite = loss[np.isfinite(loss)]
        best = f"{finite.min():.2e}" if finite.size else "none finite"
        # a compiled loop's step; host loops pass (slowest, furthest, runs not started yet)
        compiled = np.ndim(k) == 0
        lo, hi = (int(k), int(k)) if compiled else (int(k[0]), int(k[1]))
        waiting = 0 if compiled else int(k[2])
        if compiled and hi == 0:  # its first call back comes after its compilation
            print(f"{self.name}: compiled and started after {now - self.start:.0f} s, "
                  f"{done.size} runs of at most {self.max_steps} steps", file=sys.stderr,
                  flush=True)
            return
        # host loops (ICO) step at their own pace: the slowest and the furthest still going
        steps = f"step {hi}" if lo == hi else f"steps {lo}-{hi}"
        queued = f" ({waiting} waiting for a thread)" if waiting else ""
        print(f"{self.name}: {steps} of at most {self.max_steps}, "
              f"{int((~done).sum()) - waiting} of {done.size} runs training{queued}, lowest "
              f"loss {best}, {now - self.start:.0f} s", file=sys.stderr, flush=True)


def _dispatch(token, k, loss, done):
    with _LOCK:
        reporter = _REPORTERS.get(int(token))
    if reporter is not None:
        reporter(k, loss, done)


def report(token, k, loss, done, max_steps: int) -> None:
    """In the loop's body (traced): call back with step `k`, the lanes' losses and which
    lanes stopped, every `every(max_steps)` steps."""
    jax.lax.cond(k % every(max_steps) == 0,
                 lambda: jax.debug.callback(_dispatch, token, k, loss, done),
                 lambda: None)


@contextlib.contextmanager
def reporting(name: str, max_steps: int, enabled: bool, scale: float = 1.0, lanes: int = 0):
    """The token of a run's reporter (an int32 array, traced by the compiled run), or 0
    when `enabled` is False; the reporter lives until the block exits. `scale` multiplies
    the losses it reports (a balanced problem's, $c^2$, to the user's units); `lanes`: the
    number of runs of a loop vmapped by its caller, which calls back once per run."""
    if not enabled:
        yield jnp.asarray(0, jnp.int32)
        return
    with _LOCK:
        token = next(_IDS)
        _REPORTERS[token] = reporter = _Reporter(name, max_steps, scale, lanes)
    try:
        with _heartbeat(reporter):
            yield jnp.asarray(token, jnp.int32)
    finally:
        with _LOCK:
            del _REPORTERS[token]


@contextlib.contextmanager
def _heartbeat(reporter: _Reporter):
    """A thread that calls `reporter.heartbeat()` every `_BEAT` seconds while the block
    runs."""
    stop = threading.Event()

    def beat():
        while not stop.wait(_BEAT):
            reporter.heartbeat()

    thread = threading.Thread(target=beat, name=f"{reporter.name}-progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def phase(token, text: str) -> None:
    """Tell the reporter of `token` what the run does now that its loop has ended (the
    heartbeat prints it when the run is long); nothing for token 0 (no reports)."""
    with _LOCK:
        reporter = _REPORTERS.get(int(token))
    if reporter is not None:
        with reporter.lock:
            reporter.phase = text
            reporter.last = time.perf_counter()  # the loop's last line was just now


#: Seconds between the heartbeat thread's looks at its reporter.
_BEAT = 1.0
#: What every certified trainer does after its loop.
CHECKING = "checking every result's certificate in float64"


class HostProgress:
    """Progress of `num_runs` runs stepping on host threads (ICO): `step(i, k, loss)` after
    each accepted step of run `i` (step 0 when it starts), `done(i)` when it ends; reported
    like the compiled loops' (nothing when not `enabled`). Runs waiting for a thread are
    counted apart and left out of the steps' range (with four runs on two threads it read
    "4 of 4 runs training, steps 0-11" for minutes, then "steps 1-3")."""

    def __init__(self, name: str, max_steps: int, num_runs: int, enabled: bool):
        self._reporter = _Reporter(name, max_steps) if enabled else None
        self._lock = threading.Lock()
        self._k = np.zeros(num_runs, np.int64)
        self._loss = np.full(num_runs, np.nan)
        self._done = np.zeros(num_runs, bool)
        self._started = np.zeros(num_runs, bool)

    def step(self, i: int, k: int, loss: float) -> None:
        if self._reporter is None:
            return
        with self._lock:
            self._k[i], self._loss[i], self._started[i] = k, loss, True
            going = self._k[self._started & ~self._done]
            span = (going.min(), going.max()) if going.size else (self._k.max(),) * 2
            waiting = int((~self._started & ~self._done).sum())
            self._reporter((*span, waiting), self._loss.copy(), self._done.copy())

    def done(self, i: int) -> None:
        with self._lock:
            self._done[i] = True


@contextlib.contextmanager
def working(name: str, text: str, enabled: bool = True):
    """Host work without steps (`certify`'s SDPs): the heartbeat says `text` once the block
    has run past the delay, then every interval, until it ends; silent inside a run that
    reports already (a trainer's float64 check)."""
    with _LOCK:
        inside = bool(_REPORTERS)  # a trainer's own check: its heartbeat speaks already
    if not enabled or inside:
        yield
        return
    reporter = _Reporter(name, 0)
    reporter.phase = text
    with _heartbeat(reporter):
        yield
