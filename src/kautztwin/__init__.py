"""kautztwin: digital twins of dynamic systems on orthonormal Kautz functions."""

from __future__ import annotations

from .approx import (
    Approximation,
    KautzModel,
    PoleOptimization,
    approximate,
    coefficients_from_system,
    impulse_to_step,
    ise_from_system,
    optimize_poles,
    pole_sensitivity,
    project,
    step_to_impulse,
)
from .basis import KautzBasis, LaguerreBasis
from .metrics import fit_percent, ise, mse, nrmse, r_squared

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "approximate",
    "Approximation",
    "coefficients_from_system",
    "fit_percent",
    "impulse_to_step",
    "ise",
    "ise_from_system",
    "KautzBasis",
    "KautzModel",
    "LaguerreBasis",
    "mse",
    "nrmse",
    "optimize_poles",
    "pole_sensitivity",
    "PoleOptimization",
    "project",
    "r_squared",
    "step_to_impulse",
]
