"""Physical plant simulators that stand in for the paper's (non-public) test rigs.

:mod:`kautztwin.simulators.hydraulic` models the electro-hydraulic servo drive of
the paper's section 3.2: a throttle-controlled (valve-controlled) hydraulic
motor whose parameters drift with the oil temperature.
"""

from __future__ import annotations

from .hydraulic import (
    HydraulicParameters,
    HydraulicServoDrive,
    Linearization,
    PlantResponse,
    StepTestRecords,
    simulate_step_tests,
    walther_viscosity,
)

__all__ = [
    "HydraulicParameters",
    "HydraulicServoDrive",
    "Linearization",
    "PlantResponse",
    "StepTestRecords",
    "simulate_step_tests",
    "walther_viscosity",
]
