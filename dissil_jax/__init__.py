"""dissil_jax: dissipative imitation learning of LTI output-feedback controllers in JAX."""

from ._certify.certify import Certificate as Certificate, certify as certify
from ._controller import LTIController as LTIController
from ._data import Windows as Windows
from ._outcome import Outcome as Outcome
from ._projection.project import Projection as Projection, project as project
from ._ren.certify import RENCertificate as RENCertificate, certify_ren as certify_ren
from ._ren.controller import (
    RENController as RENController,
    ren_imitation_loss as ren_imitation_loss,
    ren_predict as ren_predict,
    ren_rollout as ren_rollout,
)
from ._rollout import (
    imitation_loss as imitation_loss,
    observability_toeplitz as observability_toeplitz,
    predict as predict,
    rollout as rollout,
)
from ._sdp.lmi import kyp_matrix as kyp_matrix
from ._supply import QSR as QSR
from ._sweep import sweep as sweep
from ._theorem1 import (
    ClosedLoopCertificate as ClosedLoopCertificate,
    closed_loop_certificate as closed_loop_certificate,
    stabilising_qsr as stabilising_qsr,
)

__version__ = "0.1.0"

from . import experts as experts, systems as systems
from ._plant_qsr import (
    input_passivity_qsr as input_passivity_qsr,
    lti_cone_qsr as lti_cone_qsr,
    output_passivity_qsr as output_passivity_qsr,
    passivity_indices as passivity_indices,
    sector_lemma_matrix as sector_lemma_matrix,
    sector_plant_qsr as sector_plant_qsr,
)
from ._train.direct import direct_run as direct_run, fit_direct as fit_direct
from ._train.gd import fit_gd as fit_gd
from ._train.ico.fit import fit_ico as fit_ico, fit_ico_nc as fit_ico_nc
from ._train.mlp import MLPController as MLPController, fit_mlp as fit_mlp
from ._train.pgd import fit_pgd as fit_pgd, pgd_run as pgd_run
from ._train.ren import RENFitResult as RENFitResult, fit_ren as fit_ren
from ._train.result import FitResult as FitResult
from .systems import LinearPlant as LinearPlant, SectorPlant as SectorPlant

