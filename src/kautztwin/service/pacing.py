"""Transport-independent stepping of a served plant: channels, pacing, catch-up, freeze.

A served plant (the OPC UA :class:`~kautztwin.service.PlantServer`, the MQTT
:class:`~kautztwin.service.MQTTPlantServer`) steps a
:class:`~kautztwin.twin.Plant` every ``dt / speed`` wall-clock seconds with the
last accepted input and publishes each output sample stamped with its source
time (the plant time mapped to the wall clock).  :class:`PacedPlant` holds that
logic once; a transport subclass only says how a sample is published, how the
input is read and how the status is shown.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, NamedTuple

from ..exceptions import DataError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ..twin import Plant, Reading

__all__ = ["Channel", "PacedPlant", "ServedSample", "default_channels", "unece_unit_id"]

_logger = logging.getLogger(__name__)


def unece_unit_id(code: str) -> int:
    """The ``UnitId`` of a UNECE Recommendation 20 unit code (OPC UA Part 8, 5.6.3).

    Parameters
    ----------
    code : str
        Common code of up to 3 ASCII characters, e.g. ``'CEL'`` (°C), ``'2A'`` (rad/s).

    Returns
    -------
    int
        The characters packed into an integer, most significant first.

    Raises
    ------
    DataError
        If the code is empty, longer than 3 characters or not ASCII.

    Examples
    --------
    >>> from kautztwin.service.pacing import unece_unit_id
    >>> unece_unit_id("CEL"), unece_unit_id("2A")
    (4408652, 12865)
    """
    if not (1 <= len(code) <= 3) or not code.isascii():
        raise DataError(f"a UNECE unit code has 1 to 3 ASCII characters, got {code!r}")
    out = 0
    for ch in code:
        out = (out << 8) | ord(ch)
    return out


@dataclass(frozen=True)
class Channel:
    """Engineering description of one plant variable (an OPC UA ``AnalogItem``).

    Parameters
    ----------
    unit : str
        Display name of the unit (``'rad/s'``, ``'°C'``, ``'%'``, ``''``).
    low, high : float
        ``EURange``: the range the value normally lies in; for an input, the
        limits outside which writes are rejected.
    unece : str, optional
        UNECE common code of the unit (``'2A'``, ``'CEL'``, ``'P1'``, ``'C62'``);
        ``UnitId`` is -1 when omitted.
    description : str, default=''
        What the variable is.

    Raises
    ------
    DataError
        If the range is not ``low < high`` (infinite ends are allowed).
    """

    unit: str
    low: float
    high: float
    unece: str | None = None
    description: str = ""

    def __post_init__(self) -> None:
        low, high = float(self.low), float(self.high)
        if math.isnan(low) or math.isnan(high) or not low < high:
            raise DataError(f"a channel range needs low < high, got ({low}, {high})")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        if self.unece is not None:
            unece_unit_id(self.unece)

    def contains(self, value: float) -> bool:
        """Whether ``value`` is a finite number inside ``[low, high]``.

        Parameters
        ----------
        value : float

        Returns
        -------
        bool
        """
        return math.isfinite(value) and self.low <= value <= self.high


def default_channels(plant: Plant) -> tuple[Channel, Channel]:
    """Input and output channels of a plant, from its name and limits.

    The hydraulic drive (name ``'hydraulic'``): valve command (dimensionless,
    the plant's input limits) and shaft speed in rad/s (range ± the drive's
    no-load speed).  The TCLab (``'tclab'``): heater power in % and the
    heater temperature in °C (0 to 100).  Any other plant: the input limits
    and an unbounded output without unit.

    Parameters
    ----------
    plant : Plant
        The plant.

    Returns
    -------
    tuple of Channel
        ``(input, output)``.
    """
    lo, hi = (float(v) for v in plant.input_limits)
    name = str(getattr(plant, "name", "")).lower()
    if name.startswith("hydraulic"):
        drive = getattr(plant, "drive", None)
        w = float(getattr(drive, "no_load_speed", math.inf))
        return (
            Channel("", lo, hi, "C62", "servo-valve command (fraction of full spool stroke)"),
            Channel("rad/s", -w, w, "2A", "hydraulic motor shaft speed"),
        )
    if name.startswith("tclab"):
        return (
            Channel("%", lo, hi, "P1", "heater power"),
            Channel("°C", 0.0, 100.0, "CEL", "heater temperature"),
        )
    return Channel("", lo, hi, None, "plant input"), Channel("", -math.inf, math.inf, None,
                                                              "plant output")


class ServedSample(NamedTuple):
    """One sample the server's plant produced (see :attr:`PacedPlant.history`).

    Attributes
    ----------
    k : int
        Sample index.
    t : float
        Plant time, s.
    u : float
        Input applied over the period that ended at ``t`` (NaN at ``k = 0``).
    y : float
        Output.
    published : bool
        Whether the sample was written to the address space (not while
        frozen, stopped or catching up).
    """

    k: int
    t: float
    u: float
    y: float
    published: bool


class PacedPlant:
    """Step a plant in real or scaled time; the base of the plant servers.

    Every ``dt / speed`` wall-clock seconds the plant is stepped with the last
    accepted input (:attr:`last_input`) and the sample handed to
    :meth:`_publish`, which a transport implements.  While :meth:`freeze` is on
    the plant runs and nothing is published; after a restart
    (:meth:`_begin_run` with samples already made) the plant first catches up
    with the wall clock, holding its input, publishing nothing.

    Parameters
    ----------
    plant : Plant
        The plant (on a simulated clock: the pacing is done here).  It is
        reset on the first run.
    speed : float, default=1.0
        Plant seconds per wall-clock second.
    object_name : str, optional
        Name of the served plant (node-id prefix, topic part); ``plant.name``
        when omitted.
    input_channel, output_channel : Channel, optional
        Units and ranges; :func:`default_channels` when omitted.  The input
        range may be narrower than the plant's input limits, not wider.
    initial_input : float, optional
        Input before any write; the plant's ``initial_command`` or the middle
        of the input range when omitted.
    history : int, default=100000
        How many :class:`ServedSample` records :attr:`history` keeps.

    Raises
    ------
    DataError
        On an invalid speed, object name or channel.

    Attributes
    ----------
    history : collections.deque of ServedSample
        The samples the plant produced, newest last (a test hook).
    restarts : int
        How many runs began after the first one.
    """

    def __init__(
        self,
        plant: Plant,
        *,
        speed: float = 1.0,
        object_name: str | None = None,
        input_channel: Channel | None = None,
        output_channel: Channel | None = None,
        initial_input: float | None = None,
        history: int = 100_000,
    ) -> None:
        self.plant = plant
        try:
            speed = float(speed)
        except (TypeError, ValueError):
            raise DataError(f"speed must be a positive number, got {speed!r}") from None
        if not (math.isfinite(speed) and speed > 0):
            raise DataError(f"speed must be a positive number, got {speed}")
        self.speed = speed
        self.dt = float(plant.dt)
        self.object_name = str(object_name if object_name is not None else plant.name)
        if not self.object_name or any(c in self.object_name for c in ";= /#+"):
            raise DataError(f"object name must be a non-empty word, got {self.object_name!r}")
        din, dout = default_channels(plant)
        self.input_channel = input_channel if input_channel is not None else din
        self.output_channel = output_channel if output_channel is not None else dout
        plo, phi = (float(v) for v in plant.input_limits)
        if self.input_channel.low < plo or self.input_channel.high > phi:
            raise DataError(
                f"input range ({self.input_channel.low:g}, {self.input_channel.high:g}) must lie "
                f"inside the plant's input limits ({plo:g}, {phi:g})"
            )
        if initial_input is None:
            initial_input = getattr(plant, "initial_command", None)
        if initial_input is None or not self.input_channel.contains(float(initial_input)):
            initial_input = 0.5 * (self.input_channel.low + self.input_channel.high)
        self.initial_input = float(initial_input)
        self.history: deque[ServedSample] = deque(maxlen=int(history))
        self.restarts = 0
        self._u = self.initial_input
        self._k = -1  # no sample yet: the first run resets the plant
        self._last: ServedSample | None = None
        self._origin_mono = 0.0
        self._origin_wall = datetime.now(UTC)
        self._frozen = False
        self._status = "stopped"
        self._stop_event: asyncio.Event | None = None

    # ------------------------------------------------------------------ properties
    @property
    def frozen(self) -> bool:
        """Whether publishing is frozen (see :meth:`freeze`)."""
        return self._frozen

    @property
    def status(self) -> str:
        """``'starting'``, ``'running'``, ``'frozen'``, ``'catching-up'``, ``'fault: ...'``
        or ``'stopped'``."""
        return self._status

    @property
    def k(self) -> int:
        """Index of the last sample the plant produced (-1 before the first run)."""
        return self._k

    @property
    def origin_time(self) -> float:
        """Wall-clock time (POSIX s) of plant time 0: source time = origin + t / speed."""
        return self._origin_wall.timestamp()

    @property
    def last_input(self) -> float:
        """The input the plant holds now (the last accepted one)."""
        return self._u

    def freeze(self) -> None:
        """Stop publishing outputs; the plant keeps running and inputs are still accepted."""
        self._frozen = True

    def unfreeze(self) -> None:
        """Publish outputs again (from the next sample on)."""
        self._frozen = False

    # ------------------------------------------------------------------ transport hooks
    async def _publish(self, sample: ServedSample) -> None:
        """Publish one sample (the transport's job)."""
        raise NotImplementedError

    def _read_input(self) -> float:
        """The input to apply over the next period (default: the last accepted one)."""
        return self._u

    def _set_status(self, status: str) -> None:
        """Record the status (a transport also shows it)."""
        self._status = status

    # ------------------------------------------------------------------ stepping
    def _begin_run(self) -> None:
        """Reset the plant on the first run (sample 0); count a restart otherwise."""
        if self._k < 0:
            reading = self.plant.reset()
            self._origin_mono = time.monotonic()
            self._origin_wall = datetime.now(UTC)
            self._record(reading, math.nan, publish=True)
        else:
            self.restarts += 1

    def _source_time(self, t: float) -> datetime:
        return self._origin_wall + timedelta(seconds=t / self.speed)

    def _record(self, reading: Reading, u: float, publish: bool) -> ServedSample:
        self._k = int(round(reading.t / self.dt)) if self._k >= 0 else 0
        sample = ServedSample(self._k, float(reading.t), float(u), float(reading.y), publish)
        self._last = sample
        self.history.append(sample)
        return sample

    def _step(self) -> ServedSample | None:
        u = self._read_input()
        try:
            reading = self.plant.step(u)
        except Exception as exc:  # a plant that fails: report, stop stepping
            _logger.exception("plant step failed")
            self._set_status(f"fault: {' '.join(str(exc).split()) or type(exc).__name__}")
            return None
        return self._record(reading, u, publish=not self._frozen)

    async def _catch_up(self) -> None:
        """After a restart, run the plant silently up to the wall clock."""
        assert self._stop_event is not None
        target = int((time.monotonic() - self._origin_mono) * self.speed / self.dt)
        if target <= self._k:
            return
        self._set_status("catching-up")
        while self._k < target and not self._stop_event.is_set():
            u = self._read_input()
            try:
                reading = self.plant.step(u)
            except Exception as exc:
                self._set_status(f"fault: {' '.join(str(exc).split())}")
                return
            self._record(reading, u, publish=False)
            if self._k % 200 == 0:
                await asyncio.sleep(0)  # let clients connect meanwhile
        self._set_status("running")

    async def _tick_loop(self) -> None:
        """Step and publish every ``dt / speed`` s until the stop event is set."""
        assert self._stop_event is not None
        period = self.dt / self.speed
        stop = self._stop_event
        was_frozen = False
        while not stop.is_set():
            due = self._origin_mono + (self._k + 1) * period
            delay = due - time.monotonic()
            if delay > 0:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), delay)
                if stop.is_set():
                    break
            if self._status.startswith("fault"):
                await stop.wait()
                break
            frozen = self._frozen
            if frozen != was_frozen:
                self._set_status("frozen" if frozen else "running")
                was_frozen = frozen
            sample = self._step()
            if sample is not None and sample.published:
                await self._publish(sample)
            if delay <= 0:  # behind the wall clock: let the clients' requests (writes) in
                await asyncio.sleep(0)
