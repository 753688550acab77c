"""The hydraulic servo-drive simulator as a twin plant, with an oil-temperature schedule.

:class:`HydraulicPlant` wraps :class:`kautztwin.simulators.HydraulicServoDrive`
behind the :class:`~kautztwin.twin.physical.Plant` protocol; a
:class:`TemperatureSchedule` warms the oil during the run, which moves the
poles (:func:`temperature_for_pole_ratio`, :meth:`HydraulicPlant.with_pole_drift`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_nonnegative, check_positive
from ...exceptions import DataError, DimensionError
from ...simulators.hydraulic import (
    NOMINAL_COMMAND,
    TEMPERATURE_RANGE,
    HydraulicServoDrive,
)
from .base import Reading, clip_input
from .clock import Clock

__all__ = ["HydraulicPlant", "TemperatureSchedule", "temperature_for_pole_ratio"]


# --------------------------------------------------------------------------- temperature
@dataclass(frozen=True, eq=False)
class TemperatureSchedule:
    """Oil temperature as a piecewise-linear function of time.

    Between breakpoints the temperature is interpolated linearly; before the
    first and after the last it stays constant.  Instances are callables
    ``T(t)`` accepted by :meth:`HydraulicServoDrive.simulate`.

    Parameters
    ----------
    times : array-like of shape (n_points,)
        Non-decreasing breakpoint times, s (a repeated time gives a jump).
    temperatures : array-like of shape (n_points,)
        Temperatures at the breakpoints, °C, inside the model's range
        (-20 to 120 °C).

    Raises
    ------
    DimensionError
        If the arrays are not 1-D of one length ``>= 1``.
    DataError
        If a value is not finite, the times decrease, or a temperature is out of range.

    See Also
    --------
    HydraulicPlant.with_pole_drift : A schedule that moves the dominant pole.

    Examples
    --------
    >>> from kautztwin.twin.physical import TemperatureSchedule
    >>> s = TemperatureSchedule.steps([10.0, 20.0], [20.0, 30.0, 40.0], ramp_time=2.0)
    >>> [s(t) for t in (0.0, 11.0, 12.0, 25.0)]
    [20.0, 25.0, 30.0, 40.0]
    """

    times: NDArray[np.float64]
    temperatures: NDArray[np.float64]

    def __post_init__(self) -> None:
        t = np.array(self.times, dtype=float, copy=True).reshape(-1)
        T = np.array(self.temperatures, dtype=float, copy=True).reshape(-1)
        if t.size < 1 or t.shape != T.shape:
            raise DimensionError(
                f"times and temperatures must be 1-D of one length >= 1, got {t.size} and {T.size}"
            )
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(T))):
            raise DataError("times and temperatures must be finite")
        if np.any(np.diff(t) < 0):
            raise DataError("times must be non-decreasing")
        lo, hi = TEMPERATURE_RANGE
        if np.any((T < lo) | (T > hi)):
            raise DataError(f"temperatures must lie in [{lo:g}, {hi:g}] °C, got {T.tolist()}")
        t.setflags(write=False)
        T.setflags(write=False)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "temperatures", T)

    @classmethod
    def constant(cls, temperature: float) -> TemperatureSchedule:
        """A constant temperature.

        Parameters
        ----------
        temperature : float
            °C.

        Returns
        -------
        TemperatureSchedule
        """
        return cls([0.0], [temperature])

    @classmethod
    def ramp(
        cls, start: float, end: float, temperature_start: float, temperature_end: float
    ) -> TemperatureSchedule:
        """A linear ramp from ``temperature_start`` at ``start`` to ``temperature_end`` at ``end``.

        Parameters
        ----------
        start, end : float
            Ramp start and end times, s (``start <= end``).
        temperature_start, temperature_end : float
            °C.

        Returns
        -------
        TemperatureSchedule
        """
        return cls([start, end], [temperature_start, temperature_end])

    @classmethod
    def steps(
        cls, times: ArrayLike, temperatures: ArrayLike, *, ramp_time: float = 0.0
    ) -> TemperatureSchedule:
        """Temperature steps: ``temperatures[i + 1]`` from ``times[i]`` on.

        Parameters
        ----------
        times : array-like of shape (n_steps,)
            Increasing step times, s.
        temperatures : array-like of shape (n_steps + 1,)
            The initial temperature and the level after each step, °C.
        ramp_time : float, default=0.0
            Each step is a linear ramp of this duration, s (0: a jump).

        Returns
        -------
        TemperatureSchedule

        Raises
        ------
        DimensionError
            If ``len(temperatures) != len(times) + 1``.
        DataError
            If ``ramp_time`` is negative or ramps overlap.
        """
        ts = np.atleast_1d(np.asarray(times, dtype=float))
        Ts = np.atleast_1d(np.asarray(temperatures, dtype=float))
        if Ts.size != ts.size + 1:
            raise DimensionError(
                f"temperatures needs len(times) + 1 = {ts.size + 1} values, got {Ts.size}"
            )
        ramp_time = check_nonnegative(ramp_time, "ramp_time")
        if np.any(np.diff(ts) < ramp_time):
            raise DataError("steps must be at least ramp_time apart")
        bt, bT = [0.0 if ts.size == 0 else min(0.0, float(ts[0]))], [float(Ts[0])]
        for i, ti in enumerate(ts):
            bt += [float(ti), float(ti) + ramp_time]
            bT += [float(Ts[i]), float(Ts[i + 1])]
        return cls(bt, bT)

    def __call__(self, t: float) -> float:
        """Temperature at time ``t``, °C."""
        return float(np.interp(t, self.times, self.temperatures))

    def constant_between(self, t0: float, t1: float) -> bool:
        """Whether the temperature is constant on ``[t0, t1]``.

        Parameters
        ----------
        t0, t1 : float
            Interval ends, s.

        Returns
        -------
        bool
        """
        inner = self.temperatures[(self.times > t0) & (self.times < t1)]
        T0 = self(t0)
        return bool(self(t1) == T0 and np.all(inner == T0))


def _dominant_pole(drive: HydraulicServoDrive, temperature: float, u0: float) -> float:
    """Real part of the slowest pole of the linearised drive, rad/s (negative)."""
    return float(drive.linearize(u0, temperature).poles[0].real)


def temperature_for_pole_ratio(
    ratio: float,
    *,
    base_temperature: float = 20.0,
    operating_point: float = NOMINAL_COMMAND,
    drive: HydraulicServoDrive | None = None,
) -> float:
    """Oil temperature at which the dominant pole has ``ratio`` times its base magnitude.

    The slowest pole of the linearised drive slows down as the oil warms
    (``ratio < 1``: warmer) and speeds up as it cools (``ratio > 1``).

    Parameters
    ----------
    ratio : float
        Target ``|p(T)| / |p(base_temperature)|`` of the dominant pole, ``> 0``;
        0.6 means the pole moves 40 % towards the imaginary axis.
    base_temperature : float, default=20.0
        Reference oil temperature, °C.
    operating_point : float, default=0.5
        Valve command of the linearisation.
    drive : HydraulicServoDrive, optional
        The drive; the nominal one when omitted.

    Returns
    -------
    float
        Temperature, °C.

    Raises
    ------
    DataError
        If ``ratio`` is not positive or is not reachable inside the model's
        temperature range.

    Examples
    --------
    >>> from kautztwin.twin.physical import temperature_for_pole_ratio
    >>> round(temperature_for_pole_ratio(0.6, base_temperature=20.0), 1)
    54.5
    """
    ratio = check_positive(ratio, "ratio")
    drive = drive if drive is not None else HydraulicServoDrive()
    p0 = _dominant_pole(drive, base_temperature, operating_point)
    if ratio == 1.0:
        return float(base_temperature)
    lo, hi = TEMPERATURE_RANGE
    a, b = (base_temperature, hi) if ratio < 1 else (lo, base_temperature)

    def f(T: float) -> float:
        return _dominant_pole(drive, T, operating_point) / p0 - ratio

    if f(a) * f(b) > 0:
        raise DataError(
            f"a dominant-pole ratio of {ratio:g} is not reachable between {a:g} and {b:g} °C "
            f"(base {base_temperature:g} °C)"
        )
    return float(scipy.optimize.brentq(f, a, b, xtol=1e-6))


# --------------------------------------------------------------------------- hydraulic
class HydraulicPlant:
    """The electro-hydraulic servo drive as a twin plant, with oil-temperature drift.

    Wraps :class:`kautztwin.simulators.HydraulicServoDrive`: input the valve command
    (``-1 .. 1``), output the shaft speed in rad/s.  Each :meth:`step`
    integrates the nonlinear ODE over one sampling period with the command
    held, starting from the state the previous step ended in, so a run of
    steps continues exactly like one long simulation.  The oil temperature
    follows ``temperature(t)`` over the run, which moves the poles (warming
    slows the dominant pole, see :meth:`with_pole_drift`).

    Parameters
    ----------
    drive : HydraulicServoDrive, optional
        The simulator; the nominal drive when omitted.
    dt : float, default=0.02
        Sampling period, s.
    temperature : float, callable or TemperatureSchedule, default=40.0
        Oil temperature in °C, constant or a function of the plant time.
    noise : float, default=0.0
        Standard deviation of white Gaussian sensor noise, rad/s.
    initial_command : float, default=0.5
        The run starts at the equilibrium of this valve command at the
        initial temperature (ignored when ``x0`` is given).
    x0 : array-like of shape (3,), optional
        Initial state ``(x_v [m], p_L [Pa], omega [rad/s])``.
    clock : Clock, optional
        Pacing; as fast as possible when omitted.
    random_state : int, numpy.random.Generator or None, default=None
        Seed of the sensor noise; an integer repeats the noise after every
        :meth:`reset`.
    name : str, default='hydraulic'
        Name of the plant.

    Raises
    ------
    DataError
        If ``dt`` or ``noise`` is invalid.

    Attributes
    ----------
    input_limits : tuple of float
        ``(-1.0, 1.0)``: full spool stroke in both directions.
    drift_events : tuple of float
        Start times of the temperature changes (set by :meth:`with_pole_drift`).

    See Also
    --------
    kautztwin.simulators.HydraulicServoDrive : The simulator.
    TemperatureSchedule : Piecewise-linear temperature profiles.

    Notes
    -----
    ``meta`` of each reading holds ``u`` (applied, clipped), ``k``,
    ``y_true`` (noise-free speed), ``temperature`` (°C at ``t``) and ``x``
    (the state after the step).

    Examples
    --------
    >>> from kautztwin.twin.physical import HydraulicPlant
    >>> plant = HydraulicPlant(dt=0.02, temperature=40.0)
    >>> r0 = plant.reset()
    >>> r1 = plant.step(0.6)
    >>> r1.t, bool(r1.y > r0.y)
    (0.02, True)
    """

    input_limits: tuple[float, float] = (-1.0, 1.0)

    def __init__(
        self,
        drive: HydraulicServoDrive | None = None,
        *,
        dt: float = 0.02,
        temperature: float | Callable[[float], float] = 40.0,
        noise: float = 0.0,
        initial_command: float = NOMINAL_COMMAND,
        x0: ArrayLike | None = None,
        clock: Clock | None = None,
        random_state: int | np.random.Generator | None = None,
        name: str = "hydraulic",
    ) -> None:
        self.drive = drive if drive is not None else HydraulicServoDrive()
        if not isinstance(self.drive, HydraulicServoDrive):
            raise DataError(f"drive must be a HydraulicServoDrive, got {type(drive).__name__}")
        self.dt = check_positive(dt, "dt")
        if isinstance(temperature, TemperatureSchedule) or callable(temperature):
            self.temperature = temperature
        else:
            self.temperature = TemperatureSchedule.constant(float(temperature))
        self.noise = check_nonnegative(noise, "noise")
        self.initial_command = float(initial_command)
        if x0 is not None:
            x0 = np.array(x0, dtype=float, copy=True)
            if x0.shape != (3,) or not np.all(np.isfinite(x0)):
                raise DataError(
                    f"x0 must be 3 finite numbers (spool [m], load pressure [Pa], speed [rad/s]), "
                    f"got {x0.tolist()}"
                )
        self.x0 = x0
        self.clock = clock if clock is not None else Clock()
        self.random_state = random_state
        self.name = str(name)
        self.drift_events: tuple[float, ...] = ()
        self.reset()

    @classmethod
    def with_pole_drift(
        cls,
        drift: float = 0.4,
        *,
        events: Sequence[float] = (20.0, 40.0),
        ramp_time: float = 2.0,
        base_temperature: float = 20.0,
        operating_point: float = NOMINAL_COMMAND,
        drive: HydraulicServoDrive | None = None,
        **kwargs: Any,
    ) -> HydraulicPlant:
        """A plant whose dominant pole drifts by ``drift`` (a fraction) during the run.

        The oil starts at ``base_temperature`` and warms in ``len(events)``
        equal steps of dominant-pole magnitude; step ``i`` starts at
        ``events[i]`` and ramps over ``ramp_time`` seconds.  After the last
        step the dominant pole of the linearisation at ``operating_point`` has
        moved by ``drift`` times its initial magnitude (towards the imaginary
        axis for ``drift > 0``, away from it for ``drift < 0``).

        Parameters
        ----------
        drift : float, default=0.4
            Total relative change of the dominant pole, ``|p_end| = (1 - drift) |p_0|``.
        events : sequence of float, default=(20.0, 40.0)
            Start times of the temperature steps, s.
        ramp_time : float, default=2.0
            Duration of each temperature ramp, s.
        base_temperature : float, default=20.0
            Initial oil temperature, °C.
        operating_point : float, default=0.5
            Valve command of the linearisation that defines the pole.
        drive : HydraulicServoDrive, optional
            The simulator; the nominal drive when omitted.
        **kwargs
            Further arguments of :class:`HydraulicPlant` (``dt``, ``noise``, ...).

        Returns
        -------
        HydraulicPlant
            With ``drift_events`` set and a :class:`TemperatureSchedule`.

        Raises
        ------
        DataError
            If the drift is not reachable inside the model's temperature range.
        """
        drive = drive if drive is not None else HydraulicServoDrive()
        events = [float(e) for e in events]
        n = len(events)
        temps = [float(base_temperature)]
        for i in range(1, n + 1):
            temps.append(
                temperature_for_pole_ratio(
                    1.0 - drift * i / n, base_temperature=base_temperature,
                    operating_point=operating_point, drive=drive,
                )
            )
        schedule = TemperatureSchedule.steps(events, temps, ramp_time=ramp_time)
        plant = cls(drive, temperature=schedule, initial_command=operating_point, **kwargs)
        plant.drift_events = tuple(events)
        return plant

    def dominant_pole(self, t: float, operating_point: float | None = None) -> float:
        """Real part of the dominant (slowest) pole of the linearisation at time ``t``, rad/s.

        Parameters
        ----------
        t : float
            Plant time, s (selects the oil temperature).
        operating_point : float, optional
            Valve command of the linearisation; ``initial_command`` when omitted.

        Returns
        -------
        float
        """
        u0 = self.initial_command if operating_point is None else float(operating_point)
        return _dominant_pole(self.drive, self.temperature(t), u0)

    def reset(self) -> Reading:
        """Start a new run at ``t = 0`` and return the first reading.

        Returns
        -------
        Reading
        """
        T0 = float(self.temperature(0.0))
        if self.x0 is not None:
            self._x = self.x0.copy()
        else:
            self._x = self.drive.equilibrium(self.initial_command, T0)
        self._k = 0
        self._rng = np.random.default_rng(self.random_state)
        self.clock.start()
        return self._reading(math.nan, T0)

    def step(self, u: float | None) -> Reading:
        """Hold the valve command ``u`` for one period and return the next reading.

        Parameters
        ----------
        u : float
            Valve command, clipped to :attr:`input_limits`.

        Returns
        -------
        Reading

        Raises
        ------
        DataError
            If ``u`` is not a finite number.
        """
        v = clip_input(u, self.input_limits, self.name)
        t0, t1 = self._k * self.dt, (self._k + 1) * self.dt
        temp = self.temperature
        if isinstance(temp, TemperatureSchedule) and temp.constant_between(t0, t1):
            temp = temp(t0)
        r = self.drive.simulate([t0, t1], [v, v], temp, x0=self._x)
        self._x = np.array(r.x[-1])
        self._k += 1
        self.clock.wait_until(t1)
        return self._reading(v, float(r.temperature[-1]))

    def _reading(self, u: float, temperature: float) -> Reading:
        y_true = float(self._x[2])
        y = y_true + self.noise * float(self._rng.standard_normal()) if self.noise else y_true
        q = self.drive.sensor_resolution
        if q > 0:
            y = q * round(y / q)
        meta = {"u": u, "k": self._k, "y_true": y_true, "temperature": temperature,
                "x": tuple(float(v) for v in self._x)}
        return Reading(self._k * self.dt, y, meta)

    def close(self) -> None:
        """Nothing to release for a simulator."""

    def __repr__(self) -> str:
        return f"HydraulicPlant(dt={self.dt:g}, noise={self.noise:g}, clock={self.clock!r})"
