"""A zoo of imitation problems nobody tuned for, split into a tuning and a held-out half.

Each problem ([`Problem`][dissil_jax.experiments.zoo.Problem]) has a plant, an expert,
training and held-out demonstrations, the plant's supply rate derived by the library's
plant tools and the controller's from Theorem 1, and a closed-loop test. Run your own
method with [`evaluate`][dissil_jax.experiments.zoo.evaluate]:

```python
from dissil_jax.experiments import zoo
for name in zoo.HELD_OUT:
    rep = zoo.evaluate(zoo.problem(name), my_method)
```
"""

from ._build import NOISE as NOISE
from ._evaluate import (
    certified as certified,
    evaluate as evaluate,
    imitation_error as imitation_error,
    stable as stable,
    task as task,
)
from ._problems import (
    HELD_OUT as HELD_OUT,
    PROBLEMS as PROBLEMS,
    TUNING as TUNING,
    problem as problem,
)
from ._record import (
    Facts as Facts,
    ObserverExpert as ObserverExpert,
    Problem as Problem,
    Report as Report,
    StateFeedbackExpert as StateFeedbackExpert,
    Task as Task,
)
