"""The paper's experiment protocol (§5): one configuration = (example, data, method, N).

A configuration trains `inits` controllers per plant on N expert windows, tests every
controller in closed loop against the expert from the same test states and noise, and
aggregates the paper's metrics. Training and test data depend only on the seed, the
example, the data regime, N and the plant index, so every method sees the same data.

Choices the paper leaves open (see `docs/problems.md`) are collected in `ExampleSpec`.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import os
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._supply import QSR
from .._validate import check_int
from .data import REGIMES, check_seed, demonstration_windows
from .metrics import evaluate, quantiles as _q
from .simulate import equilibrium_horizon

METHODS = ("ico", "ico_nc", "pgd", "gd", "mlp", "direct", "ren")
#: The paper's methods: the command line's default. `direct` (`dj.fit_direct`) and `ren`
#: (`dj.fit_ren`, certified nonlinear REN controllers) are our extensions, run with
#: `--methods direct ren`.
PAPER_METHODS = ("ico", "ico_nc", "pgd", "gd", "mlp")
EXAMPLES = ("linear", "nonlinear")
METHOD_LABELS = {"ico": "ICO", "ico_nc": "ICO-NC", "pgd": "PGD", "gd": "GD", "mlp": "GD+NN",
                 "direct": "Direct (ours)", "ren": "REN (ours)"}
#: Why the experiments refuse to train without float64 (the command line, `run_config`,
#: `fit` and `tuning.learning_rate_sweep` alike): in float32 the records differ (a worst
#: test MSE 27 % off in one audited configuration) without any sign in the numbers.
FLOAT64_MESSAGE = ("run the experiments with float64 enabled: set JAX_ENABLE_X64=1 before "
                   "importing jax, or call jax.config.update(\"jax_enable_x64\", True) "
                   "first (the command line sets it up itself).")


def require_float64() -> None:
    """Raise a `ValueError` (`FLOAT64_MESSAGE`) unless JAX's float64 is enabled."""
    if not jax.config.read("jax_enable_x64"):
        raise ValueError(FLOAT64_MESSAGE)


@dataclasses.dataclass(frozen=True)
class ExampleSpec:
    """Everything that defines one of the paper's two problems."""

    name: str
    qsr: QSR  # the controller's supply rate
    num_plants: int  # paper: 10 random chains (linear), 1 (nonlinear)
    train_std: float  # x0 ~ N(0, train_std^2) for demonstrations
    test_std: float  # x0 ~ N(0, test_std^2) for testing
    num_test: int  # test initial states per plant
    equilibrium_search: int  # steps simulated to find the expert's equilibrium horizon
    min_test_steps: int  # test loops run max(expert's equilibrium horizon, this) steps
    tol: float  # stopping rule |dJ| < tol (paper: 1e-3 linear, 1e-5 nonlinear)
    max_steps: int  # paper: 150
    hidden: tuple[int, ...]  # MLP baseline widths (paper: 3 x 150 linear, 3 x 25 nonlinear)
    pgd_learning_rate: float  # initial step of PGD (paper silent; chosen by `tuning.py`)
    gd_learning_rate: float  # initial step of GD (idem)
    pgd_decay: float  # per-step decay of both (paper: "exponentially decaying")
    init_scale: float
    # `dj.fit_direct` (ours, not the paper's): Adam's step, the scale of the initial draw of
    # the map's parameters (not controller entries) and the stopping tolerance, chosen on
    # training loss by `benchmarks/bench_direct.py`. tol 0 runs all `max_steps`: a step
    # costs microseconds, and Adam's |dJ| can drop below the paper's tol on a plateau.
    direct_learning_rate: float = 0.3
    direct_init_scale: float = 0.5
    direct_tol: float = 0.0
    # `dj.fit_ren` (ours): width, activation, Adam's step and initial scale (None:
    # `fit_ren`'s defaults; the examples pin the values they were chosen with, `fit_direct`'s
    # rule (0.3, 0.5), which were `fit_ren`'s defaults then) and whether the neurons see the plant output directly. All steps
    # run (tol 0), as for `direct`. Chosen on test MSE of other draws than the reported one
    # (benchmarks/README.md, "REN controllers"): nonlinear on seeds 1 and 2 (20
    # initialisations; ReLU 0.0124-0.0132 and 0.0099-0.0106 for widths 8-32, steps
    # 0.01-0.3, initial scales 0.1-1 and 150 or 600 steps, tanh 0.02-0.24), linear on the
    # first three plants of seed 1 (width 4, initial scale 0.03 gave 0.096 against 0.17-4.3
    # for larger scales, other steps or width 16; the LTI direct map 0.41). The nonlinear
    # example's REN is odd (`fit_ren(odd=True)`; the expert is odd, the plant being odd and
    # the cost even) with Adam's step 0.1: the smallest worst-case regret over initial
    # segments and sliding windows (N = 25) on seeds 1 and 2 among steps 0.03-0.3 and
    # widths 16 and 32 (1.034); without `odd`, seed 2's sliding windows tested 10x worse.
    ren_width: int = 16
    ren_activation: str = "relu"
    ren_learning_rate: float | None = 0.03
    ren_init_scale: float | None = None
    ren_direct_input: bool = False
    ren_odd: bool = False
    # The MLP baseline's step limit: `fit_mlp`'s default (Adam steps are cheap, and its
    # stopping rule is the paper's |dJ| < tol); `--quick` caps it at 30 as the others.
    mlp_max_steps: int = 2000


def example_spec(name: str, quick: bool = False) -> ExampleSpec:
    """The paper's settings for `name` in {"linear", "nonlinear"}; `quick` shrinks sizes."""
    if name == "linear":
        spec = ExampleSpec(
            name="linear", qsr=QSR.passive(3), num_plants=10, train_std=1.0, test_std=20.0,
            num_test=100, equilibrium_search=2000, min_test_steps=1, tol=1e-3, max_steps=150,
            hidden=(150, 150), pgd_learning_rate=0.3, gd_learning_rate=0.1, pgd_decay=0.99,
            init_scale=1.0, direct_learning_rate=0.5, ren_width=4, ren_learning_rate=0.3,
            ren_init_scale=0.03,
        )
    elif name == "nonlinear":
        spec = ExampleSpec(
            name="nonlinear", qsr=QSR(-29.867, 3.556, 0.601), num_plants=1, train_std=5.0,
            test_std=15.0, num_test=1000, equilibrium_search=200, min_test_steps=30, tol=1e-5,
            max_steps=150, hidden=(25, 25), pgd_learning_rate=1.0, gd_learning_rate=0.3,
            pgd_decay=0.99, init_scale=1.0, direct_learning_rate=0.1, ren_learning_rate=0.1,
            ren_init_scale=0.5, ren_odd=True,
        )
    else:
        raise ValueError(f"`example` must be one of {EXAMPLES}, got {name!r}.")
    if quick:
        spec = dataclasses.replace(spec, num_plants=min(spec.num_plants, 2),
                                   num_test=min(spec.num_test, 50), max_steps=30,
                                   mlp_max_steps=30)
    return spec


@functools.cache
def make_problem(spec: ExampleSpec, plant_index: int, seed: int):
    """(plant, expert) number `plant_index` of the example (deterministic in the seed)."""
    from ..experts import lqr_expert, nmpc_expert
    from ..systems import mass_spring_chain, paper_nonlinear_plant

    if spec.name == "linear":
        chain = mass_spring_chain(jr.fold_in(jr.PRNGKey(seed), 1000 + plant_index))
        return chain.plant, lqr_expert(chain.Ac, chain.Bc, chain.Cc)
    plant = paper_nonlinear_plant()
    return plant, nmpc_expert(plant)


def hyperparameters(spec: ExampleSpec) -> dict:
    """`spec` as a JSON-ready dict (the supply rate as its matrices `Q`, `S`, `R`): the
    settings that produced a record, stored in it."""
    out: dict[str, Any] = {}
    for field in dataclasses.fields(spec):
        value = getattr(spec, field.name)
        if isinstance(value, QSR):
            value = {k: np.asarray(getattr(value, k)).tolist() for k in ("Q", "S", "R")}
        out[field.name] = list(value) if isinstance(value, tuple) else value
    return out


def provenance(dtype) -> dict:
    """What produced a record besides its settings: the library's and JAX's versions, the
    checkout's git commit (`git_commit`), the data's `dtype`, the machine's CPU count (its
    training times depend on it) and the date (UTC)."""
    from .. import __version__

    return dict(dtype=np.dtype(dtype).name, dissil_jax_version=__version__,
                jax_version=jax.__version__, git_commit=git_commit(), cpu_count=os.cpu_count(),
                date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))


@functools.lru_cache(maxsize=1)
def git_commit() -> str | None:
    """The commit of the git checkout the library runs from, with `-dirty` when tracked
    files differ from it; None for an installed copy (no checkout that tracks this
    package), or without git. The version stays the same between commits; this does not."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    git = lambda *a: subprocess.run(["git", "-C", str(root), *a], capture_output=True,
                                    text=True, timeout=10)
    try:
        if git("ls-files", "--error-unmatch", "dissil_jax/__init__.py").returncode:
            return None  # not a checkout of this library (e.g. site-packages in a user's repo)
        head, dirty = git("rev-parse", "HEAD"), git("status", "--porcelain", "-uno")
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode:
        return None
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


def fit(method: str, key, windows, spec: ExampleSpec, inits: int):
    """Train `inits` controllers with `method` using the example's hyperparameters.

    Refuses to run without float64 (`FLOAT64_MESSAGE`), as the command line does.
    """
    import dissil_jax as dj

    require_float64()

    # The experiments record every outcome (a diverged GD run counts as unstable), so no
    # trainer raises on a run that ended early.
    # The paper's stopping rule is absolute (|dJ| < tol): `atol` = tol, `rtol` = 0.
    common: dict[str, Any] = dict(num_inits=inits, max_steps=spec.max_steps, atol=spec.tol,
                                  rtol=0.0, throw=False)
    # The step sizes were chosen on the data as they are, in one scale for every signal
    # (`tuning.py`), and the examples' outputs are 4-90x smaller than their inputs: without
    # `balance=False` the trainers would rescale the outputs (`dj.fit_pgd`, "units").
    # The command line shows its own progress bar: no trainer's reports interleave with it.
    unbalanced = dict(common, balance=False, progress=False)
    if method == "pgd":
        # The paper's Algorithm 2 outputs its last iterate, C_{i+1}.
        return dj.fit_pgd(key, windows, spec.qsr, learning_rate=spec.pgd_learning_rate,
                          decay=spec.pgd_decay, init_scale=spec.init_scale, keep="last",
                          **unbalanced)
    if method == "gd":
        return dj.fit_gd(key, windows, learning_rate=spec.gd_learning_rate,
                         decay=spec.pgd_decay, init_scale=spec.init_scale, **unbalanced)
    if method == "ico":
        return dj.fit_ico(key, windows, spec.qsr, init_scale=spec.init_scale, **unbalanced)
    if method == "ico_nc":
        return dj.fit_ico_nc(key, windows, init_scale=spec.init_scale, **unbalanced)
    if method == "direct":
        return dj.fit_direct(key, windows, spec.qsr, learning_rate=spec.direct_learning_rate,
                             init_scale=spec.direct_init_scale,
                             **dict(unbalanced, atol=spec.direct_tol))
    if method == "ren":
        return dj.fit_ren(key, windows, spec.qsr, width=spec.ren_width,
                          activation=spec.ren_activation,
                          learning_rate=spec.ren_learning_rate,
                          init_scale=spec.ren_init_scale, direct_input=spec.ren_direct_input,
                          odd=spec.ren_odd,
                          **dict(unbalanced, atol=0.0))
    if method == "mlp":
        # The paper's baseline trains on the data as they are (its learning rate was
        # chosen there), so `balance=False` as for the LTI trainers.
        return dj.fit_mlp(key, windows, hidden=spec.hidden, num_inits=inits, atol=spec.tol,
                          rtol=0.0, max_steps=spec.mlp_max_steps, throw=False,
                          balance=False, progress=False)
    raise ValueError(f"`method` must be one of {METHODS}, got {method!r}.")


def quantiles(values: np.ndarray) -> dict:
    mn, q1, med, q3, mx = _q(values, (0.0, 0.25, 0.5, 0.75, 1.0))
    return dict(mse_min=mn, mse_q1=q1, mse_median=med, mse_q3=q3, mse_max=mx)


def _finite_mean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else float("nan")


@functools.cache
def training_data(spec: ExampleSpec, plant_index: int, seed: int, data: str, segments: int):
    """`(plant, expert, windows, (k_fit, k_test, k_noise))` of one plant of a configuration.

    The windows depend only on (seed, plant, data regime, N), so every method, and the
    step-size sweep, sees the same demonstrations; they are computed once per process.
    `seed` is an integer in $[0, 2^{32})$ (`check_seed`), `segments` a positive integer.
    """
    if data not in REGIMES:
        raise ValueError(f"`data` must be one of {REGIMES}, got {data!r}.")
    seed, segments = check_seed(seed), check_int("segments", segments)
    plant_index = check_int("plant_index", plant_index, minimum=0)
    plant, expert = make_problem(spec, plant_index, seed)
    k_data, k_fit, k_test, k_noise = jr.split(jr.fold_in(jr.PRNGKey(seed), plant_index), 4)
    k_data = jr.fold_in(k_data, segments * 2 + REGIMES.index(data))
    windows = demonstration_windows(k_data, plant, expert, segments, data, x0_std=spec.train_std)
    return plant, expert, windows, (k_fit, k_test, k_noise)


@functools.cache
def evaluation_setup(spec: ExampleSpec, plant_index: int, seed: int):
    """Test states, the expert's equilibrium horizon and the test length of one plant
    (they depend on the seed and the plant only: computed once per process)."""
    plant, expert, windows, (_, k_test, k_noise) = training_data(spec, plant_index, seed,
                                                                 "initial", 2)
    x0 = spec.test_std * jr.normal(k_test, (spec.num_test, plant.n_state), windows.y.dtype)
    T = equilibrium_horizon(jr.fold_in(k_noise, 1), plant, expert, x0,
                            max_steps=spec.equilibrium_search)
    return x0, T, max(T, spec.min_test_steps)


def controller_start(spec: ExampleSpec, method: str, x0):
    """The learned controllers' initial states in the test loops: None (the plant state,
    $\\hat x_0 = x_0$, as in the training windows), or $(x_0, -x_0)$ for an odd REN
    (`fit_ren(odd=True)` returns two copies of a REN, the second started at $-x_0$)."""
    return jnp.concatenate([x0, -x0], -1) if method == "ren" and spec.ren_odd else None


def run_config(example: str, data: str, method: str, segments: int, *, inits: int,
               seed: int = 0, quick: bool = False, spec: ExampleSpec | None = None,
               on_plant: Callable[[int, int], Any] | None = None) -> dict:
    """Run one configuration and return its summary record.

    **Arguments:** the configuration (`example`, `data` regime, `method`, `segments` $N$),
    `inits` initialisations per plant, the `seed` (an integer in $[0, 2^{32})$), `quick`
    (`example_spec`'s small sizes) or an explicit `spec`, and `on_plant`, called as
    `on_plant(i, num_plants)` before plant `i` is trained (the command line's progress).

    **Returns:** the record that the command line writes to `summary.json` (every field is
    described in the reproduction guide, "The records"): the metrics, and what produced
    them (`hyperparameters`, `dtype`, `dissil_jax_version`, `jax_version`, `date`,
    `command`). Refuses to run without float64 (`FLOAT64_MESSAGE`), as the command line
    does, and checks its arguments before any work.
    """
    if example not in EXAMPLES:
        raise ValueError(f"`example` must be one of {EXAMPLES}, got {example!r}.")
    if data not in REGIMES:
        raise ValueError(f"`data` must be one of {REGIMES}, got {data!r}.")
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {METHODS}, got {method!r}.")
    segments, inits = check_int("segments", segments), check_int("inits", inits)
    seed = check_seed(seed)
    require_float64()
    command = (f"run_config({example!r}, {data!r}, {method!r}, {segments}, inits={inits}, "
               f"seed={seed}, quick={bool(quick)}{', spec=...' if spec else ''})")
    spec = spec or example_spec(example, quick)
    mse, stable, bounded, pcc, certified, reasons, horizons = [], [], [], [], [], [], []
    times = []
    for i in range(spec.num_plants):
        if on_plant is not None:
            on_plant(i, spec.num_plants)
        plant, expert, windows, (k_fit, k_test, k_noise) = training_data(
            spec, i, seed, data, segments)
        t = time.perf_counter()
        res = fit(method, k_fit, windows, spec, inits)
        jax.block_until_ready(res.final_loss)
        # Includes XLA's compilation whenever this process meets the method's shapes for
        # the first time; measuring it apart would mean training twice.
        times.append(time.perf_counter() - t)
        x0, T, steps = evaluation_setup(spec, i, seed)
        ev = evaluate(k_noise, plant, expert, res.controllers, x0, steps,
                      xhat0=controller_start(spec, method, x0))
        horizons.append((T, steps))
        mse.append(np.asarray(ev.mse))
        stable.append(np.asarray(ev.stable, bool))
        bounded.append(np.asarray(ev.bounded, bool))
        pcc.append(np.asarray(res.percent_change_cost))
        reasons += res.result_names()
        if res.certified is not None:
            certified.append(np.asarray(res.certified, bool))
    mse, stable, bounded = np.concatenate(mse), np.concatenate(stable), np.concatenate(bounded)
    n_ctrl = len(mse)
    record = dict(
        example=example, data=data, method=method, segments=segments, inits=inits,
        plants=spec.num_plants, controllers=n_ctrl, seed=seed, quick=bool(quick),
        percent_stable=100.0 * float(stable.mean()),
        percent_bounded=100.0 * float(bounded.mean()),
        equilibrium_steps=[T for T, _ in horizons], test_steps=[s for _, s in horizons],
        # Runs whose loss diverged (counted as "non_finite" in stop_reasons) have no finite
        # change in cost; the mean is over the others.
        percent_change_cost=_finite_mean(np.concatenate(pcc)),
        train_time_s=sum(times) / n_ctrl,
        certified=None if not certified else bool(np.concatenate(certified).all()),
        **{k: float(v) for k, v in quantiles(mse).items()},
        stop_reasons=dict(sorted(Counter(reasons).items())),
        train_time_per_plant_s=times, train_time_includes_compilation=True,
        **provenance(windows.y.dtype),
        command=command, hyperparameters=hyperparameters(spec),
    )
    return record


__all__ = ["METHODS", "PAPER_METHODS", "EXAMPLES", "METHOD_LABELS", "FLOAT64_MESSAGE",
           "ExampleSpec", "example_spec", "make_problem", "fit", "hyperparameters", "provenance",
           "require_float64", "run_config", "training_data"]
