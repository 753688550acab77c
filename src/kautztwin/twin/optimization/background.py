"""The optimization module off the sampling path: one worker thread for each new model version.

The step that produces a new model version stores it and queues one
:class:`OptimizationJob` for the :class:`OptimizationWorker` (a thread),
then returns.  The worker builds the MPC on the new model with the running
weights (the next step switches to it), then retunes the weights
(:meth:`~kautztwin.twin.optimization.Optimizer.tune_controller`) and
builds the controller the outcome asks for, then retrains the estimator,
if any.  Every step of the loop polls the worker and applies what has
finished with the rules, events and log entries of the synchronous path
(a rejected tuning returns to the last validated controller, the one the
synchronous path keeps); the tuning records and event payloads add
``k_submitted``, the sample at which the version appeared.  The worker
reads immutable models and settings and copies of the command histories
only, and never the history store; the controller it builds is advanced
over the samples since with the operations of a rebuild, so it equals a
rebuild on the whole history bit for bit.  At most one job is in flight: a
newer version makes it stale, its unapplied parts are logged as
``'controller-rejected'`` / ``'estimator-rejected'`` ("discarded ...:
version N superseded it"), and the newest version's job starts when the
worker is free.  The first version's tuning does not run there: it is
tuned before the first closed-loop sample (see
:meth:`kautztwin.twin.runtime.versions.ModelVersions.first`).

**Process worker** (``kind='process'``, chosen with the update module's
``worker``: a live link's twin): the weight retuning - closed-loop simulations
of every candidate weight, pure Python that would hold the GIL for 0.1 to 0.8 s
while the sampling loop needs it every period - runs in one child process
(``forkserver``, niceness +5, as the update module's re-identification; see
:mod:`kautztwin.twin.update.worker`).  Its arguments and its
:class:`~kautztwin.twin.optimization.ControllerTuning` are pickled; the
controllers are still built in the worker thread (a built MPC problem holds
solver objects that do not pickle).  The tuning is the same function of the
same arguments as in the thread.  Measured against the OPC UA plant server at
x10: with the tuning in the thread the loop fell 80 to 520 samples behind after
each new version (the plant's input then held for as long), and with it in the
child process it does not.  A child that fails (crashed, killed) is not fatal:
the tuning then runs in the thread.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass
from typing import Any, Protocol

from numpy.typing import NDArray

from ...approx.model import KautzModel
from ...exceptions import DataError, KautzTwinError
from ..prediction import MPCSettings
from ..prediction.controller import _prepare_controller, _PreparedController
from ..update.worker import WORKER_KINDS, preload_in_workers, single_worker
from .optimizer import ControllerTuning, EstimatorRetraining

__all__ = ["OptimizationJob", "OptimizationWorker", "TuningContext"]

preload_in_workers(__name__)  # its worker processes fork with this module loaded

_logger = logging.getLogger(__name__)

_Prepared = tuple[KautzModel, MPCSettings, _PreparedController | DataError]


class _Tuner(Protocol):
    def tune_controller(
        self, model: KautzModel, settings: MPCSettings, *, step: float, u_op: float | None = None,
        y_op: float = 0.0,
    ) -> ControllerTuning: ...

    def retrain_estimator(self, estimator: Any, model: KautzModel) -> EstimatorRetraining: ...


@dataclass(frozen=True, eq=False)
class _TuningOutcome:
    """A weight retuning and the controllers built for what the main thread will run."""

    tuning: ControllerTuning
    prepared: tuple[_Prepared, ...]


@dataclass(frozen=True, eq=False)
class TuningContext:
    """What the worker reads for a weight retuning (immutable objects and copies only).

    Parameters
    ----------
    mpc : MPCSettings
        The configured design (the base of the tuning).
    current : MPCSettings
        The weights the controller runs now.
    step : float
        Set-point step of the tuning simulations.
    input_offset : float
        The models' input operating point.
    fallback : (KautzModel, MPCSettings) or None
        The last validated controller.
    v_history, d_history : ndarray
        Copies of the command and dither histories.
    """

    mpc: MPCSettings
    current: MPCSettings
    step: float
    input_offset: float
    fallback: tuple[KautzModel, MPCSettings] | None
    v_history: NDArray
    d_history: NDArray


@dataclass(eq=False)
class OptimizationJob:
    """The optimisation of one model version in the worker: interim controller, tuning, retraining.

    A part is ``None`` before the job is submitted and again once it is
    applied (or discarded).
    """

    version: int
    k: int
    t: float
    model: KautzModel
    u_op: float
    y_op: float
    tune: bool
    estimator: Any
    interim: Future[_PreparedController] | None = None
    tuning: Future[_TuningOutcome] | None = None
    retraining: Future[EstimatorRetraining] | None = None
    submitted: bool = False

    def futures(self) -> list[Future[Any]]:
        """The parts not applied yet."""
        return [f for f in (self.interim, self.tuning, self.retraining) if f is not None]


def _tune(optimizer: _Tuner, model: KautzModel, mpc: MPCSettings, step: float, u_op: float,
          y_op: float) -> ControllerTuning:
    """The weight retuning alone (what the child process of a process worker runs)."""
    return optimizer.tune_controller(model, mpc, step=step, u_op=u_op, y_op=y_op)


def _ready() -> bool:
    """A no-op job: the child process has started and imported the tuning."""
    return True


def _tune_in_worker(
    optimizer: _Tuner, model: KautzModel, mpc: MPCSettings, step: float, u_op: float,
    y_op: float, current: MPCSettings,
    fallback: tuple[KautzModel, MPCSettings] | None, v_history: NDArray, d_history: NDArray,
    input_offset: float, interim: Future[_PreparedController] | None,
    process: Executor | None = None,
) -> _TuningOutcome:
    """Retune the weights, then build the controller the outcome asks for (worker thread).

    Reads its arguments only (immutable models and settings, copied
    histories): the rules of the runtime's tuning application decide which
    controller runs next - the model with the tuned weights, or the last
    validated controller when the tuning or the build fails - and it is built here, so that the main
    thread only advances it over the samples since.  With ``process`` the
    retuning runs in that child process (this thread waits for it without the
    GIL); a child that fails hands the retuning back to this thread.
    """
    tuning: ControllerTuning | None = None
    if process is not None:
        try:
            tuning = process.submit(_tune, optimizer, model, mpc, step, u_op, y_op).result()
        except Exception as exc:  # noqa: BLE001 - a broken child: tune here instead
            _logger.warning("the MPC retuning failed in the child process (%s): tuning in the "
                            "worker thread", exc)
            tuning = None
    if tuning is None:
        tuning = _tune(optimizer, model, mpc, step, u_op, y_op)
    prepared: list[_Prepared] = []

    def prepare(m: KautzModel, s: MPCSettings) -> bool:
        try:
            p: _PreparedController | DataError = _prepare_controller(
                m, s, v_history, d_history, input_offset)
        except DataError as exc:
            p = exc
        prepared.append((m, s, p))
        return not isinstance(p, DataError)

    ok = True
    if tuning.accepted:
        # the main thread may already run (model, current): the interim controller
        running = (interim is not None and not interim.cancelled()
                   and interim.exception() is None)
        if not (running and tuning.settings == current):
            ok = prepare(model, tuning.settings)
    if (not tuning.accepted or not ok) and fallback is not None:
        prepare(*fallback)
    return _TuningOutcome(tuning, tuple(prepared))


EventLog = Callable[..., None]


class OptimizationWorker:
    """One worker thread (and child process) that optimises the newest model version; one job.

    Parameters
    ----------
    optimizer : TwinOptimizer
        The optimization module (its ``tune_controller`` and ``retrain_estimator`` run here).
    event : callable
        ``event(kind, k, t, message, payload)``: logs an event of the run.
    install : callable
        ``install(prepared, k)``: runs the controller on an interim controller
        prepared by the worker (raises :class:`~kautztwin.exceptions.DataError`
        to keep the running one).
    apply_tuning : callable
        ``apply_tuning(tuning, model, version, k, t, *, initial, prepared, extra)``:
        the synchronous path's rules for a finished tuning.
    apply_retraining : callable
        ``apply_retraining(rt, version, k, t, extra)``: the same for a retraining.
    context : callable
        ``context(k)``: the :class:`TuningContext` at sample ``k``.
    kind : {'thread', 'process'}, default='thread'
        Where the weight retuning runs: the worker thread, or one child
        process (see the module notes).

    Raises
    ------
    ValueError
        If ``kind`` is not one of the two.
    """

    def __init__(
        self, optimizer: _Tuner, *, event: EventLog,
        install: Callable[[_PreparedController, int], None], apply_tuning: Callable[..., None],
        apply_retraining: Callable[..., None], context: Callable[[int], TuningContext],
        kind: str = "thread",
    ) -> None:
        if kind not in WORKER_KINDS:
            raise ValueError(f"kind must be 'thread' or 'process', got {kind!r}")
        self.kind = kind
        self._process: Executor | None = None
        self.optimizer = optimizer
        self._event = event
        self._install = install
        self._apply_tuning = apply_tuning
        self._apply_retraining = apply_retraining
        self._context = context
        self._executor: ThreadPoolExecutor | None = None
        self.job: OptimizationJob | None = None
        self.next: OptimizationJob | None = None
        self._waiting: list[Future[Any]] = []

    def _child(self) -> Executor | None:
        """The child process of a process worker (started at first use); ``None``: a thread."""
        if self.kind != "process":
            return None
        if self._process is None:
            self._process = single_worker("process", "kautztwin-tune")
        return self._process

    def prestart(self) -> None:
        """Start the child process of a process worker now (its interpreter starts meanwhile)."""
        child = self._child()
        if child is not None:
            child.submit(_ready)

    @property
    def busy(self) -> bool:
        """Whether a job is in flight or waits for the worker."""
        return self.job is not None or self.next is not None

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the job in flight has finished; whether nothing is outstanding any more."""
        futures = self.job.futures() if self.job is not None else []
        futures += self._waiting
        if not futures:
            return True
        _, not_done = wait_futures(futures, timeout=timeout)
        return not not_done

    # ------------------------------------------------------------------ jobs
    def supersede(self, reason: str, k: int, t: float) -> None:
        """Discard the job in flight and the queued one (a newer version supersedes them)."""
        if self.job is not None:
            self._discard(self.job, reason, k, t)
            self.job = None
        if self.next is not None:
            self._discard(self.next, reason, k, t)
            self.next = None

    def queue(self, job: OptimizationJob, k: int) -> None:
        """Queue ``job``; it starts at once when the worker is free."""
        self.next = job
        self.submit_next(k)

    def _discard(self, job: OptimizationJob, reason: str, k: int, t: float) -> None:
        """Drop a stale job: log the parts not applied yet, cancel what has not started."""
        when = (f"submitted at sample {job.k}" if job.submitted
                else f"queued at sample {job.k}, not started")
        payload = {"version": job.version, "k_submitted": job.k, "discarded": reason}
        if job.tune and (job.tuning is not None or not job.submitted):
            self._event("controller-rejected", k, t,
                        f"discarded the MPC retuning for version {job.version} ({when}): "
                        f"{reason}", payload)
        if job.estimator is not None and (job.retraining is not None or not job.submitted):
            self._event("estimator-rejected", k, t,
                        f"discarded the estimator retraining for version {job.version} "
                        f"({when}): {reason}", payload)
        for fut in (job.interim, job.tuning, job.retraining):
            if fut is not None and not fut.cancel() and not fut.done():
                self._waiting.append(fut)  # running: the next job waits for it
        job.interim = job.tuning = job.retraining = None

    def submit_next(self, k: int) -> None:
        """Submit the queued job once the worker is free (one job in flight at most)."""
        job = self.next
        if job is None or self.job is not None:
            return
        self._waiting = [f for f in self._waiting if not f.done()]
        if self._waiting:
            return
        self.next = None
        if self._executor is None:
            self._executor = ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="kautztwin-optimize"
            )
        ex = self._executor
        if job.tune:
            c = self._context(k)
            # the new model with the running weights, until the tuning ends
            job.interim = ex.submit(_prepare_controller, job.model, c.current, c.v_history,
                                    c.d_history, c.input_offset)
            job.tuning = ex.submit(
                _tune_in_worker, self.optimizer, job.model, c.mpc, c.step, job.u_op, job.y_op,
                c.current, c.fallback, c.v_history, c.d_history, c.input_offset,
                job.interim, self._child(),
            )
        if job.estimator is not None:
            job.retraining = ex.submit(self.optimizer.retrain_estimator, job.estimator, job.model)
        job.submitted = True
        self.job = job

    def poll(self, version: int, k: int, t: float) -> None:
        """Apply what the worker has finished, in the order of the synchronous path.

        Parameters
        ----------
        version : int
            The running model version (a job for another one is stale).
        k, t : int, float
            The sample being processed.
        """
        job = self.job
        if job is not None and job.version != version:  # pragma: no cover - defensive
            self._discard(job, f"version {version} superseded it", k, t)
            self.job = job = None
        if job is not None:
            extra = {"k_submitted": job.k}
            if job.interim is not None and job.interim.done():
                fut, job.interim = job.interim, None
                try:
                    self._install(fut.result(), k)
                except DataError:  # keep the running one; the tuning's rebuild reports it
                    pass
            if job.interim is None and job.tuning is not None and job.tuning.done():
                fut_t, job.tuning = job.tuning, None
                out = fut_t.result()
                self._apply_tuning(out.tuning, job.model, job.version, k, t,
                                   initial=False, prepared=out.prepared, extra=extra)
            if job.tuning is None and job.retraining is not None and job.retraining.done():
                fut_r, job.retraining = job.retraining, None
                try:
                    rt: EstimatorRetraining | KautzTwinError = fut_r.result()
                except KautzTwinError as exc:
                    rt = exc
                self._apply_retraining(rt, job.version, k, t, extra)
            if job.interim is None and job.tuning is None and job.retraining is None:
                self.job = None
        self.submit_next(k)

    def close(self) -> None:
        """Cancel what has not started, wait for a running part, join the thread."""
        for job in (self.job, self.next):
            for fut in (job.interim, job.tuning, job.retraining) if job is not None else ():
                if fut is not None:
                    fut.cancel()
        self.job = self.next = None
        self._waiting = []
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        if self._process is not None:
            self._process.shutdown(wait=True, cancel_futures=True)
            self._process = None


def prepared_for(
    prepared: Sequence[_Prepared], model: KautzModel, settings: MPCSettings
) -> _PreparedController | DataError | None:
    """The controller the worker prepared for ``(model, settings)`` (``None``: not prepared)."""
    for m, s, p in prepared:
        if m is model and s == settings:
            return p
    return None

