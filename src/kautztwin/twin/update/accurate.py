"""The update module's accurate path: when an attempt is due, its window, its fit, its judgement.

A ``'desync'`` of the monitor starts a **recovery**
(:meth:`AccuratePath._recovery_on_event`): the change is dated, and from
``min_reid_samples`` after it, every ``reid_every`` samples until a
``'resync'`` (at most ``max_attempts``), an attempt is due
(:meth:`AccuratePath._attempt_if_due`; :meth:`AccuratePath.request_reidentification`
schedules one on demand).  An attempt freezes the recent window into a job
(:meth:`AccuratePath._prepare`: the estimation part, the held-out
``validation_fraction`` at its end, the current poles) and fits it with
:func:`~kautztwin.ident.identify_output_error` - synchronously
(:meth:`AccuratePath.reidentify`), or with ``Updater(background=True)`` in the
single worker of :mod:`.worker` (:meth:`AccuratePath._submit`), polled by later
samples; the first one that finds it finished judges it
(:meth:`AccuratePath._poll`) on the held-out samples fixed at submission.
Candidates are judged with the rules of :mod:`.judging`.

:class:`AccuratePath` is a base class of :class:`~kautztwin.twin.update.Updater`
and holds its public handles on the accurate path:
:attr:`~AccuratePath.recovering`, :meth:`~AccuratePath.reidentify`,
:meth:`~AccuratePath.request_reidentification`, :attr:`~AccuratePath.pending`,
:meth:`~AccuratePath.cancel_pending`, :meth:`~AccuratePath.wait`,
:meth:`~AccuratePath.close` and the context manager.
"""

from __future__ import annotations

import math
import time
from typing import Any, Self

import numpy as np

from ...exceptions import KautzTwinError
from .judging import CandidateJudging
from .records import ModelUpdate
from .sync import SyncMonitor
from .worker import _ReidJob, _ReidWorker

__all__ = ["AccuratePath"]


class AccuratePath(CandidateJudging):
    """Base class of :class:`~kautztwin.twin.update.Updater`: recovery, attempts, their worker.

    Not used on its own.  Besides :class:`.CandidateJudging`'s, it reads the
    updater's settings, state and worker declared below, its
    ``recent_samples`` and ``core_poles``.
    """

    # set by Updater.__init__
    dt: float
    monitor: SyncMonitor
    reidentify_enabled: bool
    background: bool
    reid_samples: int
    min_reid_samples: int
    reid_every: int
    max_attempts: int
    burn_in: int
    validation_fraction: float
    min_rate: float | None
    max_iter: int
    _core_n: int
    _model_k: int
    _recovery: dict[str, int] | None
    _worker: _ReidWorker

    @property
    def pending(self) -> bool:
        """Whether a background attempt is in flight (submitted, not judged yet)."""
        return self._worker.pending is not None

    @property
    def recovering(self) -> bool:
        """Whether a recovery (re-identification attempts) is under way."""
        return self._recovery is not None

    def _recovery_on_event(self, kind: str) -> None:
        """A monitor event of ``kind``: a recovery starts or ends.

        ``'resync'`` ends it (an attempt in flight is stale); the first
        ``'desync'`` starts one, the change dated half a window before the
        end of the first bad window (not before the current model's adoption).
        """
        if kind == "resync":
            self._recovery = None
            self._worker.make_stale("the twin resynchronised while it ran")
        elif kind == "desync" and self.reidentify_enabled and self._recovery is None:
            mon = self.monitor
            first_bad_end = self._k - (mon.n_consecutive - 1) * mon.stride
            change = max(first_bad_end - mon.window // 2, self._model_k, 0)
            self._recovery = {
                "change": change, "next": change + self.min_reid_samples, "attempts": 0,
            }

    def _attempt_if_due(self) -> ModelUpdate | None:
        """The recovery's next attempt, if it is due and none is in flight (else ``None``).

        Synchronous, or submitted to the worker in background mode (``None``
        then, unless it cannot start); the next one is due ``reid_every``
        samples later, and the recovery ends after ``max_attempts``.
        """
        rec = self._recovery
        if rec is None or self._k < rec["next"] or self._worker.pending is not None:
            return None
        if self.background and not self._worker.closed:
            update = self._submit()
        else:
            update = self.reidentify()
        rec["attempts"] += 1
        rec["next"] = self._k + self.reid_every
        if rec["attempts"] >= self.max_attempts:
            self._recovery = None
        return update

    def _prepare(self, n_samples: int | None) -> _ReidJob | ModelUpdate:
        """Freeze the window of an attempt (counted), or reject it for too few samples."""
        start = time.perf_counter()
        self.count_attempt()
        u_all, y_all = self.recent_samples()
        if n_samples is None:
            n_samples = self.reid_samples
            if self._recovery is not None:
                n_samples = min(n_samples, self._k - self._recovery["change"])
        n_w = min(int(n_samples), u_all.size)
        h0 = max(0, u_all.size - n_w - self.burn_in)
        u, y = u_all[h0:], y_all[h0:]  # fresh arrays: the buffer is a deque
        w0 = u.size - n_w  # first sample of the window inside (u, y)
        n_val = int(self.validation_fraction * n_w)
        n_est = u.size - n_val
        n_par = self._core_n + 1
        usable = int(np.isfinite(y[w0:n_est]).sum())
        if n_val < 10 or usable < 4 * n_par or np.isfinite(y[n_est:]).sum() < 10:
            return self._finish(
                "reidentification", start, False,
                f"too few samples: {usable} usable for estimation, {n_val} for validation",
                None, math.nan, math.nan, math.nan, None,
            )
        u.setflags(write=False)
        y.setflags(write=False)
        poles = self.core_poles
        return _ReidJob(
            u=u, y=y, w0=w0, n_est=n_est, n_val=n_val, poles=poles, dt=self.dt,
            input_offset=self.input_offset, min_rate=self.min_rate, max_iter=self.max_iter,
            k=self._k,
        )

    def reidentify(self, n_samples: int | None = None) -> ModelUpdate:
        """Accurate path now, synchronously: output-error re-identification on the recent window.

        Always runs in the caller's thread, also in background mode; an
        accepted candidate makes a background attempt in flight stale.

        Parameters
        ----------
        n_samples : int, optional
            Window length; since the dated change of the current recovery
            (at most ``reid_samples``), or ``reid_samples`` outside a recovery.

        Returns
        -------
        ModelUpdate
            Accepted or not, with both validation fits.
        """
        job = self._prepare(n_samples)
        if isinstance(job, ModelUpdate):
            return job
        out = self._worker.fit_now(job)
        assert out.fit is not None  # only a cancelled fit has none
        return self._judge(
            "reidentification", time.perf_counter() - out.elapsed, out.fit.model, out.fit.offset,
            job.u, job.y, job.n_val,
        )

    def request_reidentification(self) -> bool:
        """Schedule one re-identification attempt on the recent window at the next sample.

        The attempt takes the path of a drift-triggered one (background or
        synchronous, judged on held-out data, a new model version when
        accepted), so whoever drives the loop sees it in the next
        :meth:`step`'s ``model_update``.

        Returns
        -------
        bool
            ``False`` (nothing scheduled) when re-identification is disabled or
            an attempt is already scheduled or in flight.
        """
        if (not self.reidentify_enabled or self._recovery is not None
                or self._worker.pending is not None):
            return False
        self._recovery = {"change": max(self._k - self.reid_samples, 0),
                          "next": self._k, "attempts": self.max_attempts - 1}
        return True

    def _submit(self) -> ModelUpdate | None:
        """Submit an attempt to the worker; ``None``, or the rejection when it cannot start."""
        job = self._prepare(None)
        if isinstance(job, ModelUpdate):
            return job
        self._worker.submit(job)
        return None

    def _poll(self) -> ModelUpdate | None:
        """Judge the attempt in flight if its result is ready (the caller checked one exists)."""
        p = self._worker.take_finished()
        if p is None:
            return None
        job = p.job
        if p.stale:
            return self._finish(
                "reidentification", time.perf_counter(), False,
                f"discarded the attempt submitted at sample {job.k}: {p.stale}",
                None, math.nan, math.nan, math.nan, None, k_submitted=job.k,
            )
        try:
            out = self._worker.result(p)
        except (KautzTwinError, ValueError, ArithmeticError) as exc:
            return self._finish(
                "reidentification", time.perf_counter(), False,
                f"the fit submitted at sample {job.k} failed: {exc}",
                None, math.nan, math.nan, math.nan, None, k_submitted=job.k,
            )
        assert out.fit is not None  # not cancelled: it would be stale
        # an accepted candidate starts from its state over the input up to now
        u_now = self._inputs_since(job.u.size, job.k)
        return self._judge(
            "reidentification", time.perf_counter() - out.elapsed, out.fit.model, out.fit.offset,
            job.u, job.y, job.n_val, u_now=u_now, k_submitted=job.k,
        )

    def cancel_pending(self, reason: str = "cancelled") -> bool:
        """Make the background attempt in flight stale (after a reset of your own, say).

        Its result is discarded when the worker stops (reported by a later
        :meth:`step` as a rejected :class:`ModelUpdate` with ``reason``).

        Parameters
        ----------
        reason : str, default='cancelled'
            Why, for the rejection's reason.

        Returns
        -------
        bool
            Whether an attempt was in flight.
        """
        return self._worker.cancel(reason)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the background attempt in flight has finished computing.

        The next :meth:`step` judges it; nothing is judged here.

        Parameters
        ----------
        timeout : float, optional
            Most seconds to wait (no limit when omitted).

        Returns
        -------
        bool
            Whether no computation is outstanding any more.
        """
        return self._worker.wait(timeout)

    def close(self) -> None:
        """Stop the background worker: cancel the attempt in flight and join the thread.

        A running fit stops at its next start (one ``identify_output_error``
        run at most).  Idempotent; afterwards attempts run synchronously.
        """
        self._worker.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
