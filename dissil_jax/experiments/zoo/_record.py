"""The zoo's records (a problem, what a learner sees, an evaluation) and its experts."""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ..._controller import LTIController
from ..._data import Windows
from ..._ren.controller import RENController
from ..._supply import QSR


class Facts(NamedTuple):
    """What a problem claims about itself (the zoo's tests check every claim on the data).

    - `order`, `n_in`, `n_out`: the plant's state, input and output sizes.
    - `supply`: the kind of the plant's supply rate: `"passivity"` (both passivity indices),
      `"bounded_gain"`, `"interior_cone"`, `"degenerate_cone"` (input passivity, $Q = 0$)
      or `"sector"` (a sector-bounded nonlinear plant, paper Lemma 8).
    - `has_state`: the windows record the plant state ($\\hat x_0 = x_0$), or start at rest.
    - `units`: the size of the demonstrations (the standard deviation of the initial state).
    - `noise`: `"none"`, `"light"` (the paper's 0.04 / 0.02 per unit) or `"heavy"`
      (0.2 / 0.1 per unit).
    - `num_windows`, `horizon`: $N$ and $h$ of the training windows.
    - `expert`: `"static"` (state feedback), `"observer"` (an LTI output-feedback controller
      with its own state) or `"nonlinear"` (saturated state feedback or NMPC).
    """

    order: int
    n_in: int
    n_out: int
    supply: str
    has_state: bool
    units: float
    noise: str
    num_windows: int
    horizon: int
    expert: str


class Problem(NamedTuple):
    """One imitation problem of the zoo.

    - `name`, `split`: the problem's name and its half of the zoo (`"tuning"` or
      `"held_out"`, fixed in the code).
    - `plant`: a `dj.LinearPlant` or `dj.SectorPlant`; `expert`: the demonstrator (the
      simulators' expert interface: `init(x0)`, `__call__(x, carry) -> (u, carry)`).
    - `expert_controller`: the expert as an `LTIController` in the library's convention
      (input $y$, output $\\hat y = -u$) when it reproduces the noise-free demonstrations
      exactly, else None.
    - `train`, `test`: training windows and held-out windows (another draw of the same
      demonstrations).
    - `plant_qsr`: the plant's supply rate, derived by the library's plant tools;
      `plant_storage`: its storage $P$ for sector plants (paper Lemma 8), else None.
    - `qsr`: the controller's supply rate, from
      [`stabilising_qsr`][dissil_jax.stabilising_qsr], so that Theorem 1 certifies the loop
      of the plant with any $(Q,S,R)$-dissipative controller.
    - `n_state`: the controller order to learn (the plant order when the windows record
      the state).
    - `x0_test`: `[N, n]` initial plant states of the closed-loop test.
    - `facts`: the problem's [`Facts`][dissil_jax.experiments.zoo.Facts].
    """

    name: str
    split: str
    plant: Any
    expert: Any
    expert_controller: LTIController | None
    train: Windows
    test: Windows
    plant_qsr: QSR
    plant_storage: np.ndarray | None
    qsr: QSR
    n_state: int
    x0_test: Float[Array, "N n"]
    facts: Facts


class Task(NamedTuple):
    """What a method sees: a PRNG `key`, the training `windows`, the controller's supply rate
    `qsr` and the controller order `n_state` (never the plant, the expert or the test data)."""

    key: PRNGKeyArray
    windows: Windows
    qsr: QSR
    n_state: int


class Report(NamedTuple):
    """The outcome of [`evaluate`][dissil_jax.experiments.zoo.evaluate], one entry per controller.

    - `certified`: `[K]` bool, $(Q,S,R)$-dissipativity of each controller proved by the exact
      float64 check of `dj.certify` (`dj.certify_ren` for REN controllers; False for
      other controllers, e.g. the MLP).
    - `stable`: `[K]` bool, the closed loop with the plant (exact for LTI loops).
    - `imitation_error`: `[K]` the held-out imitation loss relative to the zero controller's,
      $J(K;\\text{test}) / J(0;\\text{test})$ (0 is perfect, 1 is no better than $K = 0$;
      $+\\infty$ for a non-finite controller).
    - `train_loss`: `[K]` the method's final training loss when it returned a `FitResult`,
      else None.
    - `wall_time`: seconds spent in the method.
    """

    certified: np.ndarray
    stable: np.ndarray
    imitation_error: np.ndarray
    train_loss: np.ndarray | None
    wall_time: float


# -- experts ------------------------------------------------------------------------------


class StateFeedbackExpert(eqx.Module):
    """Static state feedback $u = -Kx$, or saturated, $u = -c\\tanh(Kx/c)$ per entry.

    `saturation` $c$ (None: linear) makes the expert nonlinear. The simulators' expert
    interface: `init(x0)` (no carry) and `__call__(x, carry) -> (u, carry)`.
    """

    K: Float[Array, "m n"]
    saturation: float | None = eqx.field(static=True, default=None)

    def init(self, x0):
        return None

    def __call__(self, x, carry=None):
        v = self.K @ x
        if self.saturation is not None:
            v = self.saturation * jnp.tanh(v / self.saturation)
        return -v, carry


class ObserverExpert(eqx.Module):
    """A dynamic output-feedback expert: the `LTIController` `controller` in negative feedback.

    The expert's state $\\hat x$ starts at rest (`init` gives zeros). At each step it outputs
    $u = -C_c\\hat x$ ($D_c = 0$, so no algebraic loop), measures $y = Cx + Du$ with the
    plant's `C`, `D`, and updates $\\hat x^+ = A_c\\hat x + B_cy$. (With control noise and
    $D\\ne0$ the measured $y$ misses the noise's feedthrough; the zoo's observer experts
    with noise are approximate demonstrators.)
    """

    controller: LTIController
    C: Float[Array, "p n"]
    D: Float[Array, "p m"]

    def init(self, x0):
        return jnp.zeros(self.controller.n_state, x0.dtype)

    def __call__(self, x, carry):
        u = -self.controller.C @ carry
        y = self.C @ x + self.D @ u
        return u, self.controller.A @ carry + self.controller.B @ y


def as_batch(controllers) -> Any:
    """A controller with one leading batch axis (a single `LTIController` or
    `RENController` gains one)."""
    if isinstance(controllers, (LTIController, RENController)) and \
            controllers.batch_shape == ():
        return jax.tree.map(lambda M: M[None], controllers)
    return controllers


def predict_any(controllers, windows: Windows, n_state: int) -> Float[Array, "K N h m"]:
    """Outputs of a batch of controllers (any `__call__(xhat, y) -> (xhat, yhat)`) on windows.

    The controller starts at `windows.x0`, or at rest (zeros of size `n_state`) when the
    windows record no state. Plain `lax.scan`, so it works for the MLP baseline too.
    """
    N = windows.num_windows
    x0 = (jnp.zeros((N, n_state), windows.y.dtype) if windows.x0 is None else windows.x0)

    def one(K):
        def window(xh, ys):
            def step(x, y):
                return K(x, y)

            return jax.lax.scan(step, xh, ys)[1]

        return jax.vmap(window)(x0, windows.y)

    return eqx.filter_vmap(one)(controllers)
