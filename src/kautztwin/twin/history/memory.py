"""History store in memory with the behaviour of the SQLite store: :class:`MemoryHistory`."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from numpy.typing import ArrayLike

from ..._validation import check_int
from ...exceptions import DataError
from ..digital import DigitalModel
from .records import (
    Event,
    HistoryError,
    Measurements,
    Prediction,
    ResumeState,
    RunInfo,
    _check_int,
    _check_text,
    _digital_model,
    _dumps,
    _measurements,
    _nan,
    _opt_int,
    _parse_rows,
    _pred_array,
    _pred_json,
    _real,
    _resume_message,
    _time,
)

__all__ = ["MemoryHistory"]


# ---------------------------------------------------------------------- in memory
@dataclass
class _Run:
    started: float
    status: str
    config: str
    finished: float | None = None
    samples: dict[int, tuple[int, float | None, float | None, float | None, int]] = field(
        default_factory=dict
    )
    # version -> (model JSON, version, provenance, created, fit_percent, k)
    models: dict[int, tuple[str, int, str, float, float | None, int | None]] = field(
        default_factory=dict
    )
    active: int | None = None
    predictions: list[tuple[int, float | None, int, int | None, str]] = field(default_factory=list)


class MemoryHistory:
    """History store in memory, with the behaviour of :class:`SQLiteHistory`.

    Values go through the same conversions as in SQLite (JSON for configs,
    payloads, models and predictions; NaN for missing numbers), so tests and
    replays against it behave like runs against the database.  Nothing
    survives the process.

    See Also
    --------
    HistoryStore : The interface, with the documentation of each method.
    SQLiteHistory : The durable implementation.

    Examples
    --------
    >>> from kautztwin.twin import MemoryHistory
    >>> store = MemoryHistory()
    >>> run = store.start_run()
    >>> store.append_measurements(run, [(0, 0.0, 1.0, 2.0)])
    1
    >>> store.resume(run).next_k
    1
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._runs: dict[int, _Run] | None = {}
        self._events: list[tuple[int, int, int | None, float, str, str, str | None]] = []

    def _run(self, run_id: Any) -> tuple[int, _Run]:
        if self._runs is None:
            raise HistoryError("the history store is closed")
        rid = check_int(run_id, "run_id")
        run = self._runs.get(rid)
        if run is None:
            raise HistoryError(f"no run with run_id = {rid}")
        return rid, run

    def _open_runs(self) -> dict[int, _Run]:
        if self._runs is None:
            raise HistoryError("the history store is closed")
        return self._runs

    # ------------------------------------------------------------------ runs
    def start_run(
        self, config: Mapping[str, Any] | None = None, *, started: float | None = None
    ) -> int:
        """Create a run; see :meth:`HistoryStore.start_run`."""
        text = _dumps({} if config is None else config, "config")
        t0 = _time(started, "started")
        with self._lock:
            runs = self._open_runs()
            rid = max(runs, default=0) + 1
            runs[rid] = _Run(t0, "running", text)
            return rid

    def resume(self, run_id: int) -> ResumeState:
        """Reopen a run after a restart; see :meth:`HistoryStore.resume`."""
        with self._lock:
            rid, run = self._run(run_id)
            last_k = max(run.samples, default=None)
            last_t = None if last_k is None else _nan(run.samples[last_k][1])
            status = run.status
            run.status, run.finished = "running", None
            self._log(rid, last_k, time.time(), "resume", _resume_message(last_k),
                      _dumps({"last_k": last_k, "previous_status": status}, "payload"))  # fmt: skip
            return ResumeState(rid, last_k, last_t, len(run.samples), run.active, status)

    def finish_run(self, run_id: int, status: str = "finished") -> None:
        """End a run; see :meth:`HistoryStore.finish_run`."""
        status = _check_text(status, "status")
        with self._lock:
            _, run = self._run(run_id)
            run.status, run.finished = status, time.time()

    def run_info(self, run_id: int) -> RunInfo:
        """Metadata of one run; see :meth:`HistoryStore.run_info`."""
        with self._lock:
            rid, run = self._run(run_id)
            return RunInfo(rid, run.started, run.finished, run.status, json.loads(run.config))

    def runs(self) -> list[RunInfo]:
        """Metadata of every run; see :meth:`HistoryStore.runs`."""
        with self._lock:
            return [self.run_info(rid) for rid in sorted(self._open_runs())]

    # ------------------------------------------------------------------ measurements
    def append_measurements(self, run_id: int, rows: Iterable[Sequence[Any]] | Measurements) -> int:
        """Append samples atomically; see :meth:`HistoryStore.append_measurements`."""
        parsed = _parse_rows(rows)
        with self._lock:
            rid, run = self._run(run_id)
            stored = [r[0] for r in parsed if r[0] in run.samples]
            if stored:
                raise HistoryError(
                    f"run {rid} already has sample k = {stored[0]}; "
                    "nothing of this batch was stored"
                )
            run.samples.update((r[0], r) for r in parsed)
        return len(parsed)

    def measurements(self, run_id: int, since: int | None = None) -> Measurements:
        """Samples of a run; see :meth:`HistoryStore.measurements`."""
        lo = -1 if since is None else _check_int(since, "since", minimum=None)
        with self._lock:
            _, run = self._run(run_id)
            rows = [run.samples[k] for k in sorted(run.samples) if k > lo]
        return _measurements(rows)

    # ------------------------------------------------------------------ models
    def add_model_version(
        self, run_id: int, model: DigitalModel, *, active: bool = True, k: int | None = None
    ) -> int:
        """Store a model version; see :meth:`HistoryStore.add_model_version`."""
        if not isinstance(model, DigitalModel):
            raise DataError(f"model must be a DigitalModel, got {type(model).__name__}")
        k = _opt_int(k, "k")
        text = _dumps(model.model.to_dict(), "model")
        with self._lock:
            rid, run = self._run(run_id)
            if model.version in run.models:
                raise HistoryError(f"run {rid} already has model version {model.version}")
            run.models[model.version] = (
                text, model.version, model.provenance, model.created, model.fit_percent, k
            )  # fmt: skip
            if active:
                run.active = model.version
        return model.version

    def activate_model(self, run_id: int, version: int) -> None:
        """Make a stored version active; see :meth:`HistoryStore.activate_model`."""
        version = _check_int(version, "version")
        with self._lock:
            rid, run = self._run(run_id)
            if version not in run.models:
                raise HistoryError(f"run {rid} has no model version {version}")
            run.active = version

    def active_model(self, run_id: int) -> DigitalModel | None:
        """The active model; see :meth:`HistoryStore.active_model`."""
        with self._lock:
            _, run = self._run(run_id)
            if run.active is None:
                return None
            return _digital_model(*run.models[run.active][:5])

    def model_versions(self, run_id: int) -> list[DigitalModel]:
        """Every stored version; see :meth:`HistoryStore.model_versions`."""
        with self._lock:
            _, run = self._run(run_id)
            return [_digital_model(*run.models[v][:5]) for v in sorted(run.models)]

    # ------------------------------------------------------------------ predictions
    def add_prediction(
        self,
        run_id: int,
        k: int,
        y_pred: ArrayLike,
        *,
        model_version: int | None = None,
        t: float | None = None,
    ) -> None:
        """Store a prediction; see :meth:`HistoryStore.add_prediction`."""
        k = _check_int(k, "k")
        model_version = _opt_int(model_version, "model_version")
        tt = _real(t, "t")
        horizon, text = _pred_json(y_pred)
        with self._lock:
            rid, run = self._run(run_id)
            if model_version is not None and model_version not in run.models:
                raise HistoryError(f"run {rid} has no model version {model_version}")
            run.predictions.append((k, tt, horizon, model_version, text))

    def predictions(self, run_id: int, since: int | None = None) -> list[Prediction]:
        """Stored predictions; see :meth:`HistoryStore.predictions`."""
        lo = -1 if since is None else _check_int(since, "since", minimum=None)
        with self._lock:
            rid, run = self._run(run_id)
            rows = sorted((p for p in run.predictions if p[0] > lo), key=lambda p: p[0])
        return [Prediction(rid, r[0], r[1], r[2], r[3], _pred_array(r[4])) for r in rows]

    # ------------------------------------------------------------------ events
    def _log(
        self, rid: int, k: int | None, t: float, kind: str, message: str, payload: str | None
    ) -> int:
        event_id = len(self._events) + 1
        self._events.append((event_id, rid, k, t, kind, message, payload))
        return event_id

    def log_event(
        self,
        run_id: int,
        kind: str,
        message: str = "",
        *,
        k: int | None = None,
        t: float | None = None,
        payload: Any = None,
    ) -> int:
        """Log an event; see :meth:`HistoryStore.log_event`."""
        kind = _check_text(kind, "kind")
        message = _check_text(message, "message", empty=True)
        k = _opt_int(k, "k")
        tt = _time(t, "t")
        text = None if payload is None else _dumps(payload, "payload")
        with self._lock:
            rid, _ = self._run(run_id)
            return self._log(rid, k, tt, kind, message, text)

    def events(self, run_id: int, kind: str | None = None) -> list[Event]:
        """Logged events; see :meth:`HistoryStore.events`."""
        if kind is not None:
            kind = _check_text(kind, "kind")
        with self._lock:
            rid, _ = self._run(run_id)
            rows = [e for e in self._events if e[1] == rid and (kind is None or e[4] == kind)]
        return [Event(*r[:6], None if r[6] is None else json.loads(r[6])) for r in rows]

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Drop the stored data; see :meth:`HistoryStore.close`."""
        with self._lock:
            self._runs = None
            self._events = []

    def __enter__(self) -> MemoryHistory:
        """Return the store itself."""
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Close the store."""
        self.close()

    def __repr__(self) -> str:
        n = "closed" if self._runs is None else f"{len(self._runs)} runs"
        return f"MemoryHistory({n})"
