"""The direct parameterisation (`dj.fit_direct`) against PGD and ICO.

Both of the paper's examples with 25 initial segments: the nonlinear one with 100
initialisations (QSR (−29.867, 3.556, 0.601)), the linear one's first plant with 20
(n̂ = 6, m = p = 3, passive). Every method runs with the protocol's settings
(`dissil_jax.experiments.protocol.fit`: the paper's tol for PGD and ICO; direct runs all 150
Adam steps at `ExampleSpec.direct_learning_rate`). Per method:

- **wall (s)**: training wall time of the second of two identical calls (so JIT
  compilation is excluded for every method), and its ratio to PGD's in the same run;
- **train loss**: median final training loss over the initialisations;
- **test MSE**: median closed-loop test MSE against the expert (`metrics.evaluate`, the
  reproduction's test states and noise, as `run_config`);
- **% cert. before**: controllers whose own `(K, P)` passes the exact float64 check before
  any fallback: for direct the map's output (in the data's dtype); PGD and ICO verify
  every iterate inside the loop, so theirs is the returned `certified`;
- **% cert.**: after the final check (direct: after the fallback projection, if any).

Also: direct in float32 (the windows cast to float32), the issue's failure case
Q = −1e-4·I on the linear data, and two sweeps on training loss only that chose the
defaults: Adam's learning rate and the map's margin ε (with the smallest relative KYP
margin, margin / `kyp_scale`, that the float64 check compares with 1e-11).

Usage: python benchmarks/bench_direct.py [--quick]
"""

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments.metrics import evaluate  # noqa: E402
from dissil_jax.experiments.protocol import (  # noqa: E402
    evaluation_setup,
    example_spec,
    fit,
    training_data,
)
from dissil_jax.internal import kyp_margin, kyp_scale  # noqa: E402


def _f32(w):
    return dj.Windows(*(jnp.asarray(a, jnp.float32) for a in (w.x0, w.y, w.u)))


def timed(run):
    run()  # compile
    t = time.perf_counter()
    res = run()
    jax.block_until_ready(res.final_loss)
    return res, time.perf_counter() - t


def test_mse(spec, res):
    plant, expert, _, (_, _, k_noise) = training_data(spec, 0, 0, "initial", 25)
    x0, _, steps = evaluation_setup(spec, 0, 0)
    K = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), res.controllers)
    return float(np.median(np.asarray(evaluate(k_noise, plant, expert, K, x0, steps).mse)))


def min_rel_margin(res, qsr):
    K = res.controllers
    mats = [np.asarray(M, np.float64) for M in (K.A, K.B, K.C, K.D, res.P)]
    return float(np.min(kyp_margin(*mats[:4], qsr, mats[4]) / kyp_scale(*mats[:4], qsr,
                                                                           mats[4])))


def row(name, res, wall, pgd_wall, spec, mse=True):
    before = np.asarray(res.certified) & ~np.asarray(
        res.projected if res.projected is not None else False)
    return dict(method=name, wall=wall, ratio=wall / pgd_wall,
                loss=float(np.median(res.final_loss)),
                mse=test_mse(spec, res) if mse else float("nan"),
                before=100 * float(before.mean()), after=100 * float(np.mean(res.certified)))


def compare(example, inits, quick):
    spec = example_spec(example)
    _, _, w, (k_fit, _, _) = training_data(spec, 0, 0, "initial", 25)
    rows, res = [], {}
    for method in ("pgd", "ico", "direct"):
        res[method], wall = timed(lambda: fit(method, k_fit, w, spec, inits))
        if method == "pgd":
            pgd_wall = wall
        rows.append(row({"pgd": "PGD", "ico": "ICO", "direct": "Direct"}[method], res[method],
                        wall, pgd_wall, spec))
    # the library's defaults (step, initial scale, budget, relative stopping rule)
    res["defaults"], wall = timed(lambda: dj.fit_direct(k_fit, w, spec.qsr, num_inits=inits,
                                                        throw=False))
    rows.append(row("Direct, library defaults", res["defaults"], wall, pgd_wall, spec))
    kw = dict(num_inits=inits, learning_rate=spec.direct_learning_rate, atol=spec.direct_tol,
              init_scale=spec.direct_init_scale, throw=False)
    r, wall = timed(lambda: dj.fit_direct(k_fit, _f32(w), spec.qsr, **kw))
    rows.append(row("Direct, float32", r, wall, pgd_wall, spec))
    if example == "linear":
        near = dj.QSR(-1e-4 * np.eye(3), np.eye(3) / 2, np.zeros((3, 3)))
        for dtype, ww in (("float64", w), ("float32", _f32(w))):
            r, wall = timed(lambda: dj.fit_direct(k_fit, ww, near, **kw))
            rows.append(row(f"Direct, Q = −1e-4·I, {dtype}", r, wall, pgd_wall, spec,
                            mse=False))
    print(f"\n### {example.capitalize()} example ({inits} initialisations, 25 initial "
          "segments)\n")
    print("| method | wall (s) | wall / PGD | train loss | test MSE | % cert. before | "
          "% cert. |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['method']} | {r['wall']:.3g} | {r['ratio']:.3g} | {r['loss']:.3g} | "
              f"{r['mse']:.3g} | {r['before']:.0f} | {r['after']:.0f} |")
    ico = float(np.median(res["ico"].final_loss))
    for m in ("direct", "defaults"):
        print(f"\n{'Direct' if m == 'direct' else 'Direct with defaults'}: median training "
              f"loss / ICO's {float(np.median(res[m].final_loss)) / ico:.2f}")
    if not quick:
        sweeps(spec, w, k_fit, inits)


def sweeps(spec, w, key, inits):
    plants = 3 if spec.name == "linear" else 1
    data = [training_data(spec, i, 0, "initial", 25) for i in range(plants)]
    ico = [float(np.median(fit("ico", d[3][0], d[2], spec, inits).final_loss)) for d in data]
    rates = (0.1, 0.3, 0.5, 1.0)
    print(f"\nLearning rate and initial scale (float64, margin 1e-2): median training loss / "
          f"ICO's, on plant(s) {', '.join(str(i) for i in range(plants))}:\n")
    print("| init_scale | " + " | ".join(f"lr {lr:g}" for lr in rates) + " |")
    print("| --- |" + " ---: |" * len(rates))
    for scale in (0.2, 0.5, 1.0):
        cells = []
        for lr in rates:
            ratios = [float(np.median(dj.fit_direct(d[3][0], d[2], spec.qsr, num_inits=inits,
                                                    learning_rate=lr, init_scale=scale,
                                                    atol=0.0, rtol=0.0, throw=False).final_loss)) / j
                      for d, j in zip(data, ico)]
            cells.append(", ".join(f"{r:.2f}" for r in ratios))
        print(f"| {scale:g} | " + " | ".join(cells) + " |")
    print(f"\nMargin ε (learning rate {spec.direct_learning_rate:g}, init_scale "
          f"{spec.direct_init_scale:g}):\n")
    print("| ε | train loss f64 | min margin/scale f64 | train loss f32 | "
          "min margin/scale f32 | % cert. before (f64, f32) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for margin in (1e-3, 1e-2, 3e-2):
        out = []
        for ww in (w, _f32(w)):
            r = dj.fit_direct(key, ww, spec.qsr, num_inits=inits, atol=0.0, rtol=0.0, margin=margin,
                              learning_rate=spec.direct_learning_rate,
                              init_scale=spec.direct_init_scale, throw=False)
            out.append((float(np.median(r.final_loss)), min_rel_margin(r, spec.qsr),
                        100 * float(np.mean(~np.asarray(r.projected)))))
        print(f"| {margin:g} | {out[0][0]:.3g} | {out[0][1]:.2g} | {out[1][0]:.3g} | "
              f"{out[1][1]:.2g} | {out[0][2]:.0f}, {out[1][2]:.0f} |")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="fewer initialisations, no sweeps")
    parser.add_argument("--no-sweeps", action="store_true", help="all initialisations, no sweeps")
    args = parser.parse_args()
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, float64 unless stated")
    skip = args.quick or args.no_sweeps
    compare("nonlinear", 20 if args.quick else 100, skip)
    compare("linear", 4 if args.quick else 20, skip)


if __name__ == "__main__":
    main()
