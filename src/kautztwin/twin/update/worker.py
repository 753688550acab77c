"""Background worker of the update module's accurate path: one fit in a worker thread.

A re-identification attempt is frozen into a :class:`_ReidJob` (a copy of the
data window and the current poles); :func:`_fit_window` computes its
candidate, a pure function of the job.  :class:`_ReidWorker` owns the single
worker thread and the attempt in flight (:class:`_Pending`): it submits a
job, marks it stale (and asks the fit to stop between its starts) when the
twin moves on, and hands a finished attempt back to the
:class:`~kautztwin.twin.update.Updater`, which judges it.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...ident.kautz_oe import OutputErrorFit, identify_output_error


@dataclass(frozen=True, eq=False)
class _ReidJob:
    """Frozen inputs of one re-identification attempt (copied when it is prepared).

    ``u`` and ``y`` are the window with its burn-in history (read-only
    copies); ``u[:n_est]`` is fitted (from sample ``w0`` on), the last
    ``n_val`` samples are held out for the validation.  ``k`` is the
    updater's sample counter when the window ended.
    """

    u: NDArray[np.float64]
    y: NDArray[np.float64]
    w0: int
    n_est: int
    n_val: int
    poles: NDArray[np.complex128]
    dt: float
    input_offset: float
    min_rate: float | None
    max_iter: int
    k: int


@dataclass(frozen=True, eq=False)
class _ReidOutcome:
    """What a fit returns: the best start (``None`` when cancelled) and its compute time."""

    fit: OutputErrorFit | None
    elapsed: float


def _fit_window(job: _ReidJob, cancel: threading.Event | None = None) -> _ReidOutcome:
    """The accurate path's computation: output error from the current poles and two scalings.

    A pure function of ``job`` (it runs in the worker thread in background
    mode).  ``cancel`` is checked between the starts.
    """
    start = time.perf_counter()
    best: OutputErrorFit | None = None
    for scale in (1.0, 0.75, 1.33):
        if cancel is not None and cancel.is_set():
            return _ReidOutcome(None, time.perf_counter() - start)
        fit = identify_output_error(
            job.u[: job.n_est], job.y[: job.n_est], _scaled_poles(job.poles, scale), dt=job.dt,
            burn_in=job.w0, input_offset=job.input_offset, min_rate=job.min_rate,
            max_iter=job.max_iter,
        )
        if best is None or fit.fit_percent > best.fit_percent:
            best = fit
    return _ReidOutcome(best, time.perf_counter() - start)


@dataclass
class _Pending:
    """A background attempt in flight."""

    job: _ReidJob
    future: Future[_ReidOutcome]
    cancel: threading.Event
    stale: str = ""  # why its result will be discarded ("" while it is current)



def _scaled_poles(poles: NDArray[np.complex128], scale: float) -> NDArray[np.complex128]:
    """Continuous poles with their decay rates (real parts) scaled."""
    return np.asarray([complex(p.real * scale, p.imag) for p in poles])


class _ReidWorker:
    """The single worker thread of the background accurate path and its attempt in flight.

    At most one attempt is in flight (:attr:`pending`).  The thread is started
    at the first :meth:`submit` and stopped by :meth:`close`.
    """

    def __init__(self) -> None:
        self._executor: ThreadPoolExecutor | None = None
        self.pending: _Pending | None = None
        self.closed = False

    @staticmethod
    def fit_now(job: _ReidJob) -> _ReidOutcome:
        """Compute an attempt in the caller's thread (the synchronous accurate path)."""
        return _fit_window(job)

    def submit(self, job: _ReidJob) -> None:
        """Start ``job`` in the worker thread (the caller checked that none is pending)."""
        if self._executor is None:
            self._executor = ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="kautztwin-reidentify"
            )
        cancel = threading.Event()
        # looked up at call time, so that tests can slow the fit down
        future = self._executor.submit(_fit_window, job, cancel)
        self.pending = _Pending(job, future, cancel)

    def make_stale(self, reason: str) -> None:
        """Mark the attempt in flight (if any) stale and ask the worker to stop early."""
        p = self.pending
        if p is not None and not p.stale:
            p.stale = reason
            p.cancel.set()
            p.future.cancel()  # succeeds only if it has not started

    def take_finished(self) -> _Pending | None:
        """The attempt in flight once its computation is done (no longer pending), else ``None``."""
        p = self.pending
        if p is None or not p.future.done():
            return None
        self.pending = None
        return p

    def cancel(self, reason: str) -> bool:
        """Make the attempt in flight stale; whether one was in flight (and not stale yet)."""
        was = self.pending is not None and not self.pending.stale
        self.make_stale(reason)
        return was

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the attempt in flight has finished computing; whether none is outstanding."""
        p = self.pending
        if p is None:
            return True
        try:
            p.future.exception(timeout=timeout)
        except TimeoutError:
            return False
        except CancelledError:
            pass
        return True

    def close(self) -> None:
        """Cancel the attempt in flight and join the thread (idempotent)."""
        self.closed = True
        if self.pending is not None:
            self.make_stale("the updater was closed")
            self.pending = None
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
