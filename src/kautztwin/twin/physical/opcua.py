"""The twin's OPC UA link: a :class:`Plant` that is an OPC UA client.

:class:`OPCUAPlant` reads the plant output through a data-change subscription
and writes the input node; node ids and scaling come from a configuration
mapping whose defaults are the address space of
:class:`kautztwin.service.PlantServer` (a real PLC maps its own node ids).
The client runs in a background thread with its own asyncio loop, so the
synchronous twin loop calls :meth:`OPCUAPlant.step` as it calls any plant.

What real links do, and what the link does about it:

* the server goes away: :meth:`~OPCUAPlant.step` never raises; it returns a
  NaN reading with ``meta['link'] == 'down'`` once per sample period, records
  the outage in :attr:`~OPCUAPlant.outages`, and reconnects in the background
  with exponential backoff (the subscription is created again);
* stale data (no new sample within ``stale_periods`` sample periods, e.g. a
  frozen server): a NaN reading flagged ``stale`` and ``dropout`` per period
  instead of blocking, recorded as an outage of kind ``'stale'``;
* late and out-of-order samples: samples are returned in source-timestamp
  order; one older than a sample already returned is dropped and counted;
* a write the server rejects: reported in ``meta['write']``, the plant holds
  its previous input.  Writes do not wait for the server (one in flight, the
  newest input next); their status shows on a later reading;
* an input that reaches the plant late: the server's ``u_applied`` (same source
  timestamp as ``y``) is subscribed and becomes ``meta['u']`` /
  ``meta['u_applied']``, the input the plant really applied over the period;
* while the link is down or the data stale, the input follows ``on_outage``
  (``'hold'``: send nothing; ``'safe'``: send ``safe_input``).

Inputs outside :attr:`~OPCUAPlant.input_limits` are refused with a
:class:`~kautztwin.exceptions.DataError` before they go out.

The sample queue, the readings, stale detection, the outage log and the
counters are shared with :class:`~.mqtt.MQTTPlant` in :class:`~.link.SampleLink`.

Size: over 600 lines (the class over 400) because the OPC UA session (connect, resolve and
check the nodes, read the metadata, subscribe, reconnect with backoff, write with its status)
runs in its own thread and loop beside the synchronous Plant interface; about half of the
lines are documentation.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...exceptions import DataError
from .base import Reading
from .link import LinkError, Outage, SampleLink, _positive, split_url

__all__ = ["NAMESPACE_URI", "LinkError", "OPCUAPlant", "Outage", "parse_endpoint"]

_logger = logging.getLogger(__name__)

#: namespace URI of the plant objects of :class:`kautztwin.service.PlantServer`
NAMESPACE_URI = "urn:kautztwin:plant"


def parse_endpoint(url: str) -> tuple[str, int]:
    """Check an ``opc.tcp://HOST:PORT`` endpoint and split it.

    Parameters
    ----------
    url : str
        Endpoint URL; the port defaults to 4840, port 0 picks a free one
        when the server starts.

    Returns
    -------
    tuple
        ``(host, port)``.

    Raises
    ------
    DataError
        If the scheme is not ``opc.tcp``, the host is missing or the port is invalid.

    Examples
    --------
    >>> from kautztwin.twin.physical import parse_endpoint
    >>> parse_endpoint("opc.tcp://127.0.0.1:4841")
    ('127.0.0.1', 4841)
    """
    return split_url(url, "opc.tcp", "endpoint", default_port=4840, min_port=0,
                     shape="opc.tcp://HOST:PORT without a path")


_NODE_KEYS = ("u", "y", "u_applied", "dt", "speed", "status")
_OPTIONAL_NODES = ("u_applied", "dt", "speed", "status")
#: shortest default publishing interval, s: faster plants get their samples in batches
#: (measured at 500 samples/s: 2 ms gave a better fit than 5 ms batches, less input delay)
PUBLISH_FLOOR_S = 0.002
_APPLIED_KEEP = 4096  # u_applied values kept while their y sample is awaited
_IDENTITY_ERRORS = ("BadUserAccessDenied", "BadIdentityTokenRejected", "BadIdentityTokenInvalid",
                    "BadSecurityPolicyRejected", "BadCertificateUntrusted")
_VARIANTS_INT = ("SByte", "Byte", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64")


@dataclass(frozen=True, order=True)
class _Sample:
    ts: float  # source timestamp, POSIX s
    seq: int
    value: float  # engineering units (NaN when unusable)
    status: str
    good: bool
    arrival: float  # time.monotonic()
    latency: float  # arrival wall time - source timestamp, s


def _scale_pair(spec: Any, key: str) -> tuple[float, float]:
    if isinstance(spec, Mapping):
        unknown = set(spec) - {"scale", "offset"}
        if unknown:
            raise DataError(f"scaling.{key}: unknown key {sorted(unknown)[0]!r}; use scale, offset")
        scale, offset = spec.get("scale", 1.0), spec.get("offset", 0.0)
    elif isinstance(spec, tuple | list) and len(spec) == 2:
        scale, offset = spec
    else:
        raise DataError(
            f"scaling.{key} must be {{'scale': a, 'offset': b}} or (a, b), got {spec!r}"
        )
    try:
        scale, offset = float(scale), float(offset)
    except (TypeError, ValueError):
        raise DataError(f"scaling.{key}: scale and offset must be numbers") from None
    if not (math.isfinite(scale) and scale != 0 and math.isfinite(offset)):
        raise DataError(f"scaling.{key}: scale must be finite and non-zero, offset finite")
    return scale, offset


class OPCUAPlant(SampleLink):
    """A plant behind an OPC UA server (a PLC, or :class:`kautztwin.service.PlantServer`).

    Parameters
    ----------
    endpoint : str
        Server URL, ``opc.tcp://HOST:PORT``.
    plant : str, default='hydraulic'
        Object name of the default node ids ``<plant>.u``, ``<plant>.y``...
    nodes : mapping, optional
        Node ids by role: ``'u'`` (input, written), ``'y'`` (output,
        subscribed), and the optional ``'u_applied'`` (the input the plant
        applied over the period of each ``y`` sample, same source timestamp:
        subscribed, it becomes ``meta['u']``), ``'dt'``, ``'speed'`` and ``'status'``.
        A value is a full OPC UA node id (``'ns=3;s=Line1.Speed'``,
        ``'nsu=urn:plc;i=1002'``) or a bare string id looked up in
        ``namespace``.  Roles left out take the defaults ``<plant>.<role>``.
    namespace : str, default=NAMESPACE_URI
        Namespace URI of bare string ids.
    scaling : mapping, optional
        ``{'u': {'scale': a, 'offset': b}, 'y': (a, b)}``: engineering value =
        ``raw * scale + offset`` (identity when omitted).
    dt : float, optional
        Sampling period, plant seconds; read from the ``dt`` node when omitted.
    input_limits : tuple of float, optional
        ``(low, high)`` in engineering units; from the input node's ``EURange``
        property when omitted.
    speed : float, optional
        Plant seconds per wall-clock second of the server's timestamps; read
        from the ``speed`` node when omitted (1.0 when the server has none: a
        real plant).
    stale_periods : float, default=3
        A sample period without a new sample this many times over makes the
        data stale (a flagged NaN reading instead of a wait).
    publishing_interval : float, optional
        Subscription publishing interval, s; ``min(period, 0.05)`` (at least
        2 ms) when omitted, ``period = dt / speed``: one notification per sample
        (a batch of samples per notification for a plant faster than 500 samples/s).
    on_outage : {'hold', 'safe'}, default='hold'
        Input while the link is down or the data stale: ``'hold'`` sends
        nothing (the plant holds the last input it accepted), ``'safe'`` sends
        ``safe_input`` (when the server can still be written to).
    safe_input : float, optional
        The input of ``on_outage='safe'``, engineering units.
    connect_timeout : float, default=10.0
        Seconds the first connection may take before :class:`LinkError`.
    request_timeout : float, default=2.0
        Seconds one OPC UA request (a write) may take.
    reconnect_delay, reconnect_max_delay : float, default=0.1, 1.0
        First and longest wait between reconnection attempts, s (doubling).
    username, password : str, optional
        User identity for the session (anonymous when omitted).
    security : str, optional
        asyncua security string ``'Policy,Mode,client_cert.pem,client_key.pem[,server_cert]'``
        (e.g. ``'Basic256Sha256,SignAndEncrypt,cert.pem,key.pem'``) when the
        server offers that policy.
    name : str, optional
        Plant name for logs (``plant`` when omitted).

    Raises
    ------
    DataError
        On an unknown node role, a malformed node id, invalid scaling or
        timing values.

    Attributes
    ----------
    outages : list of Outage
        Link and stale-data outages, oldest first.
    counters : dict of str to int
        ``samples`` (real readings returned), ``dropouts`` (NaN readings of
        any cause), ``stale``, ``link_down`` (readings while disconnected),
        ``late``, ``out_of_order`` (samples dropped: older than one returned),
        ``duplicates``, ``rejected_writes``, ``failed_writes``, ``reconnects``.

    See Also
    --------
    kautztwin.service.PlantServer : The simulated plant server with the default address space.

    Notes
    -----
    ``meta`` of each reading: ``k`` (reading index since :meth:`reset`),
    ``u`` (input applied over the period: the server's ``u_applied`` of the
    sample when it publishes one, else the last accepted write),
    ``u_requested``, ``write`` (writes do not wait for the server: the
    status of the last write completed since the previous reading, ``'ok'``,
    ``'rejected: <status>'``, ``'failed: <error>'``, or ``'pending'`` while
    none has; ``'not sent: link down'``; during an outage
    ``'not sent: holding (...)'`` or ``'sent: safe input <u>'``;
    ``'not sent: behind'`` when newer samples already wait (the caller is
    behind) and the input is the one sent last, within a sample period), ``link``
    (``'up'``/``'down'``), ``dropout``, ``stale``, ``late`` (the sample was
    taken before this step's input was written: it does not reflect it),
    ``out_of_order`` (samples dropped since the previous reading), ``status``
    (the sample's OPC UA status name), ``source_time`` (POSIX s),
    ``latency`` (arrival minus source time, s: clocks must agree) and
    ``queued`` (newer samples waiting: the caller is behind).

    The reading time is ``(source_time - source_time_at_reset) * speed``,
    snapped to the ``dt`` grid when within 10 % of it.  :meth:`reset` does not
    reset the remote plant: it starts the reading clock at the current sample.

    Examples
    --------
    >>> from kautztwin.twin.physical import OPCUAPlant
    >>> plant = OPCUAPlant("opc.tcp://127.0.0.1:4840", plant="hydraulic")  # doctest: +SKIP
    >>> r0 = plant.reset(); r1 = plant.step(0.55)  # doctest: +SKIP
    """

    def __init__(
        self,
        endpoint: str,
        *,
        plant: str = "hydraulic",
        nodes: Mapping[str, str] | None = None,
        namespace: str = NAMESPACE_URI,
        scaling: Mapping[str, Any] | None = None,
        dt: float | None = None,
        input_limits: tuple[float, float] | None = None,
        speed: float | None = None,
        stale_periods: float = 3.0,
        publishing_interval: float | None = None,
        on_outage: str = "hold",
        safe_input: float | None = None,
        connect_timeout: float = 10.0,
        request_timeout: float = 2.0,
        reconnect_delay: float = 0.1,
        reconnect_max_delay: float = 1.0,
        username: str | None = None,
        password: str | None = None,
        security: str | None = None,
        name: str | None = None,
    ) -> None:

        self.endpoint = str(endpoint).strip()
        parse_endpoint(self.endpoint)
        self.object_name = str(plant)
        self.name = str(name if name is not None else plant)
        self.namespace = str(namespace)
        spec = {k: f"{self.object_name}.{k}" for k in _NODE_KEYS}
        self._explicit: set[str] = set()
        for key, value in dict(nodes or {}).items():
            if key not in _NODE_KEYS:
                raise DataError(f"nodes: unknown role {key!r}; use one of {', '.join(_NODE_KEYS)}")
            if not isinstance(value, str) or not value.strip():
                raise DataError(f"nodes.{key} must be a node id string, got {value!r}")
            spec[key] = value.strip()
            self._explicit.add(key)
        self.nodes = spec
        self._parsed = {k: self._parse_node_id(k, v) for k, v in spec.items()}
        scaling = dict(scaling or {})
        for key in scaling:
            if key not in ("u", "y"):
                raise DataError(f"scaling: unknown variable {key!r}; use u or y")
        self._scale = {k: _scale_pair(scaling.get(k, (1.0, 0.0)), k) for k in ("u", "y")}
        self._init_config(dt, speed, input_limits, stale_periods)
        self._pub = None if publishing_interval is None else _positive(
            publishing_interval, "publishing_interval")
        self._init_link(connect_timeout, request_timeout, reconnect_delay, reconnect_max_delay)
        self._init_policy(on_outage, safe_input)
        self._applied: dict[float, float] = {}  # source timestamp -> u_applied
        self._ua_nodeid: Any = None
        self._w_busy = False  # a write in flight
        self._w_next: float | None = None  # the newest input waiting for it (coalesced)
        self._w_result = ""  # status of the last completed write
        self._w_done = 0  # writes completed
        self._w_seen = 0  # writes completed when the last reading was made
        self._w_sent = -math.inf  # monotonic time of the last input sent
        self.username, self.password, self.security = username, password, security
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closing: asyncio.Event | None = None
        self._ready = threading.Event()
        self._u_node: Any = None
        self._u_variant: Any = None

    # ------------------------------------------------------------------ configuration
    def _parse_node_id(self, key: str, text: str) -> Any:
        from asyncua import ua

        if "=" not in text:
            return ("bare", text)
        try:
            nid = ua.NodeId.from_string(text)
        except Exception as exc:
            raise DataError(
                f"nodes.{key}: {text!r} is not an OPC UA node id "
                f"(write e.g. 'ns=2;s=plant.y', 'nsu=URI;i=1001' or a bare string id): "
                f"{' '.join(str(exc).split())}"
            ) from None
        return ("id", nid)

    # ------------------------------------------------------------------ connection
    def connect(self) -> OPCUAPlant:
        """Start the background link and wait for the first connection.

        Returns
        -------
        OPCUAPlant
            ``self``.

        Raises
        ------
        LinkError
            If the server cannot be reached within ``connect_timeout``.
        DataError
            If a node id does not exist on the server, or ``dt`` or the input
            limits are neither configured nor readable.
        """
        if self._thread is not None and self._thread.is_alive():
            if self._ready.is_set() and self._fatal is None:
                return self
        else:
            self._ready.clear()
            self._fatal = None
            self._thread = threading.Thread(target=self._thread_main, daemon=True,
                                            name=f"kautztwin-opcua-{self.name}")
            self._thread.start()
        if not self._ready.wait(self.connect_timeout):
            self.close()
            detail = f": {self._last_error}" if self._last_error else ""
            raise LinkError(
                f"cannot connect to {self.endpoint} within {self.connect_timeout:g} s{detail}"
            )
        if self._fatal is not None:
            fatal = self._fatal
            self.close()
            raise fatal
        return self

    def _thread_main(self) -> None:
        try:
            asyncio.run(self._supervise())
        except BaseException as exc:  # pragma: no cover - a crash of the link thread
            _logger.exception("OPC UA link thread crashed")
            self._fatal = self._fatal or exc
            self._ready.set()
        finally:
            self._link_up = False
            self._loop = None

    def _make_client(self) -> Any:
        from asyncua import Client

        client = Client(self.endpoint, timeout=self.request_timeout, watchdog_intervall=2.0)
        if self.username is not None:
            client.set_user(self.username)
        if self.password is not None:
            client.set_password(self.password)
        return client

    async def _supervise(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._closing = asyncio.Event()
        delay = self.reconnect_delay
        while not self._closing.is_set():
            client = None
            up = False
            reason = "connection lost"
            try:
                client = self._make_client()
                if self.security:
                    try:
                        await client.set_security_string(self.security)
                    except Exception as exc:
                        raise DataError(
                            f"security {self.security!r}: {' '.join(str(exc).split()) or exc!r}"
                            " (write 'Policy,Mode,client_cert,client_key[,server_cert]')"
                        ) from None
                budget = max(self.connect_timeout, 2 * self.request_timeout)
                await asyncio.wait_for(client.connect(), budget)
                await self._setup(client)
                lost = asyncio.Event()

                async def on_lost(exc: Exception, lost: asyncio.Event = lost) -> None:
                    lost.set()

                client.connection_lost_callback = on_lost
                self._on_up(client)
                up = True
                delay = self.reconnect_delay
                while not (lost.is_set() or self._closing.is_set()):
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(lost.wait(), 0.2)
                    if client.uaclient.state.name not in ("CONNECTED",):
                        reason = f"connection lost ({client.uaclient.state.value})"
                        break
            except DataError as exc:  # a configuration error: no retry before the first link
                if self._connections == 0:
                    self._fatal = exc
                    self._ready.set()
                    return
                self._last_error = str(exc)
                reason = f"connection lost: {exc}"
            except Exception as exc:
                self._last_error = " ".join(str(exc).split()) or type(exc).__name__
                reason = f"connection lost: {self._last_error}"
                if self._connections == 0 and type(exc).__name__ in _IDENTITY_ERRORS:
                    self._fatal = LinkError(
                        f"{self.endpoint} refused the session: {self._last_error}")
                    self._ready.set()
                    return
                if self._connections == 0 and "No matching endpoints" in self._last_error:
                    wanted = ",".join(self.security.split(",")[:2]) if self.security else "None"
                    self._fatal = LinkError(
                        f"{self.endpoint} offers no endpoint with security {wanted}: "
                        f"{self._last_error}")
                    self._ready.set()
                    return
            finally:
                if up:
                    self._on_down(None if self._closing.is_set() else reason)
                if client is not None:
                    client.connection_lost_callback = None
                    with contextlib.suppress(Exception):
                        await asyncio.wait_for(client.disconnect(), 1.0)
            if self._closing.is_set():
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._closing.wait(), delay)
            delay = min(2 * delay, self.reconnect_max_delay)

    async def _node(self, client: Any, key: str) -> Any:
        from asyncua import ua

        kind, value = self._parsed[key]
        if kind == "bare":
            try:
                idx = await client.get_namespace_index(self.namespace)
            except Exception:
                raise DataError(
                    f"nodes.{key}: namespace {self.namespace!r} is not on {self.endpoint}"
                ) from None
            nid = ua.NodeId(value, idx)
        elif isinstance(value, ua.ExpandedNodeId) and value.NamespaceUri:
            try:
                idx = await client.get_namespace_index(value.NamespaceUri)
            except Exception:
                raise DataError(
                    f"nodes.{key}: namespace {value.NamespaceUri!r} is not on {self.endpoint}"
                ) from None
            nid = ua.NodeId(value.Identifier, idx, value.NodeIdType)
        else:
            nid = value
        return client.get_node(nid)

    async def _exists(self, node: Any) -> bool:
        from asyncua import ua

        try:
            await node.read_attribute(ua.AttributeIds.NodeClass)
        except ua.uaerrors.BadNodeIdUnknown:
            return False
        return True

    async def _setup(self, client: Any) -> None:
        """Resolve the nodes, read the metadata (first time) and subscribe to the output."""
        from asyncua import ua

        nodes = {}
        for key in _NODE_KEYS:
            node = await self._node(client, key)
            if not await self._exists(node):
                if key in _OPTIONAL_NODES and key not in self._explicit:
                    continue
                raise DataError(
                    f"OPC UA node {self.nodes[key]!r} ({key}) does not exist on {self.endpoint}"
                )
            nodes[key] = node
        u_node, y_node = nodes["u"], nodes["y"]
        self._u_variant = await u_node.read_data_type_as_variant_type()
        if self._dt is None:
            if "dt" not in nodes:
                raise DataError(
                    f"{self.name}: give dt (the server has no {self.nodes['dt']!r} node)"
                )
            self._dt = _positive(await nodes["dt"].read_value(), "dt read from the server")
        if self._speed is None:
            self._speed = 1.0
            if "speed" in nodes:
                self._speed = _positive(await nodes["speed"].read_value(),
                                        "speed read from the server")
        if self._limits is None:
            rng = None
            for prop in await u_node.get_properties():
                if (await prop.read_browse_name()).Name == "EURange":
                    rng = await prop.read_value()
            if rng is None:
                raise DataError(
                    f"{self.name}: give input_limits (the input node {self.nodes['u']!r} has no "
                    "EURange property)"
                )
            a, b = (self._eng("u", float(rng.Low)), self._eng("u", float(rng.High)))
            self._limits = (min(a, b), max(a, b))
        period = self._dt / self._speed
        pub = self._pub if self._pub is not None else max(PUBLISH_FLOOR_S, min(period, 0.05))
        sub = await client.create_subscription(pub * 1000.0, self)
        watched = [("u_applied", nodes["u_applied"])] if "u_applied" in nodes else []
        watched.append(("y", y_node))  # y last: its u_applied (same source time) comes first
        requests = []
        for handle, (_, node) in enumerate(watched, start=1):
            rv = ua.ReadValueId(NodeId=node.nodeid, AttributeId=ua.AttributeIds.Value)
            params = ua.MonitoringParameters(
                ClientHandle=handle, SamplingInterval=0.0, QueueSize=1000, DiscardOldest=True,
                Filter=ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp),
            )
            requests.append(ua.MonitoredItemCreateRequest(
                ItemToMonitor=rv, MonitoringMode=ua.MonitoringMode.Reporting,
                RequestedParameters=params))
        self._ua_nodeid = nodes["u_applied"].nodeid if "u_applied" in nodes else None
        for (key, _), result in zip(watched, await sub.create_monitored_items(requests),
                                    strict=True):
            if isinstance(result, ua.StatusCode):
                raise DataError(f"cannot subscribe to {self.nodes[key]!r}: {result}")
        self._u_node = u_node

    def _eng(self, key: str, raw: float) -> float:
        scale, offset = self._scale[key]
        return raw * scale + offset

    def _on_up(self, client: Any) -> None:
        with self._cond:
            self._client = client
            self._mark_up()
        self._ready.set()
        _logger.info("%s: connected to %s", self.name, self.endpoint)

    def _on_down(self, reason: str | None) -> None:
        with self._cond:
            self._link_up = False
            self._client = None
            self._u_node = None
            self._cond.notify_all()
            if reason is None:  # closed on purpose
                return
            self._mark_down(reason)
            self._cond.notify_all()
        _logger.warning("%s: link to %s down: %s", self.name, self.endpoint, reason)

    # ------------------------------------------------------------------ subscription handler
    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        """asyncua callback: queue one output sample (runs in the link thread).

        Parameters
        ----------
        node : asyncua.Node
            The output node.
        val : object
            The value.
        data : asyncua.common.subscription.DataChangeNotif
            The notification, with the full ``DataValue``.
        """
        from asyncua.ua import status_codes

        dv = data.monitored_item.Value
        now_wall, now = time.time(), time.monotonic()
        stamp = dv.SourceTimestamp or dv.ServerTimestamp
        ts = now_wall if stamp is None else stamp.timestamp()
        if self._ua_nodeid is not None and getattr(node, "nodeid", None) == self._ua_nodeid:
            try:  # the input applied over the period of the y sample with this source time
                applied = self._eng("u", float(dv.Value.Value))
            except (AttributeError, TypeError, ValueError):
                return
            with self._cond:
                self._applied[ts] = applied
                if len(self._applied) > _APPLIED_KEEP:
                    for old in sorted(self._applied)[:_APPLIED_KEEP // 2]:
                        del self._applied[old]
            return
        code = dv.StatusCode
        good = code is None or code.is_good()
        status = "Good" if code is None else status_codes.get_name_and_doc(code.value)[0]
        try:
            value = self._eng("y", float(dv.Value.Value))
        except (AttributeError, TypeError, ValueError):
            value = math.nan
        if not good:
            value = math.nan
        self._queue(_Sample(ts, next(self._seq), value, status, good, now, now_wall - ts), now)

    def status_change_notification(self, status: Any) -> None:
        """asyncua callback: a subscription status change (logged; the supervisor reconnects).

        Parameters
        ----------
        status : asyncua.ua.StatusChangeNotification
        """
        _logger.info("%s: subscription status %s", self.name, status)

    # ------------------------------------------------------------------ readings
    def reset(self) -> Reading:
        """Connect (if needed) and return the current sample as the reading at ``t = 0``.

        The remote plant is not reset: the reading clock starts at its current sample.

        Returns
        -------
        Reading

        Raises
        ------
        LinkError
            If the server cannot be reached within ``connect_timeout``.
        DataError
            On bad node ids or missing metadata (see :meth:`connect`).
        """
        self.connect()
        with self._cond:
            newest = self._start_clock(f"no sample of {self.nodes['y']!r} from {self.endpoint}")
            return self._real_reading(newest, 0, math.nan, "", written_at=None)

    def _real_reading(self, s: _Sample, dropped: int, u_req: float, write: str,
                      written_at: float | None) -> Reading:
        late = written_at is not None and s.arrival < written_at
        applied = self._applied.pop(s.ts, None)
        for old in [ts for ts in self._applied if ts < s.ts]:  # published with skipped samples
            del self._applied[old]
        if write == "sent":  # fire and forget: the status once it is known
            write = self._w_result if self._w_done > self._w_seen else "pending"
            self._w_seen = self._w_done
        return self._sample_reading(s, self._grid_time(s.ts), dropped, u_req, write, late,
                                    applied)

    def _write(self, raw: float) -> str:
        """Send ``raw`` without waiting for the server's answer (reported on a later reading).

        One write is in flight at a time; inputs given meanwhile are coalesced:
        the newest goes out when the write in flight completes.
        """
        loop = self._loop
        with self._cond:
            node, connection = self._u_node, self._connections
            if loop is None or node is None or not self._link_up:
                return "not sent: link down"
            if self._w_busy:
                self._w_next = raw
                return "sent"
            self._w_busy = True
        try:
            asyncio.run_coroutine_threadsafe(self._write_chain(node, raw, connection), loop)
        except RuntimeError as exc:  # the loop closed
            with self._cond:
                self._w_busy = False
            return f"failed: {' '.join(str(exc).split()) or type(exc).__name__}"
        return "sent"

    async def _write_chain(self, node: Any, raw: float, connection: int) -> None:
        """Write ``raw``, then each input coalesced meanwhile, recording each result.

        A write that completes after its connection went down is counted, but its
        status is not reported on a reading: the readings of the outage said "not
        sent: link down", and a reading after the reconnection must not carry the
        failure of a write sent before it. Coalesced inputs go out over the
        connection that is up when they are sent.
        """
        while True:
            try:
                result = await asyncio.wait_for(self._write_async(node, raw),
                                                self.request_timeout + 0.5)
            except Exception as exc:  # a timeout
                result = f"failed: {' '.join(str(exc).split()) or type(exc).__name__}"
            with self._cond:
                if self._link_up and connection == self._connections:
                    self._w_result = result
                    self._w_done += 1
                if result == "ok":
                    self._u = self._eng("u", raw)
                elif result.startswith("rejected"):
                    self.counters["rejected_writes"] += 1
                else:
                    self.counters["failed_writes"] += 1
                nxt, self._w_next = self._w_next, None
                if nxt is None or not self._link_up or self._u_node is None:
                    self._w_busy = False
                    return
                node, connection = self._u_node, self._connections
            raw = nxt

    async def _write_async(self, node: Any, raw: float) -> str:
        from asyncua import ua
        from asyncua.ua import status_codes

        vtype = self._u_variant or ua.VariantType.Double
        value: Any = int(round(raw)) if vtype.name in _VARIANTS_INT else raw
        try:
            await node.write_attribute(ua.AttributeIds.Value,
                                       ua.DataValue(ua.Variant(value, vtype)))
        except ua.UaStatusCodeError as exc:
            return f"rejected: {status_codes.get_name_and_doc(exc.code)[0]}"
        except Exception as exc:
            return f"failed: {' '.join(str(exc).split()) or type(exc).__name__}"
        return "ok"

    def step(self, u: float | None) -> Reading:
        """Write ``u``, wait for the next output sample and return it.

        Never raises on link faults: while the server is unreachable, or no
        new sample arrives within ``stale_periods`` periods, it returns a NaN
        reading flagged in ``meta`` (one per sample period).

        Parameters
        ----------
        u : float
            Input in engineering units, inside :attr:`input_limits`.

        Returns
        -------
        Reading

        Raises
        ------
        DataError
            If ``u`` is not a finite number inside :attr:`input_limits` (nothing is written).
        """
        value = self._check_input(u, "written")
        scale, offset = self._scale["u"]
        written_at = time.monotonic()

        def send(target: float) -> str:
            self._w_sent = written_at
            return self._write((target - offset) / scale)

        # newer samples wait and an input went out within the period: the caller is behind
        # (the same input is not sent again then)
        behind = bool(self._heap) and written_at - self._w_sent < self.dt / self.speed
        write = self._send_input(value, send, behind)
        return self._next_reading(value, write, lambda sample, dropped: self._real_reading(
            sample, dropped, value, write, written_at), lambda sample: self._grid_time(sample.ts))

    def read(self, node: str, timeout: float | None = None) -> tuple[Any, float]:
        """Read one node over the link's session: its value and source timestamp.

        Parameters
        ----------
        node : str
            A full OPC UA node id or a bare string id in ``namespace``.
        timeout : float, optional
            Seconds to wait (``request_timeout`` when omitted).

        Returns
        -------
        tuple
            ``(value, source_time)``, the time in POSIX seconds (the server's
            timestamp when the value has no source timestamp).

        Raises
        ------
        LinkError
            If the link is down or the read does not answer in time.
        DataError
            If ``node`` is not a node id or the server refuses the read.
        """
        parsed = self._parse_node_id("read", str(node))
        loop, client = self._loop, self._client
        if loop is None or client is None or not self._link_up:
            raise LinkError(f"{self.name}: the link to {self.endpoint} is down")

        async def read() -> Any:
            from asyncua import ua

            kind, value = parsed
            if kind == "bare":
                value = ua.NodeId(value, await client.get_namespace_index(self.namespace))
            elif isinstance(value, ua.ExpandedNodeId) and value.NamespaceUri:
                idx = await client.get_namespace_index(value.NamespaceUri)
                value = ua.NodeId(value.Identifier, idx, value.NodeIdType)
            return await client.get_node(value).read_data_value()

        wait = self.request_timeout if timeout is None else float(timeout)
        try:
            dv = asyncio.run_coroutine_threadsafe(read(), loop).result(wait)
        except TimeoutError:
            raise LinkError(f"{self.name}: reading {node!r} took over {wait:g} s") from None
        except Exception as exc:
            raise DataError(f"{self.name}: cannot read {node!r}: "
                            f"{' '.join(str(exc).split()) or type(exc).__name__}") from None
        stamp = dv.SourceTimestamp or dv.ServerTimestamp
        return dv.Value.Value, (math.nan if stamp is None else stamp.timestamp())

    def close(self) -> None:
        """Disconnect and stop the background link (idempotent)."""
        loop, closing, thread = self._loop, self._closing, self._thread
        if loop is not None and closing is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(closing.set)
        if thread is not None:
            thread.join(5.0)
        self._thread = None
        self._link_up = False

    def __enter__(self) -> OPCUAPlant:
        return self

    def __repr__(self) -> str:
        state = "up" if self._link_up else "down"
        return f"OPCUAPlant({self.endpoint!r}, plant={self.object_name!r}, link {state})"
