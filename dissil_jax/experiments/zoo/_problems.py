"""The zoo's problems: one function per problem, and the fixed tuning / held-out split.

Every function takes a `seed` (default 0) and is deterministic given it; the expert designs
and supply rates are float64 host computations, the demonstrations are simulated in JAX.
"""

from __future__ import annotations

import functools
from typing import Any

from ...experts import nmpc_expert
from ...systems import paper_nonlinear_plant
from ..data import check_seed
from ._build import (
    chain_plant,
    make_problem,
    observer,
    random_stable_plant,
    sector_plant,
    static_expert,
)
from ._record import Problem


def _static(plant, **kw) -> dict[str, Any]:
    expert, exact = static_expert(plant, **kw)
    return dict(plant=plant, expert=expert, expert_controller=exact,
                expert_kind="nonlinear" if kw.get("saturation") else "static")


def _observer(plant) -> dict[str, Any]:
    expert, exact = observer(plant)
    return dict(plant=plant, expert=expert, expert_controller=exact, expert_kind="observer")


# -- the tuning half ----------------------------------------------------------------------


def scalar_static(seed: int = 0) -> Problem:
    """Order 1, SISO, bounded gain; LQR state feedback; 25 windows of 2 steps, light noise."""
    return make_problem("scalar_static", "tuning", seed,
                        **_static(random_stable_plant(seed, 1, 1, 1, radius=0.9)),
                        supply="bounded_gain", has_state=True, units=1.0, noise="light",
                        num_windows=25, horizon=2)


def paper_nonlinear(seed: int = 0) -> Problem:
    """The paper's nonlinear example (eq. 20) with its NMPC expert; sliding 2-step windows."""
    return make_problem("paper_nonlinear", "tuning", seed, plant=paper_nonlinear_plant(),
                        expert=nmpc_expert(), expert_controller=None, expert_kind="nonlinear",
                        supply="sector", has_state=True, units=5.0, noise="light",
                        num_windows=25, horizon=2, sliding=True)


def chain3_paper(seed: int = 0) -> Problem:
    """The paper's linear example's size: 3 masses (order 6, 3x3), passivity indices."""
    return make_problem("chain3_paper", "tuning", seed, **_static(chain_plant(seed, 3)),
                        supply="passivity", has_state=True, units=1.0, noise="light",
                        num_windows=25, horizon=2)


def chain5_siso_io(seed: int = 0) -> Problem:
    """Order 10 SISO chain, observer expert, input-output logs (no state), no noise."""
    return make_problem("chain5_siso_io", "tuning", seed, **_observer(chain_plant(seed, 5, [0])),
                        supply="passivity", has_state=False, units=1.0, noise="none",
                        num_windows=200, horizon=9, n_state=4)


def cone_siso_tiny(seed: int = 0) -> Problem:
    """Order 4 SISO, interior cone; 2 windows of 8 steps in units of 1e-3, no noise."""
    return make_problem("cone_siso_tiny", "tuning", seed, **_static(chain_plant(seed, 2, [1])),
                        supply="interior_cone", has_state=True, units=1e-3, noise="none",
                        num_windows=2, horizon=8)


def gain_2x2_io(seed: int = 0) -> Problem:
    """Order 5, 2x2, bounded gain, observer expert, logs without state in units of 1e3."""
    return make_problem("gain_2x2_io", "tuning", seed,
                        **_observer(random_stable_plant(seed + 1, 5, 2, 2)),
                        supply="bounded_gain", has_state=False, units=1e3, noise="heavy",
                        num_windows=100, horizon=7, n_state=3)


def sector_saturated(seed: int = 0) -> Problem:
    """Order 2 sector plant, saturated LQR expert, sliding 3-step windows."""
    return make_problem("sector_saturated", "tuning", seed,
                        **_static(sector_plant(seed + 2, 2, 1, 1, 0.2), saturation=1.0),
                        supply="sector", has_state=True, units=1.0, noise="light",
                        num_windows=100, horizon=3, sliding=True)


def chain6_2x2_io(seed: int = 0) -> Problem:
    """Order 12 chain actuated at both ends (2x2), degenerate cone, observer, 10-step logs."""
    return make_problem("chain6_2x2_io", "tuning", seed,
                        **_observer(chain_plant(seed, 6, [0, 5])), supply="degenerate_cone",
                        has_state=False, units=10.0, noise="light", num_windows=500,
                        horizon=10, n_state=4)


def chain12_siso_io(seed: int = 0) -> Problem:
    """Order 24 SISO chain, bounded gain, observer expert, a 2-state controller."""
    return make_problem("chain12_siso_io", "tuning", seed,
                        **_observer(chain_plant(seed, 12, [0])), supply="bounded_gain",
                        has_state=False, units=1.0, noise="light", num_windows=50, horizon=5,
                        n_state=2)


# -- the held-out half --------------------------------------------------------------------


def scalar_heavy(seed: int = 0) -> Problem:
    """Order 1, degenerate cone (input passivity), 5 windows of 10 steps, heavy noise."""
    return make_problem("scalar_heavy", "held_out", seed,
                        **_static(random_stable_plant(seed + 3, 1, 1, 1, radius=0.7,
                                                      feedthrough=1.0)),
                        supply="degenerate_cone", has_state=True, units=1e-2, noise="heavy",
                        num_windows=5, horizon=10)


def chain2_passive(seed: int = 0) -> Problem:
    """Two masses (order 4, 2x2), passivity indices, LQR expert, 100 windows."""
    return make_problem("chain2_passive", "held_out", seed, **_static(chain_plant(seed + 4, 2)),
                        supply="passivity", has_state=True, units=1.0, noise="light",
                        num_windows=100, horizon=2)


def chain4_4x4_io(seed: int = 0) -> Problem:
    """Four masses (order 8, 4x4), degenerate cone, observer expert, 6-step logs."""
    return make_problem("chain4_4x4_io", "held_out", seed, **_observer(chain_plant(seed + 5, 4)),
                        supply="degenerate_cone", has_state=False, units=1.0, noise="light",
                        num_windows=60, horizon=6, n_state=2)


def chain8_siso_io(seed: int = 0) -> Problem:
    """Order 16 SISO chain, degenerate cone, observer, 1000 logs in units of 1e-3."""
    return make_problem("chain8_siso_io", "held_out", seed,
                        **_observer(chain_plant(seed + 6, 8, [3])), supply="degenerate_cone",
                        has_state=False, units=1e-3, noise="none", num_windows=1000,
                        horizon=7, n_state=3)


def cone_3x2(seed: int = 0) -> Problem:
    """Order 5, 2 inputs and 3 outputs, interior cone, LQR expert, units of 1e2."""
    return make_problem("cone_3x2", "held_out", seed,
                        **_static(random_stable_plant(seed + 7, 5, 2, 3)),
                        supply="interior_cone", has_state=True, units=1e2, noise="light",
                        num_windows=40, horizon=4)


def gain_saturated(seed: int = 0) -> Problem:
    """Order 3 SISO, bounded gain, saturated (nonlinear) expert on an LTI plant, heavy noise."""
    return make_problem("gain_saturated", "held_out", seed,
                        **_static(random_stable_plant(seed + 8, 3, 1, 1), saturation=0.5),
                        supply="bounded_gain", has_state=True, units=1.0, noise="heavy",
                        num_windows=60, horizon=2)


def sector_2x2(seed: int = 0) -> Problem:
    """Order 4 sector plant (2x2), saturated LQR expert, 300 windows in units of 1e2."""
    return make_problem("sector_2x2", "held_out", seed,
                        **_static(sector_plant(seed + 9, 4, 2, 2, 0.15), saturation=100.0),
                        supply="sector", has_state=True, units=1e2, noise="light",
                        num_windows=300, horizon=2)


def sector_io(seed: int = 0) -> Problem:
    """Order 3 sector plant, LQR expert, input-output logs, a 2-state controller."""
    return make_problem("sector_io", "held_out", seed,
                        **_static(sector_plant(seed + 10, 3, 1, 1, 0.2)), supply="sector",
                        has_state=False, units=0.3, noise="none", num_windows=80, horizon=5,
                        n_state=2)


def chain2_sliding(seed: int = 0) -> Problem:
    """Order 4 SISO chain, passivity indices, sliding 4-step windows, heavy noise."""
    return make_problem("chain2_sliding", "held_out", seed,
                        **_static(chain_plant(seed + 11, 2, [1])), supply="passivity",
                        has_state=True, units=0.1, noise="heavy", num_windows=30, horizon=4,
                        sliding=True)


#: Every problem by name, in a fixed order.
PROBLEMS = {f.__name__: f for f in (
    scalar_static, paper_nonlinear, chain3_paper, chain5_siso_io, cone_siso_tiny,
    gain_2x2_io, sector_saturated, chain6_2x2_io, chain12_siso_io,
    scalar_heavy, chain2_passive, chain4_4x4_io, chain8_siso_io, cone_3x2, gain_saturated,
    sector_2x2, sector_io, chain2_sliding)}

#: The fixed split: defaults are chosen on `TUNING` and reported on `HELD_OUT`.
TUNING = ("scalar_static", "paper_nonlinear", "chain3_paper", "chain5_siso_io",
          "cone_siso_tiny", "gain_2x2_io", "sector_saturated", "chain6_2x2_io",
          "chain12_siso_io")
HELD_OUT = ("scalar_heavy", "chain2_passive", "chain4_4x4_io", "chain8_siso_io", "cone_3x2",
            "gain_saturated", "sector_2x2", "sector_io", "chain2_sliding")


@functools.lru_cache(maxsize=64)
def problem(name: str, seed: int = 0) -> Problem:
    """The problem `name` built with `seed`, an integer in $[0, 2^{32})$ as for the
    experiments' command line (cached: building solves a few small SDPs)."""
    if name not in PROBLEMS:
        raise ValueError(f"`name` must be one of the zoo's problems {sorted(PROBLEMS)}, "
                         f"got {name!r}.")
    return PROBLEMS[name](check_seed(seed))
