"""The paper's experiment protocols: demonstrations, closed-loop simulation, metrics (paper §5)."""

from .data import (
    demonstration_windows as demonstration_windows,
    demonstrations as demonstrations,
    initial_segments as initial_segments,
    realisable_windows as realisable_windows,
    sliding_windows as sliding_windows,
    windows_per_trajectory as windows_per_trajectory,
)
from .metrics import (
    Evaluation as Evaluation,
    Summary as Summary,
    evaluate as evaluate,
    lti_closed_loop_matrix as lti_closed_loop_matrix,
    lti_spectral_radius as lti_spectral_radius,
    rule_bounded as rule_bounded,
    rule_stable as rule_stable,
    state_mse as state_mse,
    summarize as summarize,
)
from .simulate import (
    Noise as Noise,
    Trajectories as Trajectories,
    equilibrium_horizon as equilibrium_horizon,
    sample_noise as sample_noise,
    simulate_controllers as simulate_controllers,
    simulate_expert as simulate_expert,
)
