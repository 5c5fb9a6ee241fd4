"""The step-size sweep behind the reproduction's PGD/GD learning rates."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import dissil_jax as dj
from dissil_jax.experiments.protocol import example_spec, training_data
from dissil_jax.experiments.tuning import choose_rate, learning_rate_sweep, sweep_markdown


def test_sweep_equals_separate_runs_and_picks_the_lowest_median():
    spec = dataclasses.replace(example_spec("nonlinear"), max_steps=15)
    lrs = [1e-4, 3e-3, 1e-1]
    out = learning_rate_sweep("nonlinear", "gd", lrs, segments=5, inits=4, spec=spec)
    J = np.asarray(out["final_loss"])  # [plants, rates, inits]
    assert J.shape == (1, 3, 4)
    # Each rate equals a separate (unswept) GD run on the same training windows.
    _, _, windows, (k_fit, _, _) = training_data(spec, 0, 0, "initial", 5)
    for j, lr in enumerate(lrs):
        res = dj.fit_gd(k_fit, windows, learning_rate=lr, decay=spec.pgd_decay, throw=False,
                        init_scale=spec.init_scale, num_inits=4, max_steps=15, atol=spec.tol,
                        balance=False)  # the sweep's pgd_run trains in one scale
        ref = np.where(np.isfinite(res.final_loss), res.final_loss, np.inf)
        np.testing.assert_allclose(J[0, j], ref, rtol=1e-9)
    med = np.median(J[0], axis=1)
    assert out["best"] == lrs[int(np.argmin(med))]
    np.testing.assert_allclose(out["median_loss"], med)
    assert f"chosen: {out['best']:g}" in sweep_markdown([out])
    with pytest.raises(ValueError, match="`learning_rates`"):
        learning_rate_sweep("nonlinear", "gd", [0.1, -1.0], spec=spec)
    with pytest.raises(ValueError, match="`method`"):
        learning_rate_sweep("nonlinear", "ico", lrs, spec=spec)
    assert jnp.isfinite(jnp.asarray(out["median_loss"][0]))


def _sweep(medians, lrs=(0.01, 0.1, 1.0), data="initial"):
    return dict(example="linear", method="pgd", data=data, segments=2, plants=1, inits=1,
                learning_rates=list(lrs), median_loss=list(medians),
                diverged=[0.0] * len(lrs))


def test_choose_rate_minimises_the_worst_regret():
    # regrets: A = [100, 10, 1], B = [10, 1, 1e4]; worst = [100, 10, 1e4] -> the middle rate,
    # which is best in neither configuration.
    a, b = _sweep([1.0, 0.1, 0.01]), _sweep([1.0, 0.1, 1000.0], data="sliding")
    best, regret = choose_rate([a, b])
    assert best == 0.1
    np.testing.assert_allclose(regret, [[100, 10, 1], [10, 1, 1e4]])
    assert choose_rate([a])[0] == 1.0  # one configuration: the lowest median
    assert choose_rate([_sweep([np.inf, 2.0, np.inf])])[0] == 0.1  # diverged medians lose
    text = sweep_markdown([a, b])
    assert "chosen: 0.1" in text and "median J, sliding N=2" in text
    with pytest.raises(ValueError, match="`sweeps`"):
        choose_rate([a, _sweep([1.0, 2.0], lrs=(0.1, 1.0))])
    with pytest.raises(ValueError, match="`sweeps`"):
        choose_rate([])
