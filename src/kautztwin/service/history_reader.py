"""Pages of a twin's history for ``GET /history``: samples, predictions, set-points.

:class:`HistoryReader` reads one run of the twin's SQLite store on read-only
connections of its own (one per thread): in WAL mode they never block the
sample loop's commits, nor they them, and they never take the store's lock
(which the loop needs to commit).  A page is one bounded query on the primary
key (``k > after ... LIMIT``), so it costs the same at any point of a long
run.  Besides the measurements (``k, t, u, y, flags``) a page can carry the
twin's one-step ``prediction`` of each sample (as the store holds it: made at
the sample before) and the ``setpoint`` in force, rebuilt from the run's
configured schedule and the set-points written through the API
(:func:`setpoint_segments`, :func:`setpoints_at`).

The fleet's reader (:class:`~kautztwin.service.fleet_api.FleetHistoryReader`)
pages another table the same way, with the same pieces: :class:`ReadOnlyPages`
(the per-thread read-only connections, one snapshot a page, closed together),
:func:`window_query` (the bounded query of one page) and :func:`page_columns`
(rows to the page's columns, the set-points and the next cursor).
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import threading
import urllib.parse
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from ..twin.history.setpoints import control_start, setpoint_segments, setpoints_at
from .twin_view import ApiError

__all__ = ["HISTORY_SIGNALS", "HistoryReader", "ReadOnlyPages", "page_columns",
           "window_query"]

_T = TypeVar("_T")

#: per-sample signals of ``GET /history``: the store's measurements, the twin's one-step
#: prediction of each sample and the set-point in force at it
HISTORY_SIGNALS = ("k", "t", "u", "y", "flags", "prediction", "setpoint")


def _first_number(v: Any) -> float:
    """A stored prediction's first value: a number, its JSON text, or missing (NaN)."""
    if v is None or v == "null" or v == "":
        return math.nan
    return float(v)



def window_query(select: str, args: list[Any], after: int, start: float | None,
                 end: float | None, limit: int) -> tuple[str, tuple[Any, ...]]:
    """The bounded query of one page: ``select`` rows with ``k > after`` within ``[start, end]``.

    Parameters
    ----------
    select : str
        ``SELECT ... FROM ... WHERE ...`` naming the run (and more), without the window.
    args : list
        Its parameters.
    after : int
        The page cursor: rows with ``k > after``.
    start, end : float or None
        Time window on the column ``t`` (inclusive).
    limit : int
        Most rows of the page; one more is asked for, to tell whether a next page exists.

    Returns
    -------
    str
        The query, ordered by ``k``.
    tuple
        Its parameters.
    """
    query = select + " AND k > ?"
    args = [*args, after]
    if start is not None:
        query += " AND t >= ?"
        args.append(start)
    if end is not None:
        query += " AND t <= ?"
        args.append(end)
    return query + " ORDER BY k LIMIT ?", (*args, limit + 1)


def page_columns(rows: list[Any], signals: list[str], limit: int, config: Any,
                 events: list[Any]) -> tuple[dict[str, NDArray[Any]], int | None]:
    """A page's columns from rows ``(k, t, u, y, flags[, prediction])`` (at most ``limit + 1``).

    Parameters
    ----------
    rows : list of tuple
        The rows of :func:`window_query`; the sixth value, when there, is the
        prediction (a number, its JSON text or ``None``).
    signals : list of str
        Among :data:`HISTORY_SIGNALS` (``prediction`` only when the rows carry it).
    limit : int
        Most samples of the page.
    config : dict
        The run's stored configuration (its set-point schedule).
    events : list of tuple
        ``(kind, k, t, payload)`` of the run's set-point writes and resumes
        (:func:`setpoint_segments`).

    Returns
    -------
    dict of str to ndarray
        One column per signal (``k`` and ``flags`` int64, the others float, NaN
        where missing).
    int or None
        The cursor of the next page (``None``: this was the last).
    """
    more = len(rows) > limit
    rows = rows[:limit]
    columns = list(zip(*rows, strict=True)) if rows else [()] * 6
    cols: dict[str, NDArray[Any]] = {
        "k": np.array(columns[0], dtype=np.int64),
        "flags": np.array(columns[4], dtype=np.int64),
    }
    for i, name in ((1, "t"), (2, "u"), (3, "y")):
        cols[name] = np.array([math.nan if v is None else v for v in columns[i]],
                              dtype=float)
    if "prediction" in signals:
        cols["prediction"] = np.array([_first_number(v) for v in columns[5]], dtype=float)
    if "setpoint" in signals:
        dt, k_control = control_start(config)
        cols["setpoint"] = setpoints_at(setpoint_segments(config, events), cols["k"],
                                        cols["t"], dt, k_control)
    nxt = int(cols["k"][-1]) if more and rows else None
    return {s: cols[s] for s in signals}, nxt


class ReadOnlyPages:
    """Read-only SQLite connections of its own on a store's file, one per thread, closed together.

    The base of the ``/history`` readers (:class:`HistoryReader`, the fleet's
    :class:`~kautztwin.service.fleet_api.FleetHistoryReader`): in WAL mode
    these connections never block the writer's commits, nor it them.

    Parameters
    ----------
    path : str or None
        The SQLite file (``None``: no file, nothing is opened).
    """

    def __init__(self, path: str | None) -> None:
        self.path = path
        self._local = threading.local()
        self._lock = threading.Lock()
        self._connections: list[sqlite3.Connection] = []
        self._configs: dict[int, Any] = {}
        self._closed = False

    def _connection(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            assert self.path is not None
            uri = f"file:{urllib.parse.quote(self.path)}?mode=ro"
            conn = sqlite3.connect(uri, uri=True, timeout=5.0, isolation_level=None,
                                   check_same_thread=False)
            with self._lock:
                if self._closed:
                    conn.close()
                    raise ApiError(503, "the history store is closed")
                self._connections.append(conn)
            self._local.conn = conn
        return conn

    def _snapshot(self, read: Callable[[sqlite3.Connection], _T]) -> _T:
        """``read(connection)`` in one read transaction (one snapshot); SQLite errors: 503."""
        conn = self._connection()
        try:
            conn.execute("BEGIN")  # one snapshot for the page
            try:
                return read(conn)
            finally:
                conn.execute("COMMIT")
        except sqlite3.Error as exc:
            raise ApiError(503, f"cannot read the history store: {exc}") from None

    def _run_config(self, conn: sqlite3.Connection, table: str, run_id: int) -> Any:
        """The run's stored configuration (``{}`` when missing), read once per run."""
        config = self._configs.get(run_id)
        if config is None:
            row = conn.execute(f"SELECT config FROM {table} WHERE run_id = ?",
                               (run_id,)).fetchone()
            config = self._configs[run_id] = json.loads(row[0]) if row else {}
        return config

    def close(self) -> None:
        """Close the read connections (later pages: 503).  Idempotent."""
        with self._lock:
            self._closed = True
            conns, self._connections = self._connections, []
        for conn in conns:
            conn.close()


class HistoryReader(ReadOnlyPages):
    """Pages of a run's stored samples for ``GET /history``, off the store's lock.

    On an SQLite file it reads on connections of its own, opened read-only (one per
    thread): in WAL mode they never block the loop's commits, nor they them, and a page is
    one bounded query on the primary key (``k > after ... LIMIT``), so it costs the same at
    any point of a long run.  A store without a file (in memory) is read through its own
    methods, under its lock.

    Parameters
    ----------
    history : HistoryStore
        The twin's store.
    """

    def __init__(self, history: Any) -> None:
        path = getattr(history, "path", None)
        super().__init__(os.path.abspath(path) if isinstance(path, str) and path != ":memory:"
                         and os.path.exists(path) else None)
        self.history = history

    def page(self, run_id: int, signals: list[str], *, after: int = -1,
             start: float | None = None, end: float | None = None,
             limit: int = 1000) -> tuple[dict[str, NDArray[Any]], int | None]:
        """One page of samples ``k > after`` within ``[start, end]``, oldest first.

        Parameters
        ----------
        run_id : int
            The run.
        signals : list of str
            Among :data:`HISTORY_SIGNALS`.
        after : int, default=-1
            The page cursor: samples with ``k > after``.
        start, end : float, optional
            Time window, plant s (inclusive).
        limit : int, default=1000
            Most samples of the page.

        Returns
        -------
        dict of str to ndarray
            One column per signal (``k`` and ``flags`` int64, the others float, NaN
            where missing).  ``prediction`` is the twin's one-step prediction of the
            sample (stored as made at the sample before; NaN before the first model, and
            for a moment for the newest samples, committed just before their predictions);
            ``setpoint`` the set-point in force (:func:`setpoint_segments`; NaN in the
            identification phase and without control).
        int or None
            The cursor of the next page (``None``: this was the last).
        """
        if self._closed:
            raise ApiError(503, "the history store is closed")
        want = "prediction" in signals
        read = self._read_sqlite if self.path is not None else self._read_store
        rows, config, events = read(run_id, after, start, end, limit, want)
        return page_columns(rows, signals, limit, config, events)

    def _read_sqlite(self, run_id: int, after: int, start: float | None, end: float | None,
                     limit: int, prediction: bool) -> tuple[list[Any], Any, list[Any]]:
        """Rows ``(k, t, u, y, flags[, prediction])``, the run's configuration, its events."""
        select = "SELECT k, t, u, y, flags"
        if prediction:  # the newest one-step prediction of sample k, made at k - 1, as the
            # text of the JSON array's first number (Python parses it: exactly the stored float)
            select += (", (SELECT substr(p.y_pred, 2, CASE WHEN instr(p.y_pred, ',') > 0"
                       " THEN instr(p.y_pred, ',') - 2 ELSE length(p.y_pred) - 2 END)"
                       " FROM predictions p WHERE p.run_id = m.run_id AND p.k = m.k - 1"
                       " AND p.horizon >= 1 ORDER BY p.prediction_id DESC LIMIT 1)")
        query, args = window_query(select + " FROM measurements m WHERE run_id = ?", [run_id],
                                   after, start, end, limit)

        def read(conn: sqlite3.Connection) -> tuple[list[Any], Any, list[Any]]:
            rows = conn.execute(query, args).fetchall()
            config = self._run_config(conn, "runs", run_id)
            events = [(kind, k, t, None if p is None else json.loads(p)) for kind, k, t, p in
                      conn.execute("SELECT kind, k, t, payload FROM events WHERE run_id = ? "
                                   "AND kind IN ('api-setpoint', 'resume') ORDER BY event_id",
                                   (run_id,))]
            return rows, config, events

        return self._snapshot(read)

    def _read_store(self, run_id: int, after: int, start: float | None, end: float | None,
                    limit: int, prediction: bool) -> tuple[list[Any], Any, list[Any]]:
        """As :meth:`_read_sqlite`, through the store's methods (a store without a file)."""
        h = self.history
        m = h.measurements(run_id, since=after if after >= 0 else None)
        mask = np.ones(len(m), dtype=bool)
        if start is not None:
            mask &= m.t >= start
        if end is not None:
            mask &= m.t <= end
        idx = np.flatnonzero(mask)[:limit + 1]
        cols = [m.k[idx].tolist(), m.t[idx].tolist(), m.u[idx].tolist(), m.y[idx].tolist(),
                m.flags[idx].tolist()]
        if prediction:
            preds: dict[int, float] = {}
            if idx.size:
                for p in h.predictions(run_id, since=int(m.k[idx[0]]) - 2):
                    if p.horizon >= 1:
                        preds[int(p.k)] = float(p.y_pred[0])
            cols.append([preds.get(k - 1) for k in cols[0]])
        events = [(e.kind, e.k, e.t, e.payload) for e in h.events(run_id)
                  if e.kind in ("api-setpoint", "resume")]
        return list(zip(*cols, strict=True)), h.run_info(run_id).config, events
