r"""Nonlinear model of an electro-hydraulic servo drive (throttle-controlled hydraulic motor).

The paper's experimental system (section 3.2) is a laboratory stand on which the
speed of a hydraulic motor is controlled by throttling the oil flow with an
electrically driven valve.  Its measurements are not public, so this module
simulates a physically equivalent drive: a proportional 4-way critical-centre
spool valve fed from a constant supply pressure drives a fixed-displacement
motor with a flywheel and a viscous load.  The model has three states,

* the spool position :math:`x_v` (first-order lag of the valve command, with
  the stroke limited to :math:`\pm x_{max}`),
* the load pressure :math:`p_L = p_A - p_B` across the motor,
* the shaft speed :math:`\omega` (the measured output),

and the equations of Merritt (1967), Watton (1989) and Jelali & Kroll (2003):

.. math::

    \tau_v \dot x_v &= x_{max}\,\mathrm{sat}(u) - x_v \\
    Q_L &= C_d w x_v \sqrt{(p_s - \mathrm{sgn}(x_v)\, p_L)/\rho} \\
    \frac{V_t}{4\beta_e(T)} \dot p_L &= Q_L - D_m \omega - C_l(T)\, p_L \\
    J \dot\omega &= D_m p_L - B(T)\,\omega - T_c \tanh(\omega/\omega_c)

The oil temperature :math:`T` enters through the kinematic viscosity
:math:`\nu(T)` (Walther's equation, ASTM D341): the laminar leakage scales as
:math:`C_l \propto 1/\nu`, the motor's viscous friction as
:math:`B_v \propto \nu` (Wilson's loss model) and the bulk modulus falls
linearly with temperature.  The full derivation, the parameter table with
sources and the resulting pole drift are in ``docs/hydraulic.md``.

Linearised at a constant valve command the drive is a third-order system with
three distinct real poles (the structure the paper identifies, 97.31 % fit);
with the nominal parameters at 40 °C and ``u0 = 0.5`` they lie at about
``-2.94, -10.0, -41.3`` rad/s (at 20 °C ``-3.87, -10.0, -33.8``, at 60 °C
``-2.13, -10.0, -56.9``): oil warming slows the slow pole and speeds up the fast one.

The package splits the simulator by job: :mod:`.parameters` (physical
parameters, oil viscosity and temperature range), :mod:`.drive` (the ODE model
:class:`HydraulicServoDrive`: equilibrium, linearisation, simulation),
:mod:`.results` (the returned records) and :mod:`.steptests` (a session of
step tests while the oil warms up).
"""

from __future__ import annotations

from .drive import HydraulicServoDrive
from .parameters import (
    DEFAULT_T_END,
    NOMINAL_COMMAND,
    NOMINAL_TEMPERATURE,
    TEMPERATURE_RANGE,
    HydraulicParameters,
    walther_viscosity,
)
from .results import Linearization, PlantResponse, StepTestRecords
from .steptests import simulate_step_tests

__all__ = [
    "DEFAULT_T_END",
    "NOMINAL_COMMAND",
    "NOMINAL_TEMPERATURE",
    "TEMPERATURE_RANGE",
    "HydraulicParameters",
    "HydraulicServoDrive",
    "Linearization",
    "PlantResponse",
    "StepTestRecords",
    "simulate_step_tests",
    "walther_viscosity",
]
