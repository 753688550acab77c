"""The twin's MQTT link: a :class:`Plant` that subscribes to JSON samples and publishes inputs.

:class:`MQTTPlant` is the second transport beside :class:`~.opcua.OPCUAPlant`
and behaves like it.  Under a topic prefix (default ``kautztwin/<plant>``):

* ``<prefix>/y``: output samples ``{"t": .., "y": .., "k": .., "ts": ..}``
  (``ts``: source timestamp, POSIX s; ``u``, the input applied, optional), subscribed;
* ``<prefix>/u``: the input ``{"u": .., "ts": .., "seq": ..}``, published (QoS 1,
  not waited for);
* ``<prefix>/u/ack``: the plant's verdict on an input (``"status": "ok"`` or
  ``"rejected: ..."``), optional;
* ``<prefix>/meta`` (retained): ``dt``, ``speed`` and the input range, read when
  they are not configured; ``<prefix>/status`` (retained): the plant's status.

What real links do, and what the link does about it (as the OPC UA link):

* the broker goes away: :meth:`~MQTTPlant.step` never raises; it returns a NaN
  reading with ``meta['link'] == 'down'`` once per sample period, records the
  outage in :attr:`~MQTTPlant.outages`; paho reconnects in the background with a
  short exponential backoff and the subscriptions are made again;
* stale data (no new sample within ``stale_periods`` periods): a NaN reading
  flagged ``stale`` and ``dropout`` per period, an outage of kind ``'stale'``;
* late and out-of-order samples: returned in source-timestamp order; one older
  than a sample already returned is dropped and counted;
* NaN, inf, a non-number or a payload that is not JSON: a flagged dropout;
* an input that reaches the plant late: a sample's ``u`` (the input the plant
  applied over the period that ended with it) becomes ``meta['u']`` /
  ``meta['u_applied']``, and the input delay is estimated from it
  (``meta['input_delay']``, see :mod:`~.link`);
* while the link is down or the data stale, the input follows ``on_outage``
  (``'hold'``: publish nothing; ``'safe'``: publish ``safe_input``).

Inputs outside :attr:`~MQTTPlant.input_limits` are refused with a one-line
:class:`~kautztwin.exceptions.DataError` before they are published.  ``paho-mqtt``
is imported when the link connects (install ``kautztwin[service]``).

The sample queue, the readings, stale detection, the outage log and the
counters are shared with :class:`~.opcua.OPCUAPlant` in :class:`~.link.SampleLink`.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...exceptions import DataError
from .base import Reading
from .link import LinkError, SampleLink, _positive, split_url

__all__ = ["DEFAULT_BROKER", "MQTTPlant", "default_topics", "parse_broker"]

_logger = logging.getLogger(__name__)

#: broker of ``kautztwin plant serve --transport mqtt`` when none is given
DEFAULT_BROKER = "mqtt://127.0.0.1:1883"
_TOPIC_KEYS = ("y", "u", "ack", "meta", "status")


def parse_broker(url: str) -> tuple[str, int]:
    """Check an ``mqtt://HOST:PORT`` broker address and split it.

    Parameters
    ----------
    url : str
        Broker URL; the port defaults to 1883.

    Returns
    -------
    tuple
        ``(host, port)``.

    Raises
    ------
    DataError
        If the scheme is not ``mqtt``, the host is missing or the port is invalid.

    Examples
    --------
    >>> from kautztwin.twin.physical import parse_broker
    >>> parse_broker("mqtt://127.0.0.1:1884")
    ('127.0.0.1', 1884)
    """
    return split_url(url, "mqtt", "broker", default_port=1883, min_port=1,
                     shape="mqtt://HOST:PORT (port 1..65535), no path")


def default_topics(prefix: str) -> dict[str, str]:
    """The topics of a plant under ``prefix``.

    Parameters
    ----------
    prefix : str
        Topic prefix, e.g. ``'kautztwin/hydraulic'``.

    Returns
    -------
    dict
        Keys ``'y'``, ``'u'``, ``'ack'``, ``'meta'``, ``'status'``.

    Raises
    ------
    DataError
        If the prefix is empty or holds a wildcard (``+``, ``#``).

    Examples
    --------
    >>> from kautztwin.twin.physical import default_topics
    >>> default_topics("kautztwin/tclab")["u"]
    'kautztwin/tclab/u'
    """
    text = str(prefix).strip().strip("/")
    if not text or "+" in text or "#" in text:
        raise DataError(f"topic prefix must be a non-empty topic without wildcards, got {prefix!r}")
    return {"y": f"{text}/y", "u": f"{text}/u", "ack": f"{text}/u/ack",
            "meta": f"{text}/meta", "status": f"{text}/status"}


def _import_paho() -> Any:
    try:
        import paho.mqtt.client as mqtt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the MQTT link needs paho-mqtt: pip install 'kautztwin[service]'") from exc
    return mqtt


def _number(value: Any) -> float:
    """A float from a JSON value (NaN when it is not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return math.nan
    return float(value)


@dataclass(frozen=True, order=True)
class _Sample:
    ts: float  # source timestamp, POSIX s
    seq: int
    value: float  # NaN when unusable
    status: str
    t_src: float  # plant time in the payload (NaN when absent)
    k_src: float  # sample index in the payload (NaN when absent)
    arrival: float  # time.monotonic()
    latency: float  # arrival wall time - source timestamp, s
    u_applied: float = math.nan  # input applied over the period (NaN when absent)


def decode_sample(payload: bytes,
                  arrival_wall: float) -> tuple[float, float, float, str, float, float]:
    """Decode one output payload.

    Parameters
    ----------
    payload : bytes
        The MQTT message body: ``{"t": .., "y": .., "k": .., "u": .., "ts": ..}``
        in JSON (``u``: the input applied over the period that ended with the sample).
    arrival_wall : float
        Wall-clock arrival time (POSIX s), the timestamp of a sample without one.

    Returns
    -------
    tuple
        ``(ts, y, t, status, k, u)``: ``y`` is NaN unless finite, ``status`` is
        ``'Good'``, ``'BadValue'`` (not a finite number) or ``'BadDecoding'``
        (not a JSON object); ``t``, ``k`` and ``u`` are NaN when absent
        (``u`` also when not finite).

    Examples
    --------
    >>> from kautztwin.twin.physical.mqtt import decode_sample
    >>> decode_sample(b'{"t": 0.5, "y": 2.0, "k": 25, "u": 0.4, "ts": 100.0}', 101.0)
    (100.0, 2.0, 0.5, 'Good', 25.0, 0.4)
    >>> decode_sample(b'{"y": NaN, "ts": 100.0}', 101.0)[1:4]
    (nan, nan, 'BadValue')
    """
    try:
        data = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return arrival_wall, math.nan, math.nan, "BadDecoding", math.nan, math.nan
    if not isinstance(data, dict):
        return arrival_wall, math.nan, math.nan, "BadDecoding", math.nan, math.nan
    ts = _number(data.get("ts"))
    if not math.isfinite(ts):
        ts = arrival_wall
    y = _number(data.get("y"))
    status = "Good" if math.isfinite(y) else "BadValue"
    u = _number(data.get("u"))
    return (ts, (y if status == "Good" else math.nan), _number(data.get("t")), status,
            _number(data.get("k")), u if math.isfinite(u) else math.nan)


class MQTTPlant(SampleLink):
    """A plant behind an MQTT broker (a gateway, or :class:`kautztwin.service.MQTTPlantServer`).

    Parameters
    ----------
    broker : str, default='mqtt://127.0.0.1:1883'
        Broker URL, ``mqtt://HOST:PORT``.
    plant : str, default='hydraulic'
        Name in the default topic prefix ``kautztwin/<plant>``.
    topic : str, optional
        Topic prefix (``kautztwin/<plant>`` when omitted).
    topics : mapping, optional
        Topics by role (``'y'``, ``'u'``, ``'ack'``, ``'meta'``, ``'status'``)
        overriding the ones under the prefix.
    dt : float, optional
        Sampling period, plant seconds; read from the retained meta topic when omitted.
    input_limits : tuple of float, optional
        ``(low, high)``; from the meta topic when omitted.
    speed : float, optional
        Plant seconds per wall-clock second of the timestamps; from the meta
        topic when omitted (1.0 when it has none: a real plant).
    stale_periods : float, default=3
        A sample period without a new sample this many times over makes the
        data stale (a flagged NaN reading instead of a wait).
    on_outage : {'hold', 'safe'}, default='hold'
        Input while the link is down or the data stale: ``'hold'`` publishes
        nothing (the plant holds the last input it took), ``'safe'`` publishes
        ``safe_input`` (when the broker still takes it).
    safe_input : float, optional
        The input of ``on_outage='safe'``.
    connect_timeout : float, default=10.0
        Seconds the first connection (and the first sample) may take before :class:`LinkError`.
    request_timeout : float, default=2.0
        Seconds :meth:`close` waits for inputs still in flight.
    reconnect_delay, reconnect_max_delay : float, default=0.1, 1.0
        First and longest wait between reconnection attempts, s (doubling).
    keepalive : int, default=5
        MQTT keep-alive, s: a silent broker is noticed within about 1.5 times this.
    username, password : str, optional
        Credentials for the broker.
    client_id : str, optional
        MQTT client id (a random one when omitted).
    name : str, optional
        Plant name for logs (``plant`` when omitted).

    Raises
    ------
    DataError
        On a bad broker URL, topic, or timing value.

    Attributes
    ----------
    outages : list of Outage
        Link and stale-data outages, oldest first.
    counters : dict of str to int
        ``samples``, ``dropouts``, ``stale``, ``link_down``, ``late``,
        ``out_of_order``, ``duplicates``, ``rejected_writes``, ``failed_writes``,
        ``reconnects`` (as :class:`~.opcua.OPCUAPlant`).

    See Also
    --------
    OPCUAPlant : The OPC UA link, with the same ``meta`` and fault behaviour.
    kautztwin.service.MQTTPlantServer : The simulated plant on the other side.

    Notes
    -----
    ``meta`` of each reading as :class:`~.opcua.OPCUAPlant`: ``k``, ``u`` (the
    input the plant applied over the period: the sample's ``u`` when the
    plant publishes it, else the last input the broker took and the plant did
    not reject), ``u_applied`` (the sample's ``u``, NaN without), ``u_requested``,
    ``write`` (``'ok'``, ``'rejected: <reason>'`` when the plant's ack says so
    before the reading, ``'failed: <error>'``, ``'not sent: link down'``; during
    an outage ``'not sent: holding (...)'`` or ``'sent: safe input <u>'``),
    ``input_delay`` (samples, see :mod:`~.link`),
    ``link``, ``dropout``, ``stale``, ``late`` (the sample was taken before the
    input was published or, with a plant that acknowledges inputs, before its
    ack for this input arrived or the ack's ``k``),
    ``out_of_order``, ``status``
    (``'Good'``, ``'BadValue'``, ``'BadDecoding'``), ``source_time``,
    ``latency`` and ``queued``.  Reading times are the payload's ``t`` minus
    ``t`` at :meth:`reset` (``(ts - ts_at_reset) * speed`` without ``t``).

    Examples
    --------
    >>> from kautztwin.twin.physical import MQTTPlant
    >>> plant = MQTTPlant("mqtt://127.0.0.1:1883", plant="hydraulic")  # doctest: +SKIP
    >>> r0 = plant.reset(); r1 = plant.step(0.55)  # doctest: +SKIP
    """

    def __init__(
        self,
        broker: str = DEFAULT_BROKER,
        *,
        plant: str = "hydraulic",
        topic: str | None = None,
        topics: Mapping[str, str] | None = None,
        dt: float | None = None,
        input_limits: tuple[float, float] | None = None,
        speed: float | None = None,
        stale_periods: float = 3.0,
        on_outage: str = "hold",
        safe_input: float | None = None,
        connect_timeout: float = 10.0,
        request_timeout: float = 2.0,
        reconnect_delay: float = 0.1,
        reconnect_max_delay: float = 1.0,
        keepalive: int = 5,
        username: str | None = None,
        password: str | None = None,
        client_id: str | None = None,
        name: str | None = None,
    ) -> None:
        self.broker = str(broker).strip()
        self._host, self._port = parse_broker(self.broker)
        self.name = str(name if name is not None else plant)
        spec = default_topics(topic if topic is not None else f"kautztwin/{plant}")
        for key, value in dict(topics or {}).items():
            if key not in _TOPIC_KEYS:
                raise DataError(
                    f"topics: unknown role {key!r}; use one of {', '.join(_TOPIC_KEYS)}")
            if not isinstance(value, str) or not value.strip() or "#" in value or "+" in value:
                raise DataError(f"topics.{key} must be a topic without wildcards, got {value!r}")
            spec[key] = value.strip()
        self.topics = spec
        self._init_config(dt, speed, input_limits, stale_periods)
        self._init_link(connect_timeout, request_timeout, reconnect_delay, reconnect_max_delay)
        self._init_policy(on_outage, safe_input)
        self.keepalive = max(1, int(keepalive))
        self.username, self.password, self.client_id = username, password, client_id
        self.plant_status = ""
        self._meta: dict[str, Any] | None = None
        self._acks: dict[int, tuple[str, float]] = {}
        self._mine: dict[int, float] = {}  # inputs published, awaiting the plant's ack
        self._write_seq = itertools.count(1)
        self._origin_t = math.nan
        self._published = math.nan  # the input of this step's publish (NaN: none)

    # ------------------------------------------------------------------ configuration
    def _need_config(self) -> None:
        self.connect()
        deadline = time.monotonic() + self.connect_timeout
        with self._cond:
            while self._meta is None or self._missing_from_meta():
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = self._missing_from_meta() or "meta"
                    raise DataError(f"{self.name}: give {missing} (no retained "
                                    f"{self.topics['meta']!r} with it within "
                                    f"{self.connect_timeout:g} s)")
                self._cond.wait(left)

    def _missing_from_meta(self) -> str:
        """Read dt, speed and limits from the meta message; name what is still missing."""
        meta = self._meta or {}
        if self._dt is None and "dt" in meta:
            self._dt = _positive(meta["dt"], "dt read from the meta topic")
        if self._speed is None and "speed" in meta:
            self._speed = _positive(meta["speed"], "speed read from the meta topic")
        if self._limits is None and isinstance(meta.get("u"), Mapping):
            lo, hi = _number(meta["u"].get("low")), _number(meta["u"].get("high"))
            if lo < hi:
                self._limits = (lo, hi)
        missing = [n for n, v in (("dt", self._dt), ("input_limits", self._limits)) if v is None]
        return " and ".join(missing)

    # ------------------------------------------------------------------ connection
    def connect(self) -> MQTTPlant:
        """Start the background client and wait for the first connection.

        Returns
        -------
        MQTTPlant
            ``self``.

        Raises
        ------
        LinkError
            If the broker cannot be reached (or refuses the session) within ``connect_timeout``.
        """
        if self._client is not None and self._connections > 0:
            return self
        if self._client is None:
            mqtt = _import_paho()
            client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id or "",
                                 clean_session=True)
            if self.username is not None:
                client.username_pw_set(self.username, self.password)
            client.reconnect_delay_set(self.reconnect_delay, self.reconnect_max_delay)
            client.on_connect = self._on_connect
            client.on_disconnect = self._on_disconnect
            client.on_message = self._on_message
            client.on_connect_fail = self._on_connect_fail
            self._client = client
            client.connect_async(self._host, self._port, keepalive=self.keepalive)
            client.loop_start()
        deadline = time.monotonic() + self.connect_timeout
        with self._cond:
            while self._connections == 0 and self._fatal is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
        if self._fatal is not None or self._connections == 0:
            fatal = self._fatal
            self.close()
            if fatal is not None:
                raise fatal
            detail = f": {self._last_error}" if self._last_error else ""
            raise LinkError(
                f"cannot connect to {self.broker} within {self.connect_timeout:g} s{detail}"
            )
        return self

    def _on_connect_fail(self, client: Any, userdata: Any) -> None:
        self._last_error = "connection refused"

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any,
                    props: Any = None) -> None:
        if reason.is_failure:
            self._last_error = str(reason)
            if self._connections == 0 and reason.value in (0x86, 0x87, 0x04, 0x05, 134, 135):
                with self._cond:
                    self._fatal = LinkError(f"{self.broker} refused the session: {reason}")
                    self._cond.notify_all()
            return
        for key in ("y", "ack", "meta", "status"):  # made again on every connection
            client.subscribe(self.topics[key], qos=1)
        with self._cond:
            self._mark_up()
        _logger.info("%s: connected to %s", self.name, self.broker)

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason: Any,
                       props: Any = None) -> None:
        with self._cond:
            was_up, self._link_up = self._link_up, False
            self._cond.notify_all()
            if not was_up or self._closing:
                return
            self._mark_down(f"connection lost: {reason}")
        _logger.warning("%s: link to %s down: %s", self.name, self.broker, reason)

    _closing = False

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        topic = msg.topic
        if topic == self.topics["y"]:
            self._on_sample(msg.payload)
            return
        try:
            data = json.loads(msg.payload)
        except (ValueError, UnicodeDecodeError):
            data = None
        with self._cond:
            if topic == self.topics["meta"] and isinstance(data, dict):
                self._meta = data
            elif topic == self.topics["status"]:
                text = data if isinstance(data, str) else msg.payload.decode("utf-8", "replace")
                self.plant_status = text.strip()
            elif topic == self.topics["ack"] and isinstance(data, dict):
                seq = data.get("seq")
                if isinstance(seq, int):
                    status = str(data.get("status", "ok"))
                    self._acks[seq] = (status, _number(data.get("k")))
                    if len(self._acks) > 1000:
                        self._acks.pop(next(iter(self._acks)))
                    if self._mine.pop(seq, None) is not None and status.startswith("rejected"):
                        self.counters["rejected_writes"] += 1  # counted when the verdict comes
            self._cond.notify_all()

    def _on_sample(self, payload: bytes) -> None:
        now_wall, now = time.time(), time.monotonic()
        ts, y, t_src, status, k_src, u = decode_sample(payload, now_wall)
        self._queue(_Sample(ts, next(self._seq), y, status, t_src, k_src, now, now_wall - ts, u),
                    now)

    # ------------------------------------------------------------------ readings
    def _plant_time(self, s: _Sample) -> float:
        assert self._origin_ts is not None
        if math.isfinite(s.t_src) and math.isfinite(self._origin_t):
            return s.t_src - self._origin_t
        return self._grid_time(s.ts)

    def reset(self) -> Reading:
        """Connect (if needed) and return the newest sample as the reading at ``t = 0``.

        The remote plant is not reset: the reading clock starts at its current sample.

        Returns
        -------
        Reading

        Raises
        ------
        LinkError
            If the broker cannot be reached, or no sample arrives, within ``connect_timeout``.
        DataError
            If ``dt`` or the input limits are neither configured nor in the meta topic.
        """
        self.connect()
        _ = self.dt, self.input_limits, self.speed
        with self._cond:
            newest = self._start_clock(f"no sample on {self.topics['y']!r} from {self.broker}")
            self._origin_t = newest.t_src
            return self._real_reading(newest, 0, math.nan, "", None, None)

    def _real_reading(self, s: _Sample, dropped: int, u_req: float, write: str,
                      written_at: float | None, seq: int | None) -> Reading:
        late = written_at is not None and s.arrival < written_at
        verdict, from_k = self._acks.get(seq, ("ok", math.nan)) if seq is not None else ("", 0.0)
        if seq is not None and self._acks and seq not in self._acks:
            late = True  # a plant that acknowledges inputs has not taken this one yet
        late = late or s.k_src < from_k  # the plant took the input after this sample
        if verdict.startswith("rejected"):
            write = verdict
        elif seq is not None and math.isfinite(self._published):
            self._u = self._published
        return self._sample_reading(s, self._plant_time(s), dropped, u_req, write, late,
                                    s.u_applied)

    def _write(self, value: float, seq: int) -> str:
        client = self._client
        if client is None or not self._link_up:
            return "not sent: link down"
        payload = json.dumps({"u": value, "ts": time.time(), "seq": seq})
        with self._cond:
            self._mine[seq] = value
            if len(self._mine) > 1000:
                self._mine.pop(next(iter(self._mine)))
        info = client.publish(self.topics["u"], payload, qos=1)  # not waited for: no round trip
        if info.rc != 0:
            return f"failed: {_import_paho().error_string(info.rc)}"
        return "ok"

    def step(self, u: float | None) -> Reading:
        """Publish ``u``, wait for the next output sample and return it.

        Never raises on link faults: while the broker is unreachable, or no new
        sample arrives within ``stale_periods`` periods, it returns a NaN reading
        flagged in ``meta`` (one per sample period).

        Parameters
        ----------
        u : float
            Input, inside :attr:`input_limits`.

        Returns
        -------
        Reading

        Raises
        ------
        DataError
            If ``u`` is not a finite number inside :attr:`input_limits` (nothing is published).
        """
        value = self._check_input(u, "published")
        seq = next(self._write_seq)
        written_at = time.monotonic()
        self._published = math.nan

        def send(target: float) -> str:
            result = self._write(target, seq)
            if result == "ok":
                self._published = target
            return result

        write = self._send_input(value, send)
        sent = seq if math.isfinite(self._published) else None
        return self._next_reading(value, write, lambda sample, dropped: self._real_reading(
            sample, dropped, value, write, written_at, sent),
            lambda sample: self._plant_time(sample))

    def _missing_reading(self, u_req: float, write: str, dropped: int, at: float) -> Reading:
        """A NaN reading: no sample in time (call with the lock held)."""
        if math.isfinite(self._published):
            self._u = self._published
        return super()._missing_reading(u_req, write, dropped, at)

    def close(self) -> None:
        """Disconnect and stop the background client (idempotent)."""
        client, self._client = self._client, None
        self._closing = True
        if client is not None:
            try:
                client.disconnect()
            finally:
                client.loop_stop()
        self._link_up = False
        self._connections = 0
        self._closing = False

    def __enter__(self) -> MQTTPlant:
        return self

    def __repr__(self) -> str:
        state = "up" if self._link_up else "down"
        return f"MQTTPlant({self.broker!r}, topic={self.topics['y']!r}, link {state})"
