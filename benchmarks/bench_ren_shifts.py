"""Odd REN controllers with shifted activations, and where the test error lies, on the
nonlinear example's initial segments (tuning seeds 1 and 2; a prototype outside the library).

- **shifts** (default): odd ReLU RENs whose neurons compute
  $\\sigma(v + \\beta_i) - \\sigma(\\beta_i)$ (still slope-restricted in $[0, 1]$ and zero at
  zero, so `fit_ren`'s certificate covers them), with $\\beta$ trained or fixed, against the
  same code without shifts; median test MSE over the initialisations;
- **activations** (`--activations`): odd RENs through `dj.fit_ren` with tanh and with
  0.75 ReLU + 0.25 tanh (bounded parts; the experiments' settings otherwise);
- **errors** (`--errors`): for the median controller of REN, MLP and ICO on seed 1, the
  share of the test error at $x_1$ (the first control's effect), at $x_2$ (the second's) and
  later, and by the size of the test state $|x_0|$.

Usage: python benchmarks/bench_ren_shifts.py [--inits 20] [--activations | --errors]
"""

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import dissil_jax as dj  # noqa: E402
from dissil_jax.experiments.metrics import evaluate  # noqa: E402
from dissil_jax.experiments.protocol import (  # noqa: E402
    controller_start,
    evaluation_setup,
    example_spec,
    fit,
    training_data,
)
from dissil_jax.internal import direct_map, loss_scale, ren_map, ren_train, scaled  # noqa: E402

SPEC = example_spec("nonlinear")
MARGIN = direct_map.MARGIN


class ShiftedREN(eqx.Module):
    """A REN whose neuron $i$ computes $\\sigma(v_i + \\beta_i) - \\sigma(\\beta_i)$ (ReLU)."""

    K: dj.RENController
    beta: jax.Array

    def __call__(self, x, u):
        K, w = self.K, []
        b = K.C1 @ x + K.D12 @ u
        for i in range(b.shape[0]):
            v = b[i] + (K.D11[i, :i] @ jnp.stack(w) if i else 0.0)
            w.append(jax.nn.relu(v + self.beta[i]) - jax.nn.relu(self.beta[i]))
        w = jnp.stack(w)
        return K.A @ x + K.B1 @ w + K.B2 @ u, K.C2 @ x + K.D21 @ w + K.D22 @ u


def _odd_loss(C, W):
    run = lambda x0, y: jax.lax.scan(lambda x, u: C(x, u), x0, y)[1]
    plus = jax.vmap(run)(W.x0, W.y)
    minus = jax.vmap(run)(-W.x0, -W.y)
    return jnp.mean(jnp.sum((0.5 * (plus - minus) - W.target) ** 2, axis=(-2, -1)))


def train(key, W, inits, lr, beta_scale, beta_train, width=16, steps=150, init_scale=0.5,
          direct_input=False):
    """Odd shifted RENs as `fit_ren(odd=True)` trains them (normalised units, Adam)."""
    s2 = loss_scale(W)
    data, qsr = scaled(W, s2), SPEC.qsr
    theta = ren_map.init_ren_params(key, inits, W.n_state, width, W.n_in, W.n_out, init_scale,
                            W.y.dtype)
    beta = beta_scale * jax.random.normal(jax.random.fold_in(key, 9), (inits, width))
    params, opt = (theta, beta), optax.adam(lr)

    def loss(p):
        K = ren_map.ren_map(p[0], qsr, width, "relu", MARGIN, direct_input)[0]
        return _odd_loss(ShiftedREN(K, p[1] if beta_train else jax.lax.stop_gradient(p[1])),
                         data)

    grad = jax.vmap(jax.value_and_grad(loss))

    @jax.jit
    def step(params, state):
        J, g = grad(params)
        upd, state = jax.vmap(opt.update)(g, state, params)
        return optax.apply_updates(params, upd), state, J

    state = jax.vmap(opt.init)(params)
    for _ in range(steps):
        params, state, J = step(params, state)
    K, _, lam = jax.vmap(lambda t: ren_map.ren_map(t, qsr, width, "relu", MARGIN, direct_input))(
        params[0])
    K = ren_train.to_user_units(K, lam, s2**0.5)[0].odd_part()
    return ShiftedREN(K, jnp.concatenate([params[1], params[1]], -1)), J


def shifts(inits):
    print("| odd REN, width 16 | seed 1 | seed 2 |\n|---|---:|---:|")
    runs = [("no shifts", 0.1, 0.0, False, {}),
            ("shifts trained from 0", 0.1, 0.0, True, {}),
            ("fixed shifts N(0, 0.5^2)", 0.1, 0.5, False, {}),
            ("fixed shifts N(0, 2^2)", 0.1, 2.0, False, {}),
            ("trained from N(0, 0.5^2), step 0.03", 0.03, 0.5, True, {}),
            ("trained from 0, 30 steps", 0.1, 0.0, True, dict(steps=30)),
            ("trained from 0, direct input", 0.1, 0.0, True, dict(direct_input=True)),
            ("trained from 0, width 4, step 0.03", 0.03, 0.0, True, dict(width=4)),
            ("trained from 0, width 4, 40 steps, direct input", 0.1, 0.0, True,
             dict(width=4, steps=40, direct_input=True))]
    for name, lr, scale, trained, extra in runs:
        cells = []
        for seed in (1, 2):
            plant, expert, W, (k_fit, _, k_noise) = training_data(SPEC, 0, seed, "initial", 25)
            C, J = train(k_fit, W, inits, lr, scale, trained, **extra)
            x0, _, steps = evaluation_setup(SPEC, 0, seed)
            ev = evaluate(k_noise, plant, expert, C, x0, steps,
                          xhat0=jnp.concatenate([x0, -x0], -1))
            cells.append(f"{np.median(np.asarray(ev.mse)):.4g} (train {np.median(J):.1e})")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def activations(inits):
    import dataclasses

    mix = lambda v: 0.75 * jax.nn.relu(v) + 0.25 * jnp.tanh(v)
    print("| odd REN, width 16 | seed 1 | seed 2 |\n|---|---:|---:|")
    for name, act, lr in [("ReLU, step 0.1 (the experiments')", "relu", 0.1),
                          ("tanh, step 0.1", "tanh", 0.1), ("tanh, step 0.03", "tanh", 0.03),
                          ("0.75 ReLU + 0.25 tanh, step 0.1", mix, 0.1)]:
        spec = dataclasses.replace(SPEC, ren_activation=act, ren_learning_rate=lr)
        cells = []
        for seed in (1, 2):
            plant, expert, W, (k_fit, _, k_noise) = training_data(SPEC, 0, seed, "initial", 25)
            res = fit("ren", k_fit, W, spec, inits)
            x0, _, steps = evaluation_setup(SPEC, 0, seed)
            ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                          xhat0=controller_start(spec, "ren", x0))
            cells.append(f"{np.median(np.asarray(ev.mse)):.4g}")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def errors(inits, seed=1):
    plant, expert, W, (k_fit, _, k_noise) = training_data(SPEC, 0, seed, "initial", 25)
    x0, _, steps = evaluation_setup(SPEC, 0, seed)
    size = np.abs(np.asarray(x0[:, 0]))
    edges = [0, 5, 10, 20, 30, np.inf]
    print(f"seed {seed}, median controller of {inits}: share of the test error")
    print("| method | at x1 | at x2 | later | " + " | ".join(
        f"|x0| in [{a:g}, {b:g})" for a, b in zip(edges, edges[1:])) + " |")
    print("|---|---:|---:|---:|" + "---:|" * (len(edges) - 1))
    for method in ("ren", "mlp", "ico"):
        res = fit(method, k_fit, W, SPEC, inits)
        ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                      xhat0=controller_start(SPEC, method, x0))
        mse = np.asarray(ev.mse)
        i = int(np.argsort(mse)[len(mse) // 2])
        d = np.sum((np.asarray(ev.learned.x)[i, :, 1:] - np.asarray(ev.expert.x)[:, 1:]) ** 2, -1)
        per_state = d.sum(1)
        share = [per_state[(size >= a) & (size < b)].sum() / per_state.sum()
                 for a, b in zip(edges, edges[1:])]
        at = d.sum(0) / d.sum()
        print(f"| {method} | {at[0]:.2f} | {at[1]:.2f} | {at[2:].sum():.2f} | "
              + " | ".join(f"{s:.3f}" for s in share) + " |", flush=True)
    print("test states per bin:", [int(((size >= a) & (size < b)).sum())
                                   for a, b in zip(edges, edges[1:])])


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inits", type=int, default=20)
    parser.add_argument("--activations", action="store_true")
    parser.add_argument("--errors", action="store_true")
    args = parser.parse_args()
    run = errors if args.errors else activations if args.activations else shifts
    run(args.inits)
