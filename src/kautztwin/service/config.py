"""Configuration of ``kautztwin twin serve``: a TOML file, overridden key by key by flags.

The file has the sections ``[plant]``, ``[model]``, ``[estimator]``, ``[mpc]``,
``[history]``, ``[logging]``, ``[service]`` and ``[http]`` (the reference is in
``docs/service.md``; ``examples/twin.toml`` is a complete example).  Every key
is also a command-line flag ``--SECTION-KEY`` (``--mpc-u-max 0.65``); a few
have short forms (``--plant``, ``--speed``, ``--drift``, ``--out``,
``--duration``, ``--store``, ``--estimator``, ``--seed``, ``--log-level``).
An unknown section or key, a value of the wrong type or a missing file is a
one-line :class:`~kautztwin.exceptions.DataError` naming the entry.

``plant.kind`` picks the link: ``hydraulic`` / ``tclab`` (in-process
simulators), ``opcua`` (``plant.endpoint``), ``mqtt`` (``plant.broker``,
``plant.topic``) or ``replay`` (``plant.file``, ``plant.columns``); an
``opc.tcp://`` or ``mqtt://`` URL, or ``replay:FILE``, as the kind implies
the kind and its address (``--plant mqtt://127.0.0.1:1883``).
"""

from __future__ import annotations

import ipaddress
import math
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..exceptions import DataError

__all__ = ["SCHEMA", "ServiceConfig", "load_service_config", "parse_bind", "parse_value"]

#: ``{section: {key: (type, default, help)}}``; types: float, int, bool, str,
#: 'floats' (a list of numbers), 'table' (a table of strings), 'limits' (two numbers)
SCHEMA: dict[str, dict[str, tuple[Any, Any, str]]] = {
    "plant": {
        "kind": (str, "hydraulic", "hydraulic, tclab (in-process simulators), opcua, mqtt "
                 "or replay"),
        "endpoint": (str, None, "OPC UA server URL opc.tcp://HOST:PORT (kind = opcua)"),
        "broker": (str, None, "MQTT broker URL mqtt://HOST:PORT (kind = mqtt; default "
                   "mqtt://127.0.0.1:1883)"),
        "topic": (str, None, "MQTT: topic prefix (default kautztwin/OBJECT)"),
        "topics": ("table", None, "MQTT: topics by role (y, u, ack, meta, status)"),
        "dt": (float, None, "MQTT: sampling period, plant s (default: the retained meta topic)"),
        "file": (str, None, "replay: the recorded CSV file"),
        "columns": ("table", None, "replay: column names by role t, u, y (default t, u, y)"),
        "object": (str, "hydraulic", "OPC UA / MQTT: object name of the default node ids "
                   "OBJECT.u... and topic prefix kautztwin/OBJECT"),
        "nodes": ("table", None, "OPC UA: node ids by role (u, y, dt, speed, status)"),
        "namespace": (str, None, "OPC UA: namespace URI of bare string node ids"),
        "time_node": (str, None, "OPC UA: node with the plant's own time (default OBJECT.t), "
                      "to place drift_events on the twin's clock"),
        "input_limits": ("limits", None, "OPC UA / MQTT: (low, high) input bounds (default: "
                         "EURange / the meta topic)"),
        "username": (str, None, "OPC UA / MQTT user name"),
        "password": (str, None, "OPC UA / MQTT password"),
        "security": (str, None, "OPC UA security string Policy,Mode,cert,key"),
        "connect_timeout": (float, 10.0, "seconds to reach the plant before giving up"),
        "stale_periods": (float, 3.0, "sample periods without data that make a dropout"),
        "on_outage": (str, "hold", "input while the link is down or its data stale: hold (send "
                      "nothing: the plant holds its last input) or safe (send safe_input)"),
        "safe_input": (float, None, "the input of on_outage = safe"),
        "speed": (float, 1.0, "simulators and replay: plant seconds per wall-clock second"),
        "drift": (float, 0.0, "hydraulic simulator: relative slowing of the dominant pole"),
        "drift_events": ("floats", None, "start times of the drift steps, plant seconds"),
        "noise": (float, None, "simulators: sensor noise (default: the plant's)"),
        "seed": (int, 0, "seed of the excitation, the dither and the sensor noise"),
    },
    "model": {
        "duration": (float, None, "horizon of the run, plant s (default: a day, at most "
                     "1e6 samples)"),
        "ident_duration": (float, None, "open-loop identification phase, s"),
        "n_poles": (int, None, "order of the identified model"),
        "min_rate": (float, None, "slowest pole rate of the identification, 1/s"),
        "profile": (str, None, "tuned twin profile of an OPC UA plant: hydraulic or tclab "
                    "(default: plant.object when it is one of them)"),
        "setpoints": (str, None, "set-points: v1,v2,... or t1:v1,t2:v2,..."),
        "quick": (bool, False, "the quick profile (short identification)"),
        "static_twin": (bool, False, "also run the static twin (updates disabled)"),
        "retune": (bool, True, "run the optimization module (weight retuning)"),
        "background": (bool, None, "re-identify and retune in worker threads (default: on)"),
        "worker": (str, "auto", "where a background re-identification runs: thread, process "
                   "or auto (a process for an OPC UA or MQTT plant, else a thread)"),
        "retune_poles": (bool, None, "re-optimise the poles on a resync (synchronous, in the "
                         "sample loop; default: on)"),
        "commit_every": (int, None, "samples per history transaction"),
        "recovery_window": (float, None, "recovery window after each drift event, s"),
    },
    "estimator": {
        "path": (str, None, "folder of a trained DNN estimator (kautztwin train)"),
        "max_relative_width": (float, None, "defer a DNN update whose 90-percent band is wider "
                               "than this share of the response (default: never defer)"),
    },
    "mpc": {
        "horizon": (int, None, "prediction horizon, samples"),
        "laguerre_pole": (float, None, "Laguerre pole of the input parametrisation"),
        "n_functions": (int, None, "Laguerre functions of the input"),
        "r": (float, None, "input weight"),
        "u_min": (float, None, "lowest input"),
        "u_max": (float, None, "highest input"),
        "du_max": (float, None, "largest input change per sample"),
        "y_min": (float, None, "lowest output"),
        "y_max": (float, None, "highest output"),
        "dither": (float, None, "excitation dither amplitude"),
    },
    "history": {
        "path": (str, None, "SQLite history (default: OUT/history.sqlite)"),
        "resume": (bool, True, "resume an unfinished run with the same configuration"),
        "synchronous": (str, "normal", "SQLite commit durability: normal (survives a killed "
                        "process; no fsync per commit) or full (also a power cut; one fsync "
                        "per commit)"),
    },
    "logging": {
        "level": (str, "info", "debug, info, warning or error"),
        "file": (str, None, "also write the log to this file"),
        "format": (str, "kv", "kv (key=value) or json (one JSON object a line)"),
    },
    "service": {
        "out": (str, None, "folder for the store, metrics.json and report.md"),
        "duration": (float, None, "stop after this many wall-clock seconds (default: never)"),
        "max_memory_mb": (float, 512.0, "refuse a horizon whose arrays need more memory"),
        "report": (bool, True, "write metrics.json and report.md at shutdown"),
        "plots": (bool, False, "also write the plots at shutdown"),
    },
    "http": {
        "bind": (str, None, "serve the HTTP API and dashboard on HOST:PORT (or PORT: on "
                 "127.0.0.1); default: no HTTP server"),
        "token": (str, None, "API token (bearer) required by writes and the stream (default: "
                  "the environment variable KAUTZTWIN_HTTP_TOKEN); needed off loopback"),
        "rate_limit": (float, 60.0, "writes a minute per client (0: no limit)"),
    },
}

#: short command-line forms: flag -> (section, key)
SHORT_FLAGS = {
    "--speed": ("plant", "speed"), "--drift": ("plant", "drift"), "--seed": ("plant", "seed"),
    "--out": ("service", "out"), "--duration": ("service", "duration"),
    "--store": ("history", "path"), "--estimator": ("estimator", "path"),
    "--log-level": ("logging", "level"), "--log-file": ("logging", "file"),
    "--http": ("http", "bind"),
}

_PATH_KEYS = ("service.out", "history.path", "estimator.path", "logging.file", "plant.file")
#: kinds of plant link: in-process simulators, then the remote and recorded ones
KINDS = ("hydraulic", "tclab", "opcua", "mqtt", "replay")
_REMOTE = ("opcua", "mqtt")
_COLUMN_ROLES = ("t", "u", "y")
_LEVELS = ("debug", "info", "warning", "error")


def _type_name(kind: Any) -> str:
    names = {float: "a number", int: "an integer", bool: "true or false", str: "a string",
             "floats": "a list of numbers", "table": "a table of strings",
             "limits": "two numbers [low, high]"}
    return names[kind]


def parse_value(section: str, key: str, value: Any, *, text: bool = False) -> Any:
    """Check (and, from the command line, read) one configuration value.

    Parameters
    ----------
    section, key : str
        The entry.
    value : object
        The TOML value, or the command-line text when ``text`` is true.
    text : bool, default=False
        Read ``value`` as command-line text (``'0.5'``, ``'true'``,
        ``'30,60'``, ``'u=ns=2;s=a.u,y=ns=2;s=a.y'``).

    Returns
    -------
    object
        The value with its schema type.

    Raises
    ------
    DataError
        On an unknown entry or a value of the wrong type.

    Examples
    --------
    >>> from kautztwin.service.config import parse_value
    >>> parse_value("plant", "speed", "10", text=True)
    10.0
    >>> parse_value("plant", "drift_events", [30, 60])
    (30.0, 60.0)
    """
    if section not in SCHEMA:
        raise DataError(f"unknown section [{section}]; use one of {', '.join(SCHEMA)}")
    if key not in SCHEMA[section]:
        raise DataError(f"unknown key {key!r} in [{section}]; use one of "
                        f"{', '.join(SCHEMA[section])}")
    kind = SCHEMA[section][key][0]
    where = f"{section}.{key}"
    bad = DataError(f"{where} must be {_type_name(kind)}, got {value!r}")
    if text:
        value = str(value).strip()
        try:
            if kind is bool:
                low = value.lower()
                if low not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                    raise bad
                return low in ("true", "1", "yes", "on")
            if kind in (float, int):
                value = float(value) if kind is float else int(value)
            elif kind in ("floats", "limits"):
                value = [float(v) for v in value.split(",") if v.strip()]
            elif kind == "table":
                table = {}
                for part in (p for p in value.split(",") if p.strip()):
                    k, sep, v = part.partition("=")
                    if not sep:
                        raise bad
                    table[k.strip()] = v.strip()
                value = table
        except ValueError:
            raise bad from None
    if kind is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad
        if not math.isfinite(float(value)):
            raise DataError(f"{where} must be finite, got {value!r}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise bad
        return value
    if kind in ("floats", "limits"):
        if not isinstance(value, list | tuple) or any(
                isinstance(v, bool) or not isinstance(v, int | float) for v in value):
            raise bad
        out = tuple(float(v) for v in value)
        if kind == "limits" and (len(out) != 2 or not out[0] < out[1]):
            raise DataError(f"{where} must be [low, high] with low < high, got {value!r}")
        return out
    if not isinstance(value, Mapping) or any(not isinstance(v, str) for v in value.values()):
        raise bad
    return {str(k): v for k, v in value.items()}


@dataclass
class ServiceConfig:
    """The checked configuration of one ``twin serve`` service.

    Parameters
    ----------
    values : dict
        ``{section: {key: value}}`` with every key of :data:`SCHEMA` (defaults filled in).
    source : str, default='command line'
        Where it came from (the file, or the command line), for messages.

    Raises
    ------
    DataError
        If the entries do not fit together (an OPC UA plant without an
        endpoint, a missing estimator folder, a bad logging level...).

    Examples
    --------
    >>> from kautztwin.service import load_service_config
    >>> cfg = load_service_config(None, {"plant.kind": "hydraulic", "service.out": "runs/x"})
    >>> cfg.plant["kind"], cfg.plant["speed"], cfg.history_path.name
    ('hydraulic', 1.0, 'history.sqlite')
    """

    values: dict[str, dict[str, Any]]
    source: str = "command line"
    base: Path = field(default_factory=Path)

    def __post_init__(self) -> None:
        p = self.plant
        self._plant_kind(p)
        if p["kind"] == "opcua":
            if not p["endpoint"]:
                raise DataError("plant.endpoint is needed for an OPC UA plant "
                                "(opc.tcp://HOST:PORT)")
            from ..twin.physical.opcua import parse_endpoint

            parse_endpoint(p["endpoint"])
        elif p["kind"] == "mqtt":
            self._mqtt_entries(p)
        elif p["kind"] == "replay":
            self._replay_entries(p)
        if p["kind"] != "hydraulic" and p["drift"]:
            raise DataError("plant.drift applies to the hydraulic simulator only")
        if p["kind"] not in _REMOTE:
            for key in ("topic", "topics", "dt", "broker"):
                if p[key] is not None:
                    raise DataError(f"plant.{key} applies to an MQTT plant (kind = mqtt), "
                                    f"not to kind = {p['kind']}")
        if p["kind"] != "replay":
            for key in ("file", "columns"):
                if p[key] is not None:
                    raise DataError(f"plant.{key} applies to a replay (kind = replay), "
                                    f"not to kind = {p['kind']}")
        for key in ("speed", "connect_timeout", "stale_periods"):
            if not p[key] > 0:
                raise DataError(f"plant.{key} must be positive, got {p[key]:g}")
        if not -0.9 < p["drift"] < 0.9:
            raise DataError(f"plant.drift must be a fraction in (-0.9, 0.9), got {p['drift']:g}")
        if p["drift"] and p["kind"] == "hydraulic" and not p["drift_events"]:
            p["drift_events"] = (20.0, 40.0)
        if p["on_outage"] not in ("hold", "safe"):
            raise DataError(f"plant.on_outage must be hold or safe, got {p['on_outage']!r}")
        if p["on_outage"] == "safe" and p["safe_input"] is None:
            raise DataError("plant.on_outage = safe needs plant.safe_input")
        m = self.values["model"]
        m["worker"] = str(m["worker"]).strip().lower()
        if m["worker"] not in ("auto", "thread", "process"):
            raise DataError(f"model.worker must be auto, thread or process, got {m['worker']!r}")
        hist = self.values["history"]
        hist["synchronous"] = str(hist["synchronous"]).strip().lower()
        if hist["synchronous"] not in ("normal", "full"):
            raise DataError(f"history.synchronous must be normal or full, got "
                            f"{hist['synchronous']!r}")
        log = self.values["logging"]
        if log["level"].lower() not in _LEVELS:
            raise DataError(f"logging.level must be one of {', '.join(_LEVELS)}, "
                            f"got {log['level']!r}")
        if log["format"] not in ("kv", "json"):
            raise DataError(f"logging.format must be kv or json, got {log['format']!r}")
        svc = self.values["service"]
        if not svc["out"]:
            raise DataError("service.out is needed: the folder for the store and the report "
                            "(--out DIR)")
        if svc["duration"] is not None and not svc["duration"] > 0:
            raise DataError(f"service.duration must be positive, got {svc['duration']:g}")
        self._check_http()
        est = self.values["estimator"]["path"]
        if est is not None:
            path = self._path(est)
            if not path.is_dir():
                raise DataError(f"estimator.path {est!r}: no such estimator folder ({path})")
            self.values["estimator"]["path"] = str(path)
        width = self.values["estimator"]["max_relative_width"]
        if width is not None and not (math.isfinite(width) and width > 0):
            raise DataError(f"estimator.max_relative_width must be a positive number, got "
                            f"{width:g}")
        for key in ("duration", "ident_duration", "min_rate", "recovery_window"):
            v = self.model[key]
            if v is not None and not v > 0 and key != "recovery_window":
                raise DataError(f"model.{key} must be positive, got {v:g}")

    @staticmethod
    def _plant_kind(p: dict[str, Any]) -> None:
        """Read ``plant.kind``: a kind, or a URL / ``replay:FILE`` that implies one."""
        text = p["kind"].strip()
        low = text.lower()
        if low.startswith("opc.tcp://"):
            p["kind"], p["endpoint"] = "opcua", text
        elif low.startswith("mqtt://"):
            p["kind"], p["broker"] = "mqtt", text
        elif low.startswith("replay:"):
            p["kind"], p["file"] = "replay", text.partition(":")[2].strip() or p["file"]
        else:
            p["kind"] = low
        if p["kind"] not in KINDS:
            raise DataError(f"plant.kind must be one of {', '.join(KINDS)} (or an "
                            f"opc.tcp:// or mqtt:// URL), got {text!r}")

    @staticmethod
    def _mqtt_entries(p: dict[str, Any]) -> None:
        """Check the MQTT entries: broker URL, topic prefix, topics by role."""
        from ..twin.physical.mqtt import DEFAULT_BROKER, default_topics, parse_broker

        if p["broker"] is None and p["endpoint"] and p["endpoint"].lower().startswith("mqtt://"):
            p["broker"] = p["endpoint"]
        p["broker"] = (p["broker"] or DEFAULT_BROKER).strip()
        try:
            parse_broker(p["broker"])
            if p["topic"] is not None:
                default_topics(p["topic"])
        except DataError as exc:
            raise DataError(f"plant.{'broker' if 'broker' in str(exc) else 'topic'}: "
                            f"{exc}") from None
        roles = ("y", "u", "ack", "meta", "status")
        for role, topic in (p["topics"] or {}).items():
            if role not in roles:
                raise DataError(f"plant.topics: unknown role {role!r}; use one of "
                                f"{', '.join(roles)}")
            if not topic.strip() or "#" in topic or "+" in topic:
                raise DataError(f"plant.topics.{role} must be a topic without wildcards, "
                                f"got {topic!r}")
        if p["dt"] is not None and not p["dt"] > 0:
            raise DataError(f"plant.dt must be positive, got {p['dt']:g}")
        p["endpoint"] = p["broker"]  # where the service is attached, for the logs

    def _replay_entries(self, p: dict[str, Any]) -> None:
        """Check the replay entries: the CSV file exists, the columns name t, u and y."""
        if not p["file"]:
            raise DataError("plant.file is needed for a replay (a CSV file with t, u, y "
                            "columns; --plant replay:FILE)")
        path = self._path(p["file"])
        if not path.is_file():
            raise DataError(f"plant.file {p['file']!r}: no such file ({path})")
        p["file"] = str(path)
        columns = dict(p["columns"] or {})
        for role in columns:
            if role not in _COLUMN_ROLES:
                raise DataError(f"plant.columns: unknown role {role!r}; use t, u and y")
        p["columns"] = {r: columns.get(r, r).strip() or r for r in _COLUMN_ROLES}

    def _check_http(self) -> None:
        """``[http]``: a bind off the loopback interface needs a token."""
        h = self.values["http"]
        if h["token"] is None and os.environ.get("KAUTZTWIN_HTTP_TOKEN"):
            h["token"] = os.environ["KAUTZTWIN_HTTP_TOKEN"]
        if h["token"] is not None and len(h["token"].strip()) < 8:
            raise DataError("http.token must have at least 8 characters")
        if not h["rate_limit"] >= 0:
            raise DataError(f"http.rate_limit must be >= 0, got {h['rate_limit']:g}")
        if h["bind"] is None:
            return
        host, port = parse_bind(h["bind"])
        if not _is_loopback(host) and h["token"] is None:
            raise DataError(f"http.bind {h['bind']!r} is not a loopback address: set an API "
                            "token (http.token or KAUTZTWIN_HTTP_TOKEN) to serve beyond this "
                            "machine")

    def _path(self, text: str) -> Path:
        path = Path(text).expanduser()
        return path if path.is_absolute() else self.base / path

    @property
    def plant(self) -> dict[str, Any]:
        """The ``[plant]`` section."""
        return self.values["plant"]

    @property
    def model(self) -> dict[str, Any]:
        """The ``[model]`` section."""
        return self.values["model"]

    @property
    def mpc(self) -> dict[str, Any]:
        """The ``[mpc]`` entries that are set (overrides of the plant profile)."""
        return {k: v for k, v in self.values["mpc"].items() if v is not None}

    @property
    def out(self) -> Path:
        """The output folder."""
        return self._path(self.values["service"]["out"])

    @property
    def history_path(self) -> Path:
        """The SQLite history file."""
        path = self.values["history"]["path"]
        return self.out / "history.sqlite" if path is None else self._path(path)

    @property
    def log_file(self) -> Path | None:
        """The log file, or ``None``."""
        path = self.values["logging"]["file"]
        return None if path is None else self._path(path)

    @property
    def estimator_path(self) -> Path | None:
        """The DNN estimator folder, or ``None``."""
        path = self.values["estimator"]["path"]
        return None if path is None else Path(path)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The entries that are set, by section (the password left out).

        Returns
        -------
        dict
        """
        return {s: {k: ("***" if k in ("password", "token") else v)
                    for k, v in kv.items() if v is not None}
                for s, kv in self.values.items()}


def parse_bind(text: str) -> tuple[str, int]:
    """``(host, port)`` of ``HOST:PORT``, ``[IPv6]:PORT`` or ``PORT`` (on 127.0.0.1).

    Parameters
    ----------
    text : str

    Returns
    -------
    tuple of (str, int)

    Raises
    ------
    DataError
        When it is none of these, or the port is outside 0..65535.

    Examples
    --------
    >>> from kautztwin.service.config import parse_bind
    >>> parse_bind("8000"), parse_bind("0.0.0.0:80"), parse_bind("[::1]:8000")
    (('127.0.0.1', 8000), ('0.0.0.0', 80), ('::1', 8000))
    """
    value = str(text).strip()
    host, sep, port = value.rpartition(":")
    if not sep:
        host, port = "127.0.0.1", value
    host = host.strip("[]") or "127.0.0.1"
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 65535 or any(c.isspace() for c in host):
        raise DataError(f"http.bind must be HOST:PORT or PORT, got {text!r}")
    return host, number


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def load_service_config(
    path: str | Path | None, overrides: Mapping[str, Any] | None = None
) -> ServiceConfig:
    """Read a service configuration file and apply command-line overrides.

    Parameters
    ----------
    path : str, Path or None
        The TOML file (``None``: defaults and overrides only).  Relative paths
        inside it are relative to its folder.
    overrides : mapping, optional
        ``{'section.key': value}``; a ``str`` value is read as command-line
        text, anything else is checked as a TOML value.

    Returns
    -------
    ServiceConfig

    Raises
    ------
    DataError
        Missing or malformed file, unknown section or key, wrong type, or
        entries that do not fit together.
    """
    data: dict[str, Any] = {}
    base = Path()
    source = "command line"
    if path is not None:
        file = Path(path)
        if not file.is_file():
            raise DataError(f"config file {str(path)!r} does not exist")
        try:
            data = tomllib.loads(file.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise DataError(f"{path}: malformed TOML: {exc}") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise DataError(f"cannot read config file {str(path)!r}: {exc}") from None
        base = file.resolve().parent
        source = str(path)
    values = {s: {k: spec[1] for k, spec in keys.items()} for s, keys in SCHEMA.items()}
    for section, table in data.items():
        if section not in SCHEMA:
            raise DataError(f"{source}: unknown section [{section}]; use one of "
                            f"{', '.join(SCHEMA)}")
        if not isinstance(table, Mapping):
            raise DataError(f"{source}: {section} must be a table [{section}]")
        for key, value in table.items():
            try:
                values[section][key] = parse_value(section, key, value)
            except DataError as exc:
                raise DataError(f"{source}: {exc}") from None
    for dotted, value in dict(overrides or {}).items():
        section, _, key = dotted.partition(".")
        value = parse_value(section, key, value, text=isinstance(value, str))
        if dotted in _PATH_KEYS and value is not None:
            value = str(Path(value).expanduser().absolute())  # relative to the working folder
        elif dotted == "plant.kind" and value.strip().lower().startswith("replay:"):
            file = value.strip().partition(":")[2].strip()
            value = f"replay:{Path(file).expanduser().absolute()}" if file else value
        values[section][key] = value
    return ServiceConfig(values, source, base)
