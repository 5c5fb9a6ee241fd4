"""REN controllers with extra states started at zero, on the paper's nonlinear example.

An odd ReLU REN without biases is positively homogeneous: started at the plant state
($\\hat x_0 = (x_0, -x_0)$) its first control is exactly linear in $x_0$ (`docs/ren.md`).
This measures whether $k$ extra controller states, started at 0, buy a better fit: the
training windows' $x_0$ is padded with $k$ zeros and the test loops start the REN at the
padded state. Everything else is the protocol's REN (`protocol.fit`, 25 initial segments,
the example's width, activation, step and budget); `k0` is exactly
`run_config(..., "ren", ...)`. Config names: `k<K>[w<width>][d]`, `d` for `direct_input`.

Usage: python benchmarks/bench_ren_states.py [--seeds 1,2] [--inits 40]
       [--configs k0,k1,k2,k4,k0d,k1d,k0w32,k1w32]
"""

import argparse
import os
import re

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments.metrics import evaluate  # noqa: E402
from dissil_jax.experiments.protocol import (  # noqa: E402
    controller_start,
    evaluation_setup,
    example_spec,
    training_data,
)


def padded(x0, k):
    return jnp.concatenate([x0, jnp.zeros(x0.shape[:-1] + (k,), x0.dtype)], -1)


def run(seed, inits, k, width, direct_input):
    """(median test MSE, % stable, % certified) of one configuration on one seed."""
    spec = example_spec("nonlinear")
    plant, expert, w, (k_fit, _, k_noise) = training_data(spec, 0, seed, "initial", 25)
    res = dj.fit_ren(k_fit, dj.Windows(padded(w.x0, k), w.y, w.u), spec.qsr,
                     width=width or spec.ren_width, activation=spec.ren_activation,
                     learning_rate=spec.ren_learning_rate, init_scale=spec.ren_init_scale,
                     direct_input=direct_input or spec.ren_direct_input, odd=spec.ren_odd,
                     num_inits=inits, max_steps=spec.max_steps, atol=0.0, rtol=0.0,
                     throw=False, balance=False, progress=False)
    x0, _, steps = evaluation_setup(spec, 0, seed)
    ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                  xhat0=controller_start(spec, "ren", padded(x0, k)))
    return (float(np.median(np.asarray(ev.mse))), 100 * float(np.mean(np.asarray(ev.stable))),
            100 * float(np.mean(np.asarray(res.certified))))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--inits", type=int, default=40)
    parser.add_argument("--configs", default="k0,k1,k2,k4,k0d,k1d,k0w32,k1w32")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    print(f"nonlinear example, 25 initial segments, {args.inits} initialisations: median "
          "test MSE (ratio to k0 of the same seed); % stable, % certified")
    print("| config | " + " | ".join(f"seed {s}" for s in seeds) + " | worst ratio |")
    print("|---|" + "---:|" * (len(seeds) + 1))
    base = {}
    for name in args.configs.split(","):
        m = re.fullmatch(r"k(\d+)(?:w(\d+))?(d?)", name)
        if m is None:
            raise SystemExit(f"bad config {name!r}: k<K>[w<width>][d]")
        cells, ratios = [], []
        for seed in seeds:
            mse, stable, cert = run(seed, args.inits, int(m[1]), m[2] and int(m[2]), m[3] == "d")
            base.setdefault(seed, mse)  # the first config is the reference (k0)
            ratios.append(mse / base[seed])
            cells.append(f"{mse:.4g} ({ratios[-1]:.3f}); {stable:.0f}, {cert:.0f}")
        print(f"| {name} | " + " | ".join(cells) + f" | {max(ratios):.3f} |", flush=True)


if __name__ == "__main__":
    main()
