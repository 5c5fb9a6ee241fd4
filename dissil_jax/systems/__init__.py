"""Plants and the paper's benchmark problems (paper §5)."""

from ._mass_spring import (
    MassSpringChain as MassSpringChain,
    chain_matrices as chain_matrices,
    mass_spring_chain as mass_spring_chain,
)
from ._plants import (
    LinearPlant as LinearPlant,
    SectorPlant as SectorPlant,
    paper_nonlinear_plant as paper_nonlinear_plant,
)
