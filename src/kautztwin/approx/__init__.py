"""Approximation of responses on orthonormal bases: coefficients, models, pole studies."""

from __future__ import annotations

from .model import KautzModel
from .poles import PoleOptimization, optimize_poles, pole_sensitivity
from .projection import (
    Approximation,
    approximate,
    coefficients_from_system,
    impulse_to_step,
    ise_from_system,
    project,
    step_to_impulse,
)

__all__ = [
    "Approximation",
    "KautzModel",
    "PoleOptimization",
    "approximate",
    "coefficients_from_system",
    "impulse_to_step",
    "ise_from_system",
    "optimize_poles",
    "pole_sensitivity",
    "project",
    "step_to_impulse",
]
