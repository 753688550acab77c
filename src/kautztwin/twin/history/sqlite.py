"""History store on an embedded SQLite file in WAL mode: :class:`SQLiteHistory`.

Durability
----------
A sample is *committed* when :meth:`HistoryStore.append_measurements` returns.
:class:`SQLiteHistory` runs SQLite in write-ahead-log mode with
``synchronous=FULL`` by default: every commit appends to the WAL file and
fsyncs it before returning.  A committed sample therefore survives a killed
process (``kill -9``), an operating-system crash and a power cut.  With
``synchronous='NORMAL'`` a commit only writes the WAL (fsync at checkpoints):
that still survives ``kill -9`` - the data are in the OS page cache - but the
last transactions can roll back on power loss.  The price of ``FULL`` is one
fsync per transaction, so batch samples (one transaction per batch) when the
sample rate is high.

Concurrency
-----------
SQLite admits one writer at a time.  Run one writing store per database file
(the twin process); other processes can open the same file and read
concurrently (WAL readers do not block the writer, nor it them).  Both
implementations serialise their calls with a lock, so one instance can be
shared between threads.

Size: :class:`SQLiteHistory` is over 400 lines because it implements every
method of :class:`~kautztwin.twin.history.HistoryStore` as one SQL transaction
each; splitting it would scatter one schema over several files.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..._validation import check_choice, check_int
from ...exceptions import DataError
from ..digital import DigitalModel
from .records import (
    SCHEMA_VERSION,
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

__all__ = ["SQLiteHistory"]

_SYNCHRONOUS = ("NORMAL", "FULL", "EXTRA")


# ---------------------------------------------------------------------- SQLite
_SCHEMA = (
    """CREATE TABLE schema_version (
        version INTEGER NOT NULL,
        applied REAL NOT NULL
    )""",
    """CREATE TABLE runs (
        run_id INTEGER PRIMARY KEY AUTOINCREMENT,
        started REAL NOT NULL,
        finished REAL,
        status TEXT NOT NULL,
        config TEXT NOT NULL
    )""",
    """CREATE TABLE measurements (
        run_id INTEGER NOT NULL REFERENCES runs(run_id) ON DELETE CASCADE,
        k INTEGER NOT NULL CHECK (k >= 0),
        t REAL,
        u REAL,
        y REAL,
        flags INTEGER NOT NULL DEFAULT 0 CHECK (flags >= 0),
        PRIMARY KEY (run_id, k)
    ) WITHOUT ROWID""",
    "CREATE INDEX measurements_run_t ON measurements(run_id, t)",
    """CREATE TABLE model_versions (
        run_id INTEGER NOT NULL REFERENCES runs(run_id) ON DELETE CASCADE,
        version INTEGER NOT NULL CHECK (version >= 0),
        created REAL NOT NULL,
        k INTEGER,
        provenance TEXT NOT NULL,
        fit_percent REAL,
        active INTEGER NOT NULL DEFAULT 0 CHECK (active IN (0, 1)),
        model TEXT NOT NULL,
        PRIMARY KEY (run_id, version)
    )""",
    # at most one active model per run, enforced by the database
    "CREATE UNIQUE INDEX model_versions_one_active ON model_versions(run_id) WHERE active = 1",
    """CREATE TABLE predictions (
        prediction_id INTEGER PRIMARY KEY AUTOINCREMENT,
        run_id INTEGER NOT NULL REFERENCES runs(run_id) ON DELETE CASCADE,
        k INTEGER NOT NULL,
        t REAL,
        horizon INTEGER NOT NULL CHECK (horizon >= 0),
        model_version INTEGER,
        y_pred TEXT NOT NULL,
        FOREIGN KEY (run_id, model_version) REFERENCES model_versions(run_id, version)
    )""",
    "CREATE INDEX predictions_run_k ON predictions(run_id, k)",
    """CREATE TABLE events (
        event_id INTEGER PRIMARY KEY AUTOINCREMENT,
        run_id INTEGER NOT NULL REFERENCES runs(run_id) ON DELETE CASCADE,
        k INTEGER,
        t REAL NOT NULL,
        kind TEXT NOT NULL,
        message TEXT NOT NULL,
        payload TEXT
    )""",
    "CREATE INDEX events_run_t ON events(run_id, t)",
    "CREATE INDEX events_run_kind ON events(run_id, kind)",
)

_MODEL_COLUMNS = "model, version, provenance, created, fit_percent"


class SQLiteHistory:
    """History store on an embedded SQLite database file (WAL mode).

    Opening a new file creates the schema; opening an existing one checks its
    schema version.  Every write is one transaction; a method that returns
    has committed (see the module notes on durability).

    Parameters
    ----------
    path : str or os.PathLike
        Database file; ``':memory:'`` gives a private in-memory database
        (no WAL, no durability).
    synchronous : {'FULL', 'NORMAL', 'EXTRA'}, default='FULL'
        SQLite ``synchronous`` setting.  ``'FULL'`` fsyncs the WAL at every
        commit, so a committed sample survives a process kill and a power cut;
        ``'NORMAL'`` survives a process kill only.
    timeout : float, default=5.0
        Seconds to wait for a lock held by another connection.

    Raises
    ------
    DataError
        If ``synchronous`` is not one of the accepted values.
    HistoryError
        If the file is not a SQLite database, belongs to another
        application, or has another schema version.

    Attributes
    ----------
    path : str
        The database path.
    journal_mode : str
        SQLite journal mode in use (``'wal'`` for a file).

    See Also
    --------
    HistoryStore : The interface, with the documentation of each method.
    MemoryHistory : The in-memory implementation.

    Notes
    -----
    Tables: ``schema_version``, ``runs``, ``measurements`` (primary key
    ``(run_id, k)``, index on ``(run_id, t)``), ``model_versions`` (primary
    key ``(run_id, version)``, a partial unique index allowing one active
    version per run), ``predictions`` and ``events`` (indices on
    ``(run_id, t)`` and ``(run_id, kind)``).  Foreign keys are enforced.
    SQLite stores NaN as ``NULL``; it reads back as NaN.

    Examples
    --------
    >>> from kautztwin.twin import SQLiteHistory
    >>> with SQLiteHistory(":memory:") as store:
    ...     run = store.start_run({"dt": 0.1})
    ...     store.append_measurements(run, [(0, 0.0, 1.0, 0.5), (1, 0.1, 1.0, float("nan"), 1)])
    ...     m = store.measurements(run)
    ...     state = store.resume(run)
    2
    >>> m.y.tolist(), m.flags.tolist(), state.last_k
    ([0.5, nan], [0, 1], 1)
    """

    def __init__(
        self, path: str | os.PathLike[str], *, synchronous: str = "FULL", timeout: float = 5.0
    ) -> None:
        sync = str(synchronous).upper()
        check_choice(sync, "synchronous", _SYNCHRONOUS)
        self.path = os.fspath(path)
        self._lock = threading.RLock()
        try:
            conn = sqlite3.connect(
                self.path, timeout=timeout, isolation_level=None, check_same_thread=False
            )
        except sqlite3.Error as exc:
            raise HistoryError(f"cannot open the history database {self.path!r}: {exc}") from exc
        self._conn: sqlite3.Connection | None = conn
        try:
            self.journal_mode = str(conn.execute("PRAGMA journal_mode=WAL").fetchone()[0])
            conn.execute(f"PRAGMA synchronous={sync}")
            conn.execute("PRAGMA foreign_keys=ON")
            self._init_schema()
        except sqlite3.DatabaseError as exc:
            self.close()
            raise HistoryError(f"{self.path!r} is not a usable SQLite database: {exc}") from exc
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ plumbing
    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise HistoryError(f"the history store {self.path!r} is closed")
        return self._conn

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``), rolled back on error."""
        with self._lock:
            conn = self._connection()
            try:
                conn.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as exc:
                raise HistoryError(f"cannot write to {self.path!r}: {exc}") from exc
            try:
                yield conn
            except BaseException as exc:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                if isinstance(exc, sqlite3.Error):
                    raise HistoryError(f"history database {self.path!r}: {exc}") from exc
                raise
            try:
                conn.execute("COMMIT")
            except sqlite3.Error as exc:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise HistoryError(f"commit to {self.path!r} failed: {exc}") from exc

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            try:
                yield self._connection()
            except sqlite3.Error as exc:
                raise HistoryError(f"history database {self.path!r}: {exc}") from exc

    def _init_schema(self) -> None:
        with self._write() as conn:
            tables = {
                r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")
            }
            if "schema_version" not in tables:
                if tables - {"sqlite_sequence"}:
                    raise HistoryError(
                        f"{self.path!r} holds tables {sorted(tables)} but no kautztwin history"
                    )
                for statement in _SCHEMA:
                    conn.execute(statement)
                conn.execute(
                    "INSERT INTO schema_version(version, applied) VALUES (?, ?)",
                    (SCHEMA_VERSION, time.time()),
                )
                return
            version = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
            if version != SCHEMA_VERSION:
                raise HistoryError(
                    f"{self.path!r} has history schema version {version}; "
                    f"this kautztwin reads version {SCHEMA_VERSION}"
                )

    @staticmethod
    def _require_run(conn: sqlite3.Connection, run_id: Any) -> tuple[int, str]:
        rid = check_int(run_id, "run_id")
        row = conn.execute("SELECT status FROM runs WHERE run_id = ?", (rid,)).fetchone()
        if row is None:
            raise HistoryError(f"no run with run_id = {rid}")
        return rid, row[0]

    # ------------------------------------------------------------------ runs
    def start_run(
        self, config: Mapping[str, Any] | None = None, *, started: float | None = None
    ) -> int:
        """Create a run; see :meth:`HistoryStore.start_run`."""
        text = _dumps({} if config is None else config, "config")
        t0 = _time(started, "started")
        with self._write() as conn:
            cur = conn.execute(
                "INSERT INTO runs(started, status, config) VALUES (?, 'running', ?)", (t0, text)
            )
            return int(cur.lastrowid)  # type: ignore[arg-type]

    def resume(self, run_id: int) -> ResumeState:
        """Reopen a run after a restart; see :meth:`HistoryStore.resume`."""
        with self._write() as conn:
            rid, status = self._require_run(conn, run_id)
            n, last_k = conn.execute(
                "SELECT COUNT(*), MAX(k) FROM measurements WHERE run_id = ?", (rid,)
            ).fetchone()
            last_t = None
            if last_k is not None:
                (t,) = conn.execute(
                    "SELECT t FROM measurements WHERE run_id = ? AND k = ?", (rid, last_k)
                ).fetchone()
                last_t = _nan(t)
            row = conn.execute(
                "SELECT version FROM model_versions WHERE run_id = ? AND active = 1", (rid,)
            ).fetchone()
            conn.execute(
                "UPDATE runs SET status = 'running', finished = NULL WHERE run_id = ?", (rid,)
            )
            conn.execute(
                "INSERT INTO events(run_id, k, t, kind, message, payload) "
                "VALUES (?, ?, ?, 'resume', ?, ?)",
                (rid, last_k, time.time(), _resume_message(last_k),
                 _dumps({"last_k": last_k, "previous_status": status}, "payload")),
            )  # fmt: skip
        return ResumeState(rid, last_k, last_t, int(n), None if row is None else row[0], status)

    def finish_run(self, run_id: int, status: str = "finished") -> None:
        """End a run; see :meth:`HistoryStore.finish_run`."""
        status = _check_text(status, "status")
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            conn.execute(
                "UPDATE runs SET status = ?, finished = ? WHERE run_id = ?",
                (status, time.time(), rid),
            )

    def run_info(self, run_id: int) -> RunInfo:
        """Metadata of one run; see :meth:`HistoryStore.run_info`."""
        rid = check_int(run_id, "run_id")
        with self._read() as conn:
            row = conn.execute(
                "SELECT run_id, started, finished, status, config FROM runs WHERE run_id = ?",
                (rid,),
            ).fetchone()
        if row is None:
            raise HistoryError(f"no run with run_id = {rid}")
        return RunInfo(row[0], row[1], row[2], row[3], json.loads(row[4]))

    def runs(self) -> list[RunInfo]:
        """Metadata of every run; see :meth:`HistoryStore.runs`."""
        with self._read() as conn:
            rows = conn.execute(
                "SELECT run_id, started, finished, status, config FROM runs ORDER BY run_id"
            ).fetchall()
        return [RunInfo(r[0], r[1], r[2], r[3], json.loads(r[4])) for r in rows]

    # ------------------------------------------------------------------ measurements
    def append_measurements(self, run_id: int, rows: Iterable[Sequence[Any]] | Measurements) -> int:
        """Append samples in one transaction; see :meth:`HistoryStore.append_measurements`."""
        parsed = _parse_rows(rows)
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            try:
                conn.executemany(
                    "INSERT INTO measurements(run_id, k, t, u, y, flags) VALUES (?, ?, ?, ?, ?, ?)",
                    [(rid, *r) for r in parsed],
                )
            except sqlite3.IntegrityError as exc:
                conn.execute("ROLLBACK")  # undo the rows inserted before the clash
                ks = [r[0] for r in parsed]
                stored = [
                    k
                    for k in ks
                    if conn.execute(
                        "SELECT 1 FROM measurements WHERE run_id = ? AND k = ?", (rid, k)
                    ).fetchone()
                ]
                raise HistoryError(
                    f"run {rid} already has sample k = {stored[0] if stored else '?'}; "
                    "nothing of this batch was stored"
                ) from exc
        return len(parsed)

    def measurements(self, run_id: int, since: int | None = None) -> Measurements:
        """Samples of a run; see :meth:`HistoryStore.measurements`."""
        lo = -1 if since is None else _check_int(since, "since", minimum=None)
        with self._read() as conn:
            rid, _ = self._require_run(conn, run_id)
            rows = conn.execute(
                "SELECT k, t, u, y, flags FROM measurements WHERE run_id = ? AND k > ? ORDER BY k",
                (rid, lo),
            ).fetchall()
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
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            exists = conn.execute(
                "SELECT 1 FROM model_versions WHERE run_id = ? AND version = ?",
                (rid, model.version),
            ).fetchone()
            if exists:
                raise HistoryError(f"run {rid} already has model version {model.version}")
            if active:
                conn.execute(
                    "UPDATE model_versions SET active = 0 WHERE run_id = ? AND active = 1", (rid,)
                )
            conn.execute(
                "INSERT INTO model_versions(run_id, version, created, k, provenance, "
                "fit_percent, active, model) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (rid, model.version, model.created, k, model.provenance, model.fit_percent,
                 int(bool(active)), text),
            )  # fmt: skip
        return model.version

    def activate_model(self, run_id: int, version: int) -> None:
        """Make a stored version active; see :meth:`HistoryStore.activate_model`."""
        version = _check_int(version, "version")
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            exists = conn.execute(
                "SELECT 1 FROM model_versions WHERE run_id = ? AND version = ?", (rid, version)
            ).fetchone()
            if not exists:
                raise HistoryError(f"run {rid} has no model version {version}")
            conn.execute(
                "UPDATE model_versions SET active = 0 WHERE run_id = ? AND active = 1", (rid,)
            )
            conn.execute(
                "UPDATE model_versions SET active = 1 WHERE run_id = ? AND version = ?",
                (rid, version),
            )

    def active_model(self, run_id: int) -> DigitalModel | None:
        """The active model; see :meth:`HistoryStore.active_model`."""
        with self._read() as conn:
            rid, _ = self._require_run(conn, run_id)
            row = conn.execute(
                f"SELECT {_MODEL_COLUMNS} FROM model_versions WHERE run_id = ? AND active = 1",
                (rid,),
            ).fetchone()
        return None if row is None else _digital_model(*row)

    def model_versions(self, run_id: int) -> list[DigitalModel]:
        """Every stored version; see :meth:`HistoryStore.model_versions`."""
        with self._read() as conn:
            rid, _ = self._require_run(conn, run_id)
            rows = conn.execute(
                f"SELECT {_MODEL_COLUMNS} FROM model_versions WHERE run_id = ? ORDER BY version",
                (rid,),
            ).fetchall()
        return [_digital_model(*r) for r in rows]

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
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            if (
                model_version is not None
                and not conn.execute(
                    "SELECT 1 FROM model_versions WHERE run_id = ? AND version = ?",
                    (rid, model_version),
                ).fetchone()
            ):
                raise HistoryError(f"run {rid} has no model version {model_version}")
            conn.execute(
                "INSERT INTO predictions(run_id, k, t, horizon, model_version, y_pred) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (rid, k, tt, horizon, model_version, text),
            )

    def add_predictions(
        self, run_id: int, rows: Iterable[tuple[int, float | None, int | None, ArrayLike]]
    ) -> int:
        """Store many predictions in one transaction.

        Parameters
        ----------
        run_id : int
            The run.
        rows : iterable of (k, t, model_version, y_pred)
            As the arguments of :meth:`add_prediction`.

        Returns
        -------
        int
            Number of predictions stored.

        Raises
        ------
        HistoryError
            If a ``model_version`` is not stored for the run.
        """
        values = []
        for k, t, version, y_pred in rows:
            horizon, text = _pred_json(np.atleast_1d(np.asarray(y_pred, dtype=float)))
            values.append((_check_int(k, "k"), _real(t, "t"), horizon,
                           _opt_int(version, "model_version"), text))
        if not values:
            return 0
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            stored = {r[0] for r in conn.execute(
                "SELECT version FROM model_versions WHERE run_id = ?", (rid,))}
            missing = {v[3] for v in values if v[3] is not None} - stored
            if missing:
                raise HistoryError(f"run {rid} has no model version {min(missing)}")
            conn.executemany(
                "INSERT INTO predictions(run_id, k, t, horizon, model_version, y_pred) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                [(rid, *v) for v in values],
            )
        return len(values)

    def predictions(self, run_id: int, since: int | None = None) -> list[Prediction]:
        """Stored predictions; see :meth:`HistoryStore.predictions`."""
        lo = -1 if since is None else _check_int(since, "since", minimum=None)
        with self._read() as conn:
            rid, _ = self._require_run(conn, run_id)
            rows = conn.execute(
                "SELECT k, t, horizon, model_version, y_pred FROM predictions "
                "WHERE run_id = ? AND k > ? ORDER BY k, prediction_id",
                (rid, lo),
            ).fetchall()
        return [Prediction(rid, r[0], r[1], r[2], r[3], _pred_array(r[4])) for r in rows]

    # ------------------------------------------------------------------ events
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
        with self._write() as conn:
            rid, _ = self._require_run(conn, run_id)
            cur = conn.execute(
                "INSERT INTO events(run_id, k, t, kind, message, payload) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (rid, k, tt, kind, message, text),
            )
            return int(cur.lastrowid)  # type: ignore[arg-type]

    def events(self, run_id: int, kind: str | None = None) -> list[Event]:
        """Logged events; see :meth:`HistoryStore.events`."""
        query = "SELECT event_id, run_id, k, t, kind, message, payload FROM events WHERE run_id = ?"
        with self._read() as conn:
            rid, _ = self._require_run(conn, run_id)
            if kind is None:
                rows = conn.execute(query + " ORDER BY event_id", (rid,)).fetchall()
            else:
                rows = conn.execute(
                    query + " AND kind = ? ORDER BY event_id", (rid, _check_text(kind, "kind"))
                ).fetchall()
        return [Event(*r[:6], None if r[6] is None else json.loads(r[6])) for r in rows]

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Close the database connection; see :meth:`HistoryStore.close`."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> SQLiteHistory:
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
        state = "closed" if self._conn is None else self.journal_mode
        return f"SQLiteHistory({self.path!r}, {state})"
