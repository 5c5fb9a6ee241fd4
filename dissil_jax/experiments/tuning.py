"""Step sizes for PGD and GD, chosen by the library's own vmapped sweep on training loss.

The paper states that "an exponentially decaying learning rate was used" (paper §4.2) but
not its value. We pick it per example and per method by running [`pgd_run`][dissil_jax.pgd_run]
vmapped over a grid of initial learning rates on the training windows of one configuration
(never on test data), and take the rate with the lowest median final training loss $J$
over plants and initialisations. A run whose loss becomes non-finite (GD diverging) counts
as $J = \\infty$.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .protocol import ExampleSpec, example_spec, training_data


def learning_rate_sweep(example: str, method: str, learning_rates, *, segments: int = 25,
                        data: str = "initial", inits: int = 10, plants: int | None = None,
                        seed: int = 0, spec: ExampleSpec | None = None) -> dict:
    """Final training losses of PGD or GD for every learning rate in `learning_rates`.

    **Arguments:** `example` ("linear"/"nonlinear"), `method` ("pgd"/"gd"), the grid
    `learning_rates`, the configuration (`segments`, `data`, `seed`), `inits`
    initialisations per plant and the first `plants` plants (default: all of the example).

    **Returns:** a dict with `learning_rates`, `final_loss` `[plants, rates, inits]`
    (`inf` where the loss diverged), `median_loss` and `diverged` (fraction of runs with
    a non-finite loss) per rate, and `best`, the rate with the lowest median.
    """
    import dissil_jax as dj

    if method not in ("pgd", "gd"):
        raise ValueError(f"`method` must be 'pgd' or 'gd', got {method!r}.")
    spec = spec or example_spec(example)
    lrs = np.asarray(learning_rates, np.float64)
    if lrs.ndim != 1 or lrs.size == 0 or not np.all(np.isfinite(lrs) & (lrs > 0)):
        raise ValueError(f"`learning_rates` must be a non-empty list of positive numbers, got "
                         f"{learning_rates!r}.")
    qsr = spec.qsr if method == "pgd" else None
    losses = []
    for i in range(plants or spec.num_plants):
        _, _, windows, (k_fit, _, _) = training_data(spec, i, seed, data, segments)

        def run(lr, windows=windows, k_fit=k_fit):
            return dj.pgd_run(k_fit, windows, qsr, learning_rate=lr, decay=spec.pgd_decay,
                              init_scale=spec.init_scale, num_inits=inits,
                              max_steps=spec.max_steps, tol=spec.tol).final_loss

        J = np.asarray(jax.jit(jax.vmap(run))(jnp.asarray(lrs, windows.y.dtype)))
        losses.append(np.where(np.isfinite(J), J, np.inf))
    J = np.stack(losses)  # [plants, rates, inits]
    per_rate = np.moveaxis(J, 1, 0).reshape(len(lrs), -1)
    median = np.median(per_rate, axis=1)
    return dict(example=example, method=method, data=data, segments=int(segments),
                inits=int(inits), plants=int(J.shape[0]), learning_rates=lrs.tolist(),
                final_loss=J.tolist(), median_loss=median.tolist(),
                diverged=np.mean(~np.isfinite(per_rate), axis=1).tolist(),
                best=float(lrs[int(np.argmin(median))]))


def sweep_markdown(sweeps: list[dict]) -> str:
    """A markdown table per sweep: median final training loss and share diverged per rate."""
    out = []
    for s in sweeps:
        out += [f"**{s['method'].upper()}, {s['example']} example** ({s['data']}, "
                f"N = {s['segments']}, {s['plants']} plant(s) × {s['inits']} inits); "
                f"chosen: {s['best']:g}", "",
                "| learning rate | median final J | diverged |", "|---:|---:|---:|"]
        for lr, med, div in zip(s["learning_rates"], s["median_loss"], s["diverged"]):
            mark = " ←" if lr == s["best"] else ""
            out.append(f"| {lr:g}{mark} | {med:.4g} | {100 * div:.0f} % |")
        out.append("")
    return "\n".join(out)


__all__ = ["learning_rate_sweep", "sweep_markdown"]
