"""History store of the digital twin: runs, measurements, model versions, predictions, events.

:class:`HistoryStore` is the interface the twin runtime writes to.  Two
implementations ship: :class:`SQLiteHistory` (the default, an embedded SQLite
file in WAL mode) and :class:`MemoryHistory` (in memory, for tests and
replay).  A server database can implement the same protocol later.

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
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..approx.model import KautzModel
from ..exceptions import DataError, KautzTwinError
from .digital_model import DigitalModel

__all__ = [
    "SCHEMA_VERSION",
    "Event",
    "HistoryError",
    "HistoryStore",
    "Measurement",
    "Measurements",
    "MemoryHistory",
    "Prediction",
    "ResumeState",
    "RunInfo",
    "SQLiteHistory",
]

SCHEMA_VERSION = 1
"""Version of the SQLite schema written by :class:`SQLiteHistory`."""

_SYNCHRONOUS = ("NORMAL", "FULL", "EXTRA")


class HistoryError(KautzTwinError, RuntimeError):
    """The history store cannot do what was asked.

    Raised for an unknown run or model version, a sample index or model
    version that is already stored, a closed store, or a database file with
    another schema version.
    """


# ---------------------------------------------------------------------- records
class Measurement(NamedTuple):
    """One stored sample: a row for :meth:`HistoryStore.append_measurements`.

    Parameters
    ----------
    k : int
        Sample index (unique within a run, ``>= 0``).
    t : float
        Timestamp (NaN if unknown).
    u : float
        Input (NaN for a dropout).
    y : float
        Output (NaN for a dropout).
    flags : int, default=0
        :class:`~kautztwin.twin.SampleFlag` bitmask.
    """

    k: int
    t: float
    u: float
    y: float
    flags: int = 0


@dataclass(frozen=True, eq=False)
class Measurements:
    """The samples of a run as read-only arrays, ordered by sample index.

    Parameters
    ----------
    k : array-like of int, shape (n_samples,)
        Sample indices.
    t, u, y : array-like of float, shape (n_samples,)
        Timestamps, inputs and outputs; NaN where missing.
    flags : array-like of int, shape (n_samples,)
        :class:`~kautztwin.twin.SampleFlag` bitmasks.

    Raises
    ------
    DataError
        If the arrays are not 1-D of one common length.
    """

    k: NDArray[np.int64]
    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    flags: NDArray[np.int64]

    def __post_init__(self) -> None:
        n = None
        for name in ("k", "t", "u", "y", "flags"):
            dtype = np.int64 if name in ("k", "flags") else np.float64
            a = np.array(getattr(self, name), dtype=dtype, copy=True).reshape(-1)
            if np.ndim(getattr(self, name)) > 1:
                raise DataError(f"{name} must be 1-D, got shape {np.shape(getattr(self, name))}")
            if n is not None and a.size != n:
                raise DataError(f"{name} has {a.size} samples but k has {n}")
            n = a.size
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.k.size)

    def rows(self) -> list[Measurement]:
        """The samples as :class:`Measurement` rows (to copy them into another store).

        Returns
        -------
        list of Measurement
        """
        return [
            Measurement(int(k), float(t), float(u), float(y), int(f))
            for k, t, u, y, f in zip(self.k, self.t, self.u, self.y, self.flags, strict=True)
        ]


@dataclass(frozen=True)
class RunInfo:
    """A run's metadata.

    Parameters
    ----------
    run_id : int
        Run identifier.
    started : float
        Start time (seconds since the epoch).
    finished : float or None
        Time of :meth:`HistoryStore.finish_run`, or ``None`` while running.
    status : str
        ``'running'`` or the status given to :meth:`HistoryStore.finish_run`.
    config : dict
        The run configuration (as decoded from JSON).
    """

    run_id: int
    started: float
    finished: float | None
    status: str
    config: dict[str, Any] = field(hash=False)


@dataclass(frozen=True)
class ResumeState:
    """Where a run stands when it is resumed.

    Parameters
    ----------
    run_id : int
        Run identifier.
    last_k : int or None
        Largest committed sample index, ``None`` if the run has no sample.
    last_t : float or None
        Timestamp of sample ``last_k`` (``None`` without samples; NaN if unknown).
    n_samples : int
        Number of committed samples.
    active_version : int or None
        Version of the active model, ``None`` if none was stored.
    previous_status : str
        The run's status before :meth:`HistoryStore.resume` (``'running'``
        after a crash).
    """

    run_id: int
    last_k: int | None
    last_t: float | None
    n_samples: int
    active_version: int | None
    previous_status: str

    @property
    def next_k(self) -> int:
        """The sample index to continue with: ``last_k + 1`` (0 for an empty run)."""
        return 0 if self.last_k is None else self.last_k + 1


@dataclass(frozen=True)
class Event:
    """A logged event (model update, alarm, resume, ...).

    Parameters
    ----------
    event_id : int
        Identifier, increasing in logging order.
    run_id : int
        Run identifier.
    k : int or None
        Sample index the event refers to, if any.
    t : float
        Event time.
    kind : str
        Category, for example ``'model-update'``, ``'alarm'``, ``'resume'``.
    message : str
        Human-readable text.
    payload : Any
        JSON-decoded payload (``None`` when none was given).
    """

    event_id: int
    run_id: int
    k: int | None
    t: float
    kind: str
    message: str
    payload: Any = field(hash=False)


@dataclass(frozen=True, eq=False)
class Prediction:
    """A stored multi-step prediction made at sample ``k``.

    Parameters
    ----------
    run_id : int
        Run identifier.
    k : int
        Sample index at which the prediction was made.
    t : float or None
        Its time, if given.
    horizon : int
        Number of predicted steps, ``len(y_pred)``.
    model_version : int or None
        Version of the model that made it, if given.
    y_pred : ndarray of shape (horizon,)
        Predicted outputs for samples ``k + 1, ..., k + horizon`` (read-only).
    """

    run_id: int
    k: int
    t: float | None
    horizon: int
    model_version: int | None
    y_pred: NDArray[np.float64]

    def __post_init__(self) -> None:
        y = np.array(self.y_pred, dtype=float, copy=True).reshape(-1)
        y.setflags(write=False)
        object.__setattr__(self, "y_pred", y)


# ---------------------------------------------------------------------- interface
@runtime_checkable
class HistoryStore(Protocol):
    """Interface of a history store; the twin runtime depends on this only.

    Every method that takes ``run_id`` raises :class:`HistoryError` when the
    run does not exist, and every method raises :class:`HistoryError` after
    :meth:`close`.  A store is a context manager that closes on exit.

    See Also
    --------
    SQLiteHistory : Durable implementation on an embedded SQLite file.
    MemoryHistory : In-memory implementation for tests and replay.
    """

    def start_run(
        self, config: Mapping[str, Any] | None = None, *, started: float | None = None
    ) -> int:
        """Create a run with status ``'running'``.

        Parameters
        ----------
        config : mapping or None, default=None
            Run configuration, stored as JSON (numpy values are converted,
            tuples become lists, non-finite floats become ``null``).
        started : float or None, default=None
            Start time; ``None`` means now.

        Returns
        -------
        int
            The new run's identifier.

        Raises
        ------
        DataError
            If ``config`` holds a value JSON cannot represent.
        """
        ...

    def resume(self, run_id: int) -> ResumeState:
        """Reopen a run after a restart: status back to ``'running'``.

        Logs a ``'resume'`` event with the last committed sample index.

        Parameters
        ----------
        run_id : int
            The run.

        Returns
        -------
        ResumeState
            Last committed sample index and time, sample count, active model
            version and the previous status.
        """
        ...

    def finish_run(self, run_id: int, status: str = "finished") -> None:
        """Mark a run as ended, with its final status and end time.

        Parameters
        ----------
        run_id : int
            The run.
        status : str, default='finished'
            Final status, for example ``'finished'``, ``'failed'``, ``'aborted'``.
        """
        ...

    def run_info(self, run_id: int) -> RunInfo:
        """Metadata of one run.

        Parameters
        ----------
        run_id : int
            The run.

        Returns
        -------
        RunInfo
        """
        ...

    def runs(self) -> list[RunInfo]:
        """Metadata of every run, by increasing ``run_id``.

        Returns
        -------
        list of RunInfo
        """
        ...

    def append_measurements(self, run_id: int, rows: Iterable[Sequence[Any]] | Measurements) -> int:
        """Append samples in one transaction: all are committed, or none.

        Parameters
        ----------
        run_id : int
            The run.
        rows : iterable of (k, t, u, y[, flags]) or Measurements
            Samples; ``k`` an integer ``>= 0`` unique within the run, ``t``,
            ``u``, ``y`` real numbers (NaN or ``None`` for missing),
            ``flags`` a non-negative integer (default 0).

        Returns
        -------
        int
            Number of samples committed.

        Raises
        ------
        DataError
            If a row is malformed or repeats a ``k`` of the batch.
        HistoryError
            If a ``k`` is already stored for the run (nothing is committed).
        """
        ...

    def measurements(self, run_id: int, since: int | None = None) -> Measurements:
        """Samples of a run ordered by ``k``.

        Parameters
        ----------
        run_id : int
            The run.
        since : int or None, default=None
            Return only samples with ``k > since`` (pass the last ``k`` seen
            to fetch new samples); ``None`` returns all.

        Returns
        -------
        Measurements
        """
        ...

    def add_model_version(
        self, run_id: int, model: DigitalModel, *, active: bool = True, k: int | None = None
    ) -> int:
        """Store a model version; with ``active=True`` it replaces the active one.

        Parameters
        ----------
        run_id : int
            The run.
        model : DigitalModel
            The versioned model (its version must be new for the run).
        active : bool, default=True
            Make it the run's active model (atomically deactivating the previous).
        k : int or None, default=None
            Sample index at which it was created, if known.

        Returns
        -------
        int
            The stored version number.

        Raises
        ------
        HistoryError
            If the run already has this version.
        """
        ...

    def activate_model(self, run_id: int, version: int) -> None:
        """Make a stored version the active model (for example a rollback).

        Parameters
        ----------
        run_id : int
            The run.
        version : int
            A stored version.

        Raises
        ------
        HistoryError
            If the version is not stored.
        """
        ...

    def active_model(self, run_id: int) -> DigitalModel | None:
        """The active model of a run, ``None`` if there is none.

        Parameters
        ----------
        run_id : int
            The run.

        Returns
        -------
        DigitalModel or None
        """
        ...

    def model_versions(self, run_id: int) -> list[DigitalModel]:
        """Every stored model version of a run, by increasing version.

        Parameters
        ----------
        run_id : int
            The run.

        Returns
        -------
        list of DigitalModel
        """
        ...

    def add_prediction(
        self,
        run_id: int,
        k: int,
        y_pred: ArrayLike,
        *,
        model_version: int | None = None,
        t: float | None = None,
    ) -> None:
        """Store a prediction of the next ``len(y_pred)`` outputs, made at sample ``k``.

        Parameters
        ----------
        run_id : int
            The run.
        k : int
            Sample index at which the prediction was made.
        y_pred : array-like of shape (horizon,)
            Predicted outputs (NaN allowed).
        model_version : int or None, default=None
            The stored model version that made it.
        t : float or None, default=None
            Time of the prediction.

        Raises
        ------
        HistoryError
            If ``model_version`` is not stored for the run.
        """
        ...

    def predictions(self, run_id: int, since: int | None = None) -> list[Prediction]:
        """Stored predictions ordered by ``k`` (then storage order).

        Parameters
        ----------
        run_id : int
            The run.
        since : int or None, default=None
            Only predictions with ``k > since``.

        Returns
        -------
        list of Prediction
        """
        ...

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
        """Log an event.

        Parameters
        ----------
        run_id : int
            The run.
        kind : str
            Non-empty category, for example ``'model-update'`` or ``'alarm'``.
        message : str, default=''
            Human-readable text.
        k : int or None, default=None
            Sample index the event refers to.
        t : float or None, default=None
            Event time; ``None`` means now.
        payload : Any, default=None
            JSON-serialisable data (converted like ``config`` in :meth:`start_run`).

        Returns
        -------
        int
            The event's identifier.
        """
        ...

    def events(self, run_id: int, kind: str | None = None) -> list[Event]:
        """Logged events of a run in logging order.

        Parameters
        ----------
        run_id : int
            The run.
        kind : str or None, default=None
            Only events of this kind.

        Returns
        -------
        list of Event
        """
        ...

    def close(self) -> None:
        """Release the store; later calls raise :class:`HistoryError`.  Idempotent."""
        ...

    def __enter__(self) -> HistoryStore:
        """Return the store itself."""
        ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Close the store."""
        ...


# ---------------------------------------------------------------------- shared helpers
def _jsonable(obj: Any, name: str) -> Any:
    """``obj`` with numpy values, tuples and non-finite floats made JSON-ready."""
    if obj is None or isinstance(obj, str | bool):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, complex | np.complexfloating):
        return [_jsonable(obj.real, name), _jsonable(obj.imag, name)]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist(), name)
    if isinstance(obj, Mapping):
        return {str(key): _jsonable(value, name) for key, value in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(value, name) for value in obj]
    raise DataError(f"{name} holds a {type(obj).__name__} ({obj!r}), which JSON cannot represent")


def _dumps(obj: Any, name: str) -> str:
    return json.dumps(_jsonable(obj, name), allow_nan=False, sort_keys=True, separators=(",", ":"))


def _check_int(value: Any, name: str, *, minimum: int | None = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise DataError(f"{name} must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        raise DataError(f"{name} must be >= {minimum}, got {value}")
    if not -(2**63) <= value < 2**63:
        raise DataError(f"{name} must fit in 64 bits, got {value}")
    return int(value)


def _check_run_id(run_id: Any) -> int:
    if isinstance(run_id, bool) or not isinstance(run_id, int | np.integer):
        raise DataError(f"run_id must be an integer, got {run_id!r}")
    return int(run_id)


def _opt_int(value: Any, name: str) -> int | None:
    return None if value is None else _check_int(value, name)


def _real(value: Any, name: str) -> float | None:
    """A float for the database: ``None`` for a missing value (NaN or None)."""
    if value is None:
        return None
    if isinstance(value, bool | np.bool_):
        raise DataError(f"{name} must be a real number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DataError(f"{name} must be a real number, got {value!r}") from exc
    return None if math.isnan(x) else x


def _time(value: Any, name: str) -> float:
    """A finite time; ``None`` means now."""
    if value is None:
        return time.time()
    x = _real(value, name)
    if x is None or not math.isfinite(x):
        raise DataError(f"{name} must be a finite number, got {value!r}")
    return x


def _nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _check_text(value: Any, name: str, *, empty: bool = False) -> str:
    if not isinstance(value, str) or (not empty and not value.strip()):
        raise DataError(f"{name} must be a {'' if empty else 'non-empty '}string, got {value!r}")
    return value


def _parse_rows(
    rows: Iterable[Sequence[Any]] | Measurements,
) -> list[tuple[int, float | None, float | None, float | None, int]]:
    if isinstance(rows, Measurements):
        rows = rows.rows()
    elif isinstance(rows, Measurement):
        rows = [rows]
    if isinstance(rows, str | bytes) or not isinstance(rows, Iterable):
        raise DataError(f"rows must be an iterable of (k, t, u, y[, flags]) rows, got {rows!r}")
    out = []
    for i, row in enumerate(rows):
        if isinstance(row, str | bytes) or not isinstance(row, Sequence | np.ndarray):
            raise DataError(f"rows[{i}] must be a (k, t, u, y[, flags]) sequence, got {row!r}")
        if len(row) not in (4, 5):
            raise DataError(
                f"rows[{i}] must have 4 or 5 fields (k, t, u, y[, flags]), got {len(row)}"
            )
        k = _check_int(row[0], f"rows[{i}].k")
        flags = _check_int(row[4], f"rows[{i}].flags") if len(row) == 5 else 0
        out.append(
            (k, _real(row[1], f"rows[{i}].t"), _real(row[2], f"rows[{i}].u"),
             _real(row[3], f"rows[{i}].y"), flags)
        )  # fmt: skip
    seen: set[int] = set()
    for r in out:
        if r[0] in seen:
            raise DataError(f"rows repeat the sample index k = {r[0]}")
        seen.add(r[0])
    return out


def _measurements(rows: list[tuple[Any, ...]]) -> Measurements:
    a = np.array(rows, dtype=float).reshape(-1, 5)  # None -> NaN
    return Measurements(
        a[:, 0].astype(np.int64), a[:, 1], a[:, 2], a[:, 3], a[:, 4].astype(np.int64)
    )


def _pred_json(y_pred: ArrayLike) -> tuple[int, str]:
    try:
        y = np.asarray(y_pred, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DataError(f"y_pred must be an array of real numbers, got {y_pred!r}") from exc
    if y.ndim != 1:
        raise DataError(f"y_pred must be 1-D (horizon,), got shape {y.shape}")
    return int(y.size), _dumps(y, "y_pred")


def _pred_array(text: str) -> NDArray[np.float64]:
    return np.array([math.nan if v is None else v for v in json.loads(text)], dtype=float)


def _digital_model(
    model_json: str, version: int, provenance: str, created: float, fit: float | None
) -> DigitalModel:
    return DigitalModel(
        KautzModel.from_dict(json.loads(model_json)), version, provenance, created, fit
    )


def _resume_message(last_k: int | None) -> str:
    return "resumed an empty run" if last_k is None else f"resumed after sample {last_k}"


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
        if sync not in _SYNCHRONOUS:
            raise DataError(
                f"synchronous must be one of {', '.join(map(repr, _SYNCHRONOUS))}; "
                f"got {synchronous!r}"
            )
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
        rid = _check_run_id(run_id)
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
        rid = _check_run_id(run_id)
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
        rid = _check_run_id(run_id)
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
