"""Physical parameters of the hydraulic drive, oil viscosity (Walther) and temperature range."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import (
    check_number,
)
from ...exceptions import DataError

__all__ = [
    "DEFAULT_T_END",
    "NOMINAL_COMMAND",
    "NOMINAL_TEMPERATURE",
    "TEMPERATURE_RANGE",
    "HydraulicParameters",
    "walther_viscosity",
]

#: oil temperatures (°C) for which the model is defined (mineral-oil operating range)
TEMPERATURE_RANGE: tuple[float, float] = (-20.0, 120.0)
#: valve command of the nominal operating point (half the rated spool stroke)
NOMINAL_COMMAND = 0.5
#: nominal oil temperature, °C (the reference temperature of the parameters)
NOMINAL_TEMPERATURE = 40.0
#: default record length of a step test, seconds (the slowest pole at 60 °C settles)
DEFAULT_T_END = 3.0
_T40_K = 313.15
_T100_K = 373.15


def walther_viscosity(
    temperature: ArrayLike, viscosity_40: float = 46.0, viscosity_100: float = 6.8
) -> float | NDArray[np.float64]:
    r"""Kinematic viscosity of a mineral oil from Walther's equation (ASTM D341).

    .. math:: \log_{10}\log_{10}(\nu + 0.7) = A - B \log_{10} T_K

    with :math:`\nu` in mm²/s (cSt) and :math:`T_K` in kelvin; :math:`A` and
    :math:`B` follow from the viscosities at 40 °C and 100 °C, the two values an
    oil datasheet gives (ISO 3104 / ISO 3448).

    Parameters
    ----------
    temperature : float or array-like
        Oil temperature in °C.
    viscosity_40 : float, default=46.0
        Kinematic viscosity at 40 °C in mm²/s (ISO VG 46: 46).
    viscosity_100 : float, default=6.8
        Kinematic viscosity at 100 °C in mm²/s (an HM oil with VI ≈ 100: 6.8).

    Returns
    -------
    float or ndarray
        Kinematic viscosity in mm²/s, same shape as ``temperature``.

    References
    ----------
    ASTM D341, Standard Practice for Viscosity–Temperature Equations and Charts
    for Liquid Petroleum or Hydrocarbon Products.

    Examples
    --------
    >>> from kautztwin.simulators import walther_viscosity
    >>> [round(float(walther_viscosity(T)), 1) for T in (20, 40, 60, 100)]
    [133.8, 46.0, 20.6, 6.8]
    """
    T = np.asarray(temperature, dtype=float) + 273.15
    y40 = math.log10(math.log10(viscosity_40 + 0.7))
    y100 = math.log10(math.log10(viscosity_100 + 0.7))
    b = (y40 - y100) / (math.log10(_T100_K) - math.log10(_T40_K))
    a = y40 + b * math.log10(_T40_K)
    nu = 10.0 ** (10.0 ** (a - b * np.log10(T))) - 0.7
    return float(nu) if nu.ndim == 0 else nu


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class HydraulicParameters:
    r"""Physical parameters of the throttle-controlled hydraulic motor drive.

    Values describe a small laboratory stand: a proportional valve of about
    20 L/min rated flow at 100 bar supply, an 8 cm³/rev motor, long hoses and a
    flywheel with a viscous load.  Temperature-dependent quantities are given
    at the reference temperature of 40 °C; :meth:`at_temperature` gives their
    values at another temperature.  Every value is a typical textbook figure,
    not a measurement of the paper's (unpublished) stand.

    Parameters
    ----------
    supply_pressure : float, default=10.0e6
        :math:`p_s`, Pa.  Constant-pressure supply (pump with relief valve),
        100 bar; tank pressure taken as 0.  Range of industrial practice
        70–210 bar (Watton 1989).
    discharge_coefficient : float, default=0.61
        :math:`C_d`, dimensionless.  Sharp-edged turbulent orifice
        (Merritt 1967: 0.60–0.61).
    area_gradient : float, default=0.01
        :math:`w`, m.  Port width per unit spool stroke (a notched 6 mm spool).
    spool_stroke : float, default=0.5e-3
        :math:`x_{max}`, m.  Spool stroke at full command; rated no-load flow
        :math:`C_d w x_{max}\sqrt{p_s/\rho} \approx 19.6` L/min.
    valve_time_constant : float, default=0.1
        :math:`\tau_v`, s.  First-order spool lag of a proportional valve
        without position feedback (catalogue step-response times 50–150 ms;
        Jelali & Kroll 2003 model valves as first- or second-order lags).
    bulk_modulus : float, default=7.0e8
        :math:`\beta_e`, Pa, at 40 °C.  Effective bulk modulus of oil, hoses
        and entrained air; Merritt recommends about 100 000 psi (0.69 GPa) for
        design when the hoses are not stiff.
    bulk_modulus_slope : float, default=0.004
        Relative decrease of :math:`\beta_e` per kelvin,
        :math:`\beta_e(T) = \beta_e(40)\,(1 - k_\beta (T - 40))`; mineral oils
        lose roughly 0.3–0.5 %/K of their bulk modulus (Watton 1989).
    volume : float, default=1.0e-3
        :math:`V_t`, m³.  Total oil volume of both motor lines and chambers
        (about 2 × 4 m of 1/2" hose).
    displacement : float, default=8e-6 / (2 pi)
        :math:`D_m`, m³/rad.  An 8 cm³/rev gear motor.
    inertia : float, default=0.05
        :math:`J`, kg m².  Motor, coupling and flywheel (a 10 kg steel disc of
        0.2 m diameter).
    leakage : float, default=6.0e-12
        :math:`C_l`, m³/(s Pa), at 40 °C.  Total laminar leakage coefficient of
        the motor (internal plus external), about 2 L/min at 100 bar, i.e. a
        volumetric efficiency near 90 % (Merritt; Watton).  Scales with
        :math:`\nu(40)/\nu(T)`.
    viscous_friction : float, default=0.005
        :math:`B_v`, N m s/rad, at 40 °C.  Viscous torque loss of the motor;
        scales with :math:`\nu(T)/\nu(40)` (Wilson's model, see Merritt).
    load_damping : float, default=0.03
        :math:`B_L`, N m s/rad.  Viscous load (a loading pump discharging
        through a throttle), independent of the oil temperature of the drive.
    coulomb_friction : float, default=0.0
        :math:`T_c`, N m.  Optional Coulomb (dry) friction torque, smoothed as
        :math:`T_c\tanh(\omega/\omega_c)`; 0 keeps the model smooth at rest.
    coulomb_speed : float, default=1.0
        :math:`\omega_c`, rad/s.  Smoothing width of the Coulomb friction.
    density : float, default=870.0
        :math:`\rho`, kg/m³.  Mineral hydraulic oil (taken constant; it changes
        by less than 3 % between 20 and 60 °C).
    viscosity_40 : float, default=46.0
        Kinematic viscosity at 40 °C, mm²/s (ISO VG 46).
    viscosity_100 : float, default=6.8
        Kinematic viscosity at 100 °C, mm²/s (HM oil, viscosity index ≈ 100).
    transition_pressure : float, default=1.0e4
        :math:`\delta`, Pa.  Width of the smooth laminar–turbulent transition of
        the orifice law near zero pressure drop (numerical regularisation of
        the square root, relative error below :math:`10^{-4}` above 1 bar).

    Raises
    ------
    DataError
        If a value is not finite, not positive where it must be, or makes the
        bulk modulus non-positive inside the temperature range.

    See Also
    --------
    HydraulicServoDrive : The simulator that uses these parameters.
    walther_viscosity : The viscosity–temperature law.

    References
    ----------
    H. E. Merritt, *Hydraulic Control Systems*, Wiley, 1967.
    J. Watton, *Fluid Power Systems: Modeling, Simulation, Analog and
    Microcomputer Control*, Prentice Hall, 1989.
    M. Jelali and A. Kroll, *Hydraulic Servo-systems: Modelling,
    Identification and Control*, Springer, 2003.

    Examples
    --------
    >>> from kautztwin.simulators import HydraulicParameters
    >>> p = HydraulicParameters()
    >>> round(p.rated_flow * 60e3, 1)  # L/min
    19.6
    >>> round(p.at_temperature(60.0)["leakage"] / p.leakage, 2)
    2.23
    """

    supply_pressure: float = 10.0e6
    discharge_coefficient: float = 0.61
    area_gradient: float = 0.01
    spool_stroke: float = 0.5e-3
    valve_time_constant: float = 0.1
    bulk_modulus: float = 7.0e8
    bulk_modulus_slope: float = 0.004
    volume: float = 1.0e-3
    displacement: float = 8e-6 / (2 * math.pi)
    inertia: float = 0.05
    leakage: float = 6.0e-12
    viscous_friction: float = 0.005
    load_damping: float = 0.03
    coulomb_friction: float = 0.0
    coulomb_speed: float = 1.0
    density: float = 870.0
    viscosity_40: float = 46.0
    viscosity_100: float = 6.8
    transition_pressure: float = 1.0e4

    def __post_init__(self) -> None:
        may_be_zero = {"coulomb_friction", "bulk_modulus_slope", "viscous_friction", "load_damping"}
        for f in fields(self):
            value = check_number(getattr(self, f.name), f.name)
            if f.name in may_be_zero:
                if value < 0:
                    raise DataError(f"{f.name} must be >= 0, got {value:g}")
            elif value <= 0:
                raise DataError(f"{f.name} must be > 0, got {value:g}")
            object.__setattr__(self, f.name, value)
        if self.discharge_coefficient > 1:
            raise DataError(
                f"discharge_coefficient must lie in (0, 1], got {self.discharge_coefficient:g}"
            )
        if self.viscous_friction + self.load_damping <= 0:
            raise DataError(
                "viscous_friction + load_damping must be > 0 (the motor would not settle)"
            )
        if self.viscosity_100 >= self.viscosity_40:
            raise DataError(
                f"viscosity_100 ({self.viscosity_100:g}) must be below viscosity_40 "
                f"({self.viscosity_40:g}); oil thins as it warms"
            )
        hot = TEMPERATURE_RANGE[1] - NOMINAL_TEMPERATURE
        if self.bulk_modulus_slope * hot >= 1:
            raise DataError(
                f"bulk_modulus_slope = {self.bulk_modulus_slope:g} /K makes the bulk modulus "
                f"non-positive below {TEMPERATURE_RANGE[1]:g} °C; it must be < {1 / hot:g}"
            )

    @property
    def rated_flow(self) -> float:
        r"""No-load flow at full spool stroke, :math:`C_d w x_{max}\sqrt{p_s/\rho}`, m³/s."""
        return (
            self.discharge_coefficient * self.area_gradient * self.spool_stroke
            * math.sqrt(self.supply_pressure / self.density)
        )

    @property
    def no_load_speed(self) -> float:
        """Speed the rated flow gives a loss-free motor, ``rated_flow / displacement``, rad/s."""
        return self.rated_flow / self.displacement

    def viscosity(self, temperature: ArrayLike) -> float | NDArray[np.float64]:
        """Kinematic viscosity of the oil in mm²/s (see :func:`walther_viscosity`).

        Parameters
        ----------
        temperature : float or array-like
            Oil temperature, °C.

        Returns
        -------
        float or ndarray
        """
        return walther_viscosity(temperature, self.viscosity_40, self.viscosity_100)

    def at_temperature(self, temperature: float) -> dict[str, float]:
        r"""The temperature-dependent parameters at one oil temperature.

        Parameters
        ----------
        temperature : float
            Oil temperature, °C, inside ``TEMPERATURE_RANGE`` (-20 to 120 °C).

        Returns
        -------
        dict
            ``viscosity`` (mm²/s), ``leakage`` (m³/(s Pa)),
            ``viscous_friction`` (N m s/rad, motor part only), ``damping``
            (N m s/rad, motor plus load) and ``bulk_modulus`` (Pa).

        Raises
        ------
        DataError
            If ``temperature`` is not finite or outside the range.

        Notes
        -----
        .. math::

            C_l(T) = C_l(40)\,\frac{\nu(40)}{\nu(T)}, \quad
            B_v(T) = B_v(40)\,\frac{\nu(T)}{\nu(40)}, \quad
            \beta_e(T) = \beta_e(40)\,\bigl(1 - k_\beta (T - 40)\bigr)
        """
        T = _check_temperature(temperature, "temperature")
        ratio = float(self.viscosity(T)) / self.viscosity_40
        bv = self.viscous_friction * ratio
        return {
            "viscosity": ratio * self.viscosity_40,
            "leakage": self.leakage / ratio,
            "viscous_friction": bv,
            "damping": bv + self.load_damping,
            "bulk_modulus": self.bulk_modulus * (1 - self.bulk_modulus_slope * (T - 40.0)),
        }

    def to_dict(self) -> dict[str, float]:
        """All parameters as a ``{name: value}`` dict of floats (SI units).

        Returns
        -------
        dict
        """
        return {k: float(v) for k, v in asdict(self).items()}


def _check_temperature(value: Any, name: str) -> float:
    try:
        T = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{name} must be a number in °C, got {value!r}") from None
    lo, hi = TEMPERATURE_RANGE
    if not (math.isfinite(T) and lo <= T <= hi):
        raise DataError(f"{name} must lie in [{lo:g}, {hi:g}] °C (mineral oil), got {T:g}")
    return T
