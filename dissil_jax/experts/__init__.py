"""Expert controllers for the paper's benchmarks: LQR (linear) and NMPC (nonlinear)."""

from ._lqr import LQRExpert as LQRExpert, lqr_expert as lqr_expert, lqr_gain as lqr_gain
from ._nmpc import (
    NMPCExpert as NMPCExpert,
    NMPCSolution as NMPCSolution,
    nmpc_expert as nmpc_expert,
)
