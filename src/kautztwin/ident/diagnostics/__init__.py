r"""Model diagnostics: residual tests, confidence bands and the verdict of an identification.

What MATLAB's ``resid``, ``compare`` and ``bode`` with confidence regions tell a control
engineer, as numbers:

* :func:`whiteness_test`: the residual autocorrelation with its confidence bound
  :math:`\pm z_{1-\alpha/2}/\sqrt N` and the Ljung-Box portmanteau test;
* :func:`cross_correlation_test`: the cross-correlation of residual and input with its
  bound, and a portmanteau test (prewhitened regression on the lagged inputs) that stays
  valid for coloured residuals and inputs;
* :func:`frequency_response_band`, :func:`step_response_band` and :func:`pole_uncertainty`:
  the parameter covariance of a :class:`~kautztwin.ident.TransferFunctionModel` carried to
  the Bode plot, the step response and the poles by first-order (delta-method) propagation
  through the exact Jacobians;
* :func:`diagnose`: all of them for a fitted
  :class:`~kautztwin.ident.TransferFunctionEstimator`, on its estimation and validation
  data, with a one-page verdict (:meth:`IdentificationDiagnostics.to_markdown`).

The residual functions take one sequence or a list of sequences (one per record): lagged
products are summed within each sequence only, never across the gap between two records.
The figures are drawn by :mod:`kautztwin.ident.diagnostics_plots`. Modules:
``correlation`` (the residual tests), ``bands`` (the propagation of the covariance) and
``report`` (:func:`diagnose` and the verdict).
"""

from __future__ import annotations

from .bands import (
    FrequencyResponseBand,
    PoleUncertainty,
    StepResponseBand,
    frequency_response_band,
    frequency_response_jacobian,
    pole_uncertainty,
    step_response_band,
    step_response_jacobian,
)
from .correlation import (
    DEFAULT_MAX_LAG,
    CrossCorrelationTest,
    WhitenessTest,
    autocorrelation,
    cross_correlation,
    cross_correlation_test,
    whiteness_test,
)
from .report import IdentificationDiagnostics, ResidualAnalysis, diagnose

__all__ = [
    "DEFAULT_MAX_LAG",
    "CrossCorrelationTest",
    "FrequencyResponseBand",
    "IdentificationDiagnostics",
    "PoleUncertainty",
    "ResidualAnalysis",
    "StepResponseBand",
    "WhitenessTest",
    "autocorrelation",
    "cross_correlation",
    "cross_correlation_test",
    "diagnose",
    "frequency_response_band",
    "frequency_response_jacobian",
    "pole_uncertainty",
    "step_response_band",
    "step_response_jacobian",
    "whiteness_test",
]
