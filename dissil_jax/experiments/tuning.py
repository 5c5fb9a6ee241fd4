"""Step sizes for PGD and GD, chosen by the library's own vmapped sweep on training loss.

The paper states that "an exponentially decaying learning rate was used" (paper §4.2) but
not its value. We pick it per example and per method by running [`pgd_run`][dissil_jax.pgd_run]
vmapped over a grid of initial learning rates on the training windows of several
configurations (data regime x N; never on test data). In each configuration a rate's score
is its median final training loss $J$ over plants and initialisations, divided by the best
rate's median there (its regret, $\\ge 1$); the chosen rate has the smallest worst-case
regret over the configurations ([`choose_rate`]). One rate must serve every configuration
of the example, and a rate that is best at N = 25 can oscillate at N = 2 or on sliding
windows. A run whose loss becomes non-finite (GD diverging) counts as $J = \\infty$.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._validate import check_int
from .data import check_seed
from .protocol import ExampleSpec, example_spec, provenance, require_float64, training_data


def learning_rate_sweep(example: str, method: str, learning_rates, *, segments: int = 25,
                        data: str = "initial", inits: int = 10, plants: int | None = None,
                        seed: int = 0, spec: ExampleSpec | None = None) -> dict:
    """Final training losses of PGD or GD for every learning rate in `learning_rates`.

    **Arguments:** `example` ("linear"/"nonlinear"), `method` ("pgd"/"gd"), the grid
    `learning_rates`, the configuration (`segments`, `data`, `seed`), `inits`
    initialisations per plant and the first `plants` plants (default: all of the example).

    **Returns:** a dict with `learning_rates`, `final_loss` `[plants, rates, inits]`
    (`inf` where the loss diverged), `median_loss` and `diverged` (fraction of runs with
    a non-finite loss) per rate, `best`, the rate with the lowest median, and what produced
    them: the configuration, the `seed`, the example's `max_steps`, `decay`, `tol` and
    `init_scale`, and `protocol.provenance` (`dtype`, versions, date). Refuses to run
    without float64, as the command line does.
    """
    import dissil_jax as dj

    if method not in ("pgd", "gd"):
        raise ValueError(f"`method` must be 'pgd' or 'gd', got {method!r}.")
    segments, inits = check_int("segments", segments), check_int("inits", inits)
    seed = check_seed(seed)
    if plants is not None:
        plants = check_int("plants", plants)
    require_float64()
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
                              max_steps=spec.max_steps, atol=spec.tol, rtol=0.0,
                              keep="last", throw=False).final_loss

        J = np.asarray(jax.jit(jax.vmap(run))(jnp.asarray(lrs, windows.y.dtype)))
        losses.append(np.where(np.isfinite(J), J, np.inf))
    J = np.stack(losses)  # [plants, rates, inits]
    per_rate = np.moveaxis(J, 1, 0).reshape(len(lrs), -1)
    median = np.median(per_rate, axis=1)
    return dict(example=example, method=method, data=data, segments=segments,
                inits=inits, plants=int(J.shape[0]), learning_rates=lrs.tolist(),
                final_loss=J.tolist(), median_loss=median.tolist(),
                diverged=np.mean(~np.isfinite(per_rate), axis=1).tolist(),
                best=float(lrs[int(np.argmin(median))]), seed=seed, max_steps=spec.max_steps,
                decay=spec.pgd_decay, tol=spec.tol, init_scale=spec.init_scale,
                **provenance(windows.y.dtype))


def choose_rate(sweeps: list[dict]) -> tuple[float, np.ndarray]:
    """The rate with the smallest worst-case regret over several sweeps of one method.

    **Arguments:** `sweeps`, results of `learning_rate_sweep` over the same grid (one per
    configuration).

    **Returns:** `(rate, regret)` with `regret` `[configs, rates]`: each rate's median final
    loss over the best median of its configuration (`inf` where the median diverged).
    """
    grids = {tuple(s["learning_rates"]) for s in sweeps}
    if not sweeps or len(grids) != 1:
        raise ValueError("`sweeps` must be a non-empty list of sweeps over one grid of rates.")
    med = np.asarray([s["median_loss"] for s in sweeps], np.float64)
    regret = med / med.min(axis=1, keepdims=True)
    lrs = sweeps[0]["learning_rates"]
    return float(lrs[int(np.argmin(regret.max(axis=0)))]), regret


def sweep_markdown(sweeps: list[dict]) -> str:
    """Markdown per method: median final training loss per rate and configuration, the
    share of diverged runs, the worst-case regret, and the rate `choose_rate` picks."""
    out = []
    for method in dict.fromkeys(s["method"] for s in sweeps):
        group = [s for s in sweeps if s["method"] == method]
        best, regret = choose_rate(group)
        first = group[0]
        configs = [f"{s['data']} N={s['segments']}" for s in group]
        out += [f"**{method.upper()}, {first['example']} example** ({first['plants']} plant(s) "
                f"× {first['inits']} inits per configuration); chosen: {best:g}", "",
                "| learning rate | " + " | ".join(f"median J, {c}" for c in configs)
                + " | diverged | worst regret |",
                "|---:|" + "---:|" * (len(configs) + 2)]
        for j, lr in enumerate(first["learning_rates"]):
            mark = " ←" if lr == best else ""
            meds = " | ".join(f"{s['median_loss'][j]:.4g}" for s in group)
            div = np.mean([s["diverged"][j] for s in group])
            out.append(f"| {lr:g}{mark} | {meds} | {100 * div:.0f} % | "
                       f"{regret[:, j].max():.3g} |")
        out.append("")
    return "\n".join(out)


__all__ = ["learning_rate_sweep", "choose_rate", "sweep_markdown"]
