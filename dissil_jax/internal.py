"""What tests and benchmarks use from the inside, under public names.

Not part of the stable API: names here may change between releases without notice. Tests
and benchmarks import from here, never from a `_private` module, so that the private
layout can change behind this one list (as lineax's `internal`).

Modules, for monkeypatching in tests and for benchmarks that time one layer alone:
`certify_fast`, `certify_sdp`, `direct`, `direct_map`, `experiment_figures`, `experiment_jobs` (the command
line's runs of configurations, `--jobs`), `ico`, `ico_run`, `ico_sdp`, `linalg`, `lmi`, `mlp`, `outcome`,
`pgd`, `pgd_steps`, `plant_common`, `progress`, `projection`, `projection_admm`, `projection_admm_rate`, `projection_cache`, `projection_fo`, `ren_certify`, `ren_controller`, `ren_init` (`fit_ren(init=...)`), `ren_inverse` (the REN map backwards), `ren_map`, `ren_train`, `ren_units`, `rollout`,
`rate_scale`, `sdp`, `units` (the trainers' changes of units), `zoo_build` (the problem zoo's plants, experts and rates); and the functions and constants in
`__all__`.
"""

from . import (
    _direct_map as direct_map,
    _linalg as linalg,
    _outcome as outcome,
    _plant_common as plant_common,
    _progress as progress,
    _rate_scale as rate_scale,
    _rollout as rollout,
)
from ._certify import fast as certify_fast, sdp as certify_sdp
from ._certify.coordinates import state_scale as certify_state_scale
from ._frequency import vanishing_supply
from ._lru import LRU
from ._plant_common import balanced_realisation
from ._projection import (
    admm as projection_admm,
    admm_rate as projection_admm_rate,
    cache as projection_cache,
    first_order as projection_fo,
    project as projection,
)
from ._projection.project import solver_stats
from ._ren import (
    certify as ren_certify,
    controller as ren_controller,
    inverse as ren_inverse,
    map as ren_map,
    units as ren_units,
)
from ._sdp import lmi, sdp
from ._sdp.indefinite import check_feasible, is_indefinite, static_point
from ._sdp.lmi import (
    ConvexifiedLMI,
    certified,
    kyp_bound_holds,
    kyp_certified,
    kyp_margin,
    kyp_scale,
    smat,
)
from ._sdp.sdp import single_threaded_blas
from ._train import (
    _units as units,
    direct,
    mlp,
    pgd,
    pgd_steps,
    ren as ren_train,
    ren_init,
)
from ._train._checks import check_n_state
from ._train._init import INIT_SCALE, init_controllers
from ._train._iterate import Method, iterate
from ._train._scale import loss_scale, scaled
from ._train._units import BAND as OUTPUT_BAND, output_factor, output_ratio, state_ratios
from ._train.direct import (
    MapDescent,
    _run as direct_run_unchecked,
    default_hyperparameters,
    map_loss,
)
from ._train.ico import fit as ico, run as ico_run, sdp as ico_sdp, step as ico_step
from ._train.ico.blocks import Iterate
from ._train.ico.layout import svec_len
from ._train.ico.sdp import ICOProblem
from ._train.ico.solver import ICOSolver
from ._train.ico.windows import stacked_factor
from ._train.mlp import demonstration_pairs
from ._train.steps import METRIC_FLOOR, gd_init_scale, gd_learning_rate, optimizer_metric
from .experiments import _figures as experiment_figures, _jobs as experiment_jobs
from .experiments._paper import FIGURES, TABLES
from .experiments.zoo import _build as zoo_build

__all__ = [
    "balanced_realisation", "ConvexifiedLMI", "FIGURES", "LRU", "ICOProblem", "ICOSolver", "INIT_SCALE", "Iterate",
    "METRIC_FLOOR", "MapDescent", "Method", "OUTPUT_BAND", "TABLES", "certified", "certify_fast", "certify_sdp", "certify_state_scale",
    "check_feasible", "check_n_state", "default_hyperparameters", "demonstration_pairs", "direct", "gd_init_scale", "gd_learning_rate",
    "direct_map", "direct_run_unchecked", "experiment_figures", "experiment_jobs", "ico", "ico_run", "ico_sdp", "ico_step", "init_controllers", "is_indefinite",
    "iterate",
    "kyp_bound_holds", "kyp_certified", "kyp_margin", "kyp_scale", "linalg", "lmi", "loss_scale", "map_loss", "mlp",
    "optimizer_metric", "outcome", "output_factor", "output_ratio", "pgd", "pgd_steps", "plant_common", "progress", "projection", "projection_admm", "projection_admm_rate", "projection_cache", "projection_fo",
    "ren_certify",
    "ren_controller", "ren_init", "ren_inverse",
    "ren_map", "ren_train", "ren_units", "rollout", "rate_scale", "units", "scaled", "sdp", "single_threaded_blas", "smat",
    "solver_stats", "stacked_factor", "state_ratios", "static_point", "svec_len", "vanishing_supply",
    "zoo_build",
]
