"""Learn under a plant's own controller supply rate, whose Q is positive (an indefinite Q).

    python examples/indefinite_q.py [--quick]

For chains of the paper's linear example (zero-order hold, D = phi I, so every chain has
excess passivity):

1. the plant's joint passivity indices give its rate (Q1, S1, R1) = (-rho I, I/2, -nu I);
2. `dj.stabilising_qsr` with alpha = 1 and margins (rho/10, nu/10) gives the controller
   rate (0.9 nu I, I/2, 0.9 rho I): Q2 > 0, a larger set than the passive controllers;
3. PGD and ICO learn under it (they linearise Q2's positive part);
4. every controller is checked: its certificate (float64 KYP), Theorem 1 for the pair of
   rates, and the exact closed-loop spectral radius.
"""

import argparse

import jax
import numpy as np

import dissil_jax as dj
from dissil_jax.experiments import lti_spectral_radius, protocol

jax.config.update("jax_enable_x64", True)  # examples may; the library never does


def main(plants, inits, max_steps) -> None:
    spec = protocol.example_spec("linear")
    for i in plants:
        plant, _, windows, (key, _, _) = protocol.training_data(spec, i, 0, "initial", 25)
        plant_qsr = dj.passivity_indices(plant)
        rho, nu = -plant_qsr.Q[0, 0], -plant_qsr.R[0, 0]
        qsr = dj.stabilising_qsr(plant_qsr, alpha=1.0, margins=(0.1 * rho, 0.1 * nu))
        thm = dj.closed_loop_certificate(plant_qsr, qsr)
        print(f"plant {i}: rho = {rho:.3f}, nu = {nu:.3f} -> controller Q2 = "
              f"{qsr.Q[0, 0]:.3f} I, R2 = {qsr.R[0, 0]:.3f} I; Theorem 1: {thm.holds}")
        assert thm.holds
        for name, fit in (("PGD", dj.fit_pgd), ("ICO", dj.fit_ico)):
            res = fit(key, windows, qsr, num_inits=inits, max_steps=max_steps, atol=spec.tol)
            cert = dj.certify(res.controllers, qsr, P=np.asarray(res.P))
            radius = lti_spectral_radius(plant, res.controllers)
            print(f"  {name}: final loss {np.median(np.asarray(res.final_loss)):.4f}, "
                  f"certified {bool(cert.holds.all())}, closed-loop spectral radius "
                  f"<= {radius.max():.4f}")
            assert cert.holds.all() and np.all(radius < 1)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one chain, few steps (CI)")
    quick = parser.parse_args().quick
    main(range(1) if quick else range(3), 2 if quick else 4, 5 if quick else 150)
