"""A learning-rate sweep done with `jax.vmap`: one compiled program trains every setting.

`dj.pgd_run` is the pure, traceable PGD loop behind `dj.fit_pgd`, so it can be vmapped over
its hyperparameters (learning rate, decay, initialisation scale). The host projection is a
`jax.pure_callback` with `vmap_method="broadcast_all"`: each training step sends all
(learning rate x initialisation) controllers to the host at once.

Run:  python examples/lr_sweep.py [--quick]
"""

import argparse
import time

import jax
import jax.numpy as jnp
from quickstart import demonstrations

import dissil_jax as dj


def main(quick: bool = False):
    jax.config.update("jax_enable_x64", True)
    windows = demonstrations(jax.random.PRNGKey(0), num=25)
    qsr = dj.QSR(-29.867, 3.556, 0.601)
    # eta_0 of the paper's decaying-step rule, selected by `learning_rate` (normalised
    # units; the rule's default is 1, while the trainers' default step is Adam at 0.1)
    lrs = jnp.logspace(-2, 0.5, 4 if quick else 8)
    steps = 30 if quick else 150

    def run(lr):
        return dj.pgd_run(jax.random.PRNGKey(1), windows, qsr, learning_rate=lr,
                          num_inits=4, max_steps=steps, atol=1e-5)

    t = time.perf_counter()
    res = jax.jit(jax.vmap(run))(lrs)
    jax.block_until_ready(res.final_loss)
    print(f"{len(lrs)} learning rates x 4 initialisations in {time.perf_counter() - t:.1f} s")
    print(f"{'learning rate':>14s} {'median final loss':>18s} {'mean steps':>11s} {'certified':>10s}")
    for j, lr in enumerate(lrs):
        print(f"{float(lr):14.2e} {float(jnp.median(res.final_loss[j])):18.5f} "
              f"{float(jnp.mean(res.steps[j])):11.1f} {str(bool(jnp.all(res.certified[j]))):>10s}")
    best = int(jnp.argmin(jnp.median(res.final_loss, axis=1)))
    print(f"best learning rate: {float(lrs[best]):.2e}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes (CI)")
    main(parser.parse_args().quick)
