"""Background worker of the update module's accurate path: one fit in a worker thread or process.

A re-identification attempt is frozen into a :class:`_ReidJob` (a copy of the
data window and the current poles); :func:`_fit_window` computes its
candidate, a pure function of the job.  :class:`_ReidWorker` owns the single
worker (a thread, or a process) and the attempt in flight (:class:`_Pending`):
it submits a job, marks it stale (a fit that has not begun its search then
skips it) when the twin moves on, and hands a finished attempt back to the
:class:`~kautztwin.twin.update.Updater`, which judges it.

**Process worker** (``kind='process'``, ``Updater(worker='process')``): the fit
runs in one child process started with the ``forkserver`` method (``spawn``
where that is missing; never ``fork``: the parent runs threads, e.g. a network
link's client), at a lower CPU priority (``nice`` +5), so that it takes neither
the parent's GIL nor CPU time the sampling loop needs first.  The job and its
outcome are pickled (numpy arrays, floats, an
:class:`~kautztwin.ident.kautz_oe.OutputErrorFit`); the result is the same
function of the job as in a thread.  A stale attempt is not interrupted (its
result is dropped as in a thread).  The child is started when
the worker is created (:meth:`_ReidWorker.prestart`), so that the first attempt
does not wait for an interpreter to start.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import (
    CancelledError,
    Executor,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
)
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...approx.model import KautzModel
from ...basis import KautzBasis
from ...ident.kautz_oe import OutputErrorFit, identify_output_error

#: a window starts where the plant may have changed: its state there is estimated
_INITIAL_STATE = "estimate"
#: the starts: the current poles' decay rates scaled by these
_START_SCALES = (1.0, 0.75, 1.33)


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
    mode).  The three starts are searched together (one batched evaluation
    of all of them per step, :func:`~kautztwin.ident.identify_output_error`);
    ``cancel``, when set before the search begins, skips it.
    """
    start = time.perf_counter()
    if cancel is not None and cancel.is_set():
        return _ReidOutcome(None, time.perf_counter() - start)
    starts = np.array([_scaled_poles(job.poles, scale) for scale in _START_SCALES])
    fit = identify_output_error(
        job.u[: job.n_est], job.y[: job.n_est], starts, dt=job.dt,
        burn_in=job.w0, input_offset=job.input_offset, min_rate=job.min_rate,
        max_iter=job.max_iter, initial_state=_INITIAL_STATE,
    )
    return _ReidOutcome(fit, time.perf_counter() - start)


def portable_model(model: KautzModel) -> tuple[Any, ...]:
    """``model`` as plain, picklable values (for a worker process's result).

    A :class:`~kautztwin.basis.KautzBasis` does not pickle (it is immutable);
    its block kinds and parameters do, and rebuild it exactly
    (:func:`model_from_portable`).

    Parameters
    ----------
    model : KautzModel

    Returns
    -------
    tuple
    """
    b = model.basis
    return (b._kinds, np.asarray(b._params), b._dt, b._delayed, np.asarray(model.coefficients))


def model_from_portable(plain: tuple[Any, ...]) -> KautzModel:
    """The :class:`~kautztwin.KautzModel` of :func:`portable_model`'s values (bit for bit).

    Parameters
    ----------
    plain : tuple

    Returns
    -------
    KautzModel
    """
    kinds, params, dt, delayed, coef = plain
    return KautzModel(KautzBasis._from_blocks(tuple(kinds), params, dt, delayed), coef)


def portable_fit(fit: OutputErrorFit) -> tuple[Any, ...]:
    """An :class:`~kautztwin.ident.kautz_oe.OutputErrorFit` as plain, picklable values.

    Parameters
    ----------
    fit : OutputErrorFit

    Returns
    -------
    tuple
        Rebuilt by :func:`fit_from_portable`.
    """
    return (portable_model(fit.model), fit.offset, fit.input_offset, fit.fit_percent,
            fit.n_evaluations, fit.success, fit.message)


def fit_from_portable(plain: tuple[Any, ...]) -> OutputErrorFit:
    """The :class:`~kautztwin.ident.kautz_oe.OutputErrorFit` of :func:`portable_fit` (bit for bit).

    Parameters
    ----------
    plain : tuple

    Returns
    -------
    OutputErrorFit
    """
    model, offset, input_offset, fit_percent, n_eval, ok, msg = plain
    return OutputErrorFit(model_from_portable(model), offset, input_offset, fit_percent, n_eval,
                          ok, msg)


def _fit_window_portable(job: _ReidJob) -> tuple[Any, ...]:
    """:func:`_fit_window` in a worker process, its outcome as plain, picklable values."""
    out = _fit_window(job)
    if out.fit is None:  # pragma: no cover - no cancel event in a process
        return (None, out.elapsed)
    return (portable_fit(out.fit), out.elapsed)


def _from_portable(value: tuple[Any, ...]) -> _ReidOutcome:
    """The :class:`_ReidOutcome` of :func:`_fit_window_portable`'s values (bit for bit)."""
    plain, elapsed = value
    if plain is None:  # pragma: no cover
        return _ReidOutcome(None, elapsed)
    return _ReidOutcome(fit_from_portable(plain), elapsed)


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


#: niceness added to the process worker (it yields the CPU to the sampling loop)
PROCESS_NICE = 5
WORKER_KINDS = ("thread", "process")
#: modules the forkserver imports once, before it forks a worker (see :func:`preload_in_workers`)
_PRELOAD: list[str] = ["__main__", __name__]


def preload_in_workers(module: str) -> None:
    """Have the ``forkserver`` import ``module`` once, so that worker processes fork with it.

    Each process worker would otherwise import its job's module (numpy, SciPy's
    solvers, the library: about 0.5 to 1 s of CPU) when it starts - on a
    2-core host at the closed loop's start, where a live twin's first
    seconds need the CPU (measured against the OPC UA plant at x10: the
    workers' start-up took 2.6 s of CPU there, and the loop decided a third
    less often in its first 500 closed-loop samples than later).  The first
    worker to start now waits for the forkserver's import (about 1 s), so
    :meth:`~kautztwin.twin.DigitalTwin.start` starts its workers before the
    plant's samples flow.  The modules that run jobs in a worker register
    themselves at import; a forkserver already running keeps what it
    preloaded.

    Parameters
    ----------
    module : str
        A module's import name.
    """
    if module not in _PRELOAD:
        _PRELOAD.append(module)


def _process_init() -> None:
    """Start-up of the worker process: a lower CPU priority (best effort)."""
    try:
        os.nice(PROCESS_NICE)
    except OSError:  # pragma: no cover - not permitted: keep the priority
        pass


def _ready() -> bool:
    """A no-op job: the worker process has started and imported this module."""
    return True


def _process_context() -> multiprocessing.context.BaseContext:
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(_PRELOAD))
    return ctx


def single_worker(kind: str, name: str) -> Executor:
    """One background worker: a thread, or a child process (``forkserver``, niceness +5).

    The update module's re-identification, the resync pole re-optimisation and the
    MPC weight retuning each start theirs with it (see the module notes).

    Parameters
    ----------
    kind : {'thread', 'process'}
        Where the jobs run.
    name : str
        The thread's name prefix (a thread worker).

    Returns
    -------
    concurrent.futures.Executor
        With one worker.

    Raises
    ------
    ValueError
        If ``kind`` is not one of the two.
    """
    if kind == "process":
        return ProcessPoolExecutor(max_workers=1, mp_context=_process_context(),
                                   initializer=_process_init)
    if kind == "thread":
        return ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
    raise ValueError(f"kind must be 'thread' or 'process', got {kind!r}")


class _ReidWorker:
    """The single worker (thread or process) of the background accurate path and its attempt.

    At most one attempt is in flight (:attr:`pending`).  The worker is started
    at the first :meth:`submit` (or by :meth:`prestart`) and stopped by :meth:`close`.

    Parameters
    ----------
    kind : {'thread', 'process'}, default='thread'
        Where the fit runs (see the module notes).
    """

    def __init__(self, kind: str = "thread") -> None:
        if kind not in WORKER_KINDS:
            raise ValueError(f"kind must be 'thread' or 'process', got {kind!r}")
        self.kind = kind
        self._executor: Executor | None = None
        self.pending: _Pending | None = None
        self.closed = False

    def _start(self) -> Executor:
        if self._executor is None:
            self._executor = single_worker(self.kind, "kautztwin-reidentify")
        return self._executor

    def prestart(self) -> None:
        """Start the worker now (a process: its interpreter starts in the background)."""
        if not self.closed:
            self._start().submit(_ready)

    @staticmethod
    def fit_now(job: _ReidJob) -> _ReidOutcome:
        """Compute an attempt in the caller's thread (the synchronous accurate path)."""
        return _fit_window(job)

    def submit(self, job: _ReidJob) -> None:
        """Start ``job`` in the worker (the caller checked that none is pending)."""
        executor = self._start()
        cancel = threading.Event()
        # looked up at call time, so that tests can slow the fit down (thread worker)
        if self.kind == "process":  # an Event does not cross processes
            future = executor.submit(_fit_window_portable, job)
        else:
            future = executor.submit(_fit_window, job, cancel)
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

    def result(self, pending: _Pending) -> _ReidOutcome:
        """The outcome of a finished attempt (its exception raised, as ``Future.result``)."""
        out = pending.future.result()
        return _from_portable(out) if self.kind == "process" else out

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
        """Cancel the attempt in flight and join the worker (idempotent).

        A process worker finishes a fit it has started (at most about a second)
        before it exits.
        """
        self.closed = True
        if self.pending is not None:
            self.make_stale("the updater was closed")
            self.pending = None
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
