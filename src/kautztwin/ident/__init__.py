"""Identification: transfer-function estimation (tfest), Kautz output error, ARX, simulation.

* :class:`TransferFunctionEstimator` estimates a continuous-time transfer
  function (chosen or automatic order, optional delay) from one or many step,
  impulse or input/output :class:`Record` objects, by output-error refinement
  of an orthonormal-basis (Kautz) initialisation;
* :func:`identify_output_error` fits a discrete Kautz model to input/output data
  by output error (variable projection over the poles): the twin's identification;
* :class:`ARXEstimator` is the discrete-time least-squares baseline;
* :func:`identify_mimo` and :class:`MIMOKautzEstimator` fit multi-input
  multi-output Kautz models (shared or per-output poles; :mod:`kautztwin.ident.mimo`);
* :func:`identify_nonlinear` fits nonlinear Kautz models (Wiener, Hammerstein,
  Wiener-Hammerstein, Kautz-Volterra; :mod:`kautztwin.ident.nonlinear`);
* :func:`simulate_lti`, :func:`step_response` and :func:`impulse_response`
  simulate continuous models exactly for sampled (held or interpolated) inputs.
"""

from __future__ import annotations

from .arx import ARXEstimator, ARXModel
from .kautz_oe import OutputErrorFit, identify_output_error
from .mimo import MIMOKautzEstimator, MIMOKautzModel, identify_mimo, load_mimo_model
from .nonlinear import (
    NonlinearFit,
    NonlinearKautzEnsemble,
    NonlinearKautzModel,
    identify_nonlinear,
    load_nonlinear_model,
)
from .records import Record, load_records
from .simulate import impulse_response, simulate_lti, step_response
from .tfest import TransferFunctionEstimator, TransferFunctionModel

__all__ = [
    "ARXEstimator",
    "ARXModel",
    "MIMOKautzEstimator",
    "MIMOKautzModel",
    "NonlinearFit",
    "NonlinearKautzEnsemble",
    "NonlinearKautzModel",
    "OutputErrorFit",
    "Record",
    "TransferFunctionEstimator",
    "TransferFunctionModel",
    "identify_mimo",
    "identify_nonlinear",
    "identify_output_error",
    "impulse_response",
    "load_mimo_model",
    "load_nonlinear_model",
    "load_records",
    "simulate_lti",
    "step_response",
]
