r"""Update module of the digital twin: keeps the twin's model synchronised with the plant.

Three rooms:

* :mod:`.recursive`: :class:`RecursiveKautzEstimator`, the **fast path**:
  recursive least squares with exponential forgetting on Kautz-filtered
  regressors, :math:`y(k) \approx c^T x_f(k) + d` (:math:`O(N^2)` per sample);
* :mod:`.sync`: :class:`SyncMonitor`, the rolling fit of the twin's predicted
  output against the measured one, with desynchronisation detection
  (:class:`SyncEvent`, :class:`FitHistory`);
* :mod:`.reidentify`: :class:`Updater`, which runs the two each sample and the
  **accurate path** when the monitor triggers: output-error re-identification
  (:func:`kautztwin.ident.identify_output_error`) validated on held-out recent
  data (:class:`ModelUpdate`, :class:`UpdateResult`).  Its jobs beside the
  sample loop and the recovery policy are base classes in their own modules:
  :mod:`.accurate` (the accurate path: when an attempt is due, its window,
  fitted now or in the background worker of :mod:`.worker`),
  :mod:`.steptest` (the step-test / DNN path),
  :mod:`.judging` (the validation and acceptance of every candidate);
  :mod:`.records` holds the two records.

:func:`discretize_model` (:mod:`kautztwin.twin.digital`) and the output-error
identification (:mod:`kautztwin.ident.kautz_oe`) are re-exported here.
"""

from __future__ import annotations

from ...ident.kautz_oe import OutputErrorFit, identify_output_error
from ..digital import discretize_model
from .records import ModelUpdate, UpdateResult
from .recursive import RecursiveKautzEstimator
from .reidentify import Updater
from .sync import FitHistory, SyncEvent, SyncMonitor

__all__ = [
    "FitHistory",
    "ModelUpdate",
    "OutputErrorFit",
    "RecursiveKautzEstimator",
    "SyncEvent",
    "SyncMonitor",
    "UpdateResult",
    "Updater",
    "discretize_model",
    "identify_output_error",
]
