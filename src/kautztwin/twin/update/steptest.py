"""The update module's step-test path: a candidate from a step test (DNN or pole optimisation).

:meth:`StepTestPath.update_from_step_test` (a method of
:class:`~kautztwin.twin.update.Updater`) turns a recent step test into a
candidate - a trained DNN estimator's model (with the width of its confidence
band when the estimator has ``estimate``), or :func:`kautztwin.optimize_poles`
from the running poles without one - and judges it with the updater's rules
(:mod:`.judging`) on :meth:`StepTestPath.validation_window`, or on the step
test itself (:func:`step_test_record`) when the buffer holds too little.  The
runtime's pole re-optimisation off the sample thread
(:mod:`kautztwin.twin.optimization.poles`) uses the same window and record.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_number
from ...approx.model import KautzModel
from ...approx.poles import optimize_poles
from ...basis import KautzBasis
from ...exceptions import DataError
from ..digital import discretize_model
from .judging import CandidateJudging
from .records import ModelUpdate

__all__ = ["StepTestPath", "step_test_record"]


def step_test_record(
    y: NDArray[np.float64], *, u0: float, y0: float, amplitude: float, burn_in: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A step test as a validation window: the plant at rest at ``u0``, then the step.

    Parameters
    ----------
    y : ndarray of shape (n_samples,)
        Measured output of the step test, the step applied at its first sample.
    u0, y0 : float
        Input and output before the step.
    amplitude : float
        Step height of the input.
    burn_in : int
        Samples at rest before the step (at least one is used).

    Returns
    -------
    u, y : ndarray of shape (max(burn_in, 1) + n_samples,)
        Input and output of the window; its last ``n_samples`` are the step test.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.update.steptest import step_test_record
    >>> u, y = step_test_record(np.array([0.0, 0.5, 0.8]), u0=1.0, y0=0.0, amplitude=2.0,
    ...                         burn_in=2)
    >>> u.tolist(), y.tolist()
    ([1.0, 1.0, 3.0, 3.0, 3.0], [0.0, 0.0, 0.0, 0.5, 0.8])
    """
    n_pre = max(burn_in, 1)
    u_rec = np.concatenate([np.full(n_pre, u0), np.full(y.size, u0 + amplitude)])
    y_rec = np.concatenate([np.full(n_pre, y0), y])
    return u_rec, y_rec


class StepTestPath(CandidateJudging):
    """Base class of :class:`~kautztwin.twin.update.Updater`: the step-test path.

    Not used on its own.  Besides :class:`.CandidateJudging`'s, it reads the
    updater's settings declared below and its ``recent_samples`` and
    ``core_poles``.
    """

    # set by Updater.__init__
    dt: float
    dnn: Any
    max_relative_width: float | None
    reid_samples: int
    validation_fraction: float
    burn_in: int

    def validation_window(self) -> tuple[NDArray[np.float64], NDArray[np.float64], int] | None:
        """The recent buffered samples a step-test candidate is validated on.

        The last ``reid_samples`` buffered samples, their final
        ``validation_fraction`` held out, with up to ``burn_in`` samples of
        history before them that settle the filters.

        Returns
        -------
        u, y, n_val : ndarray, ndarray, int
            Inputs and outputs of the window (new arrays) and the number of
            held-out samples at its end; ``None`` when the buffer holds fewer
            than 10 held-out samples, or fewer than 10 of them are usable.
        """
        u_all, y_all = self.recent_samples()
        n_w = min(self.reid_samples, u_all.size)
        n_val = int(self.validation_fraction * n_w)
        if n_val >= 10 and np.isfinite(y_all[-n_val:]).sum() >= 10:
            h0 = max(0, u_all.size - n_w - self.burn_in)
            return u_all[h0:], y_all[h0:], n_val
        return None

    def _dnn_candidate(
        self, record: NDArray, t: NDArray | None
    ) -> tuple[KautzModel, tuple[float, float]]:
        """The DNN's model of a step record and ``(relative_width, level)`` of its band.

        The estimator's ``estimate`` when it has one (the same model as
        ``predict_models``, with the uncertainty), else ``predict_models``
        and no width (NaN).
        """
        estimate = getattr(self.dnn, "estimate", None)
        if not callable(estimate):
            return self.dnn.predict_models(record, t=t)[0], (math.nan, math.nan)
        result = estimate(record, t=t)
        return result.model(0), (float(result.relative_width[0]), float(result.level))

    def update_from_step_test(
        self,
        y: ArrayLike,
        *,
        t: ArrayLike | None = None,
        amplitude: float = 1.0,
        u0: float | None = None,
        y0: float | None = None,
        from_live: bool = False,
    ) -> ModelUpdate:
        """Fast path from a step test: a DNN (or pole optimisation) estimate, validated.

        Parameters
        ----------
        y : array-like of shape (n_samples,)
            Measured output of a step test from an equilibrium, the step
            applied at the first sample.
        t : array-like of shape (n_samples,), optional
            Its sample times from the step (``k * dt`` when omitted; a DNN may
            need its own training grid).
        amplitude : float, default=1.0
            Step height of the input.
        u0 : float, optional
            Input before the step; the updater's ``input_offset`` when omitted.
        y0 : float, optional
            Output before the step; ``y[0]`` when omitted.
        from_live : bool, default=False
            Whether ``y`` is the live model's own step response
            (:meth:`~kautztwin.twin.Optimizer.retune_model`): an accepted pole
            re-optimisation then continues the fast path from the live model
            projected onto the new basis (see
            :meth:`~kautztwin.twin.update.judging.CandidateJudging.judge_candidate`).
            A DNN candidate ignores it: the DNN's model is the update.

        Returns
        -------
        ModelUpdate
            ``kind='dnn-update'`` with an estimator, else ``'step-test'``;
            a DNN candidate carries the ``relative_width`` of its band and
            is deferred (rejected, reason ``'deferred: ...'``, fits NaN)
            when that exceeds ``max_relative_width``.
            The candidate is validated on the last ``reid_samples`` buffered
            samples (their final ``validation_fraction``) when the buffer holds
            enough, else on the step test itself (on the twin's grid only; an
            accepted model then continues from the state at the end of the
            step test).

        Raises
        ------
        DataError
            If the record is not finite or ``amplitude`` is zero.
        """
        start = time.perf_counter()
        self.count_attempt()
        yy = np.asarray(y, dtype=float).reshape(-1)
        if yy.size < 3 or not np.all(np.isfinite(yy)):
            raise DataError("y must hold at least 3 finite samples of a step test")
        amp = check_number(amplitude, "amplitude")
        if amp == 0:
            raise DataError(f"amplitude must be a nonzero number, got {amplitude!r}")
        base_u = self.input_offset if u0 is None else check_number(u0, "u0")
        base_y = float(yy[0]) if y0 is None else check_number(y0, "y0")
        record = (yy - base_y) / amp
        tt = None if t is None else np.asarray(t, dtype=float)
        band = (math.nan, math.nan)
        if self.dnn is not None:
            kind = "dnn-update"
            model, band = self._dnn_candidate(record, tt)
        else:
            kind = "step-test"
            grid = np.arange(yy.size) * self.dt if tt is None else tt
            model = optimize_poles(grid, record, KautzBasis(self.core_poles), kind="step").model
        md = discretize_model(model, self.dt)
        offset = base_y - md.dc_gain * (base_u - self.input_offset)
        width, level = band
        limit = self.max_relative_width
        if kind == "dnn-update" and limit is not None and not width <= limit:
            why = (
                f"the {100 * level:g} % band is {width:.3g} of the response (RMS half-width "
                f"over RMS), above max_relative_width = {limit:g}" if not math.isnan(level)
                else f"the estimator gives no uncertainty (no estimate method) and "
                f"max_relative_width = {limit:g} is set"
            )
            return self._finish(kind, start, False, f"deferred: {why}", md, offset,
                                math.nan, math.nan, None, band=band)
        carry = from_live and kind == "step-test"
        window = self.validation_window()
        if window is not None:
            return self._judge(kind, start, md, offset, *window, band=band, from_live=carry)
        if tt is not None and (
            tt.size != yy.size or not np.allclose(np.diff(tt), self.dt, rtol=1e-6, atol=0)
        ):
            return self._finish(
                kind, start, False, "no buffered data to validate on, and the step test is "
                "not on the twin's sampling grid", md, offset, math.nan, math.nan, None,
                band=band,
            )
        # validate on the step test itself: the twin at rest at u0, the step at the first sample
        u_rec, y_rec = step_test_record(yy, u0=base_u, y0=base_y, amplitude=amp,
                                        burn_in=self.burn_in)
        return self._judge(kind, start, md, offset, u_rec, y_rec, yy.size, band=band,
                           from_live=carry)
