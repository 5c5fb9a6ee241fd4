"""Learn a QSR-dissipative controller from a few demonstrations, then certify it.

Plant (the paper's nonlinear example): x+ = 0.5 x + 0.4 sin x + u,  y = x - 2u.
Expert (a stand-in for the paper's NMPC, kept simple so this runs in seconds): u = -0.45 x
plus N(0, 0.02^2) control noise; plant noise N(0, 0.04^2) on the state.
Controller supply rate: the paper's (Q, S, R) = (-29.867, 3.556, 0.601), which Theorem 1
pairs with the plant's (-1, 3.556, 29.333) into a stable loop.

Run:  python examples/quickstart.py [--quick]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import dissil_jax as dj


def demonstrations(key, num, horizon=2):
    """First `horizon` steps of `num` expert trajectories from x0 ~ N(0, 5^2)."""
    kx, kw, kv = jax.random.split(key, 3)
    x = 5.0 * jax.random.normal(kx, (num,))
    w = 0.04 * jax.random.normal(kw, (horizon, num))
    v = 0.02 * jax.random.normal(kv, (horizon, num))
    x0, ys, us = x, [], []
    for k in range(horizon):
        u = -0.45 * x + v[k]
        ys.append(x - 2 * u)
        us.append(u)
        x = 0.5 * x + 0.4 * jnp.sin(x) + u + w[k]
    return dj.Windows(x0[:, None], jnp.stack(ys, 1)[..., None], jnp.stack(us, 1)[..., None])


def main(quick: bool = False):
    jax.config.update("jax_enable_x64", True)  # an application's choice, not the library's
    key = jax.random.PRNGKey(0)
    windows = demonstrations(key, num=25)
    plant_qsr = dj.QSR(-1.0, 3.556, 29.333)
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    holds, alpha = dj.closed_loop_certificate(plant_qsr, qsr)
    print(f"Theorem 1 for plant {plant_qsr} and controller {qsr}: holds={holds}, alpha={alpha:.3g}")

    t = time.perf_counter()
    res = dj.fit_pgd(jax.random.PRNGKey(1), windows, qsr, num_inits=4 if quick else 10,
                     max_steps=40 if quick else 150, atol=1e-5)
    print(f"PGD: {res.num_inits} initialisations in {time.perf_counter() - t:.2f} s")
    for i in range(res.num_inits):
        print(f"  init {i}: loss {float(res.initial_loss[i]):8.4f} -> {float(res.final_loss[i]):8.4f}"
              f"  ({int(res.steps[i])} steps, certified={bool(res.certified[i])})")
    i = int(jnp.argmin(res.final_loss))
    K = jax.tree.map(lambda a: a[i], res.controllers)
    cert = dj.certify(K, qsr)
    print("best controller (A, B, C, D) =",
          np.round([float(K.A[0, 0]), float(K.B[0, 0]), float(K.C[0, 0]), float(K.D[0, 0])], 4))
    print(f"independent KYP certificate: holds={cert.holds}, margin={cert.margin:.3g}, "
          f"P={np.round(cert.P, 4).tolist()}")
    # Unconstrained runs may diverge; throw=False returns them (stop_reason "non_finite").
    gd = dj.fit_gd(jax.random.PRNGKey(1), windows, num_inits=4, max_steps=40 if quick else 150,
                   atol=1e-5, throw=False)
    Kg = jax.tree.map(lambda a: a[int(jnp.nanargmin(gd.final_loss))], gd.controllers)
    print(f"unconstrained GD reaches loss {float(gd.final_loss.min()):.4f}; "
          f"dissipative w.r.t. the controller QSR: {dj.certify(Kg, qsr).holds}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (CI)")
    main(parser.parse_args().quick)
