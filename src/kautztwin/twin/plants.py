"""Physical-system module of the digital twin: one plant interface, three implementations.

The twin talks to the physical system through the small :class:`Plant`
protocol: it reads the output, applies an input for one sampling period and
reads again.  Three plants implement it:

* :class:`HydraulicPlant`: the electro-hydraulic servo-drive simulator of
  :mod:`kautztwin.plants.hydraulic`, with an oil-temperature schedule that
  moves its poles during the run (:class:`TemperatureSchedule`,
  :meth:`HydraulicPlant.with_pole_drift`), sensor noise, and the ODE state
  carried from one sample (chunk) to the next;
* :class:`TCLabPlant`: the Temperature Control Lab through the third-party
  ``tclab`` package, its emulator ``tclab.TCLabModel`` on a simulated clock, or
  a real board (``connected=True``) on the same code path;
* :class:`ReplayPlant`: a recorded CSV file of ``t, u, y`` played back.

A :class:`Clock` paces the plants: in real time (optionally sped up) with
``time.monotonic``/``time.sleep``, or as fast as possible (simulated time).

Timing convention
-----------------
:meth:`Plant.reset` returns the reading at ``t = 0`` (the first sample).
:meth:`Plant.step` holds ``u`` constant over one sampling period
``[t_k, t_k + dt)`` (zero-order hold, as a D/A converter does) and returns the
reading at ``t_{k+1}``.  The plants are strictly proper: ``y(t_{k+1})`` depends
on ``u`` up to ``u_k``.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError, DimensionError, KautzTwinError
from ..plants.hydraulic import (
    NOMINAL_COMMAND,
    TEMPERATURE_RANGE,
    HydraulicServoDrive,
)

__all__ = [
    "Clock",
    "HydraulicPlant",
    "Plant",
    "PlantRun",
    "Reading",
    "ReplayExhaustedError",
    "ReplayInputWarning",
    "ReplayPlant",
    "TCLabPlant",
    "TemperatureSchedule",
    "run_open_loop",
    "temperature_for_pole_ratio",
]


class ReplayInputWarning(UserWarning):
    """A replayed record was asked to follow an input other than the recorded one."""


class ReplayExhaustedError(KautzTwinError, EOFError):
    """:meth:`ReplayPlant.step` was called after the last recorded sample."""


# --------------------------------------------------------------------------- readings
@dataclass(frozen=True, eq=False)
class Reading:
    """One measurement of a plant.

    Parameters
    ----------
    t : float
        Sample time in seconds since :meth:`Plant.reset` (a replay keeps the
        recorded times).
    y : float
        Measured output (NaN when a replayed record holds a dropout).
    meta : mapping, optional
        Plant-specific extras, read-only; every plant stores ``'u'``, the
        input applied over the period that ended at ``t`` (NaN for the
        reading of :meth:`Plant.reset`), and ``'k'``, the sample index.

    See Also
    --------
    Plant : The interface that produces readings.

    Examples
    --------
    >>> from kautztwin.twin.plants import Reading
    >>> r = Reading(0.5, 21.3, {"u": 40.0, "k": 1})
    >>> r.t, r.y, r.meta["u"]
    (0.5, 21.3, 40.0)
    """

    t: float
    y: float
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", float(self.t))
        object.__setattr__(self, "y", float(self.y))
        object.__setattr__(self, "meta", MappingProxyType(dict(self.meta)))


@runtime_checkable
class Plant(Protocol):
    """Interface of a physical system (simulated, emulated, real or replayed).

    Attributes
    ----------
    dt : float
        Sampling period, s.
    name : str
        Short human-readable name (for logs and reports).
    input_limits : tuple of float
        ``(low, high)`` bounds of the input; plants clip to them.

    See Also
    --------
    HydraulicPlant, TCLabPlant, ReplayPlant : The implementations.
    run_open_loop : Drive any plant with a known input sequence.
    """

    dt: float
    name: str
    input_limits: tuple[float, float]

    def reset(self) -> Reading:
        """Restart the run and return the reading at ``t = 0``.

        Returns
        -------
        Reading
        """
        ...

    def step(self, u: float | None) -> Reading:
        """Hold ``u`` for one sampling period and return the next reading.

        Parameters
        ----------
        u : float or None
            Input, clipped to :attr:`input_limits`; ``None`` is allowed only
            where a plant defines it (a replay follows its record).

        Returns
        -------
        Reading
        """
        ...

    def close(self) -> None:
        """Release the plant (a real device: heaters off, port closed)."""
        ...


# --------------------------------------------------------------------------- clock
class Clock:
    """Paces a plant in real time, or lets it run as fast as possible.

    With ``realtime=True`` :meth:`wait_until` sleeps until the wall-clock time
    (``time.monotonic``) of a plant time has come, ``speedup`` plant seconds per
    wall-clock second; with ``realtime=False`` the time is simulated and
    nothing waits.

    Parameters
    ----------
    realtime : bool, default=False
        Pace in real time (``True``) or run as fast as possible.
    speedup : float, default=1.0
        Plant seconds per wall-clock second in real-time mode (``> 0``).
    tolerance : float, default=inf
        A target reached more than this many plant seconds late counts as a
        late tick (:attr:`n_late`).

    Raises
    ------
    DataError
        If ``speedup`` is not positive or ``tolerance`` is negative.

    Attributes
    ----------
    n_late : int
        Targets that were already more than ``tolerance`` in the past.
    max_lateness : float
        Largest lateness seen, plant seconds.

    Examples
    --------
    >>> from kautztwin.twin.plants import Clock
    >>> clock = Clock()          # simulated time: never sleeps
    >>> clock.start()
    >>> clock.wait_until(10.0), clock.now()
    (0.0, 10.0)
    """

    def __init__(
        self, realtime: bool = False, *, speedup: float = 1.0, tolerance: float = math.inf
    ) -> None:
        speedup = float(speedup)
        if not (math.isfinite(speedup) and speedup > 0):
            raise DataError(f"speedup must be a positive number, got {speedup}")
        tolerance = float(tolerance)
        if math.isnan(tolerance) or tolerance < 0:
            raise DataError(f"tolerance must be >= 0 s, got {tolerance}")
        self.realtime = bool(realtime)
        self.speedup = speedup
        self.tolerance = tolerance
        self.start()

    @classmethod
    def real_time(cls, speedup: float = 1.0, *, tolerance: float = math.inf) -> Clock:
        """A real-time clock (``speedup`` plant seconds per wall-clock second).

        Parameters
        ----------
        speedup : float, default=1.0
            Plant seconds per wall-clock second.
        tolerance : float, default=inf
            Lateness that counts as a late tick, plant seconds.

        Returns
        -------
        Clock
        """
        return cls(True, speedup=speedup, tolerance=tolerance)

    def start(self) -> None:
        """Set plant time 0 to now and clear the lateness counters."""
        self._origin = time.monotonic()
        self._t = 0.0
        self.n_late = 0
        self.max_lateness = 0.0

    def now(self) -> float:
        """Plant time since :meth:`start`, s (simulated: the last target)."""
        if self.realtime:
            return (time.monotonic() - self._origin) * self.speedup
        return self._t

    def wait_until(self, t: float) -> float:
        """Wait until plant time ``t`` (real time) or jump to it (simulated).

        Parameters
        ----------
        t : float
            Target plant time, s since :meth:`start`.

        Returns
        -------
        float
            How late the target was reached, plant seconds (0 when on time or simulated).
        """
        self._t = float(t)
        if not self.realtime:
            return 0.0
        delay = self._origin + self._t / self.speedup - time.monotonic()
        if delay > 0:
            time.sleep(delay)
            return 0.0
        late = -delay * self.speedup
        self.max_lateness = max(self.max_lateness, late)
        if late > self.tolerance:
            self.n_late += 1
        return late

    def __repr__(self) -> str:
        mode = f"real time x{self.speedup:g}" if self.realtime else "as fast as possible"
        return f"Clock({mode})"


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
    >>> from kautztwin.twin.plants import TemperatureSchedule
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
        ramp_time = float(ramp_time)
        if not (math.isfinite(ramp_time) and ramp_time >= 0):
            raise DataError(f"ramp_time must be >= 0 s, got {ramp_time}")
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
    >>> from kautztwin.twin.plants import temperature_for_pole_ratio
    >>> round(temperature_for_pole_ratio(0.6, base_temperature=20.0), 1)
    54.5
    """
    ratio = float(ratio)
    if not (math.isfinite(ratio) and ratio > 0):
        raise DataError(f"ratio must be a positive number, got {ratio}")
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


# --------------------------------------------------------------------------- helpers
def _check_dt(dt: Any) -> float:
    try:
        out = float(dt)
    except (TypeError, ValueError):
        raise DataError(f"dt must be a positive number of seconds, got {dt!r}") from None
    if not (math.isfinite(out) and out > 0):
        raise DataError(f"dt must be a positive number of seconds, got {out}")
    return out


def _check_input(u: Any, limits: tuple[float, float], name: str) -> float:
    try:
        value = float(u)
    except (TypeError, ValueError):
        raise DataError(f"u must be a number for {name}, got {u!r}") from None
    if not math.isfinite(value):
        raise DataError(f"u must be finite for {name}, got {value}")
    return min(limits[1], max(limits[0], value))


def _rng(random_state: int | np.random.Generator | None) -> np.random.Generator:
    return np.random.default_rng(random_state)


# --------------------------------------------------------------------------- hydraulic
class HydraulicPlant:
    """The electro-hydraulic servo drive as a twin plant, with oil-temperature drift.

    Wraps :class:`kautztwin.plants.HydraulicServoDrive`: input the valve command
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
    kautztwin.plants.HydraulicServoDrive : The simulator.
    TemperatureSchedule : Piecewise-linear temperature profiles.

    Notes
    -----
    ``meta`` of each reading holds ``u`` (applied, clipped), ``k``,
    ``y_true`` (noise-free speed), ``temperature`` (°C at ``t``) and ``x``
    (the state after the step).

    Examples
    --------
    >>> from kautztwin.twin.plants import HydraulicPlant
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
        self.dt = _check_dt(dt)
        if isinstance(temperature, TemperatureSchedule) or callable(temperature):
            self.temperature = temperature
        else:
            self.temperature = TemperatureSchedule.constant(float(temperature))
        noise = float(noise)
        if not (math.isfinite(noise) and noise >= 0):
            raise DataError(f"noise must be >= 0 rad/s, got {noise}")
        self.noise = noise
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
        self._rng = _rng(self.random_state)
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
        v = _check_input(u, self.input_limits, self.name)
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


# --------------------------------------------------------------------------- TCLab
_TCLAB_NOISE = 0.043  # standard deviation of tclab's emulated thermistor noise, °C


class TCLabPlant:
    """The Temperature Control Lab (heater -> temperature) through the ``tclab`` package.

    With ``connected=False`` (default) the plant is ``tclab.TCLabModel``, the
    package's emulator of the board (two heaters, two thermistors, a
    fourth-order heat-transfer model), driven on a simulated clock: its
    ``update(t)`` integrates to the plant time of each sample, so a run goes as
    fast as the CPU allows (or paced by a real-time ``clock``).  With
    ``connected=True`` the same code path drives a real board through
    ``tclab.TCLab`` (serial port) in real time.

    Parameters
    ----------
    dt : float, default=1.0
        Sampling period, s.
    connected : bool, default=False
        Use a real board (``tclab.TCLab``) instead of the emulator.
    heater : {1, 2}, default=1
        Which heater/thermistor pair is the input/output (``Q1``/``T1`` or ``Q2``/``T2``).
    clock : Clock, optional
        Pacing.  Emulator: as fast as possible when omitted.  Real board: a
        real-time clock (the default); a faster clock is an error.
    noise : float, default=0.043
        Emulator only: standard deviation of the thermistor noise, °C (tclab's
        own value).  It is drawn from ``random_state`` (tclab draws from the
        global ``random`` module, which would make runs irreproducible); the
        reading is then quantised as tclab does.
    port : str, default=''
        Real board only: serial port ('' searches for the board).
    random_state : int, numpy.random.Generator or None, default=None
        Seed of the emulator's noise.
    name : str, default='tclab'
        Name of the plant.

    Raises
    ------
    ImportError
        If the ``tclab`` package is missing (``pip install 'kautztwin[tclab]'``).
    DataError
        If ``heater`` or ``dt`` is invalid, or a real board is asked to run
        faster than real time.

    Attributes
    ----------
    input_limits : tuple of float
        ``(0.0, 100.0)``: heater power in percent.

    See Also
    --------
    HydraulicPlant, ReplayPlant : The other plants.

    Notes
    -----
    The emulator is driven through its documented attributes of tclab 1.0:
    ``TCLabModel(synced=False)``, ``Q1``/``Q2``, ``update(t)``, ``quantize``
    and the noise-free thermistor temperatures ``_T1``/``_T2``.  tclab prints
    a banner on connection; it is suppressed.  ``meta`` holds ``u``, ``k``,
    ``y_true`` (emulator only) and ``lateness`` (s behind the real-time clock).

    Examples
    --------
    >>> from kautztwin.twin.plants import TCLabPlant
    >>> lab = TCLabPlant(dt=1.0, random_state=0)
    >>> r0 = lab.reset()
    >>> readings = [lab.step(100.0) for _ in range(120)]
    >>> readings[-1].t, bool(readings[-1].y > r0.y + 2.0)
    (120.0, True)
    >>> lab.close()
    """

    input_limits: tuple[float, float] = (0.0, 100.0)

    def __init__(
        self,
        *,
        dt: float = 1.0,
        connected: bool = False,
        heater: int = 1,
        clock: Clock | None = None,
        noise: float = _TCLAB_NOISE,
        port: str = "",
        random_state: int | np.random.Generator | None = None,
        name: str = "tclab",
    ) -> None:
        try:
            import tclab
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "TCLabPlant needs the tclab package: pip install 'kautztwin[tclab]'"
            ) from exc
        self._tclab = tclab
        self.dt = _check_dt(dt)
        if heater not in (1, 2):
            raise DataError(f"heater must be 1 or 2, got {heater!r}")
        self.heater = int(heater)
        self.connected = bool(connected)
        if clock is None:
            clock = Clock.real_time() if self.connected else Clock()
        if self.connected and not (clock.realtime and clock.speedup == 1.0):
            raise DataError(
                "a real TCLab board runs in real time: pass clock=Clock.real_time() (speedup 1)"
            )
        self.clock = clock
        noise = float(noise)
        if not (math.isfinite(noise) and noise >= 0):
            raise DataError(f"noise must be >= 0 °C, got {noise}")
        self.noise = noise
        self.port = str(port)
        self.random_state = random_state
        self.name = str(name)
        self._lab: Any = None
        self.reset()

    def _quiet(self) -> contextlib.AbstractContextManager[Any]:
        return contextlib.redirect_stdout(io.StringIO())

    def _set_heater(self, value: float) -> None:
        (self._lab.Q1 if self.heater == 1 else self._lab.Q2)(value)

    def reset(self) -> Reading:
        """Start a new run and return the reading at ``t = 0``.

        The emulator restarts from ambient temperature (a fresh
        ``TCLabModel``).  A real board cannot be reset: its heaters are
        switched off and the clock restarts; wait for it to cool first when a
        run needs to start from ambient.

        Returns
        -------
        Reading
        """
        self._k = 0
        self._rng = _rng(self.random_state)
        with self._quiet():
            if self.connected:
                if self._lab is None:
                    self._lab = self._tclab.TCLab(port=self.port)
                self._set_heater(0.0)
            else:
                if self._lab is not None:
                    self._lab.close()
                self._lab = self._tclab.TCLabModel(synced=False)
                self._origin = float(self._lab.tlast)  # the emulator's own time origin
        self.clock.start()
        return self._read(math.nan, 0.0)

    def step(self, u: float | None) -> Reading:
        """Set the heater to ``u`` percent for one period and return the next reading.

        Parameters
        ----------
        u : float
            Heater power, %, clipped to ``[0, 100]``.

        Returns
        -------
        Reading

        Raises
        ------
        DataError
            If ``u`` is not a finite number.
        """
        v = _check_input(u, self.input_limits, self.name)
        self._set_heater(v)
        self._k += 1
        t1 = self._k * self.dt
        late = self.clock.wait_until(t1)
        if not self.connected:
            self._lab.update(self._origin + t1)
        return self._read(v, late)

    def _read(self, u: float, late: float) -> Reading:
        meta: dict[str, Any] = {"u": u, "k": self._k, "lateness": late}
        if self.connected:
            y = float(self._lab.T1 if self.heater == 1 else self._lab.T2)
        else:
            y_true = float(self._lab._T1 if self.heater == 1 else self._lab._T2)
            y = float(self._lab.quantize(y_true + self.noise * self._rng.standard_normal()))
            meta["y_true"] = y_true
        return Reading(self._k * self.dt, y, meta)

    def close(self) -> None:
        """Switch the heaters off and release the board (or the emulator)."""
        if self._lab is not None:
            with self._quiet():
                self._lab.close()
            self._lab = None

    def __repr__(self) -> str:
        kind = "board" if self.connected else "emulator"
        return f"TCLabPlant({kind}, dt={self.dt:g}, heater={self.heater}, clock={self.clock!r})"


# --------------------------------------------------------------------------- replay
def _read_replay_csv(path: Path, columns: tuple[str, str, str]) -> dict[str, NDArray]:
    """Read three named columns; empty cells and ``nan`` in u and y become NaN."""
    name = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"cannot read {name}: {exc.strerror or exc}") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip()]
    if not lines:
        raise DataError(f"{name} is empty")
    header_line = lines[0][1].lstrip("#").strip()
    delimiter = next((d for d in (",", ";", "\t") if d in header_line), None)

    def split(line: str) -> list[str]:
        if delimiter is None:
            return line.split()
        return [c.strip() for c in next(csv.reader([line], delimiter=delimiter))]

    header = split(header_line)
    index = {}
    for col in columns:
        if col not in header:
            raise DataError(f"{name} has no column {col!r}; columns are {', '.join(header)}")
        index[col] = header.index(col)
    out: dict[str, list[float]] = {c: [] for c in columns}
    for lineno, line in lines[1:]:
        if line.lstrip().startswith("#"):
            continue
        cells = split(line)
        for col in columns:
            j = index[col]
            cell = cells[j] if j < len(cells) else ""
            try:
                value = float(cell) if cell else math.nan
            except ValueError:
                raise DataError(
                    f"{name}, line {lineno}: column {col!r} holds {cell!r}, not a number"
                ) from None
            out[col].append(value)
    return {c: np.asarray(v, dtype=float) for c, v in out.items()}


class ReplayPlant:
    """Replay of a recorded run ``t, u, y`` as a plant.

    :meth:`reset` returns the first recorded sample; each :meth:`step`
    returns the next one.  The recorded output cannot react to another input:
    the input passed to :meth:`step` is ignored (pass ``None`` to follow the
    record), and one :class:`ReplayInputWarning` per run says so when it
    differs from the recorded input by more than ``input_tolerance``.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times, s.
    u : array-like of shape (n_samples,)
        Recorded input (``u[k]`` was applied from ``t[k]`` on); NaN allowed.
    y : array-like of shape (n_samples,)
        Recorded output; NaN (a recorded dropout) allowed.
    clock : Clock, optional
        Pacing; as fast as possible when omitted.  A real-time clock replays
        at the recorded pace.
    input_tolerance : float, default=1e-9
        Largest difference from the recorded input that is not warned about.
    name : str, default='replay'
        Name of the plant.

    Raises
    ------
    DimensionError
        If the arrays are not 1-D of one length ``>= 2``.
    DataError
        If ``t`` is not finite and strictly increasing.

    Attributes
    ----------
    dt : float
        Median sampling period of the record, s.
    input_limits : tuple of float
        Range of the recorded input (``(-inf, inf)`` if it holds no finite value).
    n_samples : int
        Number of recorded samples.

    See Also
    --------
    ReplayPlant.from_csv : Read the record from a file.

    Notes
    -----
    ``meta`` holds ``u`` (the recorded input of the period that ended at
    ``t``), ``k`` and ``u_requested`` (what :meth:`step` was given).

    Examples
    --------
    >>> from kautztwin.twin.plants import ReplayPlant
    >>> plant = ReplayPlant([0.0, 0.1, 0.2], [1.0, 1.0, 0.0], [0.0, 0.5, 0.8])
    >>> plant.reset().y, plant.step(None).y, plant.step(None).y
    (0.0, 0.5, 0.8)
    """

    def __init__(
        self,
        t: ArrayLike,
        u: ArrayLike,
        y: ArrayLike,
        *,
        clock: Clock | None = None,
        input_tolerance: float = 1e-9,
        name: str = "replay",
    ) -> None:
        arrays = [np.array(a, dtype=float, copy=True) for a in (t, u, y)]
        for label, a in zip("tuy", arrays, strict=True):
            if a.ndim != 1:
                raise DimensionError(f"{label} must be 1-D, got shape {a.shape}")
        if not arrays[0].size == arrays[1].size == arrays[2].size:
            raise DimensionError(
                f"t, u and y must have one length, got {arrays[0].size}, {arrays[1].size} "
                f"and {arrays[2].size}"
            )
        if arrays[0].size < 2:
            raise DimensionError(f"a replay needs at least 2 samples, got {arrays[0].size}")
        tt = arrays[0]
        if not np.all(np.isfinite(tt)) or np.any(np.diff(tt) <= 0):
            raise DataError("t must be finite and strictly increasing")
        for a in arrays:
            a.setflags(write=False)
        self.t, self.u, self.y = arrays
        self.dt = float(np.median(np.diff(tt)))
        finite = self.u[np.isfinite(self.u)]
        self.input_limits = (
            (float(finite.min()), float(finite.max())) if finite.size else (-math.inf, math.inf)
        )
        self.clock = clock if clock is not None else Clock()
        self.input_tolerance = float(input_tolerance)
        self.name = str(name)
        self.reset()

    @classmethod
    def from_csv(
        cls,
        path: str | os.PathLike[str],
        *,
        columns: tuple[str, str, str] = ("t", "u", "y"),
        **kwargs: Any,
    ) -> ReplayPlant:
        """Read a record from a CSV (or whitespace-separated) file with a header row.

        Parameters
        ----------
        path : str or os.PathLike
            The file.  The first non-blank line names the columns (a leading
            ``#`` is ignored); the separator is a comma, a semicolon, a tab or
            whitespace.  Empty cells and ``nan`` in ``u`` and ``y`` are dropouts.
        columns : (str, str, str), default=('t', 'u', 'y')
            Names of the time, input and output columns.
        **kwargs
            Further arguments of :class:`ReplayPlant`.

        Returns
        -------
        ReplayPlant

        Raises
        ------
        DataError
            If the file is missing, empty, lacks a column or holds a
            non-numeric value.
        """
        data = _read_replay_csv(Path(path), tuple(columns))
        tc, uc, yc = columns
        kwargs.setdefault("name", Path(path).stem)
        return cls(data[tc], data[uc], data[yc], **kwargs)

    @property
    def n_samples(self) -> int:
        """Number of recorded samples."""
        return int(self.t.size)

    @property
    def remaining(self) -> int:
        """Steps left before the record ends."""
        return self.n_samples - 1 - self._k

    def reset(self) -> Reading:
        """Rewind to the first sample and return it.

        Returns
        -------
        Reading
        """
        self._k = 0
        self._warned = False
        self.clock.start()
        return Reading(self.t[0], self.y[0], {"u": math.nan, "k": 0, "u_requested": math.nan})

    def step(self, u: float | None = None) -> Reading:
        """Return the next recorded sample; ``u`` is only compared with the record.

        Parameters
        ----------
        u : float or None, default=None
            The input the caller wanted to apply; ``None`` follows the record.

        Returns
        -------
        Reading

        Raises
        ------
        ReplayExhaustedError
            After the last recorded sample.
        """
        if self._k + 1 >= self.n_samples:
            raise ReplayExhaustedError(
                f"the record {self.name!r} ends after {self.n_samples} samples"
            )
        recorded = float(self.u[self._k])
        requested = math.nan if u is None else float(u)
        if u is not None and not self._warned:
            same = (math.isnan(requested) and math.isnan(recorded)) or (
                abs(requested - recorded) <= self.input_tolerance
            )
            if not same:
                self._warned = True
                warnings.warn(
                    f"{self.name}: a replay cannot follow another input; u = {requested:g} "
                    f"was asked at t = {self.t[self._k]:g} s but {recorded:g} was recorded "
                    "(warned once per run)",
                    ReplayInputWarning,
                    stacklevel=2,
                )
        self._k += 1
        self.clock.wait_until(self.t[self._k] - self.t[0])
        return Reading(
            self.t[self._k], self.y[self._k],
            {"u": recorded, "k": self._k, "u_requested": requested},
        )

    def close(self) -> None:
        """Nothing to release for a replay."""

    def __repr__(self) -> str:
        return f"ReplayPlant({self.name!r}, n_samples={self.n_samples}, dt={self.dt:g})"


# --------------------------------------------------------------------------- open loop
@dataclass(frozen=True, eq=False)
class PlantRun:
    """Samples of an open-loop run of a plant (see :func:`run_open_loop`).

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Sample times, s.
    u : ndarray of shape (n_samples,)
        Input applied from ``t[k]`` on (the last one is NaN: never applied).
    y : ndarray of shape (n_samples,)
        Measured output.
    readings : tuple of Reading
        The readings themselves (with their ``meta``).
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    readings: tuple[Reading, ...]

    def __post_init__(self) -> None:
        for name in ("t", "u", "y"):
            a = np.array(getattr(self, name), dtype=float, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def meta(self, key: str) -> NDArray[np.float64]:
        """One numeric ``meta`` entry of every reading as an array (NaN where missing).

        Parameters
        ----------
        key : str
            The entry, for example ``'y_true'`` or ``'temperature'``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return np.array([float(r.meta.get(key, math.nan)) for r in self.readings])


def run_open_loop(plant: Plant, u: ArrayLike) -> PlantRun:
    """Reset a plant, drive it with a known input sequence and collect the readings.

    Parameters
    ----------
    plant : Plant
        Any plant.
    u : array-like of shape (n_steps,)
        Finite inputs, one per step.

    Returns
    -------
    PlantRun
        ``n_steps + 1`` samples: the reading of :meth:`Plant.reset` and one per step.

    Raises
    ------
    DimensionError
        If ``u`` is not 1-D.

    Examples
    --------
    >>> from kautztwin.twin.plants import HydraulicPlant, run_open_loop
    >>> run = run_open_loop(HydraulicPlant(dt=0.05), [0.5] * 10)
    >>> run.y.shape
    (11,)
    """
    u = np.atleast_1d(np.asarray(u, dtype=float))
    if u.ndim != 1:
        raise DimensionError(f"u must be 1-D, got shape {u.shape}")
    readings = [plant.reset()]
    readings += [plant.step(float(v)) for v in u]
    return PlantRun(
        t=np.array([r.t for r in readings]),
        u=np.append(u, math.nan),
        y=np.array([r.y for r in readings]),
        readings=tuple(readings),
    )
