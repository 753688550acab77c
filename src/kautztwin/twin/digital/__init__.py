"""The digital model of the twin: the versioned Kautz model and its discretisation.

* :class:`DigitalModel` (:mod:`.model`): the current model with its version and provenance;
* :func:`discretize_model` (:mod:`.discretize`): a continuous Kautz model on the twin's
  delayed discrete basis (zero-order hold, exact).
"""

from __future__ import annotations

from .discretize import discretize_model
from .model import DigitalModel

__all__ = ["DigitalModel", "discretize_model"]
