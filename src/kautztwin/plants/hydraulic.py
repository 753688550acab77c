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
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
import scipy.integrate
import scipy.optimize
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from .._validation import check_finite, check_time
from ..exceptions import DataError, DimensionError

__all__ = [
    "HydraulicParameters",
    "HydraulicServoDrive",
    "Linearization",
    "PlantResponse",
    "StepTestRecords",
    "simulate_step_tests",
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
_METHODS = ("LSODA", "Radau", "BDF", "RK45", "DOP853", "RK23")
_IMPLICIT = ("LSODA", "Radau", "BDF")
_T40_K = 313.15
_T100_K = 373.15

Temperature = float | ArrayLike | Callable[[float], float]


def _readonly(a: ArrayLike, dtype: Any = float) -> NDArray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


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
    >>> from kautztwin.plants import walther_viscosity
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
    >>> from kautztwin.plants import HydraulicParameters
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
            value = getattr(self, f.name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise DataError(f"{f.name} must be a number, got {value!r}") from None
            if not math.isfinite(value):
                raise DataError(f"{f.name} must be finite, got {value}")
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


# --------------------------------------------------------------------------- scaled model
class _Coefficients:
    """Coefficients of the scaled model at one temperature (all rates in 1/s).

    States are scaled to order one: ``xi = x_v / x_max``, ``pi = p_L / p_s``,
    ``w = omega / omega_nl`` with the no-load speed ``omega_nl = Q_max / D_m``.
    """

    __slots__ = ("b", "c", "eps2", "kq", "lam", "m", "tau", "wc")

    def __init__(self, p: HydraulicParameters, temperature: float) -> None:
        eff = p.at_temperature(temperature)
        qmax = p.rated_flow
        w_nl = p.no_load_speed
        self.tau = p.valve_time_constant
        self.kq = 4.0 * eff["bulk_modulus"] * qmax / (p.volume * p.supply_pressure)
        self.lam = eff["leakage"] * p.supply_pressure / qmax
        self.m = p.displacement * p.supply_pressure / (p.inertia * w_nl)
        self.b = eff["damping"] / p.inertia
        self.c = p.coulomb_friction / (p.inertia * w_nl)
        self.wc = p.coulomb_speed / w_nl
        self.eps2 = (p.transition_pressure / p.supply_pressure) ** 2


def _orifice(s: float, eps2: float) -> tuple[float, float]:
    """Regularised ``sign(s) sqrt(|s|)`` and its derivative."""
    r = s * s + eps2
    q = r**0.25
    return s / q, (0.5 * s * s + eps2) / (r * q)


def _rhs(z: NDArray, v: float, c: _Coefficients) -> list[float]:
    xi, pi, w = z
    sg = 1.0 if xi > 0 else (-1.0 if xi < 0 else 0.0)
    f, _ = _orifice(1.0 - sg * pi, c.eps2)
    dxi = (v - xi) / c.tau
    dpi = c.kq * (xi * f - w - c.lam * pi)
    dw = c.m * pi - c.b * w - (c.c * math.tanh(w / c.wc) if c.c else 0.0)
    return [dxi, dpi, dw]


def _jac(z: NDArray, c: _Coefficients) -> NDArray[np.float64]:
    xi, pi, w = z
    sg = 1.0 if xi > 0 else (-1.0 if xi < 0 else 0.0)
    f, df = _orifice(1.0 - sg * pi, c.eps2)
    dfric = c.c / c.wc * (1.0 - math.tanh(w / c.wc) ** 2) if c.c else 0.0  # sech^2, no overflow
    return np.array([
        [-1.0 / c.tau, 0.0, 0.0],
        [c.kq * f, -c.kq * (abs(xi) * df + c.lam), -c.kq],
        [0.0, c.m, -c.b - dfric],
    ])


# --------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class Linearization:
    r"""Small-signal model of the drive around an equilibrium.

    The transfer function from a change of the valve command :math:`\Delta u`
    to the change of shaft speed :math:`\Delta\omega` (rad/s per unit command)
    is

    .. math:: G(s) = \frac{b_0}{(s - p_1)(s - p_2)(s - p_3)}

    (no zeros: the command reaches the speed only through the spool and the
    pressure).

    Parameters
    ----------
    num, den : ndarray
        Transfer-function coefficients in descending powers of ``s``; ``den``
        is monic.
    poles : ndarray of complex, shape (3,)
        Roots of ``den``, slowest (closest to the imaginary axis) first.
    A, B, C, D : ndarray
        State-space matrices of the deviations of the physical states
        ``(x_v [m], p_L [Pa], omega [rad/s])``, shapes (3, 3), (3, 1), (1, 3), (1, 1).
    u0 : float
        Valve command of the operating point.
    x0 : ndarray of shape (3,)
        Equilibrium state ``(x_v, p_L, omega)`` in m, Pa, rad/s.
    temperature : float
        Oil temperature, °C.

    See Also
    --------
    HydraulicServoDrive.linearize : Builds this object.
    """

    num: NDArray[np.float64]
    den: NDArray[np.float64]
    poles: NDArray[np.complex128]
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    D: NDArray[np.float64]
    u0: float
    x0: NDArray[np.float64]
    temperature: float

    def __post_init__(self) -> None:
        for name in ("num", "den", "A", "B", "C", "D", "x0"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))
        object.__setattr__(self, "poles", _readonly(self.poles, complex))

    @property
    def y0(self) -> float:
        """Shaft speed of the operating point, rad/s."""
        return float(self.x0[2])

    @property
    def dc_gain(self) -> float:
        """Static gain ``G(0)``: rad/s per unit of valve command."""
        return float(self.num[-1] / self.den[-1])

    @property
    def is_real(self) -> bool:
        """Whether all poles are real (relative imaginary part below 1e-9)."""
        return bool(np.all(np.abs(self.poles.imag) <= 1e-9 * np.abs(self.poles)))

    def to_scipy(self) -> scipy.signal.TransferFunction:
        """The transfer function as a :class:`scipy.signal.TransferFunction`.

        Returns
        -------
        scipy.signal.TransferFunction
        """
        return scipy.signal.TransferFunction(self.num, self.den)

    def step(self, t: ArrayLike, amplitude: float = 1.0) -> NDArray[np.float64]:
        """Speed change for a command step of ``amplitude`` at ``t[0]``, from the equilibrium.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Increasing sample times, s.
        amplitude : float, default=1.0
            Size of the command step.

        Returns
        -------
        ndarray of shape (n_samples,)
            :math:`\\Delta\\omega(t)` in rad/s (add :attr:`y0` for the absolute speed).
        """
        t = check_time(t)
        _, y = scipy.signal.step(self.to_scipy(), T=t - t[0])
        return amplitude * np.asarray(y, dtype=float)


@dataclass(frozen=True, eq=False)
class PlantResponse:
    """Sampled response of the drive to a command signal.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Sample times, s.
    u : ndarray of shape (n_samples,)
        Valve command (fraction of the rated input), held between samples.
    y : ndarray of shape (n_samples,)
        Measured shaft speed, rad/s: ``y_true`` plus sensor noise, quantised.
    y_true : ndarray of shape (n_samples,)
        Noise-free shaft speed, rad/s.
    x : ndarray of shape (n_samples, 3)
        States ``(x_v [m], p_L [Pa], omega [rad/s])``; ``x[-1]`` continues a
        simulation (pass it as ``x0``).
    temperature : ndarray of shape (n_samples,)
        Oil temperature at the samples, °C.
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    y_true: NDArray[np.float64]
    x: NDArray[np.float64]
    temperature: NDArray[np.float64]

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, _readonly(getattr(self, f.name)))


@dataclass(frozen=True, eq=False)
class StepTestRecords:
    """A session of step tests: one response per record, oil warming between records.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Common sample times, s.
    u : ndarray of shape (n_records, n_samples)
        Valve command of each record.
    y : ndarray of shape (n_records, n_samples)
        Measured shaft speed (with noise), rad/s.
    y_true : ndarray of shape (n_records, n_samples)
        Noise-free shaft speed, rad/s.
    temperature : ndarray of shape (n_records,)
        Oil temperature of each record, °C.
    amplitude : float
        Step size of the valve command.
    noise : float
        Noise standard deviation as a fraction of each record's peak.
    parameters : HydraulicParameters
        Parameters of the simulated drive.
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    y_true: NDArray[np.float64]
    temperature: NDArray[np.float64]
    amplitude: float
    noise: float
    parameters: HydraulicParameters = field(default_factory=HydraulicParameters)

    def __post_init__(self) -> None:
        for name in ("t", "u", "y", "y_true", "temperature"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))

    @property
    def n_records(self) -> int:
        """Number of step responses."""
        return int(self.y.shape[0])

    @property
    def n_samples(self) -> int:
        """Samples per response."""
        return int(self.t.size)


# --------------------------------------------------------------------------- the drive
@dataclass(frozen=True, eq=False)
class HydraulicServoDrive:
    r"""Simulator of the electro-hydraulic servo drive (throttle-controlled hydraulic motor).

    Input: the valve command ``u`` (fraction of the rated input, so
    ``|u| = 1`` is the full spool stroke; larger commands saturate), held
    constant between samples as a D/A converter does.  Output: the shaft
    speed in rad/s.  The oil temperature is a second, slowly varying input;
    it changes the leakage, the friction and the bulk modulus.

    Parameters
    ----------
    parameters : HydraulicParameters, optional
        Physical parameters; the nominal set when omitted.
    sensor_resolution : float, default=0.0
        Quantisation step of the speed sensor, rad/s (0: none).
    method : str, default='LSODA'
        :func:`scipy.integrate.solve_ivp` method; ``'LSODA'`` switches to a
        stiff (BDF) integrator when needed, ``'Radau'`` and ``'BDF'`` work too.
    rtol : float, default=1e-8
        Relative tolerance of the integrator.
    atol : float, default=1e-10
        Absolute tolerance on the scaled states (spool, pressure and speed as
        fractions of stroke, supply pressure and no-load speed).

    See Also
    --------
    simulate_step_tests : A session of step tests at rising oil temperature.
    HydraulicParameters : The physical parameters and their sources.

    Notes
    -----
    The model, with :math:`\mathrm{sat}(u) = \min(1, \max(-1, u))`, is

    .. math::

        \tau_v \dot x_v &= x_{max}\,\mathrm{sat}(u) - x_v \\
        \frac{V_t}{4\beta_e} \dot p_L &=
            C_d w x_v \frac{p_s - \mathrm{sgn}(x_v) p_L}
            {\sqrt{\rho}\,\bigl((p_s - \mathrm{sgn}(x_v) p_L)^2 + \delta^2\bigr)^{1/4}}
            - D_m\omega - C_l p_L \\
        J\dot\omega &= D_m p_L - (B_v + B_L)\,\omega - T_c\tanh(\omega/\omega_c)

    The second equation is Merritt's load-flow equation of a matched,
    symmetric critical-centre 4-way valve, :math:`Q_L = C_d w x_v
    \sqrt{(p_s - \mathrm{sgn}(x_v) p_L)/\rho}`, with the square root smoothed
    over :math:`\delta` around zero pressure drop, plus the continuity
    equation of the two motor lines.  The flow saturates in two ways: the
    spool stroke is limited, and the flow falls as the load pressure
    approaches the supply pressure (e.g. while the flywheel accelerates).

    References
    ----------
    H. E. Merritt, *Hydraulic Control Systems*, Wiley, 1967.
    M. Jelali and A. Kroll, *Hydraulic Servo-systems*, Springer, 2003.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.plants import HydraulicServoDrive
    >>> drive = HydraulicServoDrive()
    >>> lin = drive.linearize(0.5, temperature=40.0)
    >>> np.round(lin.poles.real, 2)
    array([ -2.94, -10.  , -41.31])
    >>> t = np.linspace(0.0, 3.0, 900)
    >>> r = drive.step_response(t, amplitude=0.5, temperature=40.0)
    >>> bool(abs(r.y[-1] - lin.y0) < 0.05)  # settled at the linearisation's speed, rad/s
    True
    """

    parameters: HydraulicParameters = field(default_factory=HydraulicParameters)
    sensor_resolution: float = 0.0
    method: str = "LSODA"
    rtol: float = 1e-8
    atol: float = 1e-10

    def __post_init__(self) -> None:
        if not isinstance(self.parameters, HydraulicParameters):
            raise DataError(
                f"parameters must be a HydraulicParameters, got {type(self.parameters).__name__}"
            )
        res = float(self.sensor_resolution)
        if not (math.isfinite(res) and res >= 0):
            raise DataError(f"sensor_resolution must be >= 0 rad/s, got {self.sensor_resolution}")
        object.__setattr__(self, "sensor_resolution", res)
        if self.method not in _METHODS:
            raise DataError(f"method must be one of {', '.join(_METHODS)}, got {self.method!r}")
        for name in ("rtol", "atol"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise DataError(f"{name} must be > 0, got {getattr(self, name)}")
            object.__setattr__(self, name, value)

    # ---------------------------------------------------------------- scaling helpers
    @property
    def _scale(self) -> NDArray[np.float64]:
        p = self.parameters
        return np.array([p.spool_stroke, p.supply_pressure, p.no_load_speed])

    def _coefficients(self, temperature: float) -> _Coefficients:
        return _Coefficients(self.parameters, temperature)

    # ---------------------------------------------------------------- equilibrium
    def equilibrium(
        self, u0: float, temperature: float = NOMINAL_TEMPERATURE
    ) -> NDArray[np.float64]:
        """Steady state for a constant valve command.

        Parameters
        ----------
        u0 : float
            Constant valve command (saturates at ``|u0| = 1``).
        temperature : float, default=40.0
            Oil temperature, °C.

        Returns
        -------
        ndarray of shape (3,)
            ``(x_v [m], p_L [Pa], omega [rad/s])``.

        Raises
        ------
        DataError
            If ``u0`` is not finite or ``temperature`` is out of range.
        """
        u0 = _check_number(u0, "u0")
        c = self._coefficients(_check_temperature(temperature, "temperature"))
        return self._equilibrium_scaled(u0, c) * self._scale

    def _equilibrium_scaled(self, u0: float, c: _Coefficients) -> NDArray[np.float64]:
        xi = min(1.0, max(-1.0, u0))
        a = abs(xi)
        if a == 0.0:
            return np.zeros(3)

        def pressure(w: float) -> float:  # torque balance: m pi = b w + c tanh(w / wc)
            return (c.b * w + (c.c * math.tanh(w / c.wc) if c.c else 0.0)) / c.m

        def flow_balance(w: float) -> float:
            pi = pressure(w)
            return a * _orifice(1.0 - pi, c.eps2)[0] - w - c.lam * pi

        hi = a * _orifice(1.0, c.eps2)[0] * (1 + 1e-9)
        w = scipy.optimize.brentq(flow_balance, 0.0, hi, xtol=1e-15, rtol=1e-14, maxiter=200)
        sign = 1.0 if xi > 0 else -1.0
        return sign * np.array([a, pressure(w), w])

    # ---------------------------------------------------------------- linearisation
    def linearize(
        self, operating_point: float = NOMINAL_COMMAND, temperature: float = NOMINAL_TEMPERATURE
    ) -> Linearization:
        """Small-signal transfer function from valve command to speed at an equilibrium.

        Parameters
        ----------
        operating_point : float, default=0.5
            Constant valve command ``u0`` of the equilibrium.  At or beyond the
            stroke limit (``|u0| >= 1``) the spool saturates: the poles are
            those of the saturated equilibrium and the gain ``num`` is zero.
        temperature : float, default=40.0
            Oil temperature, °C.

        Returns
        -------
        Linearization
            ``num``, ``den``, ``poles`` (slowest first), the state-space
            matrices and the equilibrium.

        Raises
        ------
        DataError
            If ``operating_point`` is not finite or ``temperature`` is out of range.

        Notes
        -----
        With the Jacobian entries of the scaled model the denominator is
        :math:`(s + 1/\\tau_v)\\,(s^2 + (k_c + b)s + k_c b + k_q m)`, where
        :math:`k_c` is the pressure-flow (leakage plus valve) rate, :math:`b`
        the mechanical damping rate and :math:`k_q m` the squared hydraulic
        natural frequency; the poles are real when the hydraulic damping ratio
        exceeds one.
        """
        u0 = _check_number(operating_point, "operating_point")
        T = _check_temperature(temperature, "temperature")
        c = self._coefficients(T)
        z0 = self._equilibrium_scaled(u0, c)
        Az = _jac(z0, c)
        b1 = 1.0 / c.tau if abs(u0) < 1 else 0.0  # at the stroke limit a change has no effect
        # the command reaches the speed only along spool -> pressure -> speed: no zeros
        gain = b1 * Az[1, 0] * Az[2, 1]
        quad = [1.0, -(Az[1, 1] + Az[2, 2]), Az[1, 1] * Az[2, 2] - Az[1, 2] * Az[2, 1]]
        den_z = np.polymul([1.0, 1.0 / c.tau], quad)
        poles = np.linalg.eigvals(Az).astype(complex)
        poles = poles[np.lexsort((poles.imag, -poles.real))]
        S = self._scale
        w_nl = S[2]
        return Linearization(
            num=np.array([gain * w_nl]), den=den_z, poles=poles,
            A=(S[:, None] * Az) / S[None, :],
            B=(S * np.array([b1, 0.0, 0.0]))[:, None],
            C=np.array([[0.0, 0.0, 1.0]]), D=np.zeros((1, 1)),
            u0=u0, x0=z0 * S, temperature=T,
        )

    # ---------------------------------------------------------------- simulation
    def simulate(
        self,
        t: ArrayLike,
        u: ArrayLike,
        temperature: Temperature = NOMINAL_TEMPERATURE,
        *,
        x0: ArrayLike | None = None,
        noise: float = 0.0,
        random_state: int | np.random.Generator | None = None,
    ) -> PlantResponse:
        """Response of the nonlinear drive to an arbitrary command and oil temperature.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Strictly increasing sample times, s.
        u : float or array-like of shape (n_samples,)
            Valve command at the samples, held constant until the next sample.
        temperature : float, array-like of shape (n_samples,) or callable, default=40.0
            Oil temperature in °C: a constant, samples on ``t`` (interpolated
            linearly), or a function ``T(t)`` of time in seconds.
        x0 : array-like of shape (3,), optional
            Initial state ``(x_v [m], p_L [Pa], omega [rad/s])``; rest when
            omitted.  Pass ``response.x[-1]`` to continue a simulation.
        noise : float, default=0.0
            Standard deviation of white Gaussian sensor noise, rad/s.
        random_state : int, numpy.random.Generator or None, default=None
            Seed of the noise.

        Returns
        -------
        PlantResponse

        Raises
        ------
        DimensionError
            If ``u``, ``x0`` or a temperature array has the wrong shape.
        DataError
            On NaN/inf, a temperature out of range, a spool position beyond
            the stroke, or a negative ``noise``.
        """
        t = check_time(t)
        u = _check_signal(u, t.size, "u")
        z0 = self._check_state(x0)
        noise = _check_noise(noise, "noise")
        temp_fn, temps = _temperature_profile(temperature, t)
        z = self._integrate(t, u, z0, temp_fn)
        x = z * self._scale
        y_true = x[:, 2].copy()
        y = self._measure(y_true, noise, np.random.default_rng(random_state))
        return PlantResponse(t=t, u=u, y=y, y_true=y_true, x=x, temperature=temps)

    def step_response(
        self,
        t: ArrayLike,
        amplitude: float = NOMINAL_COMMAND,
        temperature: Temperature = NOMINAL_TEMPERATURE,
        *,
        noise: float = 0.0,
        random_state: int | np.random.Generator | None = None,
    ) -> PlantResponse:
        """Response from rest to a valve-command step at ``t[0]`` (a step test).

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Strictly increasing sample times, s; the step is applied at ``t[0]``.
        amplitude : float, default=0.5
            Step size of the valve command (nonzero; ``|amplitude| > 1``
            saturates the spool).
        temperature : float, array-like or callable, default=40.0
            Oil temperature, °C, as in :meth:`simulate`.
        noise : float, default=0.0
            Standard deviation of white Gaussian sensor noise as a fraction of
            the noise-free response's peak (0.1 = 10 %, the paper's convention).
        random_state : int, numpy.random.Generator or None, default=None
            Seed of the noise.

        Returns
        -------
        PlantResponse

        Raises
        ------
        DataError
            If ``amplitude`` is zero or not finite, ``noise`` is negative, or a
            temperature is out of range.
        """
        t = check_time(t)
        amplitude = _check_number(amplitude, "amplitude")
        if amplitude == 0:
            raise DataError("amplitude must be nonzero; a zero step gives no response")
        noise = _check_noise(noise, "noise")
        clean = self.simulate(t, np.full(t.size, amplitude), temperature)
        sigma = noise * float(np.max(np.abs(clean.y_true)))
        y = self._measure(clean.y_true, sigma, np.random.default_rng(random_state))
        return PlantResponse(
            t=clean.t, u=clean.u, y=y, y_true=clean.y_true, x=clean.x,
            temperature=clean.temperature,
        )

    # ---------------------------------------------------------------- internals
    def _measure(self, y: NDArray, sigma: float, rng: np.random.Generator) -> NDArray:
        out = y + sigma * rng.standard_normal(y.size) if sigma > 0 else y.copy()
        q = self.sensor_resolution
        return q * np.round(out / q) if q > 0 else out

    def _check_state(self, x0: ArrayLike | None) -> NDArray[np.float64]:
        if x0 is None:
            return np.zeros(3)
        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (3,):
            raise DimensionError(
                f"x0 must have shape (3,) (spool [m], load pressure [Pa], speed [rad/s]), "
                f"got {x0.shape}"
            )
        check_finite(x0, "x0")
        stroke = self.parameters.spool_stroke
        if abs(x0[0]) > stroke * (1 + 1e-9):
            raise DataError(
                f"x0[0] = {x0[0]:g} m lies beyond the spool stroke +-{stroke:g} m"
            )
        return x0 / self._scale

    def _integrate(
        self,
        t: NDArray,
        u: NDArray,
        z0: NDArray,
        temp_fn: Callable[[float], float] | float,
    ) -> NDArray[np.float64]:
        if callable(temp_fn):
            params = self.parameters

            def coef(tt: float) -> _Coefficients:
                return _Coefficients(params, temp_fn(tt))
        else:
            fixed = self._coefficients(temp_fn)

            def coef(tt: float) -> _Coefficients:
                return fixed

        jac = {"jac": lambda tt, zz: _jac(zz, coef(tt))} if self.method in _IMPLICIT else {}
        n = t.size
        held = np.clip(u[:-1], -1.0, 1.0)  # u[k] acts on [t_k, t_k+1); the spool stroke limits it
        starts = np.concatenate([[0], np.flatnonzero(np.diff(held) != 0) + 1])
        ends = np.append(starts[1:], n - 1)
        Z = np.empty((n, 3))
        Z[0] = z0
        z = np.asarray(z0, dtype=float)
        for a, b in zip(starts, ends, strict=True):
            v = float(held[a])
            sol = scipy.integrate.solve_ivp(
                lambda tt, zz, v=v: _rhs(zz, v, coef(tt)),
                (float(t[a]), float(t[b])), z, method=self.method,
                t_eval=t[a:b + 1], rtol=self.rtol, atol=self.atol, **jac,
            )
            if not sol.success:  # pragma: no cover - the scaled model is well behaved
                raise RuntimeError(
                    f"the ODE solver failed on [{t[a]:g}, {t[b]:g}] s: {sol.message}"
                )
            Z[a:b + 1] = sol.y.T
            z = sol.y[:, -1]
        return Z


def _check_number(value: Any, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise DataError(f"{name} must be finite, got {out}")
    return out


def _check_noise(value: Any, name: str) -> float:
    out = _check_number(value, name)
    if out < 0:
        raise DataError(f"{name} must be >= 0, got {out:g}")
    return out


def _check_signal(u: ArrayLike, n: int, name: str) -> NDArray[np.float64]:
    u = np.asarray(u, dtype=float)
    if u.ndim == 0:
        u = np.full(n, float(u))
    if u.shape != (n,):
        raise DimensionError(f"{name} must have shape ({n},) like t, got {u.shape}")
    check_finite(u, name)
    return u


def _temperature_profile(
    temperature: Temperature, t: NDArray
) -> tuple[Callable[[float], float] | float, NDArray[np.float64]]:
    """The temperature as a constant or a function of time, and its values at ``t``."""
    if callable(temperature):
        fn = temperature
        samples = np.array([_check_number(fn(float(tt)), "temperature(t)") for tt in t])
        for k, T in enumerate(samples):
            _check_temperature(T, f"temperature(t[{k}])")
        return (lambda tt: float(fn(tt))), samples
    arr = np.asarray(temperature, dtype=float)
    if arr.ndim == 0:
        T = _check_temperature(float(arr), "temperature")
        return T, np.full(t.size, T)
    if arr.shape != t.shape:
        raise DimensionError(
            f"temperature must be a number, a function of time or an array of shape {t.shape} "
            f"like t, got shape {arr.shape}"
        )
    check_finite(arr, "temperature")
    for k, T in enumerate(arr):
        _check_temperature(T, f"temperature[{k}]")
    if np.all(arr == arr[0]):
        return float(arr[0]), arr.copy()
    return (lambda tt: float(np.interp(tt, t, arr))), arr.copy()


# --------------------------------------------------------------------------- step tests
def simulate_step_tests(
    n_records: int = 30,
    n_samples: int = 900,
    temperatures: tuple[float, float] = (20.0, 60.0),
    *,
    t_end: float = DEFAULT_T_END,
    amplitude: float = NOMINAL_COMMAND,
    noise: float = 0.01,
    random_state: int | np.random.Generator | None = None,
    parameters: HydraulicParameters | None = None,
) -> StepTestRecords:
    """Simulate a session of step tests while the oil warms up (the paper's 30 x 900 data).

    Record ``k`` is a step response from rest at an oil temperature rising
    linearly from ``temperatures[0]`` (first record) to ``temperatures[1]``
    (last record), sampled at ``n_samples`` points on ``[0, t_end]``.

    Parameters
    ----------
    n_records : int, default=30
        Number of step responses (>= 1).
    n_samples : int, default=900
        Samples per response (>= 2).
    temperatures : (float, float), default=(20.0, 60.0)
        Oil temperature of the first and the last record, °C (``lo <= hi``).
    t_end : float, default=3.0
        Record length, s.
    amplitude : float, default=0.5
        Step size of the valve command.
    noise : float, default=0.01
        Sensor-noise standard deviation as a fraction of each record's peak.
    random_state : int, numpy.random.Generator or None, default=None
        Seed of the noise.
    parameters : HydraulicParameters, optional
        Physical parameters; the nominal set when omitted.

    Returns
    -------
    StepTestRecords

    Raises
    ------
    DataError
        On a non-positive count or length, a decreasing or out-of-range
        temperature pair, a zero amplitude or a negative noise level.

    See Also
    --------
    HydraulicServoDrive.step_response : One step response.

    Examples
    --------
    >>> from kautztwin.plants import simulate_step_tests
    >>> rec = simulate_step_tests(3, 200, (20, 60), random_state=0)
    >>> rec.y.shape, rec.temperature.tolist()
    ((3, 200), [20.0, 40.0, 60.0])
    """
    n_records = _check_count(n_records, "n_records", 1)
    n_samples = _check_count(n_samples, "n_samples", 2)
    try:
        lo, hi = (float(v) for v in temperatures)
    except (TypeError, ValueError):
        raise DataError(
            f"temperatures must be a pair (lo, hi) of numbers in °C, got {temperatures!r}"
        ) from None
    lo = _check_temperature(lo, "temperatures[0]")
    hi = _check_temperature(hi, "temperatures[1]")
    if lo > hi:
        raise DataError(f"temperatures must satisfy lo <= hi, got ({lo:g}, {hi:g})")
    t_end = _check_number(t_end, "t_end")
    if t_end <= 0:
        raise DataError(f"t_end must be > 0 s, got {t_end:g}")
    drive = HydraulicServoDrive(parameters if parameters is not None else HydraulicParameters())
    t = np.linspace(0.0, t_end, n_samples)
    temps = np.linspace(lo, hi, n_records)
    rng = np.random.default_rng(random_state)
    u = np.empty((n_records, n_samples))
    y = np.empty_like(u)
    y_true = np.empty_like(u)
    for k, T in enumerate(temps):
        r = drive.step_response(t, amplitude, float(T), noise=noise, random_state=rng)
        u[k], y[k], y_true[k] = r.u, r.y, r.y_true
    return StepTestRecords(
        t=t, u=u, y=y, y_true=y_true, temperature=temps, amplitude=float(amplitude),
        noise=float(noise), parameters=drive.parameters,
    )


def _check_count(value: Any, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise DataError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise DataError(f"{name} must be >= {minimum}, got {value}")
    return int(value)
