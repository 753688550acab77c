"""A simulated plant that publishes its samples and takes its input over MQTT.

:class:`MQTTPlantServer` is the MQTT counterpart of
:class:`~kautztwin.service.PlantServer`: the same stepping
(:class:`~kautztwin.service.pacing.PacedPlant`: every ``dt / speed``
wall-clock seconds, catch-up after a restart, freeze), with an MQTT client
(``paho-mqtt``) instead of an OPC UA server.  It needs a broker (mosquitto,
amqtt...).  Under the topic prefix (default ``kautztwin/<plant>``):

=====================  =========  =====================================================
topic                  direction  payload (JSON)
=====================  =========  =====================================================
``<prefix>/y``         out        ``{"k": 12, "t": 0.24, "y": 101.3, "u": 0.5,
                                  "ts": 1700000000.24}`` per sample (``y`` null
                                  when the plant gave no finite value)
``<prefix>/u``         in         ``{"u": 0.55, "ts": .., "seq": 7}`` (or a bare
                                  number); held from the next sample on
``<prefix>/u/ack``     out        ``{"seq": 7, "u": 0.55, "status": "ok", "k": 13}``
                                  (``k``: the first sample it shapes) or
                                  ``"status": "rejected: out of range"``
``<prefix>/meta``      out, kept  ``{"plant", "dt", "speed", "origin", "u": {"low",
                                  "high", "unit", "unece"}, "y": {...}}``
``<prefix>/status``    out, kept  ``"running"``, ``"frozen"``, ``"catching-up"``,
                                  ``"stopped"``, ``"fault: ..."``; ``"offline"``
                                  (the will) when the client vanishes
=====================  =========  =====================================================

``ts`` is the sample's source time: its plant time mapped to the wall clock
(``origin + t / speed``).  Inputs outside the input range, or not finite
numbers, are rejected (acknowledged as such) and never reach the plant.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import threading
import time
from typing import TYPE_CHECKING, Any

from ..exceptions import KautzTwinError
from ..twin.physical.mqtt import DEFAULT_BROKER, default_topics, parse_broker
from .pacing import Channel, PacedPlant, ServedSample

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ..twin import Plant

__all__ = ["MQTTPlantServer"]

_logger = logging.getLogger(__name__)


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _channel_json(channel: Channel) -> dict[str, Any]:
    return {"low": _finite_or_none(channel.low), "high": _finite_or_none(channel.high),
            "unit": channel.unit, "unece": channel.unece, "description": channel.description}


class MQTTPlantServer(PacedPlant):
    """Serve a simulated plant over MQTT in real or scaled time.

    Parameters
    ----------
    plant : Plant
        The plant (on a simulated clock: the server does the pacing).  It is
        reset on the first :meth:`start`.
    broker : str, default='mqtt://127.0.0.1:1883'
        Broker URL, ``mqtt://HOST:PORT``.
    speed : float, default=1.0
        Plant seconds per wall-clock second.
    topic : str, optional
        Topic prefix; ``kautztwin/<object_name>`` when omitted.
    object_name : str, optional
        Plant name in the default prefix; ``plant.name`` when omitted.
    input_channel, output_channel : Channel, optional
        Units and ranges (:func:`~kautztwin.service.default_channels` when omitted);
        inputs outside the input range are rejected.
    initial_input : float, optional
        Input before any is received (see :class:`~kautztwin.service.pacing.PacedPlant`).
    qos : {0, 1}, default=1
        QoS of the samples.
    connect_timeout : float, default=10.0
        Seconds :meth:`start` waits for the broker.
    reconnect_delay, reconnect_max_delay : float, default=0.1, 1.0
        First and longest wait between reconnection attempts, s (doubling).
    keepalive : int, default=5
        MQTT keep-alive, s.
    username, password : str, optional
        Credentials for the broker.
    history : int, default=100000
        How many samples :attr:`history` keeps.

    Raises
    ------
    DataError
        On an invalid broker URL, topic, speed or channel.

    Attributes
    ----------
    history : collections.deque of ServedSample
        The samples the plant produced; ``published`` is False while frozen,
        stopped, catching up or disconnected from the broker.
    rejected : list of tuple
        ``(payload, reason)`` of every input refused (a test hook).

    See Also
    --------
    kautztwin.twin.physical.MQTTPlant : The client side (the twin's MQTT link).
    PlantServer : The same plant behind an OPC UA server.

    Notes
    -----
    Fault hooks for tests: :meth:`freeze` stops publishing while the plant runs
    on; :meth:`stop` then :meth:`start` takes the plant off the broker and back
    (it catches up with the wall clock silently, holding its input).  While the
    broker is away the plant keeps running; its samples are not published.

    Examples
    --------
    >>> from kautztwin.service import MQTTPlantServer
    >>> from kautztwin.twin import HydraulicPlant
    >>> with MQTTPlantServer(HydraulicPlant(), broker="mqtt://127.0.0.1:1883",
    ...                      speed=5) as server:  # doctest: +SKIP
    ...     print(server.topics["y"])
    """

    def __init__(
        self,
        plant: Plant,
        *,
        broker: str = DEFAULT_BROKER,
        speed: float = 1.0,
        topic: str | None = None,
        object_name: str | None = None,
        input_channel: Channel | None = None,
        output_channel: Channel | None = None,
        initial_input: float | None = None,
        qos: int = 1,
        connect_timeout: float = 10.0,
        reconnect_delay: float = 0.1,
        reconnect_max_delay: float = 1.0,
        keepalive: int = 5,
        username: str | None = None,
        password: str | None = None,
        history: int = 100_000,
    ) -> None:
        self.broker = str(broker).strip()
        self._host, self._port = parse_broker(self.broker)
        super().__init__(plant, speed=speed, object_name=object_name,
                         input_channel=input_channel, output_channel=output_channel,
                         initial_input=initial_input, history=history)
        self.topics = default_topics(topic if topic is not None
                                     else f"kautztwin/{self.object_name}")
        self.qos = 1 if qos else 0
        self.connect_timeout = float(connect_timeout)
        self.reconnect_delay = float(reconnect_delay)
        self.reconnect_max_delay = max(self.reconnect_delay, float(reconnect_max_delay))
        self.keepalive = max(1, int(keepalive))
        self.username, self.password = username, password
        self.rejected: list[tuple[str, str]] = []
        self._client: Any = None
        self._connected = threading.Event()
        self._refused = ""
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------------ properties
    @property
    def running(self) -> bool:
        """Whether the stepping thread is up."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def connected(self) -> bool:
        """Whether the client is connected to the broker now."""
        return self._connected.is_set()

    # ------------------------------------------------------------------ control
    def start(self) -> MQTTPlantServer:
        """Connect to the broker (first time) and start (or restart) stepping.

        Returns
        -------
        MQTTPlantServer
            ``self``.

        Raises
        ------
        KautzTwinError
            If the broker cannot be reached (or refuses the client) within ``connect_timeout``.
        """
        if self.running:
            return self
        if self._client is None:
            self._client = self._make_client()
            self._client.connect_async(self._host, self._port, keepalive=self.keepalive)
            self._client.loop_start()
        if not self._connected.wait(self.connect_timeout) or self._refused:
            reason = self._refused or "no answer"
            self._drop_client()
            raise KautzTwinError(
                f"cannot connect to the MQTT broker {self.broker} within "
                f"{self.connect_timeout:g} s: {reason}"
            )
        ready = threading.Event()
        self._thread = threading.Thread(target=self._thread_main, args=(ready,), daemon=True,
                                        name=f"kautztwin-mqtt-plant-{self.object_name}")
        self._thread.start()
        ready.wait(10.0)
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop stepping and leave the broker (the plant stops until the next :meth:`start`).

        Parameters
        ----------
        timeout : float, default=10.0
            Seconds to wait for the stepping thread.
        """
        thread, loop, event = self._thread, self._loop, self._stop_event
        if thread is not None:
            if loop is not None and event is not None:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(event.set)
            thread.join(timeout)
        self._thread = None
        self._set_status("stopped")
        self._drop_client()

    def close(self) -> None:
        """Stop and close the plant."""
        self.stop()
        self.plant.close()

    def __enter__(self) -> MQTTPlantServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped"
        return (f"MQTTPlantServer({self.object_name!r}, broker={self.broker!r}, "
                f"topic={self.topics['y']!r}, speed={self.speed:g}, {state})")

    # ------------------------------------------------------------------ MQTT client
    def _make_client(self) -> Any:
        from ..twin.physical.mqtt import _import_paho

        mqtt = _import_paho()
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, clean_session=True)
        if self.username is not None:
            client.username_pw_set(self.username, self.password)
        client.will_set(self.topics["status"], json.dumps("offline"), qos=1, retain=True)
        client.reconnect_delay_set(self.reconnect_delay, self.reconnect_max_delay)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.message_callback_add(self.topics["u"], self._on_input)
        self._refused = ""
        self._connected.clear()
        return client

    def _drop_client(self) -> None:
        client, self._client = self._client, None
        self._connected.clear()
        if client is None:
            return
        with contextlib.suppress(Exception):
            if client.is_connected():
                client.publish(self.topics["status"], json.dumps("offline"), qos=1,
                               retain=True).wait_for_publish(1.0)
            client.disconnect()
        client.loop_stop()

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any,
                    props: Any = None) -> None:
        if reason.is_failure:
            self._refused = str(reason)
            self._connected.set()  # wakes start(), which reports the refusal
            return
        client.subscribe(self.topics["u"], qos=1)
        self._publish_meta(client)
        client.publish(self.topics["status"], json.dumps(self._status), qos=1, retain=True)
        self._connected.set()
        _logger.info("plant %s connected to %s", self.object_name, self.broker)

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, reason: Any,
                       props: Any = None) -> None:
        self._connected.clear()
        _logger.warning("plant %s: broker %s lost: %s", self.object_name, self.broker, reason)

    def _publish_meta(self, client: Any) -> None:
        meta = {"plant": self.object_name, "dt": self.dt, "speed": self.speed,
                "origin": self.origin_time if self._k >= 0 else None,
                "u": _channel_json(self.input_channel), "y": _channel_json(self.output_channel)}
        client.publish(self.topics["meta"], json.dumps(meta), qos=1, retain=True)

    def _on_input(self, client: Any, userdata: Any, msg: Any) -> None:
        """paho callback: check an input and hold it from the next sample on."""
        text = msg.payload.decode("utf-8", "replace")
        seq = None
        try:
            data = json.loads(text)
        except ValueError:
            data = None
        if isinstance(data, dict):
            seq, value = data.get("seq"), data.get("u")
        else:
            value = data
        if isinstance(value, bool) or not isinstance(value, int | float):
            reason = "rejected: not a number"
        elif not self.input_channel.contains(float(value)):
            reason = "rejected: out of range"
        else:
            reason = "ok"
            self._u = float(value)
        if reason != "ok":
            self.rejected.append((text[:200], reason))
            _logger.warning("plant %s: input %s %s", self.object_name, text[:80], reason)
        ack = {"seq": seq, "u": value if reason == "ok" else None, "status": reason,
               "k": self._k + 1, "ts": time.time()}  # k: the first sample it shapes
        client.publish(self.topics["ack"], json.dumps(ack), qos=1)

    # ------------------------------------------------------------------ transport hooks
    async def _publish(self, sample: ServedSample) -> None:
        client = self._client
        payload = json.dumps({"k": sample.k, "t": sample.t, "y": _finite_or_none(sample.y),
                              "u": _finite_or_none(sample.u),
                              "ts": self._source_time(sample.t).timestamp()})
        ok = False
        if client is not None and self._connected.is_set():
            ok = client.publish(self.topics["y"], payload, qos=self.qos).rc == 0
        if not ok and self.history and self.history[-1] is sample:
            self.history[-1] = sample._replace(published=False)

    def _set_status(self, status: str) -> None:
        self._status = status
        client = self._client
        if client is not None and self._connected.is_set():
            client.publish(self.topics["status"], json.dumps(status), qos=1, retain=True)

    # ------------------------------------------------------------------ thread
    def _thread_main(self, ready: threading.Event) -> None:
        try:
            asyncio.run(self._run(ready))
        except BaseException:  # pragma: no cover - a crash after start-up
            _logger.exception("MQTT plant server crashed")
            self._status = "fault: crashed"
        finally:
            self._loop = None
            ready.set()

    async def _run(self, ready: threading.Event) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        first = self._k < 0
        self._begin_run()
        if first and self._client is not None:
            self._publish_meta(self._client)  # with the origin now known
        if self._last is not None:
            await self._publish(self._last)
        self._set_status("running")
        ready.set()
        if self.restarts:
            await self._catch_up()
        await self._tick_loop()
