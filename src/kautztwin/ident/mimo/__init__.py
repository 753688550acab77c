"""MIMO Kautz models: one filter bank per input, shared or per-output poles, coefficient matrices.

* :class:`MIMOKautzModel` is the immutable model: simulation, frequency response,
  state-space realisation, python-control and scipy conversions (both ways), JSON files;
* :func:`identify_mimo` fits one from an input/output record by output error (variable
  projection over the poles, least squares for the coefficient matrices);
* :class:`MIMOKautzEstimator` chooses the number of poles and the pole structure on
  held-out data;
* :func:`load_mimo_record` reads several input and output columns of a text file.
"""

from __future__ import annotations

from .estimator import MIMOKautzEstimator
from .fit import MIMOFit, check_mimo_data, identify_mimo
from .model import MIMOKautzModel, load_mimo_model
from .records import MIMORecord, load_mimo_record

__all__ = [
    "MIMOFit",
    "MIMOKautzEstimator",
    "MIMOKautzModel",
    "MIMORecord",
    "check_mimo_data",
    "identify_mimo",
    "load_mimo_model",
    "load_mimo_record",
]
