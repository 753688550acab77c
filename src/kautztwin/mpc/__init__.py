"""Model predictive control on orthonormal Laguerre/Kautz parameterisations.

The control increments over the horizon are expanded on an orthonormal basis
(kautz-math.md section 6), so the QP has a handful of decision variables.
:class:`MPCProblem` builds the problem once (prediction, cost and constraint
maps) and re-solves it quickly at every sample with DAQP (or the
dependency-free Hildreth iteration); :func:`solve_mpc` is the one-shot form and
:func:`simulate_closed_loop` runs a receding-horizon loop.

Modules: :mod:`~kautztwin.mpc.plant` (the plant model), :mod:`~kautztwin.mpc.laguerre`
(discrete design), :mod:`~kautztwin.mpc.continuous` (continuous design),
:mod:`~kautztwin.mpc.prediction`, :mod:`~kautztwin.mpc.constraints`,
:mod:`~kautztwin.mpc.solve` and :mod:`~kautztwin.mpc.lean` (the parts of the QP and
the per-sample move), :mod:`~kautztwin.mpc.problem`
(:class:`MPCProblem`), :mod:`~kautztwin.mpc.results`, :mod:`~kautztwin.mpc.closed_loop`
and :mod:`~kautztwin.mpc.hildreth`.
"""

from __future__ import annotations

from .closed_loop import simulate_closed_loop
from .continuous import continuous_cost_matrices, continuous_mpc_design, continuous_phi
from .hildreth import HildrethResult, hildreth
from .laguerre import MPCDesign, discrete_mpc_design
from .plant import PlantModel, plant_model
from .problem import MPCProblem, solve_mpc
from .results import ClosedLoopResult, MPCMove, MPCResult, Prediction

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
