"""The twin as a long-running service: :class:`TwinService` behind ``kautztwin twin serve``.

A :class:`TwinService` builds the plant link from a
:class:`~kautztwin.service.config.ServiceConfig` (an in-process simulator paced
by a sped-up real-time :class:`~kautztwin.twin.physical.Clock`, a recorded
run replayed at its own pace times ``speed``, or an
:class:`~kautztwin.twin.physical.OPCUAPlant` or
:class:`~kautztwin.twin.physical.MQTTPlant` that paces the loop itself), a
:class:`~kautztwin.twin.runtime.DigitalTwin` with a long horizon (checked
against a memory limit before anything is allocated) and its SQLite history,
and steps it on the wall clock until it is asked to stop (SIGTERM/SIGINT in the
command), the optional wall-clock duration ends or the horizon is reached.  It
then commits what is pending, leaves the run resumable, writes
``metrics.json`` / ``report.md`` and closes the link and the store.  A restart
with the same configuration resumes the run from the store
(:meth:`DigitalTwin.start <kautztwin.twin.runtime.DigitalTwin.start>`).

Events (start, model versions, re-identifications, outages, reconnects,
shutdown) are logged as structured records: ``key=value`` pairs or one JSON
object a line (:func:`configure_logging`); outages and reconnects are also
logged in the store.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import threading
import time
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ..exceptions import DataError
from .config import ServiceConfig
from .process import freeze_garbage

__all__ = ["TwinService", "configure_logging", "load_estimator"]

_logger = logging.getLogger("kautztwin.service")

#: bytes of per-sample arrays one sample of the horizon costs (run arrays, excitation)
BYTES_PER_SAMPLE = 8 * 22
#: default horizon: a day of plant time, at most this many samples
DEFAULT_HORIZON_S = 86400.0
MAX_DEFAULT_SAMPLES = 1_000_000
#: GIL switch interval while a network link runs, s (default 5 ms: the link thread would
#: wait up to that long for the GIL after each socket read, behind the sample loop)
LINK_SWITCH_INTERVAL_S = 0.001


class _Formatter(logging.Formatter):
    """``time level=... event=... key=value`` or one JSON object a line."""

    def __init__(self, fmt: str) -> None:
        super().__init__()
        self.json = fmt == "json"

    def format(self, record: logging.LogRecord) -> str:
        fields = dict(getattr(record, "fields", {}) or {})
        stamp = datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds")
        if self.json:
            out = {"time": stamp, "level": record.levelname.lower(),
                   "event": getattr(record, "event", "message"), **fields}
            if not fields:
                out["message"] = record.getMessage()
            return json.dumps(out, default=str)
        parts = [stamp, f"level={record.levelname.lower()}",
                 f"event={getattr(record, 'event', 'message')}"]
        for k, v in fields.items():
            text = f"{v:.6g}" if isinstance(v, float) else str(v)
            parts.append(f"{k}={json.dumps(text) if (' ' in text or not text) else text}")
        if not fields:
            parts.append(f"message={json.dumps(record.getMessage())}")
        return " ".join(parts)


def configure_logging(level: str = "info", file: str | Path | None = None,
                      fmt: str = "kv") -> logging.Logger:
    """Send the service's structured log to stderr (and a file).

    Parameters
    ----------
    level : str, default='info'
        ``debug``, ``info``, ``warning`` or ``error``.
    file : str or Path, optional
        Also append the log to this file.
    fmt : {'kv', 'json'}, default='kv'
        ``key=value`` pairs or one JSON object a line.

    Returns
    -------
    logging.Logger
        The ``kautztwin.service`` logger.
    """
    logger = _logger
    for h in list(logger.handlers):
        logger.removeHandler(h)
        h.close()
    handlers: list[logging.Handler] = [logging.StreamHandler()]
    if file is not None:
        Path(file).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(file, encoding="utf-8"))
    for h in handlers:
        h.setFormatter(_Formatter(fmt))
        logger.addHandler(h)
    logger.setLevel(level.upper())
    logger.propagate = False
    return logger


def _log(event: str, level: int = logging.INFO, **fields: Any) -> None:
    _logger.log(level, event, extra={"event": event, "fields": fields})


def load_estimator(path: str | Path) -> Any:
    """Load a trained DNN estimator folder (either kind, as ``kautztwin train`` writes it).

    Parameters
    ----------
    path : str or Path
        The model folder.

    Returns
    -------
    CoefficientEstimator or AdaptivePoleEstimator

    Raises
    ------
    DataError
        A missing, malformed or tampered model folder.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise DataError(f"estimator.path: no estimator folder at {folder}")
    kind = "coefficients"
    kind_file = folder / "estimator.json"
    if kind_file.exists():
        try:
            kind = json.loads(kind_file.read_text(encoding="utf-8"))["estimator"]
        except (ValueError, KeyError, OSError) as exc:
            raise DataError(f"estimator.path: {kind_file} is malformed ({exc})") from None
    try:
        if kind == "adaptive":
            from ..nn.adaptive import AdaptivePoleEstimator

            return AdaptivePoleEstimator.load(folder)
        if kind != "coefficients":
            raise DataError(f"estimator.path: {kind_file} names an unknown estimator {kind!r}")
        from ..nn import CoefficientEstimator

        return CoefficientEstimator.load(folder)
    except DataError as exc:
        raise DataError(f"estimator.path: {exc}") from None
    except (OSError, ValueError, KeyError, RuntimeError) as exc:
        raise DataError(f"estimator.path: cannot load {folder}: {exc}") from None


def _open_history(config: ServiceConfig) -> Any:
    """The SQLite store (``history.path``), its folder created, at ``history.synchronous``.

    ``normal`` (the default) commits without an fsync: a committed sample
    survives a killed process (``kill -9``), the last commits may roll back on
    a power cut.  ``full`` fsyncs every commit, which on a loaded host stalled
    the sample loop 50 to 150 ms every ``commit_every`` samples (measured
    against the OPC UA plant at x10: the loop fell hundreds of samples behind).
    """
    from ..twin.history import SQLiteHistory

    path = config.history_path
    path.parent.mkdir(parents=True, exist_ok=True)
    return SQLiteHistory(path, synchronous=config.values["history"]["synchronous"])


def _optimizer(config: ServiceConfig) -> Any:
    """The optimization module, with or without the pole re-optimisation on a resync.

    ``model.retune_poles`` (default on).  The re-optimisation runs in the sample
    loop: against the OPC UA plant at x10 on a loaded host it stalled the loop
    0.2 to 2 s (0.03 to 0.5 s of CPU) while the plant held its input; switched
    off, the fits after the drift recovery windows were lower (3 runs: minima
    93.1, 90.3 and 94.0 %, against 93.0 to 97.3 % with it).
    """
    from ..twin.optimization import Optimizer

    flag = config.model["retune_poles"]
    return Optimizer(retune_poles=True if flag is None else flag)


class TwinService:
    """The digital twin as a long-running service on the wall clock.

    Parameters
    ----------
    config : ServiceConfig
        The checked configuration.

    Attributes
    ----------
    plant : Plant
        The link (after :meth:`build`).
    twin : DigitalTwin
        The twin (after :meth:`build`).
    history : SQLiteHistory or None
        The store the service opened for the twin (``history.path`` at
        ``history.synchronous``; closed by :meth:`run`).
    twin_config : TwinConfig
        The twin's run configuration (stored with the run: a restart resumes
        only with the same one).
    stop_event : threading.Event
        Set to stop the service (:meth:`request_stop`).
    summary : dict
        What the last :meth:`run` did (samples, versions, outages...).
    api : ApiServer or None
        The HTTP API and dashboard (``[http]``, :mod:`kautztwin.service.api`),
        started and stopped with :meth:`run`.

    Examples
    --------
    >>> from kautztwin.service import TwinService, load_service_config
    >>> cfg = load_service_config(None, {"plant.kind": "hydraulic", "plant.speed": "1000",
    ...                                  "model.duration": "12", "model.quick": "true",
    ...                                  "service.out": "/tmp/kt-doctest"})  # doctest: +SKIP
    >>> TwinService(cfg).run()["n_samples"]  # doctest: +SKIP
    600
    """

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self.plant: Any = None
        self.twin: Any = None
        self.twin_config: Any = None
        self.stop_event = threading.Event()
        self.history: Any = None
        self.summary: dict[str, Any] = {}
        self._reset_reading: Any = None
        self._outages_seen = 0
        self._open_outages: list[Any] = []
        self._reconnects = 0
        self._time_offset: float | None = None
        self.api: Any = None

    # ------------------------------------------------------------------ setup
    def build(self) -> None:
        """Build the plant link, the twin configuration and the twin (no sample is taken).

        Raises
        ------
        DataError
            Bad settings, a horizon too large for ``service.max_memory_mb``, a
            bad estimator folder.
        LinkError
            An OPC UA server or MQTT broker that cannot be reached within
            ``plant.connect_timeout``.
        """
        from ..twin.physical import Clock
        from ..twin.runtime import DigitalTwin

        cfg = self.config
        p = cfg.plant
        estimator = None
        if cfg.estimator_path is not None:
            estimator = load_estimator(cfg.estimator_path)
        freeze_garbage()  # the libraries, before a live plant's clock runs: the long one
        if p["kind"] in ("opcua", "mqtt"):
            _log("connecting", link=p["kind"],
                 endpoint=p["endpoint"] if p["kind"] == "opcua" else p["broker"],
                 timeout_s=p["connect_timeout"])
            plant = self._opcua_plant() if p["kind"] == "opcua" else self._mqtt_plant()
            clock = Clock()  # the link paces the loop: each step waits for the next sample
            profile: Any = cfg.model.get("profile") or (
                p["object"] if p["object"] in ("hydraulic", "tclab") else "hydraulic")
            drift_events: tuple[float, ...] = ()  # on the server's clock: mapped for metrics
        elif p["kind"] == "replay":
            plant = self._replay_plant()
            clock = Clock.real_time(p["speed"], tolerance=plant.dt)  # the recorded pace x speed
            profile = plant
            drift_events = tuple(p["drift_events"] or ())
        else:
            from ..twin.physical.factory import make_plant

            plant = make_plant(p["kind"], drift=p["drift"], drift_events=p["drift_events"] or (),
                               seed=p["seed"], noise=p["noise"])
            clock = Clock.real_time(p["speed"], tolerance=plant.dt)
            profile = plant
            drift_events = tuple(p["drift_events"] or ())
        self.plant = plant
        try:
            self.twin_config = self._twin_config(profile, plant.dt, drift_events)
            background = cfg.model["background"]
            self.history = _open_history(cfg)
            self.twin = DigitalTwin(plant, self.twin_config, history=self.history,
                                    clock=clock, estimator=estimator, optimizer=_optimizer(cfg),
                                    background=True if background is None else background)
        except BaseException:
            plant.close()
            if self.history is not None:
                self.history.close()
                self.history = None
            raise

    def _opcua_plant(self) -> Any:
        from ..twin.physical import OPCUAPlant

        p = self.config.plant
        kwargs: dict[str, Any] = dict(
            plant=p["object"], nodes=p["nodes"], scaling=None, input_limits=p["input_limits"],
            connect_timeout=p["connect_timeout"], stale_periods=p["stale_periods"],
            username=p["username"], password=p["password"], security=p["security"],
            on_outage=p["on_outage"], safe_input=p["safe_input"],
        )
        if p["namespace"]:
            kwargs["namespace"] = p["namespace"]
        plant = OPCUAPlant(p["endpoint"], **kwargs)
        plant.connected = True  # a real plant: a resumed run continues, it is not re-simulated
        reset = plant.reset

        def noting_reset() -> Any:
            self._reset_reading = reading = reset()
            return reading

        plant.reset = noting_reset
        plant.connect()  # LinkError after connect_timeout: before anything is allocated
        return plant

    def _mqtt_plant(self) -> Any:
        """The MQTT link of ``kind = mqtt``, connected (LinkError when the broker is away)."""
        from ..twin.physical import MQTTPlant

        p = self.config.plant
        plant = MQTTPlant(
            p["broker"], plant=p["object"], topic=p["topic"], topics=p["topics"], dt=p["dt"],
            input_limits=p["input_limits"], stale_periods=p["stale_periods"],
            connect_timeout=p["connect_timeout"], username=p["username"],
            password=p["password"], on_outage=p["on_outage"], safe_input=p["safe_input"],
        )
        plant.connected = True  # a real plant: a resumed run continues, it is not re-simulated
        reset = plant.reset

        def noting_reset() -> Any:
            self._reset_reading = reading = reset()
            origin = getattr(plant, "_origin_t", math.nan)  # the payload's plant time at reset
            if self.twin is not None and math.isfinite(origin):
                self._time_offset = origin - self.twin.k * plant.dt  # for drift_events
            return reading

        plant.reset = noting_reset
        try:
            plant.connect()  # LinkError after connect_timeout: before anything is allocated
            _ = plant.dt, plant.input_limits  # from the retained meta topic unless configured
        except BaseException:
            plant.close()
            raise
        return plant

    def _replay_plant(self) -> Any:
        """The recorded run of ``kind = replay``, its clock starting at 0."""
        from ..twin.physical import ReplayPlant

        p = self.config.plant
        cols = p["columns"]
        record = ReplayPlant.from_csv(p["file"], columns=(cols["t"], cols["u"], cols["y"]))
        return ReplayPlant(record.t - record.t[0], record.u, record.y, name=record.name)

    def _twin_config(self, profile: Any, dt: float, drift_events: tuple[float, ...]) -> Any:
        from ..twin.runtime import TwinConfig

        cfg = self.config
        m = cfg.model
        duration = m["duration"]
        if duration is None:
            duration = min(DEFAULT_HORIZON_S, MAX_DEFAULT_SAMPLES * dt)
        n = int(round(duration / dt))
        need_mb = n * BYTES_PER_SAMPLE / 2**20
        limit = self.config.values["service"]["max_memory_mb"]
        if need_mb > limit:
            raise DataError(
                f"model.duration = {duration:g} s is {n} samples of {dt:g} s: about "
                f"{need_mb:.0f} MB of per-sample arrays, more than service.max_memory_mb = "
                f"{limit:g}; shorten model.duration or raise the limit"
            )
        overrides: dict[str, Any] = {}
        for key in ("ident_duration", "n_poles", "min_rate", "commit_every", "recovery_window"):
            if m[key] is not None:
                overrides[key] = m[key]
        overrides["retune"] = m["retune"]
        base = TwinConfig.for_plant(
            profile, duration=duration, setpoints=m["setpoints"], quick=m["quick"],
            seed=cfg.plant["seed"], faults=None, drift_events=drift_events,
            static_twin=m["static_twin"], **overrides,
        )
        width = cfg.values["estimator"]["max_relative_width"]
        if width is not None:  # defer DNN updates whose band is wider than this share
            base = replace(base, updater={**base.updater, "max_relative_width": width})
        worker = m["worker"]
        if worker == "auto":  # a live plant: the fit off the sampling process's GIL and CPU
            worker = "process" if cfg.plant["kind"] in ("opcua", "mqtt") else "thread"
        if worker != "thread":
            base = replace(base, updater={**base.updater, "worker": worker})
        if cfg.mpc:
            if base.mpc is None:
                raise DataError("[mpc] settings need a controlled plant profile")
            base = replace(base, mpc=replace(base.mpc, **cfg.mpc))
        if drift_events and drift_events[0] <= base.ident_duration:
            raise DataError(
                f"plant.drift_events: the first event ({drift_events[0]:g} s) falls inside the "
                f"identification phase (first {base.ident_duration:g} s)")
        return base

    # ------------------------------------------------------------------ running
    def request_stop(self) -> None:
        """Ask the loop to stop after the sample in progress (safe from a signal handler)."""
        self.stop_event.set()

    def run(self) -> dict[str, Any]:
        """Run until stopped, the wall-clock duration ends or the horizon is reached.

        Builds the service first if :meth:`build` was not called.  On the way
        out the pending samples are committed (the run stays resumable unless
        its horizon was reached), the report is written and the link and the
        store are closed.

        Returns
        -------
        dict
            :attr:`summary`.
        """
        if self.twin is None:
            self.build()
        cfg = self.config
        twin = self.twin
        svc = cfg.values["service"]
        api = self._api()
        switch = sys.getswitchinterval()
        if getattr(self.plant, "outages", None) is not None:  # a network link's client thread
            sys.setswitchinterval(LINK_SWITCH_INTERVAL_S)  # gets the GIL back within 1 ms
        try:
            if api is not None:
                api.start()  # the HTTP API of [http] (a busy port: a DataError, nothing run)
            state = twin.start(resume=cfg.values["history"]["resume"])
            resumed = twin.k > 0
            freeze_garbage()  # the twin, link and store built since: a short collection
            _log("start", plant=self.twin_config.plant, link=cfg.plant["kind"],
                 endpoint=cfg.plant["endpoint"] or "in-process", run_id=twin.run_id,
                 resumed=resumed, k=twin.k, version=state.version,
                 committed=state.committed, horizon=self.twin_config.n_samples,
                 store=str(cfg.history_path))
            if cfg.plant["kind"] == "opcua":
                self._map_plant_clock()
            start_k = twin.k
            wall0 = time.monotonic()
            deadline = math.inf if svc["duration"] is None else wall0 + svc["duration"]
            reason = "horizon reached"
            while not twin.done:
                if self.stop_event.is_set():
                    reason = "stop requested"
                    break
                if time.monotonic() >= deadline:
                    reason = "duration reached"
                    break
                state = twin.step()
                if state.events:
                    self._log_events(state)
                self._watch_link(state)
                if api is not None:
                    api.view.after_sample(state)  # the API's view; runs its queued jobs
            result = twin.finish()
            wall = time.monotonic() - wall0
            self.summary = {
                "reason": reason, "run_id": twin.run_id, "resumed": resumed,
                "resume_k": start_k, "n_samples": result.n_done, "committed": result.n_done,
                "version": int(state.version) if result.n_done else 0,
                "reidentifications": int(result.counts.get("reidentifications_accepted", 0)),
                "outages": self._outages_seen, "reconnects": self._reconnects,
                "wall_s": wall, "samples_per_s": (result.n_done - start_k) / max(wall, 1e-9),
                "sync_fit": None if math.isnan(state.fit) else round(float(state.fit), 3),
                "status": result.status, "out": str(cfg.out),
            }
            if svc["report"]:
                self._report(result)
            _log("stop", **{k: v for k, v in self.summary.items() if k != "out"})
        finally:
            sys.setswitchinterval(switch)
            if api is not None:
                api.stop()
            twin.close()
            if self.history is not None:  # the service opened it (the twin does not own it)
                self.history.close()
                self.history = None
        return self.summary

    def _api(self) -> Any:
        """The HTTP API (:class:`~kautztwin.service.api.ApiServer`): ``http.bind``, or attached."""
        if self.api is None and self.config.values["http"]["bind"] is not None:
            from .api import ApiServer

            self.api = ApiServer.from_service(self)
        return self.api

    def _report(self, result: Any) -> None:
        from ..twin.report import compute_metrics, write_report

        if self._time_offset is not None and self.config.plant["drift_events"]:
            events = tuple(e - self._time_offset for e in self.config.plant["drift_events"])
            events = tuple(e for e in events if e > 0)
            result = replace(result, config=replace(result.config, drift_events=events))
        self.config.out.mkdir(parents=True, exist_ok=True)
        paths = write_report(result, self.config.out, command="kautztwin twin serve",
                             plots=self.config.values["service"]["plots"])
        m = compute_metrics(result)
        self.summary.update(
            sync_fit_mean=m["sync_fit_mean"],
            sync_fit_min_after_recovery=m["sync_fit_min_after_recovery"],
            constraint_violations=m.get("constraint_violations"),
            drift_events_s=m["drift_events_s"], metrics=str(paths["metrics"]))

    # ------------------------------------------------------------------ observation
    def _log_events(self, state: Any) -> None:
        fit = None if math.isnan(state.fit) else round(float(state.fit), 3)
        for kind in state.events:
            level = logging.WARNING if kind in ("desync", "rejected") else logging.INFO
            _log(kind, level, k=state.k, t=state.t, version=state.version, fit=fit,
                 phase=state.phase)

    def _watch_link(self, state: Any) -> None:
        """Log (and store) outages and reconnects of a link that reports them."""
        outages = getattr(self.plant, "outages", None)
        if outages is None:
            return
        while self._outages_seen < len(outages):
            o = outages[self._outages_seen]
            self._outages_seen += 1
            self._open_outages.append(o)
            _log("outage", logging.WARNING, kind=o.kind, reason=o.reason, k=state.k, t=state.t)
        for o in list(self._open_outages):
            if o.end is not None:
                self._open_outages.remove(o)
                _log("outage-end", kind=o.kind, duration_s=o.end - o.start, k=state.k,
                     t=state.t)
                if self.twin.run_id is not None:
                    self.twin.history.log_event(
                        self.twin.run_id, "outage",
                        f"{o.kind} outage of {o.end - o.start:.2f} s: {o.reason}",
                        k=int(state.k), t=float(state.t),
                        payload={"kind": o.kind, "start": o.start, "end": o.end,
                                 "reason": o.reason})
        reconnects = getattr(self.plant, "counters", {}).get("reconnects", 0)
        if reconnects > self._reconnects:
            self._reconnects = reconnects
            _log("reconnect", reconnects=reconnects, k=state.k, t=state.t)

    def _map_plant_clock(self) -> None:
        """Place the plant's own clock on the twin's (OPC UA: read the time node once).

        The node is read over the link's own session (a few tries: a loaded host may
        answer late); a plant without it (a real PLC may have none) keeps the twin's clock.
        """
        p = self.config.plant
        reading = self._reset_reading
        if reading is None:
            return
        node = p["time_node"] or f"{p['object']}.t"
        error = ""
        for _ in range(3):
            try:
                value, stamp = self.plant.read(node, timeout=max(2.0, p["connect_timeout"] / 3))
                value = float(value)
                break
            except Exception as exc:  # the node is optional
                error = " ".join(str(exc).split())
        else:
            _log("plant-clock", logging.WARNING, node=node, error=error)
            return
        origin = float(reading.meta.get("source_time", math.nan))
        if not (math.isfinite(origin) and math.isfinite(value) and math.isfinite(stamp)):
            return
        t_plant_at_reset = value + (origin - stamp) * self.plant.speed
        self._time_offset = t_plant_at_reset - self.twin.k * self.twin_config.dt
        _log("plant-clock", node=node, offset_s=self._time_offset)
