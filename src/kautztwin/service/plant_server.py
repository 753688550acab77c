"""A simulated plant behind an OPC UA server: the stand-in for a PLC.

:class:`PlantServer` steps a :class:`~kautztwin.twin.Plant` every
``dt / speed`` wall-clock seconds with the last input a client wrote, and
publishes each output sample with a source timestamp (the plant time mapped to
the wall clock).  The server runs in a background thread with its own asyncio
loop, so synchronous code and tests drive it with :meth:`PlantServer.start` and
:meth:`PlantServer.stop` (or ``with PlantServer(...) as server:``).

Address space
-------------
One object per plant under ``Objects``, in the namespace :data:`NAMESPACE_URI`
(its index is whatever the server registers, usually 2); every node id is a
string id ``<plant>.<variable>`` (``<plant>`` is the plant's ``name``):

==================  ========  =====  ==========================================
node id (``s=``)    type      access  meaning
==================  ========  =====  ==========================================
``<plant>``         Object           the plant
``<plant>.u``       Double    RW     input held over the next period; a write
                                     outside ``EURange`` (or not finite) is
                                     rejected with ``BadOutOfRange``
``<plant>.y``       Double    R      output; source timestamp = sample time
``<plant>.u_applied`` Double  R      input applied over the period that ended
                                     at the last ``y`` sample
``<plant>.k``       Int64     R      sample counter (0 at the plant's reset)
``<plant>.t``       Double    R      plant time of the last sample, s
``<plant>.dt``      Double    R      sampling period, plant seconds
``<plant>.speed``   Double    R      plant seconds per wall-clock second
``<plant>.status``  String    R      ``starting``, ``running``, ``frozen``,
                                     ``catching-up`` or ``fault: <message>``
==================  ========  =====  ==========================================

``u``, ``y`` and ``u_applied`` carry the standard ``AnalogItemType``
properties ``EngineeringUnits`` (``EUInformation``, UNECE unit codes) and
``EURange`` (``Range``) as ``HasProperty`` children (node ids
``<plant>.y.EngineeringUnits``, ``<plant>.y.EURange``...).

The transport-independent stepping (pacing, catch-up after a restart, freeze) is
:class:`~kautztwin.service.pacing.PacedPlant`, shared with the MQTT plant server.

Size: :class:`PlantServer` is just over 400 lines because it builds the documented address
space, checks writes, and runs the server (users, certificate and security policies) in
its own thread and loop; about half of it is documentation.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import ipaddress
import logging
import math
import os
import socket
import threading
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..exceptions import DataError, KautzTwinError
from ..twin.physical.opcua import NAMESPACE_URI, parse_endpoint
from .pacing import Channel, PacedPlant, ServedSample, default_channels, unece_unit_id

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ..twin import Plant

__all__ = [
    "DEFAULT_ENDPOINT",
    "Channel",
    "PlantServer",
    "ServedSample",
    "default_channels",
    "unece_unit_id",
]

_logger = logging.getLogger(__name__)

#: namespace URI of the plant objects (its index is assigned by the server)
#: endpoint of ``kautztwin plant serve`` when none is given
DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840"
#: namespace of the UNECE unit codes in ``EUInformation`` (OPC UA Part 8)
UNECE_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"

_NUMERIC_VARIANTS = ("Boolean", "SByte", "Byte", "Int16", "UInt16", "Int32", "UInt32",
                     "Int64", "UInt64", "Float", "Double")


def _import_asyncua() -> Any:
    try:
        import asyncua
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the OPC UA plant server needs asyncua: pip install 'kautztwin[service]'"
        ) from exc
    return asyncua


def _security_policy_names() -> tuple[str, ...]:
    """Names of asyncua's security policy types (``'Basic256Sha256_SignAndEncrypt'``...)."""
    asyncua = _import_asyncua()
    return tuple(member.name for member in asyncua.ua.SecurityPolicyType)


def _format_endpoint(host: str, port: int) -> str:
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(host).version == 6:
            return f"opc.tcp://[{host}]:{port}"
    return f"opc.tcp://{host}:{port}"


def _free_port(host: str) -> int:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _check_bindable(host: str, port: int) -> None:
    """Raise a one-line OSError when ``host:port`` cannot be listened on."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise KautzTwinError(f"cannot resolve endpoint host {host!r}: {exc.strerror}") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as exc:
            raise KautzTwinError(
                f"cannot listen on {_format_endpoint(host, port)}: {exc.strerror or exc}"
            ) from None


class _Users:
    """asyncua user manager: username/password pairs, role ``User``."""

    def __init__(self, users: Mapping[str, str]) -> None:
        self._users = dict(users)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> Any:
        from asyncua.crypto.permission_rules import User, UserRole

        if username is not None and self._users.get(username) == password:
            return User(role=UserRole.User, name=username)
        return None


class PlantServer(PacedPlant):
    """Serve a simulated plant over OPC UA in real or scaled time.

    Every ``dt / speed`` wall-clock seconds the server steps the plant with
    the last value written to ``<plant>.u`` and publishes the new output on
    ``<plant>.y`` with its source timestamp (the wall-clock time that
    corresponds to the sample's plant time).  Writes outside the input range
    are rejected (status ``BadOutOfRange``) and never reach the plant.  The
    address space is described in :mod:`kautztwin.service.plant_server` and
    ``docs/service.md``.

    Parameters
    ----------
    plant : Plant
        The plant (on a simulated clock: the server does the pacing).  It is
        reset on the first :meth:`start`.
    endpoint : str, default='opc.tcp://127.0.0.1:4840'
        Where to listen; port 0 picks a free port (kept across restarts, see
        :attr:`endpoint`).
    speed : float, default=1.0
        Plant seconds per wall-clock second (10: ten times faster than real time).
    namespace : str, default=NAMESPACE_URI
        Namespace URI of the plant's nodes.
    object_name : str, optional
        Name of the plant object and prefix of its node ids; ``plant.name``
        when omitted.
    input_channel, output_channel : Channel, optional
        Units and ranges; :func:`default_channels` when omitted.  The input
        range may be narrower than the plant's input limits, not wider.
    initial_input : float, optional
        Value of ``<plant>.u`` before any write; the middle of the input range
        (the plant's ``initial_command`` for the hydraulic drive) when omitted.
    users : mapping of str to str, optional
        Username/password pairs; when given, anonymous sessions are refused.
    certificate, private_key : str or Path, optional
        The server's application certificate (PEM or DER) and its private key
        (PEM); with them the server offers only the secure ``security``
        policies (no unencrypted endpoint).
    security : sequence of str, default=('Basic256Sha256_SignAndEncrypt',)
        The policies offered with a certificate: ``'<Policy>_<Mode>'`` with
        ``Policy`` in ``Basic256Sha256``, ``Aes128Sha256RsaOaep``,
        ``Aes256Sha256RsaPss`` and ``Mode`` ``Sign`` or ``SignAndEncrypt``
        (asyncua's ``SecurityPolicyType`` names).
    history : int, default=100000
        How many :class:`ServedSample` records :attr:`history` keeps.
    start_timeout : float, default=60.0
        Seconds :meth:`start` waits for the server to listen.

    Raises
    ------
    DataError
        On an invalid endpoint, speed, channel or initial input.

    Attributes
    ----------
    history : collections.deque of ServedSample
        The samples the plant produced, newest last (a test hook).
    restarts : int
        How many times the server was started after a :meth:`stop`.

    See Also
    --------
    kautztwin.twin.physical.OPCUAPlant : The client side (the twin's OPC UA link).

    Notes
    -----
    Fault hooks for tests: :meth:`freeze` stops publishing while the plant
    keeps running (a frozen PLC); :meth:`stop` then :meth:`start` takes the
    server off the network and brings it back on the same port.  While the
    server is down the plant does not run; on restart it first catches up
    with the wall clock (holding the last input, publishing nothing), so the
    source timestamps stay the plant time mapped to the wall clock.

    Examples
    --------
    >>> from kautztwin.service import PlantServer
    >>> from kautztwin.twin import HydraulicPlant
    >>> with PlantServer(HydraulicPlant(), endpoint="opc.tcp://127.0.0.1:0",
    ...                  speed=5) as server:  # doctest: +SKIP
    ...     print(server.endpoint, server.node_ids["y"])
    """

    def __init__(
        self,
        plant: Plant,
        *,
        endpoint: str = DEFAULT_ENDPOINT,
        speed: float = 1.0,
        namespace: str = NAMESPACE_URI,
        object_name: str | None = None,
        input_channel: Channel | None = None,
        output_channel: Channel | None = None,
        initial_input: float | None = None,
        users: Mapping[str, str] | None = None,
        certificate: str | os.PathLike[str] | None = None,
        private_key: str | os.PathLike[str] | None = None,
        security: Sequence[str] = ("Basic256Sha256_SignAndEncrypt",),
        history: int = 100_000,
        start_timeout: float = 60.0,
    ) -> None:
        self._host, self._port = parse_endpoint(endpoint)
        if (certificate is None) != (private_key is None):
            raise DataError("give both certificate and private_key (or neither)")
        for path in (certificate, private_key):
            if path is not None and not Path(path).is_file():
                raise DataError(f"no such certificate or key file: {str(path)!r}")
        self.certificate = None if certificate is None else Path(certificate)
        self.private_key = None if private_key is None else Path(private_key)
        self.security = tuple(str(name) for name in security)
        names = _security_policy_names()
        bad = [name for name in self.security if name not in names or name == "NoSecurity"]
        if bad or not self.security:
            raise DataError(
                f"security: unknown policy {bad[0] if bad else '(none)'!r}; use one of "
                f"{', '.join(n for n in names if n != 'NoSecurity')}")
        super().__init__(plant, speed=speed, object_name=object_name,
                         input_channel=input_channel, output_channel=output_channel,
                         initial_input=initial_input, history=history)
        self.namespace = str(namespace)
        self.users = dict(users) if users else None
        self.start_timeout = float(start_timeout)
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ properties
    @property
    def endpoint(self) -> str:
        """The endpoint URL (with the actual port once a port 0 was resolved)."""
        return _format_endpoint(self._host, self._port)

    @property
    def port(self) -> int:
        """TCP port (0 until the first :meth:`start` when port 0 was asked for)."""
        return self._port

    @property
    def running(self) -> bool:
        """Whether the server thread is up."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def status(self) -> str:
        """Value of the status variable (``'stopped'`` while the server is down)."""
        return self._status

    @property
    def node_ids(self) -> dict[str, str]:
        """String node ids of the plant object and its variables (without the namespace).

        Returns
        -------
        dict
            Keys ``'object'``, ``'u'``, ``'y'``, ``'u_applied'``, ``'k'``, ``'t'``,
            ``'dt'``, ``'speed'``, ``'status'``.
        """
        p = self.object_name
        out = {"object": p}
        for v in ("u", "y", "u_applied", "k", "t", "dt", "speed", "status"):
            out[v] = f"{p}.{v}"
        return out

    # ------------------------------------------------------------------ control
    def start(self) -> PlantServer:
        """Start (or restart) the server thread and wait until it listens.

        Returns
        -------
        PlantServer
            ``self``.

        Raises
        ------
        KautzTwinError
            If the endpoint cannot be listened on (address not local, port busy)
            or the server does not come up within ``start_timeout``.
        """
        if self.running:
            return self
        if self._port == 0:
            self._port = _free_port(self._host)
        _check_bindable(self._host, self._port)
        ready = threading.Event()
        errors: list[BaseException] = []
        self._thread = threading.Thread(
            target=self._thread_main, args=(ready, errors), daemon=True,
            name=f"kautztwin-plant-server-{self.object_name}",
        )
        self._thread.start()
        if not ready.wait(self.start_timeout):
            self.stop()
            raise KautzTwinError(
                f"the OPC UA server on {self.endpoint} did not start in {self.start_timeout:g} s"
            )
        if errors:
            self._thread.join(5.0)
            self._thread = None
            exc = errors[0]
            if isinstance(exc, OSError):
                raise KautzTwinError(
                    f"cannot listen on {self.endpoint}: {exc.strerror or exc}"
                ) from None
            raise exc
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Take the server off the network (the plant stops until the next :meth:`start`).

        Parameters
        ----------
        timeout : float, default=10.0
            Seconds to wait for the server thread.
        """
        thread, loop, event = self._thread, self._loop, self._stop_event
        if thread is None:
            return
        if loop is not None and event is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(event.set)
        thread.join(timeout)
        self._thread = None
        self._status = "stopped"

    def close(self) -> None:
        """Stop the server and close the plant."""
        self.stop()
        self.plant.close()

    def __enter__(self) -> PlantServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped"
        return (f"PlantServer({self.object_name!r}, endpoint={self.endpoint!r}, "
                f"speed={self.speed:g}, {state})")

    # ------------------------------------------------------------------ thread
    def _thread_main(self, ready: threading.Event, errors: list[BaseException]) -> None:
        try:
            asyncio.run(self._serve(ready))
        except BaseException as exc:  # reported to start() or logged
            if not ready.is_set():
                errors.append(exc)
                ready.set()
            else:  # pragma: no cover - a crash after start-up
                _logger.exception("plant server crashed")
                self._status = f"fault: {exc}"
        finally:
            self._loop = None

    async def _serve(self, ready: threading.Event) -> None:
        asyncua = _import_asyncua()
        ua = asyncua.ua
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        kwargs: dict[str, Any] = {}
        if self.users:
            kwargs["user_manager"] = _Users(self.users)
        server = asyncua.Server(**kwargs)
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"kautztwin plant server ({self.object_name})")
        if self.certificate is not None and self.private_key is not None:
            await server.load_certificate(str(self.certificate))
            await server.load_private_key(str(self.private_key))
            server.set_security_policy([getattr(ua.SecurityPolicyType, name)
                                        for name in self.security])
        else:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        if self.users:
            server.set_identity_tokens([ua.UserNameIdentityToken])
        idx = await server.register_namespace(self.namespace)
        self._server = server
        self._ids = {key: ua.NodeId(sid, idx) for key, sid in self.node_ids.items()}
        await self._build(server, idx, ua)
        self._install_write_check(server, ua)
        self._begin_run()
        await self._publish_last()
        await server.start()
        try:
            self._set_status("running")
            ready.set()
            if self._k >= 0 and self.restarts:
                await self._catch_up()
            await self._tick_loop()
        finally:
            with contextlib.suppress(Exception):
                await server.stop()

    # ------------------------------------------------------------------ address space
    async def _build(self, server: Any, idx: int, ua: Any) -> None:
        ids = self._ids
        obj = await server.nodes.objects.add_object(ids["object"], ua.QualifiedName(
            self.object_name, idx))
        description = str(getattr(self.plant, "name", self.object_name))
        await obj.write_attribute(
            ua.AttributeIds.Description,
            ua.DataValue(ua.Variant(ua.LocalizedText(f"simulated plant {description!r}"),
                                    ua.VariantType.LocalizedText)),
        )

        async def analog(key: str, value: float, channel: Channel, writable: bool) -> Any:
            var = await obj.add_variable(ids[key], ua.QualifiedName(key, idx), float(value),
                                         ua.VariantType.Double)
            eu = ua.EUInformation(
                NamespaceUri=UNECE_NAMESPACE,
                UnitId=unece_unit_id(channel.unece) if channel.unece else -1,
                DisplayName=ua.LocalizedText(channel.unit),
                Description=ua.LocalizedText(channel.description),
            )
            await var.add_property(ua.NodeId(f"{ids[key].Identifier}.EngineeringUnits", idx),
                                   ua.QualifiedName("EngineeringUnits", 0), eu)
            await var.add_property(ua.NodeId(f"{ids[key].Identifier}.EURange", idx),
                                   ua.QualifiedName("EURange", 0),
                                   ua.Range(Low=channel.low, High=channel.high))
            if channel.description:
                await var.write_attribute(
                    ua.AttributeIds.Description,
                    ua.DataValue(ua.Variant(ua.LocalizedText(channel.description),
                                            ua.VariantType.LocalizedText)),
                )
            if writable:
                await var.set_writable(True)
            return var

        await analog("u", self._u, self.input_channel, True)
        await analog("y", math.nan, self.output_channel, False)
        await analog("u_applied", math.nan, self.input_channel, False)
        await obj.add_variable(ids["k"], ua.QualifiedName("k", idx), max(self._k, 0),
                               ua.VariantType.Int64)
        await obj.add_variable(ids["t"], ua.QualifiedName("t", idx), 0.0, ua.VariantType.Double)
        await obj.add_variable(ids["dt"], ua.QualifiedName("dt", idx), self.dt,
                               ua.VariantType.Double)
        await obj.add_variable(ids["speed"], ua.QualifiedName("speed", idx), self.speed,
                               ua.VariantType.Double)
        await obj.add_variable(ids["status"], ua.QualifiedName("status", idx), "starting",
                               ua.VariantType.String)

    def _install_write_check(self, server: Any, ua: Any) -> None:
        """Reject writes of ``<plant>.u`` outside the input range before they land."""
        service = server.iserver.attribute_service
        original = service.write
        u_id = self._ids["u"]
        channel = self.input_channel

        def verdict(wv: Any) -> Any:
            variant = wv.Value.Value if wv.Value is not None else None
            if variant is None or variant.VariantType.name not in _NUMERIC_VARIANTS:
                return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
            try:
                value = float(variant.Value)
            except (TypeError, ValueError):
                return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
            if not channel.contains(value):
                return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
            if variant.VariantType != ua.VariantType.Double:
                wv.Value = dataclasses.replace(wv.Value, Value=ua.Variant(value,
                                                                          ua.VariantType.Double))
            return None

        async def write(params: Any, *args: Any, **kwargs: Any) -> list[Any]:
            results: list[Any] = [None] * len(params.NodesToWrite)
            passed, where = [], []
            for i, wv in enumerate(params.NodesToWrite):
                bad = (verdict(wv) if wv.NodeId == u_id
                       and wv.AttributeId == ua.AttributeIds.Value else None)
                if bad is None:
                    passed.append(wv)
                    where.append(i)
                else:
                    results[i] = bad
            if passed:
                sub = ua.WriteParameters(NodesToWrite=passed)
                for i, status in zip(where, await original(sub, *args, **kwargs), strict=True):
                    results[i] = status
            return results

        service.write = write

    # ------------------------------------------------------------------ stepping
    def _read_input(self) -> float:
        dv = self._server.read_attribute_value(self._ids["u"])
        try:
            value = float(dv.Value.Value)
        except (AttributeError, TypeError, ValueError):
            return self._u
        if self.input_channel.contains(value):
            self._u = value
        return self._u

    async def _write(self, key: str, value: Any, vtype: Any, ua: Any,
                     source: datetime | None = None) -> None:
        now = datetime.now(UTC)
        dv = ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=source or now,
                          ServerTimestamp=now)
        await self._server.write_attribute_value(self._ids[key], dv)

    async def _publish(self, sample: ServedSample) -> None:
        from asyncua import ua

        D = ua.VariantType.Double
        src = self._source_time(sample.t)
        await self._write("u_applied", sample.u, D, ua, src)
        await self._write("k", sample.k, ua.VariantType.Int64, ua, src)
        await self._write("t", sample.t, D, ua, src)
        await self._write("y", sample.y, D, ua, src)  # last: a client reading y finds k, t set

    async def _publish_last(self) -> None:
        if self._last is not None:
            await self._publish(self._last)

    def _set_status(self, status: str) -> None:
        self._status = status
        server = getattr(self, "_server", None)
        if server is None:
            return
        from asyncua import ua

        loop = asyncio.get_running_loop()
        loop.create_task(self._write("status", status, ua.VariantType.String, ua))

