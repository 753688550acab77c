"""Records of the history store and their row/JSON conversions (shared by both stores).

The records (:class:`Measurement`, :class:`Measurements`, :class:`RunInfo`,
:class:`ResumeState`, :class:`Event`, :class:`Prediction`) are what a store
returns; the private conversions below turn arguments into database values
(JSON text, ``None`` for a missing number) and back, so that
:class:`~kautztwin.twin.history.SQLiteHistory` and
:class:`~kautztwin.twin.history.MemoryHistory` behave alike.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._json import to_jsonable
from ..._validation import check_int
from ...approx.model import KautzModel
from ...exceptions import DataError, KautzTwinError
from ..digital import DigitalModel

__all__ = [
    "SCHEMA_VERSION",
    "Event",
    "HistoryError",
    "Measurement",
    "Measurements",
    "Prediction",
    "ResumeState",
    "RunInfo",
]

SCHEMA_VERSION = 1
"""Version of the SQLite schema written by :class:`SQLiteHistory`."""


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


# ---------------------------------------------------------------------- shared helpers
def _dumps(obj: Any, name: str) -> str:
    return json.dumps(
        to_jsonable(obj, name), allow_nan=False, sort_keys=True, separators=(",", ":")
    )


def _check_int(value: Any, name: str, *, minimum: int | None = 0) -> int:
    """:func:`~kautztwin._validation.check_int` for an SQLite ``INTEGER`` column.

    Worded ``"k must be >= 0"`` and limited to 64 bits, as the database requires.
    """
    value = check_int(value, name)
    if minimum is not None and value < minimum:
        raise DataError(f"{name} must be >= {minimum}, got {value}")
    if not -(2**63) <= value < 2**63:
        raise DataError(f"{name} must fit in 64 bits, got {value}")
    return value


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
