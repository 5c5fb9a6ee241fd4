"""XLA's compilation settings for the test run: compile and run time of one training loop.

`make test` sets `XLA_FLAGS` to the Makefile's `FAST_XLA` (the CPU backend's older loop
emitters, LLVM at -O0): the tests' arithmetic is small and most of their time is XLA
compilation. This script measures, for each setting, the compile time and the run time of
one `fit_direct` training loop (n̂ = 3, m = p = 2, passive, 6 windows, 4 initialisations,
300 steps), each in its own subprocess (XLA reads its flags once per process); the settings
alternate for `--rounds` rounds and the fastest of each is kept. Reported as ratios to the
default settings of the same run.

Usage: python benchmarks/bench_test_xla.py [--rounds 3]
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys

# The flags as `make test` sets them (the Makefile's `FAST_XLA := ...`), and each alone.
_MAKEFILE = pathlib.Path(__file__).resolve().parents[1] / "Makefile"
FAST_XLA = next(line.split(":=", 1)[1].strip() for line in _MAKEFILE.read_text().splitlines()
                if line.startswith("FAST_XLA :="))
SETTINGS = {"default": "", **{flag: flag for flag in FAST_XLA.split()}, "FAST_XLA": FAST_XLA}

CHILD = """
import json, time
import jax, jax.random as jr
jax.config.update("jax_enable_x64", True)
import dissil_jax as dj
from dissil_jax.internal import direct_run_unchecked as run
key = jr.PRNGKey(0)
n, p = 3, 2
w = dj.Windows(jr.normal(key, (6, n)), jr.normal(key, (6, 3, p)), jr.normal(key, (6, 3, p)))
f = jax.jit(lambda key, w: run(key, w, dj.QSR.passive(p), 0.03, 0.3, optimizer=None,
            num_inits=4, n_state=n, max_steps=300, atol=0.0, rtol=0.0, margin=1e-2))
lowered = f.lower(key, w)
t = time.perf_counter(); compiled = lowered.compile(); compile_s = time.perf_counter() - t
jax.block_until_ready(compiled(key, w))
t = time.perf_counter()
for _ in range(5):
    jax.block_until_ready(compiled(key, w))
print(json.dumps(dict(compile=compile_s, run=(time.perf_counter() - t) / 5)))
"""


def measure(flags: str) -> dict:
    env = {**os.environ, "XLA_FLAGS": flags, "OPENBLAS_NUM_THREADS": "1"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # a cache hit would hide the compilation
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True,
                         text=True, check=True, timeout=600)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(rounds: int):
    best = {name: {"compile": float("inf"), "run": float("inf")} for name in SETTINGS}
    for _ in range(rounds):
        for name, flags in SETTINGS.items():
            found = measure(flags)
            best[name] = {k: min(best[name][k], found[k]) for k in found}
    base = best["default"]
    print("| setting | compile (s) | run, 300 steps (ms) | compile / default | run / default |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, b in best.items():
        print(f"| {name} | {b['compile']:.2f} | {1e3 * b['run']:.1f} | "
              f"{b['compile'] / base['compile']:.2f} | {b['run'] / base['run']:.2f} |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    main(ap.parse_args().rounds)
