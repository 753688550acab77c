"""Identification: transfer-function estimation (tfest), ARX baselines, exact simulation.

* :class:`TransferFunctionEstimator` estimates a continuous-time transfer
  function (chosen or automatic order, optional delay) from one or many step,
  impulse or input/output :class:`Record` objects, by output-error refinement
  of an orthonormal-basis (Kautz) initialisation;
* :class:`ARXEstimator` is the discrete-time least-squares baseline;
* :func:`simulate_lti`, :func:`step_response` and :func:`impulse_response`
  simulate continuous models exactly for sampled (held or interpolated) inputs.
"""

from __future__ import annotations

from .arx import ARXEstimator, ARXModel
from .records import Record, load_records
from .simulate import impulse_response, simulate_lti, step_response
from .tfest import TransferFunctionEstimator, TransferFunctionModel

__all__ = [
    "ARXEstimator",
    "ARXModel",
    "Record",
    "TransferFunctionEstimator",
    "TransferFunctionModel",
    "impulse_response",
    "load_records",
    "simulate_lti",
    "step_response",
]
