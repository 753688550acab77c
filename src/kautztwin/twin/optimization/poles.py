"""The resync pole re-optimisation off the sampling path: a job, its candidate, its judgement.

:meth:`Optimizer.retune_model <kautztwin.twin.Optimizer.retune_model>` does
three things on the sample thread: a virtual step test of the live fast-path
model (cheap), :func:`~kautztwin.optimize_poles` on it (the expensive part:
0.03 to 0.5 s of CPU, 0.2 to 2.6 s of wall time measured on a loaded 2-core
host against a live plant at x10, while 150 to 195 samples queued) and the
updater's validation of the candidate on its recent buffer (cheap).  Against a
live plant the runtime splits them (:class:`~kautztwin.twin.runtime.versions.ModelVersions`):

1. :func:`pole_job` freezes the step test into a :class:`PoleJob` at the
   resync sample;
2. :func:`pole_candidate` - a pure function of the job - runs in a
   :class:`PoleWorker` (a thread, or one ``forkserver`` child process at a
   lower priority: it then takes neither the loop's GIL nor its CPU);
3. :func:`judge_pole_candidate` validates the candidate on the updater's
   buffer at the sample where the loop finds it finished, with the rules of
   :meth:`Updater.update_from_step_test
   <kautztwin.twin.Updater.update_from_step_test>` (kind ``'step-test'``),
   and adopts it when it wins.

The judgement of job ``k`` at sample ``j`` validates the candidate on the
updater's validation window frozen at ``k`` against the live model at ``j``,
as a background re-identification is judged (on the samples since, the live
model has learnt what the candidate never saw: judged on the newest window,
every delayed candidate lost: 0 of 72 in 23 slow end-to-end runs); at ``j =
k`` it is the synchronous re-optimisation bit for bit.  A resumed run replays
it so (the judging sample is read back from the stored event's ``k`` and
``k_submitted``).  The offline path keeps the synchronous call.

The job and its judgement use the :class:`~kautztwin.twin.Updater`'s public
entries for a candidate built outside it: :attr:`~kautztwin.twin.Updater.core_poles`
(the starting poles), :meth:`~kautztwin.twin.Updater.validation_window` (the
step test's validation window, frozen into the job),
:meth:`~kautztwin.twin.Updater.count_attempt` and
:meth:`~kautztwin.twin.Updater.judge_candidate` (the updater's rules; an
accepted candidate starts from its filter state now), and
:func:`~kautztwin.twin.update.steptest.step_test_record` (the step test as a
window when the buffer holds too little).  ``tests/test_twin_pole_worker.py``
checks that the split path gives the synchronous path's result bit for bit.
"""

from __future__ import annotations

import time
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...approx.model import KautzModel
from ...approx.poles import optimize_poles
from ...basis import KautzBasis
from ...exceptions import DataError
from ..digital import discretize_model
from ..update import ModelUpdate, Updater
from ..update.steptest import step_test_record
from ..update.worker import (
    WORKER_KINDS,
    _ready,
    model_from_portable,
    portable_model,
    preload_in_workers,
    single_worker,
)

__all__ = ["PoleJob", "PoleWorker", "judge_pole_candidate", "pole_candidate", "pole_job"]

preload_in_workers(__name__)  # its worker processes fork with this module loaded


@dataclass(frozen=True, eq=False)
class PoleJob:
    """The frozen inputs of one pole re-optimisation (the virtual step test at a resync).

    Parameters
    ----------
    y : ndarray of shape (n_samples,)
        The live model's response to a unit step from rest at ``u0`` (read-only copy).
    u0, y0 : float
        Input and output before the step.
    poles : ndarray of complex
        The continuous starting poles (the running model's order).
    dt : float
        Sampling period.
    k : int
        The sample of the resync.
    version : int
        The model version running then (a candidate for another one is stale).
    u_val, y_val : ndarray
        The updater's buffer then, from the validation window's burn-in on
        (read-only copies; empty when it held too little to validate on).
    n_val : int
        Held-out samples at the end of ``u_val, y_val``.
    k_updater : int
        The updater's sample counter then.
    """

    y: NDArray[np.float64]
    u0: float
    y0: float
    poles: NDArray[np.complex128]
    dt: float
    k: int
    version: int
    u_val: NDArray[np.float64]
    y_val: NDArray[np.float64]
    n_val: int
    k_updater: int


def pole_job(optimizer: Any, updater: Updater, k: int) -> PoleJob | None:
    """The step test :meth:`Optimizer.retune_model` would fit, frozen at sample ``k``.

    Parameters
    ----------
    optimizer : Optimizer
        Its ``retune_poles`` and ``max_step_samples``.
    updater : Updater
        The twin's update module (no DNN: a DNN update stays synchronous).
    k : int
        The sample.

    Returns
    -------
    PoleJob or None
        ``None`` when pole re-optimisation is switched off.
    """
    if not optimizer.retune_poles:
        return None
    est = updater.estimator_
    basis = est.basis_
    rates = -np.log(np.maximum(np.abs(basis.poles), 1e-12)) / updater.dt
    slowest = float(np.min(rates)) if rates.size else 1.0
    n = int(np.clip(8.0 / (slowest * updater.dt), 50, optimizer.max_step_samples))
    u0 = updater.input_offset
    y = np.array(est.simulate(np.full(n, u0 + 1.0), linear=True), dtype=float)
    y.setflags(write=False)
    poles = np.array(updater.core_poles)
    poles.setflags(write=False)
    # the validation window of update_from_step_test, frozen now
    window = updater.validation_window()
    u_val, y_val, n_val = (np.zeros(0), np.zeros(0), 0) if window is None else window
    u_val.setflags(write=False)
    y_val.setflags(write=False)
    return PoleJob(y, float(u0), float(est.offset_), poles, float(updater.dt), int(k),
                   int(updater.digital_model.version), u_val, y_val, n_val, int(updater.k))


@dataclass(frozen=True, eq=False)
class PoleOutcome:
    """A candidate of :func:`pole_candidate`: the continuous model (``None``: the fit failed).

    Parameters
    ----------
    model : KautzModel or None
        The fitted continuous model of the normalised step record.
    elapsed : float
        Compute seconds.
    error : str
        Why there is no model ('' when there is one).
    """

    model: KautzModel | None
    elapsed: float
    error: str = ""


def pole_candidate(job: PoleJob) -> PoleOutcome:
    """:func:`~kautztwin.optimize_poles` on the job's step test, from its poles.

    The computation of :meth:`Updater.update_from_step_test` without a DNN; a pure
    function of ``job``.

    Parameters
    ----------
    job : PoleJob
        The frozen step test.

    Returns
    -------
    PoleOutcome
    """
    start = time.perf_counter()
    yy = np.asarray(job.y, dtype=float)
    if yy.size < 3 or not np.all(np.isfinite(yy)):
        return PoleOutcome(None, time.perf_counter() - start,
                           "y must hold at least 3 finite samples of a step test")
    record = (yy - job.y0) / 1.0
    grid = np.arange(yy.size) * job.dt
    try:
        model = optimize_poles(grid, record, KautzBasis(job.poles), kind="step").model
    except (DataError, ValueError, np.linalg.LinAlgError) as exc:
        return PoleOutcome(None, time.perf_counter() - start, str(exc))
    return PoleOutcome(model, time.perf_counter() - start)


def _warm() -> bool:
    """A no-op job: the worker has started and imported the fit (this module, scipy's solver)."""
    return _ready()


def _pole_candidate_portable(job: PoleJob) -> tuple[Any, ...]:
    """:func:`pole_candidate` in a worker process, as plain picklable values."""
    out = pole_candidate(job)
    plain = None if out.model is None else portable_model(out.model)
    return (plain, out.elapsed, out.error)


def _from_portable(value: tuple[Any, ...]) -> PoleOutcome:
    """The :class:`PoleOutcome` of :func:`_pole_candidate_portable` (bit for bit)."""
    plain, elapsed, error = value
    if plain is None:
        return PoleOutcome(None, elapsed, error)
    return PoleOutcome(model_from_portable(plain), elapsed, error)


def judge_pole_candidate(
    updater: Updater, job: PoleJob, outcome: PoleOutcome
) -> ModelUpdate | None:
    """Validate the candidate now with the rules of :meth:`Updater.update_from_step_test`.

    Parameters
    ----------
    updater : Updater
        The twin's update module (its buffer now; it adopts a winner).
    job : PoleJob
        The step test.
    outcome : PoleOutcome
        Its candidate.

    Returns
    -------
    ModelUpdate or None
        The judgement (kind ``'step-test'``, ``k_submitted`` the job's sample;
        ``elapsed`` the time spent here, on the sample thread); ``None`` when
        the fit failed (the synchronous path's ``None``).
    """
    start = time.perf_counter()
    updater.count_attempt()
    if outcome.model is None:
        return None
    try:
        return _judge(updater, job, outcome.model, start)
    except (DataError, ValueError, np.linalg.LinAlgError):
        return None


def _judge(updater: Updater, job: PoleJob, model: KautzModel, start: float) -> ModelUpdate:
    md = discretize_model(model, updater.dt)
    offset = job.y0 - md.dc_gain * (job.u0 - updater.input_offset)
    if job.n_val:
        # on the window frozen at the resync (the candidate has seen it, as the live model
        # has), as a background re-identification is judged; an accepted candidate starts
        # from its filter state now
        return updater.judge_candidate(md, offset, job.u_val, job.y_val, job.n_val,
                                       kind="step-test", k_window=job.k_updater,
                                       k_submitted=job.k, start=start, from_live=True)
    # too little buffered data: validate on the step test itself (the synchronous rule)
    u_rec, y_rec = step_test_record(job.y, u0=job.u0, y0=job.y0, amplitude=1.0,
                                    burn_in=updater.burn_in)  # the step test as frozen
    return updater.judge_candidate(md, offset, u_rec, y_rec, job.y.size, kind="step-test",
                                   k_submitted=job.k, start=start, from_live=True)


@dataclass
class PendingPoles:
    """A pole re-optimisation in flight: its job and its candidate (a future, or computed)."""

    job: PoleJob
    future: Future[Any] | None = None
    outcome: PoleOutcome | None = None
    judge_at: int | None = None  # a replay: the sample the original run judged it at


class PoleWorker:
    """One worker (thread or process) for the pole re-optimisation; one job in flight.

    Parameters
    ----------
    kind : {'thread', 'process'}, default='thread'
        Where :func:`pole_candidate` runs: a worker thread, or one child
        process (``forkserver``, niceness +5; see :mod:`kautztwin.twin.update.worker`).
    """

    def __init__(self, kind: str = "thread") -> None:
        if kind not in WORKER_KINDS:
            raise ValueError(f"kind must be 'thread' or 'process', got {kind!r}")
        self.kind = kind
        self._executor: Executor | None = None

    def _start(self) -> Executor:
        if self._executor is None:
            self._executor = single_worker(self.kind, "kautztwin-poles")
        return self._executor

    def prestart(self) -> None:
        """Start the worker now (a process: its interpreter starts and imports the fit)."""
        self._start().submit(_warm)

    def submit(self, job: PoleJob) -> PendingPoles:
        """Start computing the candidate of ``job``."""
        ex = self._start()
        if self.kind == "process":
            return PendingPoles(job, ex.submit(_pole_candidate_portable, job))
        return PendingPoles(job, ex.submit(pole_candidate, job))

    def done(self, pending: PendingPoles) -> bool:
        """Whether the candidate of ``pending`` is computed."""
        return pending.outcome is not None or (
            pending.future is not None and pending.future.done())

    def outcome(self, pending: PendingPoles) -> PoleOutcome:
        """The candidate of a finished ``pending`` (a worker failure: no candidate)."""
        if pending.outcome is None:
            assert pending.future is not None
            try:
                value = pending.future.result()
            except Exception as exc:  # noqa: BLE001 - a crashed worker: no candidate
                pending.outcome = PoleOutcome(None, float("nan"), f"worker failed: {exc}")
            else:
                pending.outcome = (_from_portable(value) if self.kind == "process"
                                   else value)
        return pending.outcome

    def close(self) -> None:
        """Cancel what has not started and join the worker (idempotent)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
