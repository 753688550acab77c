"""Runtime of the digital twin: the sample loop wiring plant, update, control, optimization, store.

* :mod:`.config`: :class:`TwinConfig` (the tuned profiles of the shipped
  plants), :class:`FaultConfig`, :func:`parse_setpoints`;
* :mod:`.results`: :class:`TwinState` (one sample), :class:`TwinEvent`,
  :class:`TwinRun` (the record of a run);
* :mod:`.protocols`: the interfaces of the modules (:class:`TwinUpdater`,
  :class:`TwinPredictor`, :class:`TwinController`, :class:`TwinOptimizer`)
  and :class:`TwinError`;
* :mod:`.loop`: :class:`DigitalTwin`, the thin sample loop, helped by
  :mod:`.record` (bookkeeping, history store, resume), :mod:`.excitation`
  (excitation and faults), :mod:`.twins` (initial identification, static
  twin), :mod:`.birth` (a live plant's twin built without stalling the loop),
  :mod:`.versions` (what follows each update) and :mod:`.control` (which
  controller runs).

:class:`~kautztwin.twin.prediction.MPCController` and
:func:`~kautztwin.twin.physical.factory.make_plant` are re-exported here.
"""

from __future__ import annotations

from ..physical.factory import make_plant
from ..prediction import MPCController
from .config import FaultConfig, TwinConfig, parse_setpoints
from .loop import DigitalTwin
from .protocols import TwinController, TwinError, TwinOptimizer, TwinPredictor, TwinUpdater
from .results import TwinEvent, TwinRun, TwinState

__all__ = [
    "DigitalTwin",
    "FaultConfig",
    "MPCController",
    "TwinConfig",
    "TwinController",
    "TwinError",
    "TwinEvent",
    "TwinOptimizer",
    "TwinPredictor",
    "TwinRun",
    "TwinState",
    "TwinUpdater",
    "make_plant",
    "parse_setpoints",
]
