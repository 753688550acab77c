"""The ODE model of the hydraulic drive: :class:`HydraulicServoDrive` and its scaled equations."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.integrate
import scipy.optimize
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..._validation import (
    check_choice,
    check_finite,
    check_nonnegative,
    check_number,
    check_positive,
    check_time,
)
from ...exceptions import DataError, DimensionError
from .parameters import (
    NOMINAL_COMMAND,
    NOMINAL_TEMPERATURE,
    HydraulicParameters,
    _check_temperature,
)
from .results import Linearization, PlantResponse

__all__ = ["HydraulicServoDrive"]

_METHODS = ("LSODA", "Radau", "BDF", "RK45", "DOP853", "RK23")
_IMPLICIT = ("LSODA", "Radau", "BDF")

Temperature = float | ArrayLike | Callable[[float], float]

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
    >>> from kautztwin.simulators import HydraulicServoDrive
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
        res = check_nonnegative(self.sensor_resolution, "sensor_resolution")
        object.__setattr__(self, "sensor_resolution", res)
        check_choice(self.method, "method", _METHODS)
        for name in ("rtol", "atol"):
            object.__setattr__(self, name, check_positive(getattr(self, name), name))

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
        u0 = check_number(u0, "u0")
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
        u0 = check_number(operating_point, "operating_point")
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
        amplitude = check_number(amplitude, "amplitude")
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


def _check_noise(value: Any, name: str) -> float:
    """:func:`~kautztwin._validation.check_number`, then ``>= 0`` (worded ``"x must be >= 0"``)."""
    out = check_number(value, name)
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
        samples = np.array([check_number(fn(float(tt)), "temperature(t)") for tt in t])
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
