"""Keep the transport-independent half of a plant link: sample queue, readings, outages.

:class:`SampleLink` is the base of :class:`~.opcua.OPCUAPlant` and
:class:`~.mqtt.MQTTPlant`.  A transport (OPC UA subscription, MQTT topic) only
delivers output samples and sends inputs; what a link makes of that is the
same for both and lives here:

* the sample queue ordered by source timestamp, with late, out-of-order and
  duplicate samples dropped and counted;
* the plant-time clock started at :meth:`reset` and snapped to the ``dt`` grid;
* the reading and its ``meta`` (``k``, ``u``, ``u_requested``, ``write``,
  ``link``, ``dropout``, ``stale``, ``late``, ``out_of_order``, ``status``,
  ``source_time``, ``latency``, ``queued``);
* stale detection (no new sample within ``stale_periods`` sample periods) and
  the NaN reading per period while the link is down or the data stale;
* the outage log (:class:`Outage`) and the counters;
* the input delay estimate ``meta['input_delay']`` (see below).

Input delay
-----------
An input the twin sends after reading sample ``s`` is applied by the plant
over some later period ``p = s + d``: the loop may be behind the plant (samples
queued), and the write needs its time on the wire.  The plant reports the input
it applied over each period (``u_applied``), so the link measures ``d``: each
change of the sent input is remembered with the plant's sample index at the
time it was sent (from the wall clock, ``speed`` and the source timestamp of
the first reading); when the applied input changes to that value at period
``p``, ``p`` minus that index is one measurement of the write latency in
samples.  The estimate for the next decision is the plant's sample index now
plus the median of the recent latencies, minus the reading's index: the queue
is seen at once, the wire's latency (and any constant clock offset between
plant and twin) is learnt.  The twin's MPC predicts over that delay
(:meth:`kautztwin.twin.prediction.MPCController.solve`).

A subclass provides ``connect()``, ``_need_config()`` (make ``dt``, ``speed``
and the input limits known), a ``_Sample`` with at least ``ts``, ``seq``,
``value``, ``status``, ``arrival`` and ``latency``, and calls the helpers
below from its transport callbacks and its ``reset``/``step``.

Size: :class:`SampleLink` is over 400 lines because it is the one home of what both
transports share (queue, clock, readings, stale detection, outages, outage policy, the
input delay); about half of it is documentation, and splitting it would put helpers that
call each other under one lock into separate classes.
"""

from __future__ import annotations

import heapq
import itertools
import math
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from ...exceptions import DataError, KautzTwinError
from .base import Reading

__all__ = ["LinkError", "Outage", "SampleLink"]

#: shortest wall-clock silence that makes the data stale, s (scheduler jitter of a loaded host)
STALE_FLOOR_S = 0.5
#: write latencies (samples) the input delay estimate is the median of
DELAY_MEMORY = 32

_COUNTERS = ("samples", "dropouts", "stale", "link_down", "late", "out_of_order", "duplicates",
             "rejected_writes", "failed_writes", "reconnects")


class LinkError(KautzTwinError, ConnectionError):
    """The OPC UA server could not be reached (or refused the session) in time."""


@dataclass
class Outage:
    """One interruption of the plant data.

    Parameters
    ----------
    kind : {'link', 'stale'}
        ``'link'``: the connection was lost; ``'stale'``: connected, but no new
        sample arrived for ``stale_periods`` sample periods.
    start : float
        Wall-clock time the outage was detected (POSIX seconds).
    end : float or None
        Wall-clock time data flowed again; ``None`` while it lasts.
    reason : str
        What was seen (one line).
    t : float
        Plant time of the last reading before the outage, s.
    """

    kind: str
    start: float
    end: float | None
    reason: str
    t: float = math.nan

    @property
    def duration(self) -> float:
        """Seconds from start to end (NaN while the outage lasts)."""
        return math.nan if self.end is None else self.end - self.start


def _positive(value: Any, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(out) and out > 0):
        raise DataError(f"{name} must be a positive number, got {out}")
    return out


class SampleLink:
    """Base of the plant links: queue, clock, readings, stale detection, outages, counters.

    Not used on its own: a subclass adds the transport (see the module docstring).

    Attributes
    ----------
    name : str
        Plant name for logs and messages.
    stale_periods : float
        Sample periods without a new sample that make the data stale.
    outages : list of Outage
        Link and stale-data outages, oldest first.
    counters : dict of str to int
        ``samples``, ``dropouts``, ``stale``, ``link_down``, ``late``,
        ``out_of_order``, ``duplicates``, ``rejected_writes``, ``failed_writes``,
        ``reconnects``.

    See Also
    --------
    kautztwin.twin.physical.OPCUAPlant : The OPC UA link.
    kautztwin.twin.physical.MQTTPlant : The MQTT link.

    Examples
    --------
    >>> from kautztwin.twin.physical.link import SampleLink
    >>> from kautztwin.twin.physical import MQTTPlant, OPCUAPlant
    >>> issubclass(OPCUAPlant, SampleLink) and issubclass(MQTTPlant, SampleLink)
    True
    """

    name: str
    _dt: float | None
    _speed: float | None
    _limits: tuple[float, float] | None

    # ------------------------------------------------------------------ set-up
    def _init_config(self, dt: float | None, speed: float | None,
                     input_limits: tuple[float, float] | None, stale_periods: float) -> None:
        """Check and keep ``dt``, ``speed``, the input limits and ``stale_periods``."""
        self._dt = None if dt is None else _positive(dt, "dt")
        self._speed = None if speed is None else _positive(speed, "speed")
        self._limits = None
        if input_limits is not None:
            try:
                lo, hi = (float(v) for v in input_limits)
            except (TypeError, ValueError):
                raise DataError(f"input_limits must be (low, high), got {input_limits!r}") from None
            if not lo < hi:
                raise DataError(f"input_limits must have low < high, got ({lo}, {hi})")
            self._limits = (lo, hi)
        self.stale_periods = _positive(stale_periods, "stale_periods")

    def _init_link(self, connect_timeout: float, request_timeout: float,
                   reconnect_delay: float, reconnect_max_delay: float) -> None:
        """Check and keep the timeouts; start the queue, clock, outage log and counters."""
        self.connect_timeout = _positive(connect_timeout, "connect_timeout")
        self.request_timeout = _positive(request_timeout, "request_timeout")
        self.reconnect_delay = _positive(reconnect_delay, "reconnect_delay")
        self.reconnect_max_delay = max(self.reconnect_delay,
                                       _positive(reconnect_max_delay, "reconnect_max_delay"))
        self.outages: list[Outage] = []
        self.counters = dict.fromkeys(_COUNTERS, 0)
        self._cond = threading.Condition()
        self._heap: list[Any] = []
        self._seq = itertools.count()
        self._client: Any = None
        self._fatal: BaseException | None = None
        self._last_error = ""
        self._link_up = False
        self._connections = 0
        self._newest_ts = -math.inf
        self._last_fresh = time.monotonic()
        self._origin_ts: float | None = None
        self._last_ts = -math.inf
        self._last_t = 0.0
        self._degraded_at: float | None = None  # monotonic time of the last NaN reading
        self._overrun: float | None = None  # plant time NaN readings reached (late samples)
        self._stale_outage: Outage | None = None
        self._link_outage: Outage | None = None
        self._k = 0
        self._u = math.nan
        self._sent: deque[tuple[int, float, float]] = deque(maxlen=4 * DELAY_MEMORY)
        self._last_sent = math.nan
        self._last_applied = math.nan
        self._latencies: deque[float] = deque(maxlen=DELAY_MEMORY)

    def _init_policy(self, on_outage: str, safe_input: float | None) -> None:
        """Check and keep the outage policy (``'hold'`` or ``'safe'``) and the safe input."""
        if on_outage not in ("hold", "safe"):
            raise DataError(f"on_outage must be 'hold' or 'safe', got {on_outage!r}")
        safe = None
        if safe_input is not None:
            try:
                safe = float(safe_input)
            except (TypeError, ValueError):
                raise DataError(f"safe_input must be a number, got {safe_input!r}") from None
            if not math.isfinite(safe):
                raise DataError(f"safe_input must be finite, got {safe}")
        if on_outage == "safe" and safe is None:
            raise DataError("on_outage = 'safe' needs a safe_input (the input to fall back to)")
        self.on_outage = on_outage
        self.safe_input = safe

    @property
    def degraded(self) -> bool:
        """Whether the link is down or the last reading was a missing sample (an outage)."""
        return self._degraded_at is not None or not self._link_up

    def _policy_input(self, value: float) -> tuple[float | None, str]:
        """``(input to send, policy)``: ``value`` normally; during an outage the policy's.

        ``'hold'`` sends nothing (the plant holds the last input it accepted),
        ``'safe'`` sends :attr:`safe_input` (clipped to the input limits).
        """
        if not self.degraded:
            return value, ""
        if getattr(self, "on_outage", "hold") == "safe" and self.safe_input is not None:
            lo, hi = self.input_limits
            return min(hi, max(lo, self.safe_input)), "safe"
        return None, "hold"

    def _send_input(self, value: float, send: Callable[[float], str],
                    behind: bool = False) -> str:
        """Send ``value`` (or the outage policy's input) with ``send``; the ``write`` status.

        ``send(target)`` puts the input on the wire and returns ``'sent'``,
        ``'ok'`` or ``'failed: ...'``.  While the link is down or the data stale
        the policy decides (``'not sent: holding (...)'`` or
        ``'sent: safe input <u>'``); ``behind`` (newer samples wait and an input
        went out within the period) sends nothing when the input is the one sent
        last: ``'not sent: behind'`` (a new input always goes out).
        A sent input is remembered for the input delay estimate.
        """
        target, policy = self._policy_input(value)
        if behind and not policy and target == self._last_sent:
            return "not sent: behind"
        if target is None:
            return f"not sent: holding ({'link down' if not self._link_up else 'stale data'})"
        write = send(target)
        if write in ("sent", "ok"):
            self._note_sent(target)
            if policy:
                write = f"sent: {policy} input {target:g}"
        elif write.startswith("failed"):
            self.counters["failed_writes"] += 1
        return write

    # ------------------------------------------------------------------ configuration
    def connect(self) -> Any:  # pragma: no cover - every link defines it
        """Start the transport and wait for the first connection."""
        raise NotImplementedError

    def _need_config(self) -> None:
        """Make ``dt``, ``speed`` and the input limits known (the transport reads them)."""
        self.connect()

    @property
    def dt(self) -> float:
        """Sampling period, plant seconds (read over the link on first use when not given)."""
        if self._dt is None:
            self._need_config()
        assert self._dt is not None
        return self._dt

    @property
    def speed(self) -> float:
        """Plant seconds per wall-clock second of the source timestamps."""
        if self._speed is None:
            self._need_config()
        return 1.0 if self._speed is None else self._speed

    @property
    def input_limits(self) -> tuple[float, float]:
        """``(low, high)`` input bounds in engineering units; inputs outside are refused."""
        if self._limits is None:
            self._need_config()
        assert self._limits is not None
        return self._limits

    @property
    def link_up(self) -> bool:
        """Whether the connection and its subscription are up now."""
        return self._link_up

    # ------------------------------------------------------------------ transport events
    def _mark_up(self) -> None:
        """The link is up (again): count it, end the link outage (call with the lock held)."""
        now = time.time()
        self._link_up = True
        self._connections += 1
        if self._connections > 1:
            self.counters["reconnects"] += 1
        if self._link_outage is not None:
            self._link_outage.end = now
            self._link_outage = None
        self._last_fresh = time.monotonic()
        self._cond.notify_all()

    def _mark_down(self, reason: str) -> None:
        """The link was lost: open a link outage (call with the lock held)."""
        outage = Outage("link", time.time(), None, reason, self._last_t)
        self._link_outage = outage
        self.outages.append(outage)

    def _queue(self, sample: Any, now: float) -> None:
        """Queue one output sample that arrived at monotonic time ``now`` (takes the lock)."""
        with self._cond:
            if sample.ts > self._newest_ts:
                self._newest_ts = sample.ts
                self._last_fresh = now
            heapq.heappush(self._heap, sample)
            self._cond.notify_all()

    # ------------------------------------------------------------------ input delay
    def _plant_index(self) -> float:
        """The plant's sample index now, on the reading clock (NaN before :meth:`reset`)."""
        if self._origin_ts is None:
            return math.nan
        return (time.time() - self._origin_ts) * self.speed / self.dt

    def _note_sent(self, value: float) -> None:
        """The input ``value`` went out for the period that starts at reading ``self._k``."""
        if value != self._last_sent:
            self._last_sent = value
            self._sent.append((self._k, value, self._plant_index()))

    def _note_applied(self, period: int, applied: float) -> None:
        """The plant reports ``applied`` over ``period``: measure the latency of a change.

        Sent changes older than the matched one were overtaken (coalesced) and
        are forgotten (call with the lock held).
        """
        if not math.isfinite(applied) or applied == self._last_applied:
            return
        self._last_applied = applied
        tol = 1e-9 * max(1.0, abs(applied))
        for i, (k, value, index) in enumerate(self._sent):
            if k <= period and abs(value - applied) <= tol:
                if math.isfinite(index):
                    self._latencies.append(period - index)
                for _ in range(i + 1):
                    self._sent.popleft()
                return

    def _input_delay(self, k: int) -> int:
        """Samples from reading ``k`` to the period an input sent now will be applied over."""
        index = self._plant_index()
        if not math.isfinite(index):
            return 0
        latency = statistics.median(self._latencies) if self._latencies else 0.0
        return max(0, int(round(index + latency)) - k)

    @property
    def input_delay(self) -> int:
        """Current estimate of the input delay in samples (see the module notes).

        Returns
        -------
        int
        """
        with self._cond:
            return self._input_delay(self._k)

    # ------------------------------------------------------------------ readings
    def _grid_time(self, ts: float) -> float:
        """Plant time of source timestamp ``ts``, snapped to the ``dt`` grid within 10 %."""
        assert self._origin_ts is not None
        t = (ts - self._origin_ts) * self.speed
        dt = self.dt
        k = round(t / dt)
        return k * dt if abs(t - k * dt) <= 0.1 * dt else t

    def _pop(self) -> tuple[Any, int]:
        """Next sample newer than the last one returned (call with the lock held)."""
        dropped = 0
        while self._heap:
            s = heapq.heappop(self._heap)
            if s.ts > self._last_ts:
                return s, dropped
            if s.ts < self._last_ts:
                dropped += 1
                self.counters["out_of_order"] += 1
            else:
                self.counters["duplicates"] += 1
        return None, dropped

    def _start_clock(self, no_sample: str) -> Any:
        """Wait for a sample, start the reading clock at the newest (call with the lock held).

        Raises :class:`LinkError` ``'<no_sample> within <connect_timeout> s'`` when none comes.
        """
        deadline = time.monotonic() + self.connect_timeout
        while not self._heap:
            left = deadline - time.monotonic()
            if left <= 0:
                raise LinkError(f"{no_sample} within {self.connect_timeout:g} s")
            self._cond.wait(left)
        newest = max(self._heap)
        self._heap.clear()
        self._origin_ts = newest.ts
        self._last_ts = newest.ts
        self._last_t = 0.0
        self._k = 0
        self._u = math.nan
        self._degraded_at = None
        return newest

    def _check_input(self, u: float | None, verb: str) -> float:
        """``u`` as a float inside the input limits, else a DataError '... before it was <verb>'."""
        try:
            value = float(u)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise DataError(f"{self.name}: u must be a number, got {u!r}") from None
        lo, hi = self.input_limits
        if not (math.isfinite(value) and lo <= value <= hi):
            raise DataError(
                f"{self.name}: input {value:g} is outside the input limits [{lo:g}, {hi:g}]; "
                f"refused before it was {verb}"
            )
        if self._origin_ts is None:
            raise DataError(f"{self.name}: call reset() before step()")
        return value

    def _next_reading(self, value: float, write: str, real: Callable[[Any, int], Reading],
                      time_of: Callable[[Any], float] | None = None) -> Reading:
        """Wait for the next sample (``real(sample, dropped)``) or a NaN reading when none comes.

        ``time_of(sample)``: its plant time; a sample whose time a NaN reading
        already took (it came after the data were declared stale: the plant
        published late) is still returned, flagged ``meta['late']`` and counted
        in ``late``; its reading time is earlier than the NaN readings' (the
        twin's sanitizer flags it late and holds), and it is stored.
        """
        self._k += 1
        period = self.dt / self.speed
        with self._cond:
            while True:
                sample, dropped = self._pop()
                if sample is not None:
                    reading = real(sample, dropped)
                    if (time_of is not None and self._overrun is not None
                            and time_of(sample) <= self._overrun + 0.5 * self.dt):
                        if not reading.meta["late"]:
                            self.counters["late"] += 1
                        reading = Reading(reading.t, reading.y, {**reading.meta, "late": True})
                    else:
                        self._overrun = None
                    return reading
                now = time.monotonic()
                if self._degraded_at is not None:
                    deadline = self._degraded_at + period
                else:
                    deadline = self._last_fresh + max(self.stale_periods * period,
                                                      STALE_FLOOR_S)
                if now >= deadline:
                    at = deadline if now - deadline < period else now  # no backlog of NaNs
                    return self._missing_reading(value, write, dropped, at)
                self._cond.wait(deadline - now)

    def _sample_reading(self, s: Any, t: float, dropped: int, u_req: float, write: str,
                        late: bool, u_applied: float | None = None) -> Reading:
        """The reading of sample ``s`` at plant time ``t`` (call with the lock held).

        ``u_applied``: the input the plant reports it applied over the period
        (``meta['u']``); the last accepted write when the plant reports none.
        """
        dropout = not math.isfinite(s.value)
        self._last_ts = s.ts
        self._last_t = t
        self._degraded_at = None
        if self._stale_outage is not None:
            self._stale_outage.end = time.time()
            self._stale_outage = None
        self.counters["dropouts" if dropout else "samples"] += 1
        if late:
            self.counters["late"] += 1
        u_eff = self._u if u_applied is None or not math.isfinite(u_applied) else u_applied
        if u_applied is not None and self._k > 0:
            self._note_applied(self._k - 1, u_applied)
        meta = dict(k=self._k, u=u_eff, u_applied=math.nan if u_applied is None else u_applied,
                    u_requested=u_req, write=write,
                    link="up" if self._link_up else "down", dropout=dropout, stale=False,
                    late=late, out_of_order=dropped, status=s.status, source_time=s.ts,
                    latency=s.latency, queued=len(self._heap),
                    input_delay=self._input_delay(self._k))
        return Reading(t, math.nan if dropout else s.value, meta)

    def _missing_reading(self, u_req: float, write: str, dropped: int, at: float) -> Reading:
        """A NaN reading: no sample in time (call with the lock held)."""
        link = "up" if self._link_up else "down"
        stale = link == "up"
        self._degraded_at = at
        self._last_t += self.dt
        self._overrun = self._last_t  # the latest time a NaN reading took
        self.counters["dropouts"] += 1
        self.counters["stale" if stale else "link_down"] += 1
        if stale and self._stale_outage is None:
            self._stale_outage = Outage(
                "stale", time.time(), None,
                f"no new sample for {self.stale_periods:g} sample periods", self._last_t - self.dt)
            self.outages.append(self._stale_outage)
        meta = dict(k=self._k, u=self._u, u_requested=u_req, write=write, link=link,
                    dropout=True, stale=stale, late=False, out_of_order=dropped, status="",
                    source_time=math.nan, latency=math.nan, queued=0,
                    input_delay=self._input_delay(self._k))
        return Reading(self._last_t, math.nan, meta)

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:  # pragma: no cover - every link defines it
        """Disconnect and stop the transport (idempotent)."""
        raise NotImplementedError


def split_url(
    url: str, scheme: str, what: str, *, default_port: int, min_port: int, shape: str
) -> tuple[str, int]:
    """Check a ``SCHEME://HOST:PORT`` address of a plant link and split it.

    Parameters
    ----------
    url : str
        The address.
    scheme : str
        The required scheme (``'opc.tcp'``, ``'mqtt'``).
    what : str
        What the address is, for the messages (``'endpoint'``, ``'broker'``).
    default_port : int
        Port when the address names none.
    min_port : int
        Lowest port accepted (0: "pick a free one" is allowed).
    shape : str
        End of the message for an address with a path, query, fragment or a low port.

    Returns
    -------
    tuple
        ``(host, port)``.

    Raises
    ------
    DataError
        With a one-line message naming ``what``.
    """
    text = str(url).strip()
    parts = urlsplit(text)
    if parts.scheme != scheme:
        raise DataError(f"{what} must look like {scheme}://HOST:PORT, got {text!r}")
    try:
        port = parts.port
    except ValueError:
        raise DataError(f"{what} {text!r} has an invalid port ({min_port}..65535)") from None
    host = parts.hostname
    if not host:
        raise DataError(f"{what} {text!r} has no host")
    if parts.path not in ("", "/") or parts.query or parts.fragment or (
        port is not None and port < min_port
    ):
        raise DataError(f"{what} {text!r} must be {shape}")
    return host, default_port if port is None else int(port)
