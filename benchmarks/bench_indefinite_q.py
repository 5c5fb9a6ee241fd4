"""From plant to certificate on the paper's linear example: learning under each plant's own
(indefinite-Q) controller supply rate against learning under passivity.

For each of the 10 mass-spring chains of `example_spec("linear")` (seed 0):

1. plant rate: the joint passivity indices, `dj.passivity_indices(plant)`:
   Q1 = -rho I, S1 = I/2, R1 = -nu I;
2. controller rate by the rule alpha = 1, margins M1 = rho/10, M2 = nu/10:
   `dj.stabilising_qsr` gives Q2 = 0.9 nu I (positive: the trainers linearise it),
   S2 = I/2, R2 = 0.9 rho I; Theorem 1's matrix is then diag(-rho/10, -nu/10) < 0. Every
   passive controller satisfies this rate too (its supply adds Q2|y|^2 + R2|u|^2 >= 0);
3. PGD and ICO under this rate and under passivity (the paper's constraint), same windows
   (N = 25 initial segments, h = 2), same keys, same hyperparameters (the example's);
4. checks: every controller's certificate (float64 KYP at its P), Theorem 1 for the pair of
   rates, the exact closed-loop spectral radius, and test MSE against the expert on the
   protocol's test set (x0 ~ N(0, 20^2 I), up to the expert's equilibrium horizon).

Writes a markdown table to stdout and to `benchmarks/results/indefinite_q.md`.

Usage: python benchmarks/bench_indefinite_q.py [--quick] [--inits 4]
"""

import argparse
import dataclasses
import os
import pathlib
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments import evaluate, protocol  # noqa: E402

MARGIN_FRACTION = 0.1  # M1 = rho / 10, M2 = nu / 10


def controller_rate(plant):
    plant_qsr = dj.passivity_indices(plant)
    rho, nu = -plant_qsr.Q[0, 0], -plant_qsr.R[0, 0]
    qsr = dj.stabilising_qsr(plant_qsr, alpha=1.0,
                             margins=(MARGIN_FRACTION * rho, MARGIN_FRACTION * nu))
    return plant_qsr, qsr, rho, nu


def run(plants, inits, num_test, segments):
    spec = dataclasses.replace(protocol.example_spec("linear"), num_test=num_test)
    rows = []
    for i in plants:
        plant, expert, windows, (k_fit, _, k_noise) = protocol.training_data(
            spec, i, 0, "initial", segments)
        x0, _, steps = protocol.evaluation_setup(spec, i, 0)
        plant_qsr, qsr, rho, nu = controller_rate(plant)
        row = dict(plant=i, rho=rho, nu=nu, q2=float(qsr.Q[0, 0]),
                   thm_indef=dj.closed_loop_certificate(plant_qsr, qsr).holds,
                   thm_passive=dj.closed_loop_certificate(plant_qsr, dj.QSR.passive(3)).holds)
        for name, rate in (("passive", dj.QSR.passive(3)), ("indef", qsr)):
            for method in ("pgd", "ico"):
                t = time.perf_counter()
                res = protocol.fit(method, k_fit, windows, dataclasses.replace(spec, qsr=rate),
                                   inits)
                jax.block_until_ready(res.final_loss)
                wall = time.perf_counter() - t
                cert = dj.certify(res.controllers, rate, P=np.asarray(res.P))
                ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps)
                row[f"{method}_{name}"] = dict(
                    mse=float(np.median(np.asarray(ev.mse))),
                    loss=float(np.median(np.asarray(res.final_loss))),
                    rho_max=float(np.max(ev.spectral_radius)),
                    certified=bool(np.all(cert.holds) and np.all(np.asarray(res.certified))),
                    time=wall / inits)
        rows.append(row)
        print(_row_md(row), flush=True)
    return rows


def _row_md(r):
    cells = [str(r["plant"]), f"{r['rho']:.3f}", f"{r['nu']:.3f}", f"{r['q2']:.3f}",
             "yes" if r["thm_indef"] else "NO", "yes" if r["thm_passive"] else "NO"]
    for method in ("pgd", "ico"):
        a, b = r[f"{method}_passive"], r[f"{method}_indef"]
        cells += [f"{a['mse']:.3g}", f"{b['mse']:.3g}", f"{b['mse'] / a['mse']:.2f}"]
    worst = max(r[k]["rho_max"] for k in ("pgd_indef", "ico_indef"))
    cert = all(r[k]["certified"] for k in ("pgd_indef", "ico_indef", "pgd_passive",
                                           "ico_passive"))
    cells += [f"{worst:.4f}", "yes" if cert else "NO"]
    return "| " + " | ".join(cells) + " |"


HEADER = (
    "| plant | ρ | ν | Q₂ | Thm 1 (Q₂) | Thm 1 (passive) | PGD MSE passive | PGD MSE Q₂ | "
    "ratio | ICO MSE passive | ICO MSE Q₂ | ratio | max ρ(A_cl), Q₂ | all certified |\n"
    "| ---: | ---: | ---: | ---: | :---: | :---: | ---: | ---: | ---: | ---: | ---: | ---: | "
    "---: | :---: |"
)


def summary(rows):
    lines = []
    for method in ("pgd", "ico"):
        ratio = np.array([r[f"{method}_indef"]["mse"] / r[f"{method}_passive"]["mse"]
                          for r in rows])
        loss = np.array([r[f"{method}_indef"]["loss"] / r[f"{method}_passive"]["loss"]
                         for r in rows])
        t = np.array([r[f"{method}_indef"]["time"] / r[f"{method}_passive"]["time"]
                      for r in rows])
        lines.append(
            f"- {method.upper()}: test-MSE ratio (Q₂ / passive) median {np.median(ratio):.2f} "
            f"(min {ratio.min():.2f}, max {ratio.max():.2f}; lower on {int(np.sum(ratio < 1))} "
            f"of {len(rows)} plants); training-loss ratio median {np.median(loss):.2f}; "
            f"training time ratio median {np.median(t):.2f}.")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 plants, 2 initialisations")
    ap.add_argument("--inits", type=int, default=4)
    ap.add_argument("--num-test", type=int, default=100)
    ap.add_argument("--segments", type=int, default=25)
    args = ap.parse_args()
    plants = range(2) if args.quick else range(10)
    inits = 2 if args.quick else args.inits
    print(HEADER)
    t = time.perf_counter()
    rows = run(plants, inits, args.num_test, args.segments)
    text = (f"Settings: {len(rows)} plants (seed 0), N = {args.segments} initial segments, "
            f"h = 2, {inits} initialisations per method and rate, the example's "
            f"hyperparameters (max 150 steps, tol 1e-3), {args.num_test} test states. "
            f"MSE: median over the initialisations. Total wall time "
            f"{time.perf_counter() - t:.0f} s.\n\n" + HEADER + "\n"
            + "\n".join(_row_md(r) for r in rows) + "\n\n" + summary(rows) + "\n")
    print()
    print(summary(rows))
    if not args.quick:
        out = pathlib.Path(__file__).parent / "results"
        out.mkdir(exist_ok=True)
        (out / "indefinite_q.md").write_text(text)


if __name__ == "__main__":
    main()
