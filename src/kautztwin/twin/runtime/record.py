"""Bookkeeping of a run in the history store: per-sample arrays, events, versions; resume.

:class:`RunRecord` holds what a run has produced so far (the arrays of
:class:`~kautztwin.twin.runtime.TwinRun`, the events, the model versions
and the controller tunings) and commits it to the
:class:`~kautztwin.twin.HistoryStore`.  When a run is resumed it finds the
unfinished run with the same configuration in the store; :class:`Replay`
then feeds the committed samples back through the loop (the plant
re-simulated with the stored inputs and checked against the stored
outputs), so the run continues exactly where the committed history ends
and nothing is stored twice.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._json import to_jsonable
from ...exceptions import DataError
from ..digital import DigitalModel
from ..history import HistoryStore, Measurements, SQLiteHistory
from ..physical import Reading
from .config import TwinConfig
from .protocols import TwinError
from .results import _ARRAYS, TwinEvent, TwinRun

__all__ = ["Replay", "RunRecord", "open_history"]


def open_history(history: Any) -> tuple[HistoryStore, str, bool]:
    """``(store, where, owned)`` from a store, a path or None (an in-memory SQLite)."""
    if history is None:
        return SQLiteHistory(":memory:"), ":memory:", True
    if isinstance(history, str | os.PathLike):
        return SQLiteHistory(history), os.fspath(history), True
    if isinstance(history, HistoryStore):
        where = getattr(history, "path", type(history).__name__)
        return history, str(where), False
    raise DataError(
        f"history must be a HistoryStore, a path or None, got {type(history).__name__}"
    )


def _same(a: float, b: float, tol: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return abs(a - b) <= tol * max(1.0, abs(a), abs(b))


class Replay:
    """The committed samples of a resumed run, fed back through the loop and compared.

    Parameters
    ----------
    rows : Measurements or None
        The committed samples (``None``: nothing to replay).

    Attributes
    ----------
    resume_k : int
        Samples to replay (set when the replay starts).
    mismatches : int
        Recomputed readings or inputs that differ from the stored ones.
    """

    def __init__(self, rows: Measurements | None = None) -> None:
        self.rows = rows
        self.resume_k = 0
        self.mismatches = 0

    def active(self, k: int) -> bool:
        """Whether sample ``k`` is replayed from the store."""
        return self.rows is not None and k < self.resume_k

    def reading(self, k: int, t: float, y: float) -> tuple[float, float]:
        """The stored ``(t, y)`` of sample ``k``, counting a mismatch with the recomputed one."""
        row = self.rows
        assert row is not None
        t_s, y_s = float(row.t[k]), float(row.y[k])
        if not (_same(t_s, t, 1e-9) and _same(y_s, y, 1e-9)):
            self.mismatches += 1
        return t_s, y_s

    def input(self, k: int, u: float) -> float:
        """The stored input of sample ``k``, counting a mismatch with the recomputed one."""
        u_s = float(self.rows.u[k])  # type: ignore[union-attr]
        if not _same(u_s, u, 1e-9):
            self.mismatches += 1
        return u_s

    def next_reading(self, k: int) -> Reading | None:
        """The stored reading after sample ``k`` (a plant that cannot be re-simulated)."""
        rows = self.rows
        assert rows is not None
        if k + 1 < len(rows.k):
            return Reading(float(rows.t[k + 1]), float(rows.y[k + 1]))
        return None

    def summary(self) -> dict[str, Any]:
        """``resumed, resume_k, replayed, replay_mismatches`` (the ``resume`` of a TwinRun)."""
        return {
            "resumed": self.resume_k > 0, "resume_k": self.resume_k,
            "replayed": self.resume_k, "replay_mismatches": self.mismatches,
        }


class RunRecord:
    """What a run has produced so far, committed to the history store.

    Parameters
    ----------
    history : HistoryStore
        The store.
    store : str
        Where it is (for messages and the record).
    n_samples : int
        Samples of the run (length of the arrays).

    Attributes
    ----------
    arrays : dict of str to ndarray
        The per-sample arrays of :class:`~kautztwin.twin.runtime.TwinRun`.
    events : list of TwinEvent
        Everything that happened, in order.
    versions, tunings : list of dict
        Model versions and controller tunings.
    identification : dict
        The initial identification.
    run_id : int or None
        The run in the store (after :meth:`open`).
    committed : int
        Samples committed so far.
    version_offset : dict of int to float
        Output offset of each model version.
    """

    def __init__(self, history: HistoryStore, store: str, n_samples: int) -> None:
        self.history = history
        self.store = store
        self.arrays: dict[str, NDArray[Any]] = {}
        for name in _ARRAYS:
            dtype = np.int64 if name in ("version", "flags") else float
            fill = 0 if dtype is np.int64 else math.nan
            self.arrays[name] = np.full(n_samples, fill, dtype=dtype)
        self.arrays["mpc_ok"] = np.ones(n_samples)
        self.events: list[TwinEvent] = []
        self.versions: list[dict[str, Any]] = []
        self.tunings: list[dict[str, Any]] = []
        self.identification: dict[str, Any] = {}
        self.run_id: int | None = None
        self.committed = 0
        self.version_offset: dict[int, float] = {}
        self._pending: list[tuple[int, float, float, float, int]] = []
        self._pending_pred: list[tuple[int, float | None, int | None, float]] = []
        self._stored_events: set[tuple[str, int | None]] = set()
        self._stored_versions: set[int] = set()

    # ------------------------------------------------------------------ run
    def open(self, config: dict[str, Any], resume: bool) -> Replay:
        """Start a new run, or find an unfinished one with the same ``config`` to resume.

        Parameters
        ----------
        config : dict
            The run configuration as stored.
        resume : bool
            Look for an unfinished run with this configuration.

        Returns
        -------
        Replay
            Its committed samples (``rows`` is ``None`` for a new run).

        Raises
        ------
        TwinError
            If the committed samples of the run to resume are not a contiguous prefix.
        """
        if resume:
            for info in reversed(self.history.runs()):
                if info.status == "finished" or info.config != config:
                    continue
                state = self.history.resume(info.run_id)
                rows = self.history.measurements(info.run_id)
                k = np.asarray(rows.k)
                if not np.array_equal(k, np.arange(k.size)):
                    raise TwinError(
                        f"run {info.run_id} in {self.store} has non-contiguous samples; "
                        "it cannot be resumed"
                    )
                self.committed = int(k.size)
                self._stored_events = {
                    (e.kind, e.k) for e in self.history.events(info.run_id)
                }
                self._stored_versions = {
                    v.version for v in self.history.model_versions(info.run_id)
                }
                self.event("resume", state.next_k, math.nan,
                           f"resumed after sample {state.last_k} ({state.n_samples} committed "
                           f"samples, previous status {state.previous_status!r})",
                           {"last_k": state.last_k, "n_samples": state.n_samples},
                           store=False)
                self.run_id = info.run_id
                return Replay(rows)
        self.run_id = self.history.start_run(config)
        return Replay()

    def finish(self, status: str) -> None:
        """Commit what is pending and mark the run (``'running'`` leaves it resumable)."""
        self.flush()
        if status != "running" and self.run_id is not None:
            self.history.finish_run(self.run_id, status)

    # ------------------------------------------------------------------ entries
    def event(
        self, kind: str, k: int, t: float, message: str, payload: Mapping[str, Any] | None = None,
        *, store: bool = True,
    ) -> None:
        """Record an event (and log it in the store unless a resumed run stored it already)."""
        ev = TwinEvent(kind, int(k), float(t), message, dict(payload or {}))
        self.events.append(ev)
        if store and (kind, int(k)) not in self._stored_events and self.run_id is not None:
            self.history.log_event(
                self.run_id, kind, message, k=int(k), t=None if math.isnan(t) else float(t),
                payload=to_jsonable(dict(payload or {})),
            )

    def store_version(self, dm: DigitalModel, k: int, t: float, offset: float) -> None:
        """Record a new model version, store it, and log a ``'model-version'`` event."""
        self.version_offset[dm.version] = float(offset)
        poles = [[float(p.real), float(p.imag)] for p in dm.model.poles]
        rec = {"version": dm.version, "k": int(k), "t": float(t), "provenance": dm.provenance,
               "fit_percent": dm.fit_percent, "offset": float(offset),
               "n_functions": dm.model.n_functions, "poles": poles}
        self.versions.append(rec)
        if dm.version not in self._stored_versions and self.run_id is not None:
            self.history.add_model_version(self.run_id, dm, k=int(k))
            self._stored_versions.add(dm.version)
        self.event("model-version", k, t,
                   f"model version {dm.version} ({dm.provenance})", rec)

    def commit(self, row: tuple[int, float, float, float, int], *, every: int, last: bool) -> None:
        """Queue a sample ``(k, t, u, y, flags)``; commit ``every`` samples and after the last."""
        self._pending.append(row)
        if len(self._pending) >= every or last:
            self.flush()

    def prediction(self, k: int) -> None:
        """Queue the twin's one-step prediction of sample ``k`` (committed with the samples).

        It is stored as made at sample ``k - 1`` (horizon 1), by the model
        version in force then (at the twin's first sample, its first version;
        ``None`` when that version is not stored).

        Parameters
        ----------
        k : int
            The sample (its ``y_pred`` is NaN before the twin exists: nothing is queued).
        """
        y = float(self.arrays["y_pred"][k])
        if k < 1 or math.isnan(y):
            return
        t = float(self.arrays["t"][k - 1])
        version: int | None = int(self.arrays["version"][k - 1])
        if version not in self._stored_versions:  # the twin's first sample: its first model
            version = int(self.arrays["version"][k])
            version = version if version in self._stored_versions else None
        self._pending_pred.append((k - 1, t if math.isfinite(t) else None, version, y))

    def flush(self) -> None:
        """Commit the pending samples in one transaction (then their predictions)."""
        if self._pending and self.run_id is not None:
            self.history.append_measurements(self.run_id, self._pending)
            self.committed += len(self._pending)
            self._pending = []
        if self._pending_pred and self.run_id is not None:
            rows, self._pending_pred = self._pending_pred, []
            bulk = getattr(self.history, "add_predictions", None)
            if bulk is not None:
                bulk(self.run_id, rows)
            else:
                for k, t, version, y in rows:
                    self.history.add_prediction(self.run_id, k, [y], model_version=version, t=t)

    # ------------------------------------------------------------------ result
    def result(
        self, config: TwinConfig, plant_name: str, n_done: int, k_closed_loop: int,
        counts: Mapping[str, int], resume: Mapping[str, Any], wall_time: float, status: str,
    ) -> TwinRun:
        """The :class:`~kautztwin.twin.runtime.TwinRun` of the first ``n_done`` samples."""
        arrays = {}
        for name, arr in self.arrays.items():
            view = arr[:n_done].copy()
            view.setflags(write=False)
            arrays[name] = view
        return TwinRun(
            config=config, plant_name=plant_name, run_id=int(self.run_id or 0),
            store=self.store, n_done=n_done, k_closed_loop=k_closed_loop,
            arrays=MappingProxyType(arrays), events=tuple(self.events),
            versions=tuple(MappingProxyType(v) for v in self.versions),
            tunings=tuple(MappingProxyType(v) for v in self.tunings),
            counts=MappingProxyType(dict(counts)),
            identification=MappingProxyType(self.identification),
            resume=MappingProxyType(dict(resume)), wall_time=wall_time, status=status,
        )
