"""Read a twin's store back: one run's samples, predictions, set-points, model versions, events.

:func:`read_run` gathers what ``kautztwin twin history`` shows: the measured
output and input, the twin's one-step prediction of each sample (stored as
made at the sample before, horizon 1), the set-point in force (from the
run's stored configuration), the flags, the model versions and the events,
restricted to a time window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...exceptions import DataError
from .protocol import HistoryStore
from .setpoints import control_start, setpoint_segments, setpoints_at

__all__ = ["SIGNALS", "RunHistory", "read_run"]

#: the per-sample signals a read-back can return
SIGNALS = ("y", "u", "prediction", "setpoint", "flags")


@dataclass(frozen=True)
class RunHistory:
    """One run read back from a store.

    Parameters
    ----------
    run_id : int
        The run.
    status : str
        ``'running'``, ``'finished'``, ``'abandoned'``, ...
    plant : str
        The plant's name as stored.
    n_committed : int
        Samples committed in the whole run.
    columns : dict of str to ndarray
        ``k``, ``t`` and the requested signals, one value per sample in the window.
    versions : list of dict
        Model versions (``version``, ``provenance``, ``fit_percent``, ``created``).
    events : list of dict
        Events in the window (``k``, ``t``, ``kind``, ``message``).
    """

    run_id: int
    status: str
    plant: str
    n_committed: int
    columns: dict[str, NDArray[Any]] = field(default_factory=dict)
    versions: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (non-finite numbers become ``None``).

        Returns
        -------
        dict
        """
        def clean(a: NDArray[Any]) -> list[Any]:
            return [None if isinstance(v, float) and not math.isfinite(v) else v
                    for v in a.tolist()]

        return {
            "run_id": self.run_id, "status": self.status, "plant": self.plant,
            "n_committed": self.n_committed,
            "samples": {name: clean(col) for name, col in self.columns.items()},
            "versions": self.versions, "events": self.events,
        }


def read_run(
    history: HistoryStore,
    run_id: int | None = None,
    *,
    signals: tuple[str, ...] = SIGNALS,
    start: float | None = None,
    end: float | None = None,
) -> RunHistory:
    """Read one run of a store back.

    Parameters
    ----------
    history : HistoryStore
        The store (for example ``SQLiteHistory("runs/hyd/history.sqlite")``).
    run_id : int or None, default=None
        The run; ``None``: the last one.
    signals : tuple of str, default=SIGNALS
        Per-sample signals to return, among :data:`SIGNALS`.
    start, end : float or None
        Time window, s (inclusive); ``None``: from the first or to the last sample.

    Returns
    -------
    RunHistory

    Raises
    ------
    DataError
        If the store has no runs, the run does not exist, a signal is unknown
        or the window is empty or reversed.

    Examples
    --------
    >>> from kautztwin.twin.history import MemoryHistory, read_run
    >>> h = MemoryHistory()
    >>> rid = h.start_run({"twin": {"setpoints": [[0.0, 1.0]], "dt": 0.1}, "plant": "p"})
    >>> _ = h.append_measurements(rid, [(0, 0.0, 0.5, 0.9, 0), (1, 0.1, 0.5, 1.0, 0)])
    >>> h.add_prediction(rid, 0, [0.95], t=0.0)
    >>> r = read_run(h, signals=("y", "prediction"))
    >>> r.columns["prediction"].tolist()
    [nan, 0.95]
    """
    unknown = [s for s in signals if s not in SIGNALS]
    if unknown:
        raise DataError(f"unknown signal {unknown[0]!r}; choose among {', '.join(SIGNALS)}")
    for name, value in (("start", start), ("end", end)):
        if value is not None and not math.isfinite(value):
            raise DataError(f"--{name} must be a finite time in seconds, got {value:g}")
    if start is not None and end is not None and end < start:
        raise DataError(f"--end ({end:g} s) is before --start ({start:g} s)")
    runs = history.runs()
    if not runs:
        raise DataError("the store holds no runs")
    if run_id is None:
        info = runs[-1]
    else:
        match = [r for r in runs if r.run_id == run_id]
        if not match:
            ids = ", ".join(str(r.run_id) for r in runs)
            raise DataError(f"--run {run_id}: no such run in the store (runs: {ids})")
        info = match[0]
    rows = history.measurements(info.run_id)
    t = np.asarray(rows.t, dtype=float)
    keep = np.ones(t.shape, dtype=bool)
    if start is not None:
        keep &= t >= start
    if end is not None:
        keep &= t <= end
    columns: dict[str, NDArray[Any]] = {"k": np.asarray(rows.k)[keep], "t": t[keep]}
    for name in signals:
        if name in ("y", "u", "flags"):
            columns[name] = np.asarray(getattr(rows, name))[keep]
        elif name == "setpoint":
            events = [(e.kind, e.k, e.t, e.payload) for e in history.events(info.run_id)
                      if e.kind in ("api-setpoint", "resume")]
            dt, k_control = control_start(info.config)
            columns[name] = setpoints_at(setpoint_segments(info.config, events),
                                         np.asarray(rows.k), t, dt, k_control)[keep]
        else:  # prediction of sample j, made at sample j - 1
            pred = np.full(t.shape, math.nan)
            index = {int(k): i for i, k in enumerate(np.asarray(rows.k))}
            for p in history.predictions(info.run_id):
                i = index.get(p.k + 1)
                if i is not None and p.horizon >= 1:
                    pred[i] = float(p.y_pred[0])
            columns[name] = pred[keep]
    lo = -math.inf if start is None else start
    hi = math.inf if end is None else end
    windowed = start is not None or end is not None
    events = []
    for e in history.events(info.run_id):
        if e.k is not None and 0 <= e.k < t.size:
            if not lo <= t[int(e.k)] <= hi:
                continue
        elif windowed:
            continue
        events.append({"k": e.k, "t": e.t, "kind": e.kind, "message": e.message})
    versions = [
        {"version": v.version, "provenance": v.provenance, "fit_percent": v.fit_percent,
         "created": v.created}
        for v in history.model_versions(info.run_id)
    ]
    plant = info.config.get("plant", "") if isinstance(info.config, dict) else ""
    return RunHistory(info.run_id, info.status, str(plant), int(np.asarray(rows.k).size),
                      columns, versions, events)
