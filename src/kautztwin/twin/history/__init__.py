"""History module of the twin: runs, measurements, model versions, predictions, events.

:class:`HistoryStore` (:mod:`.protocol`) is the interface the twin runtime
writes to.  Two implementations ship: :class:`SQLiteHistory` (:mod:`.sqlite`,
the default, an embedded SQLite file in WAL mode; its module notes describe
durability and concurrency) and :class:`MemoryHistory` (:mod:`.memory`, in
memory, for tests and replay).  A server database can implement the same
protocol later.  The records they return and the row/JSON conversions they
share live in :mod:`.records`; :func:`read_run` (:mod:`.readback`) reads a run back.
"""

from __future__ import annotations

from .memory import MemoryHistory
from .protocol import HistoryStore
from .readback import SIGNALS, RunHistory, read_run
from .records import (
    SCHEMA_VERSION,
    Event,
    HistoryError,
    Measurement,
    Measurements,
    Prediction,
    ResumeState,
    RunInfo,
)
from .sqlite import SQLiteHistory

__all__ = [
    "SCHEMA_VERSION",
    "SIGNALS",
    "Event",
    "HistoryError",
    "HistoryStore",
    "Measurement",
    "Measurements",
    "MemoryHistory",
    "Prediction",
    "ResumeState",
    "RunHistory",
    "RunInfo",
    "SQLiteHistory",
    "read_run",
]
