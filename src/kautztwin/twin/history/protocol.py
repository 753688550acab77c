"""The :class:`HistoryStore` protocol: the interface the twin runtime writes its history to."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from types import TracebackType
from typing import Any, Protocol, runtime_checkable

from numpy.typing import ArrayLike

from ..digital import DigitalModel
from .records import Event, Measurements, Prediction, ResumeState, RunInfo

__all__ = ["HistoryStore"]


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
