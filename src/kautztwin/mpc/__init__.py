"""Model predictive control on orthonormal Laguerre/Kautz parameterisations.

The control increments over the horizon are expanded on an orthonormal basis
(kautz-math.md section 6), so the QP has a handful of decision variables.
:class:`MPCProblem` builds the problem once (prediction, cost and constraint
maps) and re-solves it quickly at every sample with DAQP (or the
dependency-free Hildreth iteration); :func:`solve_mpc` is the one-shot form and
:func:`simulate_closed_loop` runs a receding-horizon loop.
"""

from __future__ import annotations

from .hildreth import HildrethResult, hildreth
from .laguerre import (
    MPCDesign,
    PlantModel,
    continuous_cost_matrices,
    continuous_mpc_design,
    continuous_phi,
    discrete_mpc_design,
    plant_model,
)
from .problem import (
    ClosedLoopResult,
    MPCMove,
    MPCProblem,
    MPCResult,
    Prediction,
    simulate_closed_loop,
    solve_mpc,
)

__all__ = [
    "ClosedLoopResult",
    "HildrethResult",
    "MPCDesign",
    "MPCMove",
    "MPCProblem",
    "MPCResult",
    "PlantModel",
    "Prediction",
    "continuous_cost_matrices",
    "continuous_mpc_design",
    "continuous_phi",
    "discrete_mpc_design",
    "hildreth",
    "plant_model",
    "simulate_closed_loop",
    "solve_mpc",
]
