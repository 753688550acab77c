"""The interfaces the runtime loop wires: update, prediction, control and optimization modules.

:class:`~kautztwin.twin.runtime.DigitalTwin` talks to each module of the
twin through one of these small :class:`typing.Protocol` classes, so that
another implementation (another estimator, another controller) plugs in
without touching the loop.  :class:`TwinError` is what the runtime raises
when it cannot go on (defined beside the controller, which raises it too).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...approx.model import KautzModel
from ...exceptions import TwinError
from ...mpc import MPCResult
from ..digital import DigitalModel
from ..optimization import ControllerTuning, EstimatorRetraining
from ..prediction import MPCSettings
from ..update import ModelUpdate, Updater, UpdateResult

__all__ = [
    "TwinController",
    "TwinError",
    "TwinOptimizer",
    "TwinPredictor",
    "TwinUpdater",
]


@runtime_checkable
class TwinUpdater(Protocol):
    """Update module: keeps the digital model synchronised, one sample at a time.

    :class:`~kautztwin.twin.Updater` implements it.
    """

    digital_model: DigitalModel
    input_offset: float

    def step(self, u: Any, y: Any, t: Any = None) -> UpdateResult:
        """Process one sample ``(u(k), y(k))`` (see :meth:`Updater.step`)."""
        ...

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Predict the output for planned inputs from the current state."""
        ...


@runtime_checkable
class TwinPredictor(Protocol):
    """Prediction module, what-if part: the response of the twin to a planned input."""

    def what_if(self, u_plan: ArrayLike) -> NDArray[np.float64]:
        """Predicted outputs of the next samples for the planned inputs ``u_plan``."""
        ...


@runtime_checkable
class TwinController(Protocol):
    """Prediction module, control part: receding-horizon MPC on the current model.

    :class:`~kautztwin.twin.prediction.MPCController` implements it.
    """

    def rebuild(
        self, model: KautzModel, settings: MPCSettings, v_history: ArrayLike,
        d_history: ArrayLike,
    ) -> None:
        """Build the controller for a (new) model version, once."""
        ...

    def solve(self, y: float, reference: float, v_prev: float) -> MPCResult:
        """Solve for the current sample (fast, re-solved every sample)."""
        ...

    def advance(self, v: float, d: float) -> None:
        """Advance the controller's model state with the applied command and dither."""
        ...


@runtime_checkable
class TwinOptimizer(Protocol):
    """Optimization module: offline re-tuning; :class:`~kautztwin.twin.optimization.Optimizer`."""

    def tune_controller(
        self, model: KautzModel, settings: MPCSettings, *, step: float, u_op: float | None = None,
        y_op: float = 0.0,
    ) -> ControllerTuning:
        """Retune the MPC weights for a model version and validate them."""
        ...

    def retune_model(self, updater: Updater) -> ModelUpdate | None:
        """Re-optimise the basis poles on recent behaviour (validated by the updater)."""
        ...

    def consolidate(
        self, updater: Updater, current: KautzModel, current_offset: float, u: ArrayLike,
        y: ArrayLike,
    ) -> tuple[bool, float, float]:
        """Whether the live fast-path model beats the current version on recent data."""
        ...

    def retrain_estimator(self, estimator: Any, model: KautzModel) -> EstimatorRetraining:
        """Fine-tune the DNN estimator around a new model version and validate it."""
        ...
