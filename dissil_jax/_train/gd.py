"""Plain gradient descent, the paper's unconstrained baseline: `fit_pgd`'s loop without
the projection."""

from __future__ import annotations

from .._data import Windows
from .direct import MAX_STEPS as GD_MAX_STEPS, RTOL_DIRECT as RTOL_GD
from .pgd import _fit
from .result import FitResult
from .steps import default_rule


def fit_gd(
    key, windows: Windows, *, optimizer=None, learning_rate: float | None = None,
    decay: float | None = None, num_inits: int = 8, n_state: int | None = None,
    max_steps: int = GD_MAX_STEPS, atol: float = 0.0, rtol: float = RTOL_GD,
    init_scale: float | None = None, throw: bool = True, balance: bool = True,
    progress: bool = True,
) -> FitResult:
    """Plain gradient descent on the imitation loss: [`fit_pgd`][dissil_jax.fit_pgd] without $\\Pi$.

    The paper's unconstrained baseline; no stability guarantee (`P` and `certified` are
    None). Same arguments and defaults as `fit_pgd`, without the ones about the
    constraint (`qsr`, `eps`, `method`) and without `keep` (each run returns its last
    iterate, as the paper's baseline does), and except the step budget and Adam's step for
    wide controllers. From N(0, 1) draws the GD runs of the zoo ended up to 80x higher than
    from N(0, 0.3²), since nothing projects a wild first draw back.

    **Initial scale.** `init_scale` None (the default) draws the entries from
    $\\mathcal N(0, \\sigma^2)$ with $\\sigma = 0.3\\min(1, 3/\\sqrt{\\hat n})$: `fit_pgd`'s
    0.3 up to $\\hat n = 9$ (the paper's sizes and every problem of the zoo), smaller for
    higher orders. A draw's eigenvalues fill a disc of radius about $\\sigma\\sqrt{\\hat n}$,
    so the constant 0.3 starts unstable from $\\hat n\\approx11$ on, the first loss grows
    like $\\rho(\\hat A)^{2h}$, and 600 Adam steps do not bring such a start back. On
    the tuning chains at $\\hat n$ = 24 and 48 the constant ended the median run at
    0.29-1.5 times the zero controller's loss, this rule at 0.0007-0.08 times; on held-out realisable problems of order 12, 20 and 32 the
    median error on fresh windows fell 1.2-5.6 times
    (`benchmarks/bench_high_order.py --gd-init [--report]`).

    **Budget.** `max_steps` 600 and `rtol` 1e-8, `fit_direct`'s: GD's steps cost no
    projection. The paper's 150 steps (which the reproduction passes) left the median run
    up to 17x above the 600-step run's on the zoo's tuning half (`cone_siso_tiny`) and up
    to 3.5x on the tuning chains of order 6–48 (`benchmarks/bench_defaults.py --part
    gd-budget`, `benchmarks/bench_high_order.py --gd-budget`); 300 steps, 3.6x and 1.9x;
    600 steps at `rtol` 1e-7 stopped some runs early (worst run 15x higher at
    $\\hat n = 48$). Reported on the held-out half: up to 2.8x lower medians, and
    4.7–5.9x on six held-out order-16 problems. Longer training fits the demonstrations
    better, not the loop: on two tuning and one held-out problem fewer of GD's closed
    loops were stable after 600 steps than after 150 (nothing constrains them).

    **Step.** The default step is Adam at $\\eta = 0.1\\min(1, 9/w)$ in the
    normalised units, $w = \\hat n + p$ (`gd_learning_rate`): `fit_pgd`'s $\\eta = 0.1$ up
    to $w = 9$ (the paper's sizes and every problem of the zoo), smaller for wider
    controllers, where a step of 0.1 changes $A$ enough to leave the stable controllers
    (at $\\hat n = 48$ it ended runs up to 1.4e4 times above their initial loss). Adam
    moves each entry by about $\\eta$ per step whatever the gradient's size: with the
    paper's rule at $\\eta_0 = 1$, GD diverged on every problem of the zoo
    (`dissil_jax.experiments.zoo`, `benchmarks/bench_defaults.py`), where PGD's projection
    keeps the iterates bounded. `learning_rate` and `decay` are, as in `fit_pgd`, the
    paper's rule's $\\eta_0$ (a factor of the gradient) and $\\rho$: giving either selects
    that rule (the other then takes its default). To change Adam's step instead, pass
    `optimizer=optax.adam(step)`. With `throw=True` a diverging run (`non_finite`)
    raises.

    **Under `jax.jit` and `jax.vmap`.** Having no certificate, `fit_gd` checks nothing on
    the host, so it runs inside both, e.g. `jax.vmap(lambda k: dj.fit_gd(k, windows))(keys)`
    (tested equal to a loop over the keys). `throw=True` then raises at run time through
    `equinox.error_if` (an `EquinoxRuntimeError`) rather than a `ValueError`. The certified
    trainers cannot be traced (their float64 end check runs on the host); their vmappable
    cores are [`direct_run`][dissil_jax.direct_run] and [`pgd_run`][dissil_jax.pgd_run].
    Traced, `fit_gd` reports no progress (`progress` as in `fit_pgd`).
    """
    return _fit(key, windows, None,
                optimizer=default_rule(optimizer, learning_rate, decay, windows, n_state),
                learning_rate=learning_rate, decay=decay, init_scale=init_scale,
                num_inits=num_inits, n_state=n_state, max_steps=max_steps, atol=atol,
                rtol=rtol, eps=0.0, throw=throw, balance=balance, progress=progress)
