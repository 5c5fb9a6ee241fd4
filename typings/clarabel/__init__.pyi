# Type stub for the names dissil_jax uses from Clarabel's compiled extension module, which
# ships no stubs of its own (pyright reads this folder as its `stubPath`).
from typing import Any

DefaultSettings: Any
DefaultSolver: Any
NonnegativeConeT: Any
PSDTriangleConeT: Any
SecondOrderConeT: Any
ZeroConeT: Any
