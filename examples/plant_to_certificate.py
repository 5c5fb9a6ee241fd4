"""From coarse plant knowledge to a closed-loop certificate, for both of the paper's problems.

    python examples/plant_to_certificate.py [--quick]

1. Nonlinear plant x+ = 0.5x + 0.4 sin x + u, y = x - 2u: the sector lemma (paper Lemma 8)
   gives the plant's cone supply rate (-1, 3.556, 29.333); Theorem 1's recipe gives the
   controller supply rate (-29.867, 3.556, 0.601); a static controller inside that set is
   certified and the loop is certified stable.
2. Linear mass-spring chains (zero-order hold, D = phi I): joint passivity indices rho, nu > 0 make
   Theorem 1 hold with *every* passive controller, e.g. the (passive) static gain yhat = 0.5 y.
"""

import argparse

import jax
import numpy as np

import dissil_jax as dj

jax.config.update("jax_enable_x64", True)  # examples may; the library never does


def nonlinear() -> None:
    print("== nonlinear plant (paper section 5.2) ==")
    plant_qsr = dj.sector_plant_qsr(0.5, 1.0, 1.0, -2.0, 0.4)  # Lemma 8
    print("plant QSR      ", plant_qsr, "(paper: -1, 3.556, 29.333)")
    ctrl_qsr = dj.stabilising_qsr(plant_qsr, alpha=1.0, margins=(0.399, 0.534))
    print("controller QSR ", ctrl_qsr, "(paper: -29.867, 3.556, 0.601)")
    cert = dj.closed_loop_certificate(plant_qsr, ctrl_qsr)
    print("Theorem 1 holds:", cert.holds, "alpha =", round(cert.alpha, 4))
    # A static controller yhat = 0.2 y lies in the controller cone (d in [-0.066, 0.304]).
    K = dj.LTIController(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)), [[0.2]])
    print("yhat = 0.2 y certified for the controller QSR:", dj.certify(K, ctrl_qsr).holds)
    assert cert.holds and dj.certify(K, ctrl_qsr).holds


def linear(seeds) -> None:
    print("== linear mass-spring chains (paper section 5.1) ==")
    passive = dj.QSR.passive(3)
    gain = dj.LTIController(np.zeros((1, 1)), np.zeros((1, 3)), np.zeros((3, 1)), 0.5 * np.eye(3))
    for seed in seeds:
        chain = dj.systems.mass_spring_chain(jax.random.PRNGKey(seed))  # raises unless passive
        nu = -dj.input_passivity_qsr(chain.plant).R[0, 0]
        joint = dj.passivity_indices(chain.plant)
        rho_j, nu_j = -joint.Q[0, 0], -joint.R[0, 0]
        cert = dj.closed_loop_certificate(joint, passive)
        print(f"seed {seed}: phi = {chain.phi:.4f}, nu_max = {nu:.4f}, joint (rho, nu) = "
              f"({rho_j:.4f}, {nu_j:.4f}), passive controllers certified: {cert.holds}")
        assert cert.holds and dj.certify(gain, passive).holds


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two chains instead of ten (CI)")
    quick = parser.parse_args().quick
    nonlinear()
    linear(range(2) if quick else range(10))
