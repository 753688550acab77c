r"""The twin's update module as one object, the :class:`Updater`: sample loop and versions.

The :class:`Updater` runs the fast path (:class:`RecursiveKautzEstimator`)
and the :class:`SyncMonitor` on every sample and, when the monitor reports a
desynchronisation, the **accurate path**: output-error re-identification of
poles and coefficients on the recent window
(:func:`~kautztwin.ident.identify_output_error`), accepted only when it
predicts held-out recent data better than the current model.  A trained DNN
estimator (any object with ``predict_models``) or
:func:`kautztwin.optimize_poles` turns a step test into a model
(:meth:`Updater.update_from_step_test`).

Every accepted model is a new :class:`~kautztwin.twin.DigitalModel` version.
The model of the twin is ``y(k) = c^T x_f(k) + offset``: the
:class:`~kautztwin.KautzModel` (a discrete, delayed basis on the sampling
period) carries ``c``; the operating-point ``offset`` is kept by the updater
(:attr:`Updater.offset`) and logged with every version.

This module holds the updater's settings and state, the sample loop
(:meth:`Updater.step`: fast path, monitor) and its model versions (a winner
adopted, :meth:`Updater.snapshot`).  The other jobs are base classes of
:class:`Updater` in modules beside it: :mod:`.accurate` (the accurate path:
when an attempt is due, its window, fitted now or in the worker of
:mod:`.worker`), :mod:`.steptest` (the step-test / DNN path) and
:mod:`.judging` (the validation and acceptance of every candidate);
:mod:`.records` holds :class:`ModelUpdate` and :class:`UpdateResult`
(re-exported here).

Size: the module is over 600 lines because :class:`Updater` is (see its docstring).
"""

from __future__ import annotations

import math
import time
from collections import deque
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_int, check_number, check_positive
from ...approx.model import KautzModel
from ...approx.projection import coefficients_from_system
from ...basis import KautzBasis
from ...basis._blocks import parse_poles
from ...exceptions import DataError
from ...ident.kautz_oe import OutputErrorFit, continuous_poles, filter_states
from ..digital import DigitalModel, discretize_model
from ..physical.sanitize import SampleFlag, SampleSanitizer
from .accurate import AccuratePath
from .records import ModelUpdate, UpdateResult
from .recursive import RecursiveKautzEstimator
from .steptest import StepTestPath
from .sync import SyncEvent, SyncMonitor, _finite_or_nan
from .worker import WORKER_KINDS, _ReidWorker

__all__ = ["ModelUpdate", "UpdateResult", "Updater"]


class Updater(StepTestPath, AccuratePath):
    r"""Keeps the twin's model synchronised with the plant: fast path, monitor, accurate path.

    Each :meth:`step` takes one sample ``(u(k), y(k))`` and

    1. checks the timestamp: a sample that is not later than the previous one
       (late, out of order, duplicated) is ignored; a gap of missing samples
       advances the filter with the last input;
    2. predicts ``y(k)`` (a priori, before using it) and sanitises the
       measured value with a :class:`~kautztwin.twin.SampleSanitizer`:
       dropouts (NaN, garbage) and outliers are not used (neither by the
       estimator nor by the monitor), a missing input holds the last one;
    3. **fast path**: one :class:`RecursiveKautzEstimator` update
       (:math:`O(N^2)`, tens of microseconds including the bookkeeping);
    4. feeds the :class:`SyncMonitor` with the measured output and the
       prediction made with parameters frozen over ``horizon`` samples
       (a ``horizon``-step-ahead simulation, no output feedback inside);
    5. **accurate path**: the first ``'desync'`` event starts a recovery.
       The change is dated half a window before the end of the first bad
       window; once ``min_reid_samples`` samples have arrived since then, and
       every ``reid_every`` samples after that until the monitor reports
       ``'resync'``, poles and coefficients are re-identified by output error
       (:func:`identify_output_error`, from the current poles and two scaled
       copies) on the samples since the change (at most ``reid_samples``,
       the filters settled on ``burn_in`` samples of input history before
       them, and the free response of the plant's state at the window's
       start fitted as well: ``initial_state='estimate'``, since the burn-in
       ran on the plant's dynamics from before the change) except the final
       ``validation_fraction``.  A candidate replaces
       the current model only if it predicts those held-out samples better
       (fit percent higher by more than ``min_improvement``) *and* well
       enough in absolute terms (fit percent at least ``min_candidate_fit``).
       An accepted model is a new :class:`~kautztwin.twin.DigitalModel`
       version, the estimator continues from it and the monitor's window
       restarts.  With ``background=True`` the fit runs in a worker thread
       and a later :meth:`step` judges it (see Notes).

    :meth:`update_from_step_test` is the other fast path: a trained DNN
    estimator (any object with ``predict_models(responses, t=...)`` returning
    :class:`~kautztwin.KautzModel` objects, e.g. ``kautztwin.nn``'s) or, without
    one, :func:`kautztwin.optimize_poles` turns a recent step test into a
    candidate, validated the same way.  An estimator that also has
    ``estimate(responses, t=...)`` (``kautztwin.nn``'s, returning a
    :class:`~kautztwin.nn.ResponseEstimate`) gives the candidate with its
    uncertainty; with ``max_relative_width`` set, a candidate whose band is
    wider than that is deferred (rejected without validation, the model kept).

    :meth:`judge_candidate` judges a candidate built elsewhere (the runtime's
    pole re-optimisation) with the same rules, on a window of
    :meth:`recent_samples` such as :meth:`validation_window`.

    Size: the class is over 400 lines because it documents the recovery policy
    and every parameter (about 280 of its lines are docstrings) and checks
    every parameter in one place.  Its other jobs are its base classes, one
    module each: the accurate path
    (:class:`~kautztwin.twin.update.accurate.AccuratePath`: recovery, attempts,
    the worker of :mod:`kautztwin.twin.update.worker`), the step-test path
    (:class:`~kautztwin.twin.update.steptest.StepTestPath`) and the judging of
    candidates (:class:`~kautztwin.twin.update.judging.CandidateJudging`).

    Parameters
    ----------
    model : DigitalModel or KautzModel
        Initial model: continuous (discretised with a zero-order hold on
        ``dt``, stored as the next version) or on a delayed discrete basis
        with period ``dt``.
    dt : float
        Sampling period, s.
    offset : float, default=0.0
        Output offset ``d`` of the initial model: ``y = c^T x_f + d``.
    input_offset : float, default=0.0
        Input operating point :math:`u_0`: the filter is driven by
        :math:`u - u_0` (see :class:`RecursiveKautzEstimator`).  The twin
        starts from a zero filter state, i.e. the plant at rest at ``u_0``.
    forgetting : float, default=0.995
        Forgetting factor of the fast path (memory about ``1 / (1 - forgetting)`` samples).
    delta : float, default=1.0
        Covariance scale ``P = delta I`` at the start and after every model change.
    max_trace : float, default=1e4
        Anti-windup bound of the covariance trace.
    extra_poles : array-like of complex, optional
        Continuous-time poles (``Re < 0``) appended to the model's basis in
        the fast path only.  Their coefficients start at zero; they widen the
        span of the recursive estimator so that it can follow pole drifts
        (a slower extra pole for plants that slow down) without waiting for a
        re-identification.  Appended blocks leave the model's own basis
        functions unchanged.
    quadratic_scale : float, optional
        A quadratic input channel in the fast path (see
        :class:`RecursiveKautzEstimator`): a second bank of its filters driven by
        :math:`(u - u_0)^2 / s`, for a plant whose gain moves with the operating
        point.  Its coefficients restart at zero with every model version; its
        filter state is recomputed over the same input as the linear bank's.  Model versions,
        the controller and the exports hold the linear part.  ``None``: none.
    directional_forgetting : bool, default=False
        Forget only along the regressor (see :class:`RecursiveKautzEstimator`)
        while the twin is in sync: the closed loop's unexcited directions, the
        quadratic channel's among them, keep their information instead of
        winding up.  From a desynchronisation to the next model version or the
        resync the plant is changing in every direction, and the forgetting is
        exponential; so it is after :meth:`enter_new_regime`.
    monitor : SyncMonitor, optional
        The synchronisation monitor; ``SyncMonitor()`` when omitted.
    sanitizer : SampleSanitizer, optional
        Sanitiser of the measured output; ``SampleSanitizer(threshold=8.0,
        window=100)`` when omitted (a generous threshold: it is meant for
        gross sensor errors, not for the fast transients of the plant).
        Set ``min_scale`` to the sensor resolution for quantised sensors.
    horizon : int, optional
        Samples over which the monitored prediction keeps its parameters
        frozen; ``monitor.stride`` when omitted.
    fast_update : bool, default=True
        Run the recursive update (``False``: coefficients fixed).
    reidentify : bool, default=True
        Run the accurate path on ``'desync'`` events.  With both flags off the
        updater is a static twin that only predicts and monitors.
    estimator : object, optional
        DNN estimator with ``predict_models`` for :meth:`update_from_step_test`.
    buffer_size : int, default=2000
        Recent samples kept for re-identification and validation.
    reid_samples : int, default=300
        Most samples in a re-identification window (estimation plus validation).
    min_reid_samples : int, default=150
        Samples after the dated change before the first attempt.
    reid_every : int, default=50
        Samples between attempts while the twin is desynchronised.
    max_attempts : int, default=20
        Attempts per recovery; afterwards a new ``'desync'`` event starts a new one.
    burn_in : int, default=250
        Samples of input history before a window that settle the filters
        (the plant's own history, so the window is fitted from its first sample).
    validation_fraction : float, default=0.3
        Held-out fraction at the end of a window.
    min_improvement : float, default=0.0
        Fit percent by which a candidate must beat the current model.
    min_candidate_fit : float or None, default=50.0
        Absolute floor: a candidate whose held-out fit percent is below it is
        rejected even when it beats the current model (which can be poor
        right after a change, so beating it proves little).  Applies to
        re-identified and step-test candidates alike; ``None`` disables the
        floor.  The default of 50 % (prediction error at most half the
        output's spread) rejects candidates that would only replace one bad
        model by another, and each accepted version costs a controller
        retune, a covariance restart and a new monitor window; it stays below
        the held-out fits of the useful intermediate candidates seen while a
        window still straddles an abrupt change (54 % and more in
        ``tests/test_twin_update.py``), which a floor near the monitor's
        threshold would refuse.
    max_relative_width : float or None, default=None
        Defer a DNN update whose estimate is this uncertain: when the
        estimator's ``estimate`` gives a band (90 % by default) whose RMS
        half-width exceeds this share of the RMS step response
        (:attr:`~kautztwin.nn.ResponseEstimate.relative_width`; 0.1: the
        band is about +-10 % of the response), :meth:`update_from_step_test`
        returns a rejected :class:`ModelUpdate` whose reason starts with
        ``'deferred:'`` and keeps the current model; a width that is not
        finite (a zero response) is deferred too.  ``None`` (the default)
        decides on the validation fits alone.  The width is recorded in
        every DNN update's :class:`ModelUpdate` (and its logged payload)
        either way.  Needs an estimator with ``estimate``.
    background : bool, default=False
        Run the accurate path's fit in a single worker thread, off the
        sampling path: :meth:`step` submits an attempt with a frozen copy of
        its data window and returns at once, and a later :meth:`step` judges
        the result on the held-out samples fixed at submission (see Notes).
        Off by default because the sample at which a candidate is accepted
        then depends on wall-clock time: keep it off wherever runs must be
        reproducible.  Call :meth:`close` (or use the updater as a context
        manager) to stop the worker.
    worker : {'thread', 'process'}, default='thread'
        Where a background fit runs: a worker thread, or a worker process
        (started with ``forkserver``, at a lower CPU priority) that takes
        neither the sampling loop's GIL nor its CPU time first - for a live
        plant whose samples must be taken as they come.  The candidate is the
        same function of the frozen window either way.
    min_rate : float, optional
        Slowest pole rate the re-identification may choose, 1/s (see
        :func:`identify_output_error`).
    max_iter : int, default=30
        Iteration budget of each re-identification start.
    history : HistoryStore, optional
        Where events and model versions are logged.
    run_id : int, optional
        The run in ``history`` (required with it).

    Raises
    ------
    DataError
        On an invalid parameter, or ``history`` without ``run_id``.

    Attributes
    ----------
    digital_model : DigitalModel
        The current (last accepted) model version.
    estimator_ : RecursiveKautzEstimator
        The fast-path estimator (its live parameters may differ from
        :attr:`digital_model` between versions; see :meth:`snapshot`).
    monitor : SyncMonitor
        The monitor.
    events : list of SyncEvent
        Every monitor event so far.
    model_updates : list of ModelUpdate
        Every accurate-path and step-test attempt so far.
    background : bool
        Whether attempts are submitted to the worker (may be switched
        between steps; an attempt in flight is still judged).
    monitoring : bool
        Whether :meth:`step` feeds the monitor (``True``; may be switched
        between steps).  Switched off for samples that say nothing about the
        model's fit, e.g. a live plant's samples queued while the twin was
        being built, which carry one held input: a rolling fit percent over an
        unexcited window divides by the noise and would report a desync.

    See Also
    --------
    RecursiveKautzEstimator : The fast path.
    SyncMonitor : Rolling fit and triggers.
    identify_output_error : The accurate path.

    Notes
    -----
    **Recovery window.**  After the plant changes, the twin needs time before
    its rolling fit is back above the threshold: the change must become
    visible and settle (``T_ramp``, the duration of the change itself), a
    re-identified model must be built from data of the new behaviour
    (``min_reid_samples`` after the dated change, then one attempt every
    ``reid_every`` samples until a candidate wins), and the rolling window
    (``W = monitor.window`` samples) must slide past the samples that the old
    model predicted.  The recovery window after the start of a change is
    therefore about

    .. math::

        T_{rec} \approx T_{ramp} + \big(m + W\big)\,\Delta t,
        \qquad m \ge \mathrm{min\_reid\_samples},

    where ``m`` counts the samples until the winning attempt (or until the
    fast path has re-converged, about ``3 / (1 - forgetting)`` samples, when
    the drift stays inside the widened span of ``extra_poles``).

    Acceptance scenario (``tests/test_twin_update.py``): the hydraulic drive
    sampled at ``dt = 0.02`` s, a three-pole twin identified at 20 °C, the
    dominant pole slowed by 20 % at 30 s and by another 20 % at 60 s (40 % in
    all, 2 s oil-temperature ramps), ``forgetting=0.98``, one extra pole at
    half the slowest identified rate, ``W = 150``, stride 25,
    ``n_consecutive = 2``.  The documented recovery window is **15 s from
    the start of each drift event**; the measured recoveries are about 8 s
    and 10.5 s, and outside the windows the rolling fit of the twin's
    25-step-ahead prediction stays at or above 97 % (the static twin falls
    to a mean of about -200 %).  The fast path alone (fixed poles) recovers
    small drifts; a drift that moves the poles out of the basis' span needs
    the accurate path or ``extra_poles``.

    **Synchronous and background accurate path.**  By default an attempt
    runs inside :meth:`step` (tens of milliseconds to about two seconds,
    depending on the window and the convergence), so in a real-time loop the
    samples during an attempt wait in the caller's queue.  With
    ``background=True`` the step that starts an attempt only copies the
    window (the estimation part, the ``validation_fraction`` held out at its
    end and the current poles) and submits the fit to a single worker
    thread; the following steps run the fast path and the monitor as usual
    and poll the job.  The first :meth:`step` that finds it finished judges
    the candidate exactly as the synchronous path does - the same held-out
    samples, against the live model, with the same ``min_improvement`` and
    ``min_candidate_fit`` - and, when it wins, starts it from its filter
    state at the current sample (recomputed over the samples that arrived
    meanwhile).  The candidate is therefore the same model the synchronous
    path would have built; only the sample at which it takes over is later
    (:attr:`ModelUpdate.k` versus :attr:`ModelUpdate.k_submitted`).  At most
    one attempt is in flight: a due attempt waits until the previous one has
    been judged.  A ``'resync'`` event, another accepted model (e.g.
    :meth:`update_from_step_test`) or :meth:`cancel_pending` makes the
    attempt in flight stale: it is cancelled (a fit not yet begun is skipped)
    and reported as a rejected :class:`ModelUpdate` whose
    reason says why.  A thread is enough: a real-time loop sleeps most of
    each period and gets the GIL back within about the interpreter's switch
    interval (5 ms) when it wakes; measured on a 20 ms loop with the worker
    busy all the time, no sample was late (docs/twin.md, section 4).

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.twin.update import Updater, SyncMonitor
    >>> model = kt.KautzModel(kt.KautzBasis([-2.0]), [2.0])
    >>> upd = Updater(model, dt=0.05, monitor=SyncMonitor(window=20))
    >>> upd.digital_model.version, upd.digital_model.provenance  # continuous model: ZOH version 2
    (2, 'discretized')
    >>> res = upd.step(0.0, 0.0)
    >>> res.k, res.y_pred
    (0, 0.0)
    >>> upd.step(float("nan"), float("nan")).flags != 0   # a dropout does not crash
    True

    In background mode the updater owns a worker thread; close it when done:

    >>> with Updater(model, dt=0.05, background=True) as upd:
    ...     _ = [upd.step(1.0, 0.0) for _ in range(10)]
    ...     upd.pending            # nothing to re-identify yet
    False
    """

    def __init__(
        self,
        model: DigitalModel | KautzModel,
        *,
        dt: float,
        offset: float = 0.0,
        input_offset: float = 0.0,
        forgetting: float = 0.995,
        delta: float = 1.0,
        max_trace: float = 1e4,
        extra_poles: ArrayLike | None = None,
        quadratic_scale: float | None = None,
        directional_forgetting: bool = False,
        monitor: SyncMonitor | None = None,
        sanitizer: SampleSanitizer | None = None,
        horizon: int | None = None,
        fast_update: bool = True,
        reidentify: bool = True,
        estimator: Any = None,
        buffer_size: int = 2000,
        reid_samples: int = 300,
        min_reid_samples: int = 150,
        reid_every: int = 50,
        max_attempts: int = 20,
        burn_in: int = 250,
        validation_fraction: float = 0.3,
        min_improvement: float = 0.0,
        min_candidate_fit: float | None = 50.0,
        max_relative_width: float | None = None,
        min_rate: float | None = None,
        max_iter: int = 30,
        background: bool = False,
        worker: str = "thread",
        history: Any = None,
        run_id: int | None = None,
    ) -> None:
        dt = check_positive(dt, "dt")
        self.dt = dt
        if isinstance(model, DigitalModel):
            dm = model
        elif isinstance(model, KautzModel):
            dm = DigitalModel.initial(model)
        else:
            raise DataError(
                f"model must be a DigitalModel or a KautzModel, got {type(model).__name__}"
            )
        md = discretize_model(dm.model, dt)
        if md is not dm.model:
            dm = dm.with_update(md, "discretized", dm.fit_percent)
        self.digital_model = dm
        for name, value in (("offset", offset), ("input_offset", input_offset)):
            check_number(value, name)
        self.input_offset = float(input_offset)
        self.delta = float(delta)
        if extra_poles is None:
            self.extra_poles = np.zeros(0, dtype=complex)
        else:
            self.extra_poles = np.atleast_1d(np.asarray(extra_poles, dtype=complex))
            parse_poles(self.extra_poles, 0.0)  # validates: stable, pairs complete
        self._core_n = md.n_functions
        wide = self._widen(md)
        self.estimator_ = RecursiveKautzEstimator(
            wide.basis, dt=dt, forgetting=forgetting, delta=delta, max_trace=max_trace,
            coef_init=wide.coefficients, offset_init=float(offset), input_offset=self.input_offset,
            quadratic_scale=quadratic_scale, directional=bool(directional_forgetting),
        ).reset()
        self.monitor = monitor if monitor is not None else SyncMonitor()
        if not isinstance(self.monitor, SyncMonitor):
            raise DataError(f"monitor must be a SyncMonitor, got {type(monitor).__name__}")
        self.sanitizer = (
            sanitizer if sanitizer is not None else SampleSanitizer(threshold=8.0, window=100)
        )
        self.horizon = (
            self.monitor.stride if horizon is None else check_int(horizon, "horizon", 1)
        )
        self.fast_update = bool(fast_update)
        self.monitoring = True
        self.reidentify_enabled = bool(reidentify)
        if estimator is not None and not callable(getattr(estimator, "predict_models", None)):
            raise DataError("estimator must have a predict_models(responses, t=...) method")
        self.dnn = estimator
        self.reid_samples = check_int(reid_samples, "reid_samples", 10)
        self.min_reid_samples = check_int(min_reid_samples, "min_reid_samples", 10)
        self.reid_every = check_int(reid_every, "reid_every", 1)
        self.max_attempts = check_int(max_attempts, "max_attempts", 1)
        self.burn_in = check_int(burn_in, "burn_in", 0)
        self.buffer_size = check_int(buffer_size, "buffer_size", 10)
        if self.buffer_size < self.reid_samples + self.burn_in:
            raise DataError(
                f"buffer_size must hold reid_samples + burn_in = "
                f"{self.reid_samples + self.burn_in} samples, got {self.buffer_size}"
            )
        vf = check_number(validation_fraction, "validation_fraction")
        if not 0 < vf < 1:
            raise DataError(f"validation_fraction must lie in (0, 1), got {validation_fraction!r}")
        self.validation_fraction = vf
        self.min_improvement = check_number(min_improvement, "min_improvement")
        if min_candidate_fit is None:
            self.min_candidate_fit: float | None = None
        else:
            floor = check_number(min_candidate_fit, "min_candidate_fit")
            if not floor <= 100.0:
                raise DataError(
                    f"min_candidate_fit must be a fit percent <= 100 or None, got "
                    f"{min_candidate_fit!r}"
                )
            self.min_candidate_fit = floor
        if max_relative_width is None:
            self.max_relative_width: float | None = None
        else:
            self.max_relative_width = check_positive(max_relative_width, "max_relative_width")
            if estimator is not None and not callable(getattr(estimator, "estimate", None)):
                raise DataError(
                    "max_relative_width needs an estimator with an estimate(responses, t=...) "
                    f"method (its uncertainty); {type(estimator).__name__} has none"
                )
        self.min_rate = None if min_rate is None else _finite_or_nan(min_rate)
        self.max_iter = check_int(max_iter, "max_iter", 1)
        if not isinstance(background, bool | np.bool_):
            raise DataError(f"background must be True or False, got {background!r}")
        self.background = bool(background)
        if worker not in WORKER_KINDS:
            raise DataError(f"worker must be 'thread' or 'process', got {worker!r}")
        self.worker = worker
        self._worker = _ReidWorker(worker)
        if self.background and worker == "process":
            self._worker.prestart()  # the interpreter starts while the twin runs
        if history is not None and run_id is None:
            raise DataError("run_id is required with history")
        self.history = history
        self.run_id = run_id
        self._u: deque[float] = deque(maxlen=self.buffer_size)
        self._y: deque[float] = deque(maxlen=self.buffer_size)
        self._k = 0
        self._t_last: float | None = None
        self._u_last = self.input_offset
        self._theta_frozen = self.estimator_.parameters_
        self._recovery: dict[str, int] | None = None
        self._regime_left: int | None = None  # see enter_new_regime
        self._model_k = 0  # sample at which the current model was adopted
        self.events: list[SyncEvent] = []
        self.model_updates: list[ModelUpdate] = []
        self._counts = dict.fromkeys(
            ("samples", "used", "skipped", "late", "gap", "input_held", "attempts", "accepted"), 0
        )
        if self.history is not None and not self.history.model_versions(self.run_id):
            self.history.add_model_version(self.run_id, dm, k=0)

    @classmethod
    def from_fit(cls, fit: OutputErrorFit, *, dt: float, **kwargs: Any) -> Updater:
        """An updater that starts from an :func:`identify_output_error` result.

        Parameters
        ----------
        fit : OutputErrorFit
            The identification (its offset and input offset are used).
        dt : float
            Sampling period, s.
        **kwargs
            Further arguments of :class:`Updater`.

        Returns
        -------
        Updater
        """
        model = DigitalModel.initial(
            fit.model, provenance="identification", fit_percent=fit.fit_percent
        )
        return cls(model, dt=dt, offset=fit.offset, input_offset=fit.input_offset, **kwargs)

    def _widen(self, model: KautzModel) -> KautzModel:
        """``model`` on its basis plus the extra poles (zero coefficients for them)."""
        if self.extra_poles.size == 0:
            return model
        poles = np.concatenate([model.basis.poles, np.exp(self.extra_poles * self.dt)])
        basis = KautzBasis(poles, dt=self.dt, delayed=True)
        coef = np.concatenate([model.coefficients, np.zeros(self.extra_poles.size)])
        return KautzModel(basis, coef)

    # ------------------------------------------------------------------ state
    @property
    def k(self) -> int:
        """Index of the next sample."""
        return self._k

    @property
    def offset(self) -> float:
        """Current output offset ``d`` of the twin."""
        return self.estimator_.offset_

    @property
    def model(self) -> KautzModel:
        """The live model of the fast path (coefficients as of now)."""
        return self.estimator_.model_

    @property
    def counts(self) -> dict[str, int]:
        """Counters: samples, used, skipped, late, gap, input_held, attempts, accepted (a copy)."""
        return dict(self._counts)

    @property
    def n_core_functions(self) -> int:
        """Basis functions of the model proper: the fast path's first ones (no ``extra_poles``)."""
        return self._core_n

    @property
    def core_poles(self) -> NDArray[np.complex128]:
        """Continuous-time poles of the model proper (the fast path's, without ``extra_poles``).

        A new array each time; the starting poles of a re-identification or a
        step-test pole optimisation.
        """
        return continuous_poles(self.estimator_.basis_)[: self._core_n]

    def recent_samples(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The buffered recent samples, oldest first: what re-identification and validation use.

        Returns
        -------
        u, y : ndarray of shape (n_buffered,)
            Inputs and outputs (new arrays; at most ``buffer_size`` samples).
            ``y`` is NaN where a sample was not used (a dropout, an outlier, a
            gap); ``u`` holds the input the filters were driven with (a held
            input where one was missing).
        """
        return (np.asarray(self._u, dtype=float), np.asarray(self._y, dtype=float))

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Predict the output for future inputs from the current state (parameters as of now).

        Parameters
        ----------
        u : array-like of shape (horizon,)
            Inputs of the next samples.

        Returns
        -------
        ndarray of shape (horizon,)
            Predicted outputs of the same samples (``y(k)`` depends on inputs before ``k``).
        """
        est = self.estimator_
        return est.simulate(np.asarray(u, dtype=float), x0=est.state_)

    # ------------------------------------------------------------------ the loop
    def step(self, u: Any, y: Any, t: Any = None) -> UpdateResult:
        """Process one sample: predict, sanitise, update, monitor, maybe re-identify.

        Never raises on bad samples (NaN, garbage, outliers, late or missing
        timestamps); their flags tell what happened.  In background mode it
        never waits for the worker either: it judges an attempt whose fit has
        finished, and submits a due attempt when none is in flight.

        Parameters
        ----------
        u : float
            Input applied at this sample.
        y : float
            Measured output of this sample.
        t : float, optional
            Timestamp, s.  Without timestamps every call is one sample period.

        Returns
        -------
        UpdateResult
        """
        start = time.perf_counter()
        est = self.estimator_
        flags = SampleFlag.NONE
        self._counts["samples"] += 1
        tf: float | None = None
        if t is not None:
            tf = _finite_or_nan(t)
            if math.isnan(tf) or (self._t_last is not None and tf <= self._t_last):
                self._counts["late"] += 1
                return UpdateResult(
                    self._k, tf, math.nan, math.nan, math.nan,
                    int(SampleFlag.LATE | SampleFlag.HELD), False, self.monitor.fit, (), None,
                    self.digital_model.version, time.perf_counter() - start,
                )
            if self._t_last is not None:
                missing = min(int(round((tf - self._t_last) / self.dt)) - 1, self.buffer_size)
                if missing > 0:
                    flags |= SampleFlag.LATE | SampleFlag.GAP
                    self._counts["gap"] += missing
                    est.advance(self._u_last, missing)
                    self._u.extend([self._u_last] * missing)
                    self._y.extend([math.nan] * missing)
                    self._advance_k(missing)
            self._t_last = tf
        uf = _finite_or_nan(u)
        held = math.isnan(uf)
        if held:
            uf = self._u_last
            self._counts["input_held"] += 1
        k = self._k
        y_pred = est.predict()
        y_frozen = est.predict_with(self._theta_frozen)
        yf = _finite_or_nan(y)
        s = self.sanitizer.process(yf)
        flags |= s.flags
        events: tuple[SyncEvent, ...] = ()
        if not s.flags & (SampleFlag.HELD | SampleFlag.OUTLIER):
            self._counts["used"] += 1
            if self.fast_update:
                est.update(uf, yf)
            else:
                est.advance(uf)
            if self.monitoring:
                regime = self._regime_left is not None  # rare: after enter_new_regime
                n_fits = self.monitor.n_fits if regime else 0
                events = self.monitor.update(yf, y_frozen, k=k, t=tf)
                if regime and math.isfinite(yf + y_frozen):
                    self._regime_check(self.monitor.n_fits > n_fits)
        else:
            self._counts["skipped"] += 1
            est.advance(uf)
            yf = math.nan
        self._u.append(uf)
        self._y.append(yf)
        self._u_last = uf
        self._advance_k(1)
        for ev in events:
            self._on_event(ev)
        update = self._poll() if self._worker.pending is not None else None
        if update is None:
            update = self._attempt_if_due()
        return UpdateResult(
            k, tf, y_pred, y_frozen, yf, int(flags), held, self.monitor.fit, events, update,
            self.digital_model.version, time.perf_counter() - start,
        )

    def _advance_k(self, n: int) -> None:
        before = self._k
        self._k += n
        if self._k // self.horizon != before // self.horizon:
            self._theta_frozen = self.estimator_.parameters_

    def _on_event(self, ev: SyncEvent) -> None:
        est = self.estimator_
        if est.directional and ev.kind in ("desync", "resync"):
            est.set_directional(ev.kind == "resync")
            self._regime_left = None  # a recovery owns the forgetting now
        self.events.append(ev)
        self._log(ev.kind, ev.message, ev.k, ev.t, ev.payload())
        self._recovery_on_event(ev.kind)

    def enter_new_regime(self, *, fresh_covariance: bool = False) -> None:
        """The plant enters a regime the fast path has not seen: forget in every direction.

        Called at the closed loop's start, when the controller moves the plant
        away from the identification's operating region.  With directional
        forgetting (``directional_forgetting=True``) the fast path remembers
        the old regime along every direction the new one does not excite; so
        the forgetting is exponential from now on, as after a ``desync``, until
        the first monitor window made only of samples after this call fits at
        the resync level (``threshold + resync_margin``), a ``desync`` (its
        recovery then owns the forgetting) or a new model version.  Served
        runs replayed and offline runs measured it (docs/service.md, "The
        closed loop's start as a new regime").

        Parameters
        ----------
        fresh_covariance : bool, default=False
            Also restart the covariance at ``delta * I``.
        """
        est = self.estimator_
        if fresh_covariance:
            est.reset_covariance()
        if est.directional:
            est.set_directional(False)
            self._regime_left = self.monitor.window

    def _regime_check(self, evaluated: bool) -> None:
        """Count a new regime's monitored sample; end the regime where a window of them fits.

        Back to directional forgetting once a window of the regime's own samples
        fits at the resync level.
        """
        left = self._regime_left
        if left is None:
            return
        self._regime_left = left = max(left - 1, 0)  # 0: waiting for a good window
        mon = self.monitor
        if left <= 0 and evaluated and mon.in_sync and (
            mon.fit >= mon.threshold + mon.resync_margin
        ):
            self.estimator_.set_directional(True)
            self._regime_left = None

    def revise_last_input(self, u: float) -> None:
        """The plant applied ``u`` over the last sample's period, not the input :meth:`step` got.

        A live plant may apply an input a period late (it arrived after the
        plant's sample); it reports what it applied.  The estimator's filter
        state and the input buffer of re-identification are corrected, so
        the update module learns from the (input, output) pairs that happened.

        Parameters
        ----------
        u : float
            The input applied (ignored when not finite).
        """
        uf = _finite_or_nan(u)
        if math.isnan(uf) or not self._u or uf == self._u[-1]:
            return
        self.estimator_.revise_last_input(self._u[-1], uf)
        self._u[-1] = uf
        self._u_last = uf

    def _adopt(
        self, kind: str, model: KautzModel, offset: float, fit: float, u: NDArray,
        state: NDArray, u_now: NDArray | None, from_live: bool = False,
    ) -> DigitalModel:
        """Make a winning candidate the new model version; the fast path continues from it.

        ``state`` is the candidate's filter state at the end of ``u`` (its
        validation window); with ``u_now`` (the input from the window's first
        sample up to now, samples having arrived since) or ``extra_poles``,
        the state of the fast path's basis is recomputed over that input.
        ``from_live``: the candidate re-expresses the live model (a pole
        re-optimisation of its step response), so the fast path continues from
        the live model itself, projected onto the new basis (:meth:`_carry_over`).
        """
        est = self.estimator_
        live = (est.model_, est.offset_) if from_live else None  # before the reseed
        dm = self.digital_model.with_update(model, kind, fit)
        self.digital_model = dm
        self._core_n = model.n_functions
        wide = self._widen(model)
        u_in = u if u_now is None else u_now
        if wide is not model or u_now is not None:
            state = filter_states(wide.basis, u_in - self.input_offset)[-1]
        if live is not None:
            wide, offset = self._carry_over(live[0], wide.basis), live[1]
        if est.quadratic_scale is not None:  # its bank's state over the same input
            xq = filter_states(wide.basis, est.quadratic_input(u_in))[-1]
            state = np.concatenate([state, xq])
        est.reseed(wide, offset=offset, state=state, delta=self.delta)
        self._regime_left = None  # the reseed returns to the forgetting mode of the parameter
        self._theta_frozen = self.estimator_.parameters_
        self.monitor.clear_window()
        self._model_k = self._k
        self._counts["accepted"] += 1
        self._worker.make_stale("another model was accepted while it ran")
        if self.history is not None:
            self.history.add_model_version(self.run_id, dm, k=self._k)
        return dm

    @staticmethod
    def _carry_over(live: KautzModel, basis: KautzBasis) -> KautzModel:
        """The live fast-path model re-expressed on ``basis``: its exact projection.

        A pole re-optimisation fits a model of the core order to the live
        model's step response: it matches the live model at low frequencies,
        but not its one-step predictions, which the fast path's extra
        functions and recent recursive updates carry.  Continuing from the
        candidate's coefficients made the twin's prediction dip for a few
        seconds after such a version: 16 served runs against the OPC UA plant
        (the slow end-to-end test), replayed through the update module, had
        their lowest rolling fit after the last recovery window at 89.6 to
        97.8 % that way, 95.1 to 97.8 % from the projection.  The projection
        onto the new orthonormal basis
        (:func:`~kautztwin.approx.projection.coefficients_from_system`, a Stein
        equation) is the best approximation of the live model there: the
        prediction goes on as before, now on the new poles.
        """
        A, B, C, D = live.state_space()
        coef = coefficients_from_system(basis, (A, B, C, D, basis.dt))
        return KautzModel(basis, coef)

    def snapshot(self, provenance: str = "rls-update") -> DigitalModel:
        """Publish the fast path's live coefficients as a new model version.

        Parameters
        ----------
        provenance : str, default='rls-update'
            Provenance of the version.

        Returns
        -------
        DigitalModel
        """
        dm = self.digital_model.with_update(self.estimator_.model_, provenance)
        self.digital_model = dm
        if self.history is not None:
            self.history.add_model_version(self.run_id, dm, k=self._k)
            self._log(
                "model-update", f"{provenance}: version {dm.version}", self._k, None,
                {"version": dm.version, "offset": self.offset},
            )
        return dm

    def _log(self, kind: str, message: str, k: int | None, t: float | None, payload: Any) -> None:
        if self.history is not None:
            self.history.log_event(self.run_id, kind, message, k=k, t=t, payload=payload)

    def __repr__(self) -> str:
        return (
            f"Updater(dt={self.dt:g}, version={self.digital_model.version}, k={self._k}, "
            f"fit={self.monitor.fit:.2f})"
        )

