r"""The twin's sample loop: :class:`DigitalTwin` wires plant, update, control, optimization, store.

:class:`DigitalTwin` composes the five modules of the twin through the
small :class:`typing.Protocol` interfaces of :mod:`.protocols`:

1. the **physical system** (:class:`~kautztwin.twin.Plant`: the hydraulic drive,
   the TCLab emulator or board, or a replayed record);
2. the **digital model** (:class:`~kautztwin.twin.DigitalModel`: the current
   Kautz model, versioned, with its provenance);
3. the **update module** (:class:`~kautztwin.twin.runtime.TwinUpdater`, by default
   :class:`~kautztwin.twin.Updater`: recursive least squares on Kautz filters,
   synchronisation monitor, re-identification);
4. the **prediction module** (:class:`~kautztwin.twin.runtime.TwinController` /
   :class:`~kautztwin.twin.runtime.TwinPredictor`:
   :class:`~kautztwin.twin.prediction.MPCController`, a constrained Laguerre MPC
   built once per model version and re-solved every sample, and the twin's
   what-if prediction);
5. the **optimization module** (:class:`~kautztwin.twin.runtime.TwinOptimizer`, by
   default :class:`~kautztwin.twin.optimization.Optimizer`: pole re-optimisation,
   model consolidation and MPC weight retuning, each validated before it
   replaces the running version);

and the **history store** (:class:`~kautztwin.twin.HistoryStore`, SQLite by
default) in which every sample is committed.

A run is a deterministic function of its :class:`~kautztwin.twin.runtime.TwinConfig`
and the plant: an open-loop identification phase (binary excitation around
the operating point, then :func:`~kautztwin.twin.identify_output_error`), then
closed-loop MPC tracking of the set-point schedule while the twin updates
itself.  Each :meth:`DigitalTwin.step` returns a new immutable
:class:`~kautztwin.twin.runtime.TwinState`.  A run that is killed resumes from
its store (:mod:`.record`).  The loop delegates: the run's bookkeeping and
resume to :mod:`.record`, the excitation and the faults to :mod:`.excitation`,
the initial identification and the static twin to :mod:`.twins`, what
follows each update (resync, new model versions and their optimisation) to
:mod:`.versions`, the controller's life cycle to :mod:`.control`, and
background optimisation to :mod:`kautztwin.twin.optimization.background`.

**One sample** ``k`` (closed loop): read ``y(k)`` (with injected faults);
sanitise it (a dropout, outlier or late sample is flagged, the controller
then uses the twin's prediction instead); solve the MPC on the current
model version for the command ``v(k)`` and apply ``u(k) = v(k) + d(k)``
(a late sample holds the last input); update the twin and the static
twin with ``(u(k), y(k))``; act on the update module's events (a
``'resync'`` asks the optimizer to re-optimise the poles or consolidate
the fast path; a new model version is retuned and validated before the
controller is rebuilt on it); step the plant; commit the sample (every
``commit_every`` samples in one transaction).  A live plant (a network link)
reports the input it really applied over the period (``meta['u_applied']``):
when it differs (the input arrived late) the sample, both twins' filter states
and the MPC's take the applied one (:meth:`Updater.revise_last_input`).  Its
link also estimates the input delay (``meta['input_delay']``: samples from a
decision to the period the plant applies it), over which the MPC predicts
(:meth:`MPCController.solve`), and says how many newer samples already wait
(``meta['queued']``): more than a few, and the loop is behind, holds its input
and decides again once it has caught up.  It also holds its input until the plant reports the
last new one applied, so no input is overtaken on the wire and jumped over
(the rate limit holds at the plant): against a live plant the controller
decides once per round trip of the link.  With background workers a live plant's twin
is built without stalling the loop (:mod:`.birth`: the fit and the first tuning in a
worker, the catch-up a slice per sample) while the plant gets the excitation's
continuation; without them the identification stalls the loop while a live plant goes on
sampling, and the loop then takes the queued samples holding the last identification
input.  Either way the closed loop starts once the loop has caught up
(:meth:`DigitalTwin._catching_up`; ``k_closed_loop`` of the run is that sample).

**Resume.**  :meth:`DigitalTwin.start` with ``resume=True`` looks for an unfinished
run with the same configuration in the store.  Its committed samples are
replayed through the same code - the plant re-simulated with the stored
inputs (a real board just continues), the stored outputs used and
compared - so the run continues after the last committed sample with
every component in the state it had, and nothing is stored twice.

**Optimization in background mode.**  A new model version's weight
retuning and estimator retraining run in a worker thread
(:class:`~kautztwin.twin.optimization.background.OptimizationWorker`,
whose module notes give the rules); every :meth:`DigitalTwin.step` applies what has
finished with the rules, events and log entries of the synchronous path.

Size: the module is :class:`DigitalTwin` alone, about 1 000 lines: some 400
of them are docstrings (the numpydoc of its public API and the notes of a live
plant's paths), its code (the sample loop and its phases: identification,
the twin's birth, catching up with a live plant, control, update) some 550,
every other job delegated to the modules beside it.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...exceptions import DataError
from ..digital import DigitalModel
from ..history import HistoryStore
from ..optimization import Optimizer
from ..physical import Clock, Plant, Reading, ReplayPlant, SampleFlag
from ..prediction import MPCController
from ..prediction.controller import MAX_DELAY
from ..update import Updater
from .birth import BackgroundBirth
from .config import TwinConfig
from .excitation import FaultPlan, excitation
from .inflight import InputsInFlight
from .protocols import TwinError, TwinOptimizer
from .record import Replay, RunRecord, open_history
from .results import TwinRun, TwinState
from .twins import catch_up, identification_info, identify_initial, make_sanitizer, make_twins
from .versions import ModelVersions

__all__ = ["MAX_INPUT_WAIT", "MAX_QUEUED", "DigitalTwin"]

#: samples the loop holds its input for a live plant to report it applied, or to catch up
#: (then it decides anyway)
MAX_INPUT_WAIT = 50
#: newer samples of a live plant already waiting that make the loop hold to catch up
MAX_QUEUED = 5


def _step_updater(updater: Updater, u: float, y: float, t: float, *, adapt: bool,
                  judge: bool = True) -> Any:
    """``updater.step``; with ``adapt=False`` its recursive estimator only predicts and
    advances, with ``judge=False`` its monitor does not see the sample."""
    if adapt and judge:  # every closed-loop sample: nothing to switch
        return updater.step(u, y, t)
    fast, monitoring = updater.fast_update, updater.monitoring
    updater.fast_update = fast and adapt
    updater.monitoring = monitoring and judge
    try:
        return updater.step(u, y, t)
    finally:
        updater.fast_update, updater.monitoring = fast, monitoring


class DigitalTwin:
    r"""The digital twin runtime: identify, then control, update, optimise and record.

    Parameters
    ----------
    plant : Plant
        The physical system.
    config : TwinConfig, optional
        The run; :meth:`TwinConfig.for_plant` of the plant when omitted.
    history : HistoryStore, str, os.PathLike or None, default=None
        The history store: a store, the path of a SQLite file (durable; a
        killed run resumes from it), or ``None`` for an in-memory SQLite database.
    clock : Clock, optional
        Pacing of the loop; as fast as possible when omitted.  A real-time
        clock waits for each sample's time (``speedup`` plant seconds per
        wall-clock second) and counts late ticks (its ``tolerance``).
    optimizer : TwinOptimizer, optional
        The optimization module; :class:`~kautztwin.twin.optimization.Optimizer`
        when omitted.
    background : bool or None, default=None
        Run the update module's re-identification in a worker thread, off
        the sampling path (``Updater(background=True)``), and the
        optimization module's work on each new model version (MPC weight
        retuning, estimator retraining) in a second one (see the module notes).  ``None`` takes
        ``config.updater['background']`` when set, else turns it on only
        with a real-time ``clock``: there a synchronous attempt (tens of
        milliseconds to seconds) would make samples late, while a run as fast
        as possible gains nothing and stays reproducible only when
        synchronous (the sample at which a background candidate takes over
        depends on wall-clock time).  The replay of a resumed run is always
        synchronous.  :meth:`close` stops the workers.
    estimator : object, optional
        A trained DNN estimator (``kautztwin.nn.CoefficientEstimator`` or
        ``AdaptivePoleEstimator``, or any object with ``predict_models`` and
        ``fine_tune``) for the update module's step-test fast path
        (:meth:`Updater.update_from_step_test`).  With ``config.retune``, each
        new model version asks the optimizer to fine-tune it around the new
        operating point (:meth:`Optimizer.retrain_estimator`); a validated
        candidate replaces it (events ``'estimator-update'`` /
        ``'estimator-rejected'``).  It must have as many basis functions as the
        twin's models.

    Raises
    ------
    DataError
        If the configuration does not fit the plant (another ``dt``), or
        ``background`` is not a bool or ``None``.

    Attributes
    ----------
    updater : Updater or None
        The update module (after the identification phase).
    static : Updater or None
        The static twin (updates disabled), when ``config.static_twin``.
    controller : MPCController
        The prediction/control module.
    optimizer : TwinOptimizer
        The optimization module.
    background : bool
        Whether the update module re-identifies, and the optimization module
        retunes, in the background (resolved).
    history : HistoryStore
        The store.
    run_id : int or None
        The run in the store (after :meth:`start`).
    state : TwinState
        The latest state.

    See Also
    --------
    TwinConfig.for_plant : Tuned profiles of the shipped plants.
    kautztwin.twin.report.write_report : ``metrics.json``, ``report.md`` and plots.

    Examples
    --------
    >>> from kautztwin.twin import HydraulicPlant
    >>> from kautztwin.twin.runtime import DigitalTwin, TwinConfig
    >>> plant = HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1)
    >>> cfg = TwinConfig.for_plant(plant, duration=12.0, quick=True, static_twin=False)
    >>> run = DigitalTwin(plant, cfg).run(progress=False)
    >>> run.n_done, run.status, int(run.arrays["version"][-1]) >= 1
    (600, 'finished', True)
    """

    def __init__(
        self,
        plant: Plant,
        config: TwinConfig | None = None,
        *,
        history: HistoryStore | str | os.PathLike[str] | None = None,
        clock: Clock | None = None,
        optimizer: TwinOptimizer | None = None,
        background: bool | None = None,
        estimator: Any = None,
    ) -> None:
        self.plant = plant
        self.estimator = estimator
        self.config = config if config is not None else TwinConfig.for_plant(plant)
        if abs(self.config.dt - float(plant.dt)) > 1e-9 * plant.dt:
            raise DataError(
                f"the configuration has dt = {self.config.dt:g} s but the plant samples at "
                f"{plant.dt:g} s"
            )
        self.history, self.store, self._owns_history = open_history(history)
        self.clock = clock if clock is not None else Clock()
        if background is None:
            background = self.config.updater.get("background", self.clock.realtime)
        if not isinstance(background, bool | np.bool_):
            raise DataError(f"background must be True, False or None, got {background!r}")
        self.background = bool(background)
        self.optimizer: TwinOptimizer = optimizer if optimizer is not None else Optimizer()
        self.controller = MPCController(input_offset=self.config.operating_input)
        self.updater: Updater | None = None
        self.static: Updater | None = None
        self.run_id: int | None = None
        self.state = TwinState(-1, math.nan, "identification")
        self._started = False
        self._versions: ModelVersions | None = None
        self._birth: BackgroundBirth | None = None  # a live plant's twin in the making (.birth)

    # ------------------------------------------------------------------ properties
    @property
    def digital_model(self) -> DigitalModel | None:
        """The current model version (``None`` before identification)."""
        return None if self.updater is None else self.updater.digital_model

    @property
    def k(self) -> int:
        """Index of the next sample."""
        return self._k if self._started else 0

    @property
    def done(self) -> bool:
        """Whether every sample of the run was processed."""
        return self._started and self._k >= self.config.n_samples

    @property
    def optimizing(self) -> bool:
        """Whether a background optimization job is in flight or waits for the worker."""
        return self._versions is not None and self._versions.worker.busy

    def wait_optimization(self, timeout: float | None = None) -> bool:
        """Block until the worker has finished the optimization job in flight.

        The next :meth:`step` applies its results (and submits a queued job).

        Parameters
        ----------
        timeout : float, optional
            Most seconds to wait (no limit when omitted).

        Returns
        -------
        bool
            Whether no computation is outstanding any more.
        """
        return True if self._versions is None else self._versions.worker.wait(timeout)

    def what_if(self, u_plan: ArrayLike) -> NDArray[np.float64]:
        """Predict the plant's response to a planned input from the twin's current state.

        Parameters
        ----------
        u_plan : array-like of shape (n_steps,)
            Inputs of the next samples.

        Returns
        -------
        ndarray of shape (n_steps,)
            Predicted outputs of the same samples (the live model of the update module).

        Raises
        ------
        TwinError
            Before the identification phase has ended.
        """
        if self.updater is None:
            raise TwinError("the twin has no model yet (identification phase)")
        return self.updater.predict(np.asarray(u_plan, dtype=float))

    # ------------------------------------------------------------------ setup
    def start(self, *, resume: bool = True) -> TwinState:
        """Open the run: a new one, or resume an unfinished one with the same configuration.

        Parameters
        ----------
        resume : bool, default=True
            Look for an unfinished run with this configuration in the store
            and continue it after its last committed sample.

        Returns
        -------
        TwinState
            The state before the next sample (after the replay when resumed).

        Raises
        ------
        TwinError
            If the store's committed samples are not a contiguous prefix.
        """
        if self._started:
            raise TwinError("the run has already been started")
        cfg = self.config
        self._wall0 = time.perf_counter()
        self._record = rec = RunRecord(self.history, self.store, cfg.n_samples)
        self._u_ident, self._d = excitation(cfg)
        self._faults = FaultPlan.for_config(cfg)
        self._sanitizer = make_sanitizer(cfg)
        self._k = 0
        self._k_id = cfg.n_ident  # the identification phase ends (the initial identification)
        self._k_born = cfg.n_ident  # the twin is born (later: a live plant's background fit)
        self._born_stored: tuple[int, tuple[float, float] | None] | None = None  # resumed
        self._k_cl = cfg.n_ident  # the closed loop starts (later: a live plant catching up)
        self._k_cl_stored: int | None = None  # where a resumed live run's closed loop started
        self._v_prev = cfg.operating_input
        self._d_prev = 0.0
        self._u_prev = cfg.operating_input
        self._ref = math.nan
        self._late_ticks = 0
        self._mpc_failures = 0
        self._inflight = InputsInFlight(MAX_INPUT_WAIT)  # a new input not yet seen applied
        self._k_decided = -1  # the last sample the controller solved at
        self._drift_logged: set[float] = set()
        self._versions = ModelVersions(cfg, self.optimizer, rec, self.controller,
                                       on_estimator=self._set_estimator)
        self._replay: Replay = rec.open({"twin": cfg.to_dict(), "plant": self.plant.name}, resume)
        self.run_id = rec.run_id
        # process workers start before the plant's samples flow: the first one waits for the
        # forkserver to import the library (about 1 s of CPU); during a live plant's
        # identification that stalled the loop, which thinned the excitation the plant saw
        if self.background and cfg.retune:
            self._versions.prestart_poles(str(cfg.updater.get("worker", "thread")))
        if self.background and cfg.controlled:
            self._versions.worker.prestart()  # a process worker's child: ready by the first tuning
        self._reading = self.plant.reset()
        self._t_offset = 0.0
        self._replayable = not getattr(self.plant, "connected", False)
        if self._replay.rows is not None:
            self._versions.resumed()  # where the stored run judged its live pole retunings
        if self._replay.rows is not None and not self._replayable:
            self._k_cl_stored = self._stored_closed_loop()
            self._born_stored = self._stored_birth()
        if (self.background and cfg.controlled and not self._replayable
                and self._born_stored is None):
            # a live plant goes on sampling while its twin is built (see .birth)
            self._birth = BackgroundBirth(cfg, str(cfg.updater.get("worker", "thread")))
        self._started = True
        self.clock.start()
        self._clock_t0 = 0.0
        if self._replay.rows is not None:
            self._replay.resume_k = rec.committed
            while self._k < self._replay.resume_k:
                self.step()
            if not self._replayable and self._k < cfg.n_samples:
                # a real plant cannot be rewound: it continues from where it is now
                self._reading = self.plant.reset()
                self._t_offset = self._k * cfg.dt
            self._replay.rows = None
            if self.updater is not None:  # the replay ran synchronously
                self.updater.background = self.background
            self.clock.start()
            self._clock_t0 = self._k * cfg.dt
        return self.state

    # ------------------------------------------------------------------ one sample
    def step(self) -> TwinState:
        """Process the next sample and return the new state.

        Returns
        -------
        TwinState

        Raises
        ------
        TwinError
            If the run was not started or is complete.
        """
        if not self._started:
            raise TwinError("call start() (or run()) first")
        cfg = self.config
        k = self._k
        if k >= cfg.n_samples:
            raise TwinError(f"the run is complete ({cfg.n_samples} samples)")
        replay = self._replay.active(k)
        a = self._record.arrays
        n_ev = len(self._record.events)
        t_k, y_raw, flags = self._measure(k, replay)
        clean = not (flags & (SampleFlag.HELD | SampleFlag.OUTLIER))
        late = bool(flags & SampleFlag.LATE and flags & SampleFlag.HELD)
        versions = self._versions
        assert versions is not None
        if versions.worker.busy:
            versions.worker.poll(versions.version, k, t_k)  # apply what it has finished
        phase, u, v, d, mpc_ms = self._input(k, t_k, y_raw, clean, late)
        if replay:
            u = self._replay.input(k, u)
        a["u"][k], a["command"][k], a["dither"][k], a["mpc_ms"][k] = u, v, d, mpc_ms
        self._v_prev, self._d_prev, self._u_prev = v, d, u
        upd_ms, fit, fit_s = self._update(k, t_k, u, y_raw)
        self._advance(k, u, replay)
        if not (replay or self._replayable) and k + 1 < cfg.n_samples:
            u = self._applied_input(k, u)
        if not replay:
            self._record.prediction(k)
            self._record.commit((k, t_k, u, y_raw, int(flags)), every=cfg.commit_every,
                                last=k + 1 == cfg.n_samples)
        self._k = k + 1
        events = [e.kind for e in self._record.events[n_ev:]]
        self.state = TwinState(
            k, t_k, phase, y_raw, u, v if cfg.controlled else math.nan,
            a["setpoint"][k], a["reference"][k], a["y_pred"][k], a["y_pred_static"][k],
            int(flags), versions.version, fit, fit_s, mpc_ms, upd_ms, tuple(events),
            self._record.committed, replay,
        )
        return self.state

    def _measure(self, k: int, replay: bool) -> tuple[float, float, SampleFlag]:
        """Read sample ``k`` (faults injected, or as stored when replayed), log drift, sanitise."""
        t_k, y_raw = self._faults.apply(k, self._reading.t + self._t_offset,
                                        float(self._reading.y))
        if replay:
            t_k, y_raw = self._replay.reading(k, t_k, y_raw)
        for e in getattr(self.plant, "drift_events", ()):
            if t_k >= e and e not in self._drift_logged:
                self._drift_logged.add(e)
                self._record.event("drift", k, t_k, f"plant drift event at {e:g} s",
                                   {"t_event": e})
        s = self._sanitizer.process(y_raw, t_k)
        clean = not (s.flags & (SampleFlag.HELD | SampleFlag.OUTLIER))
        a = self._record.arrays
        a["t"][k], a["y"][k], a["flags"][k] = t_k, y_raw, int(s.flags)
        a["y_clean"][k] = y_raw if clean else math.nan
        return t_k, y_raw, s.flags

    def _input(
        self, k: int, t_k: float, y_raw: float, clean: bool, late: bool
    ) -> tuple[str, float, float, float, float]:
        """``(phase, u, v, d, mpc_ms)``: the input of sample ``k`` (identification, control)."""
        cfg = self.config
        mpc_ms = math.nan
        if k < self._k_id:
            phase = "identification"
            u = self._recorded_input(k) if not cfg.controlled else self._ident_input(k)
            v, d = u, 0.0
        elif not cfg.controlled:
            phase = "monitoring"
            u = self._recorded_input(k)
            v, d = u, 0.0
        else:
            if self.updater is None and not self._born(k, t_k):
                phase = "identification"  # the excitation goes on while the twin identifies
                u = v = self._ident_input(k)
                d = 0.0
            elif self._catching_up(k, t_k):
                phase = "identification"  # its last input held until the loop has caught up
                u = v = self._u_prev
                d = 0.0
                self.controller.advance(v, d)
            else:
                phase = "closed-loop"
                u, v, d, mpc_ms = self._track(k, t_k, y_raw, clean, late)
        if k == self._k_id and not cfg.controlled:
            self._begin_twin(k, t_k)
        return phase, u, v, d, mpc_ms

    def _catching_up(self, k: int, t_k: float) -> bool:
        """Whether the closed loop of a live plant still waits at sample ``k`` (controlled run).

        The initial identification (at sample ``n_ident``) stalls the loop while a
        live plant goes on sampling: the samples queued meanwhile
        (``meta['queued']``) are history.  The loop takes them (the twins predict
        and store them; the recursive estimator does not adapt on them: they
        carry one held input) holding the last identification input, which the plant applies
        all along, and starts the closed loop at the first sample after
        ``n_ident`` with at most :data:`MAX_QUEUED` newer ones waiting (or after
        at most ``config.n_ident`` samples): the controller then
        starts from a recent sample, its reference from the output it measures.
        A simulated or replayed plant starts it at once (``k_closed_loop = n_ident``).
        The start is stored as a ``'phase'`` event with ``k_closed_loop``; the replay
        of a resumed run starts it there.
        """
        if k != self._k_cl or self._replayable:
            return False
        if self._replay.active(k):
            stored = self._k_cl_stored
            waiting = stored is None or k < stored
        else:
            # at k_id the reading predates the identification that just stalled the loop
            waiting = ((k == self._k_born or self._behind(k))
                       and k - self._k_born < self.config.n_ident)
        if waiting:
            self._k_cl = k + 1
            return True
        self._record.event(
            "phase", k, t_k, f"closed loop from sample {k}: {k - self._k_id} samples queued "
            "during the identification taken first", {"k_closed_loop": k,
                                                       "caught_up": k - self._k_id})
        return False

    def _stored_birth(self) -> tuple[int, tuple[float, float] | None] | None:
        """``(k, tuning_point)``: where the run being resumed built its twin (``None``: not yet).

        ``tuning_point``: the ``(u_op, y_op)`` its first controller was tuned at
        when it was built in the background, else ``None``.
        """
        assert self.run_id is not None
        for e in self.history.events(self.run_id, "phase"):
            info = e.payload or {}
            if isinstance(info.get("fit_percent"), float) and e.k is not None:
                point = info.get("tuning_point")
                return int(e.k), (None if point is None else (float(point[0]),
                                                              float(point[1])))
        return None

    def _stored_closed_loop(self) -> int | None:
        """The closed-loop start stored by the run being resumed (``None``: not reached)."""
        assert self.run_id is not None
        for e in self.history.events(self.run_id, "phase"):
            k = (e.payload or {}).get("k_closed_loop")
            if isinstance(k, int):
                return k
        return None

    def _track(
        self, k: int, t_k: float, y_raw: float, clean: bool, late: bool
    ) -> tuple[float, float, float, float]:
        """``(u, v, d, mpc_ms)``: MPC tracking of the filtered set-point (closed loop)."""
        cfg = self.config
        a = self._record.arrays
        assert self.updater is not None and cfg.mpc is not None
        mpc_ms = math.nan
        y_fb = y_raw if clean else self.updater.estimator_.predict()
        if math.isnan(self._ref):
            self._ref = y_fb
        sp = cfg.setpoint(t_k)
        if cfg.reference_tau > 0:
            alpha = 1.0 - math.exp(-cfg.dt / cfg.reference_tau)
            self._ref += alpha * (sp - self._ref)
        else:
            self._ref = sp
        a["setpoint"][k], a["reference"][k] = sp, self._ref
        if late:
            v, d = self._v_prev, self._d_prev
        elif self._holding(k):
            v, d = self._v_prev, self._held_dither(k)
        else:
            self._k_decided = k
            res = self.controller.solve(y_fb, self._ref, self._v_prev,
                                        delay=self._input_delay(k))
            mpc_ms = 1e3 * res.solve_time
            a["mpc_ok"][k] = float(res.success)
            if not res.success:
                self._mpc_failures += 1
            v, d = float(res.u_next), float(self._d[k])
        u = float(np.clip(v + d, cfg.mpc.u_min, cfg.mpc.u_max))
        self.controller.advance(v, d)
        if u != self._u_prev and self._k_decided == k and self._pairs_inputs(k):
            # a new decision to a live plant: decide again once it is applied (a dither
            # switch while the command is held may be overtaken: see _held_dither)
            self._inflight.send(u, k, self._queued(), self._applied_now())
        return u, v, d, mpc_ms

    def _update(self, k: int, t_k: float, u: float, y_raw: float) -> tuple[float, float, float]:
        """``(update_ms, fit, fit_static)``: step both twins and act on the update's events."""
        a = self._record.arrays
        versions = self._versions
        assert versions is not None
        upd_ms = math.nan
        fit = fit_s = math.nan
        if self.updater is not None and k >= self._k_id:
            # the samples a live plant queued during the identification carry its last input,
            # held: the twin predicts and stores them but neither adapts on them nor judges
            # its fit on them; the monitors' first window is the closed loop's
            live = k >= self._k_cl
            if k == self._k_cl:
                fresh = self._k_cl > self._k_id
                if fresh:
                    for upd in (self.updater, self.static):
                        if upd is not None:
                            upd.monitor.clear_window()
                # the fast path enters the controller's regime: forgetting in every
                # direction until it fits there (docs/service.md, "The closed loop's start
                # as a new regime"); a live plant's, which has not adapted on the samples
                # queued meanwhile, with a fresh covariance too, as after a new model
                # version: the closed loop's first windows fit better in served runs
                # (docs/service.md, "The fast path at the closed loop's start")
                self.updater.enter_new_regime(fresh_covariance=fresh)
            r = _step_updater(self.updater, u, y_raw, t_k, adapt=live, judge=live)
            a["y_pred"][k] = r.y_pred_frozen
            if r.model_update is None:
                upd_ms = 1e3 * r.elapsed
            fit = self.updater.monitor.fit
            versions.after_update(r, k, t_k, u_op=self._v_prev, offload=self._offloaded(k))
            if self.static is not None:
                rs = _step_updater(self.static, u, y_raw, t_k, adapt=True, judge=live)
                a["y_pred_static"][k] = rs.y_pred_frozen
                fit_s = self.static.monitor.fit
        a["update_ms"][k] = upd_ms
        a["version"][k] = versions.version
        return upd_ms, fit, fit_s

    def _advance(self, k: int, u: float, replay: bool) -> None:
        """Apply ``u`` to the plant for one period (or take the stored reading) and pace."""
        if replay and not self._replayable:
            reading = self._replay.next_reading(k)
            if reading is not None:
                self._reading = reading
        elif k + 1 < self.config.n_samples:
            self._reading = self._plant_step(u)
            if not replay:
                late_s = self.clock.wait_until(self._reading.t + self._t_offset - self._clock_t0)
                if self.clock.realtime and late_s > self.clock.tolerance:
                    self._late_ticks += 1

    def _applied_input(self, k: int, u: float) -> float:
        """The input a live plant reports it applied over period ``k`` (else ``u``).

        An input that reached the plant late was applied a period later; the
        sample, the update module and the static twin take the applied one,
        so the model learns from what happened.
        """
        applied = float(self._reading.meta.get("u_applied", math.nan))
        if not math.isfinite(applied) or applied == u:
            return u
        if not self._reading.t + self._t_offset > self._record.arrays["t"][k]:
            return u  # a late sample (after NaN readings): its period is not this one
        a = self._record.arrays
        a["u"][k] = applied
        if k >= self._k_id and self.config.controlled and self.controller.model is not None:
            a["command"][k] += applied - u  # a rebuilt controller starts from what was applied
            self.controller.revise_last_input(applied - u)
        if k >= self._k_id:
            for upd in (self.updater, self.static):
                if upd is not None:
                    upd.revise_last_input(applied)
        return applied

    def _holding(self, k: int) -> bool:
        """Whether the controller holds its input at sample ``k`` of a live plant (no solve).

        It holds while the last new input has not been applied (:meth:`_awaiting`),
        and while it is behind (:meth:`_behind`) unless it has learnt the input
        delay from the sample stream and the MPC's predictor covers it
        (:data:`~kautztwin.twin.prediction.controller.MAX_DELAY`): a decision on a
        sample the queue has made history is then a decision for the period it
        will be applied over.  In both cases for at most :data:`MAX_INPUT_WAIT`
        samples since its last decision.
        """
        if self._awaiting(k):
            return True
        if not self._behind(k):
            return False
        own = self._inflight.delay(self._queued())
        if own is not None and own <= MAX_DELAY:
            return False
        return k - self._k_decided <= MAX_INPUT_WAIT

    def _held_dither(self, k: int) -> float:
        """The dither of sample ``k`` while the controller holds its command (a live plant).

        While the loop is behind (:meth:`_behind`) the dither follows its schedule,
        even with an input in flight: the plant stays excited while the loop
        catches up, instead of holding a flat input (and output) until the loop
        has read its way to the samples that show the input applied - windows of
        a flat output score a noise-dominated sync fit (measured against the OPC
        UA plant at x10: 92 to 94 % with a prediction error at the noise level).
        The command is held, so every input sent since the last decision differs
        from it by the dither alone: whichever of them the link overtakes, the
        plant's input moves by at most the decision's step plus twice the dither
        amplitude, within the rate limit (``du_max - 2 * dither`` is the
        command's).  Otherwise the dither is held while an input is in flight
        (one input in flight at a time, :meth:`_awaiting`).
        """
        if self._inflight.pending and not self._behind(k):
            return self._d_prev
        return float(self._d[k])

    def _behind(self, k: int) -> bool:
        """Whether more than :data:`MAX_QUEUED` newer samples of a live plant already wait.

        The loop is then behind the plant (``meta['queued']``, e.g. after the
        initial identification, or on a stalled host): this sample is history
        for the controller, whose decision would reach the plant after the newer
        ones are taken.  It holds its input until it has caught up, so it
        decides on recent samples and catches up faster; the update module
        still takes every sample.  A short queue (samples delivered in batches,
        a scheduling hiccup) is part of the input delay the MPC predicts over.
        """
        if self._replay.active(k):
            return False
        queued = self._reading.meta.get("queued", 0)
        return isinstance(queued, int | float) and queued > MAX_QUEUED

    def _pairs_inputs(self, k: int) -> bool:
        """Whether the plant is live and reports the input it applied (``meta['u_applied']``)."""
        if self._replayable or self._replay.active(k):
            return False
        return math.isfinite(float(self._reading.meta.get("u_applied", math.nan)))

    def _awaiting(self, k: int) -> bool:
        """Whether the last decision sent to a live plant has not been applied yet.

        A link may overtake an input with a newer one (one write in flight, the
        newest next); the plant would then jump over it, by more than the rate
        limit allows.  The loop decides again only once its last decided input is
        applied, so no decision is jumped over: the decisions come once per round
        trip of the link.  Applied means: the plant reports it
        (``meta['u_applied']``, on a sample at or after the newest one the link
        held when it was sent), or :data:`MAX_INPUT_WAIT` samples passed (an
        input that never arrives: refused, lost); see
        :class:`~kautztwin.twin.runtime.inflight.InputsInFlight`.  While a
        decision is awaited the dither is held too, unless the loop is behind
        (:meth:`_held_dither`).
        """
        return self._inflight.awaiting(k, self._applied_now(), self._queued())

    def _applied_now(self) -> float:
        """The input the live plant reports it applied over the current sample (NaN: none)."""
        try:
            return float(self._reading.meta.get("u_applied", math.nan))
        except (TypeError, ValueError):
            return math.nan

    def _queued(self) -> int:
        """Newer samples the live plant's link already holds (``meta['queued']``, else 0)."""
        queued = self._reading.meta.get("queued", 0)
        return int(queued) if isinstance(queued, int | float) and queued > 0 else 0

    def _input_delay(self, k: int) -> int:
        """Samples from a decision to the period a live plant applies it.

        The samples queued plus the wire latency the loop has learnt from the
        inputs it saw applied (:meth:`InputsInFlight.delay`); before any, the
        link's own estimate ``meta['input_delay']``.  0 for a simulated plant, a
        replayed sample, or a link that does not estimate it.  The loop's
        estimate needs no clock: the link's (the plant's index from the wall
        clock and the plant's nominal speed) drifts when a plant server runs
        slower than its nominal speed (measured: 300 to 450 samples with none
        queued, the server at x5.5 of a nominal x10 on a loaded host).
        """
        if self._replay.active(k):
            return 0
        own = self._inflight.delay(self._queued())
        if own is not None:
            return own
        value = self._reading.meta.get("input_delay", 0)
        try:
            delay = int(value)
        except (TypeError, ValueError):
            return 0
        return max(0, delay)

    def _ident_input(self, k: int) -> float:
        """The identification input of sample ``k`` (controlled run).

        Without background workers a live plant goes on sampling while the twin
        identifies (the loop stalls at ``n_ident``), holding the input of the last
        identification sample: that one is the excitation's centre ``ident_level``, so
        the plant waits at the operating point it was identified around, not at an edge
        of the excitation (where the closed loop would start outside the identified
        range).  Its response falls after the identification record, which it therefore
        leaves unchanged.  With them, the samples from ``n_ident`` until the twin is
        born get the excitation's continuation (:mod:`.birth`).
        """
        if k == self._k_id - 1 and not self._replayable:
            return float(self.config.ident_level)
        if k >= self._k_id:  # the twin is being identified in the background (.birth)
            birth = self._birth
            return birth.input(k - self._k_id) if birth is not None else self._u_prev
        return float(self._u_ident[k])

    def _recorded_input(self, k: int) -> float:
        u = getattr(self.plant, "u", None)
        if u is not None and k < len(u):
            value = float(u[k])
            return value if math.isfinite(value) else self._u_prev
        return float(self._u_ident[k]) if k < self._u_ident.size else self._u_prev

    def _plant_step(self, u: float) -> Reading:
        if isinstance(self.plant, ReplayPlant):
            return self.plant.step(None)
        return self.plant.step(u)

    # ------------------------------------------------------------------ identification
    def _born(self, k: int, t: float) -> bool:
        """Whether the twin of a controlled run exists at sample ``k >= n_ident`` (built now?).

        At ``n_ident`` it is identified and built at once, unless a live plant's
        twin is built in the background (:mod:`.birth`): then it is born at the
        first sample at which its fit, catch-up and first tuning are done.  The
        replay of a resumed live run builds it where the stored run did.
        """
        birth = self._birth
        if self._replay.active(k) and not self._replayable:
            stored = self._born_stored
            if stored is None or k < stored[0]:
                return False
            self._begin_twin(k, t, tuning_point=stored[1])
        elif birth is not None:
            if not birth.grow(self._record.arrays, k, optimizer=self.optimizer,
                              estimator=self.estimator):
                return False
            assert birth.twins is not None
            _, tuning = birth.tuning(wait=True)
            self._begin_twin(k, t, fit=birth.fit, twins=birth.twins, start=birth.started_at,
                             tuning_point=birth.tuning_point, tuning=tuning)
            birth.close()
            self._birth = None
        else:
            self._begin_twin(k, t)
        self._k_born = k
        self._k_cl = max(self._k_cl, k)
        return True

    def _begin_twin(
        self, k: int, t: float, *, fit: Any = None, twins: Any = None, start: float | None = None,
        tuning_point: tuple[float, float] | None = None, tuning: Any = None,
    ) -> None:
        """The twin's birth: identify, build the twins and the first controller (or take them).

        The twins catch up on the samples before ``k`` (unless ``twins`` have);
        the first controller is tuned at ``tuning_point`` (``(u_op, y_op)``;
        the command in force and the sample's output when omitted), or takes
        ``tuning``, made there in the background.
        """
        cfg = self.config
        rec = self._record
        a = rec.arrays
        start = time.perf_counter() if start is None else start
        if fit is None:
            fit = identify_initial(cfg, a["u"][:self._k_id].copy(),
                                   a["y_clean"][:self._k_id].copy())
        if twins is None:
            # a resumed run replays its committed samples synchronously (as fast as possible)
            background = self.background and not self._replay.active(k)
            twins = make_twins(fit, cfg, background=background, estimator=self.estimator)
            catch_up(twins[0], twins[1], a, k)  # the twins catch up on the samples so far
        self.updater, self.static, rates = twins
        rec.identification = identification_info(fit, rates, self._k_id, start, k_twin=k,
                                                 tuning_point=tuning_point)
        rec.event("phase", k, t, f"identified the initial model: fit {fit.fit_percent:.2f} %",
                  rec.identification)
        assert self._versions is not None
        u_op, y_op = tuning_point if tuning_point is not None else (self._v_prev, None)
        self._versions.first(self.updater, k, t, u_op=u_op, offload=self._offloaded(k),
                             y_op=y_op, tuning=tuning)

    def _offloaded(self, k: int) -> bool:
        """Whether a new version's optimisation runs in the worker (background, not replaying)."""
        return self.background and self.config.retune and not self._replay.active(k)

    def _set_estimator(self, estimator: Any) -> None:
        self.estimator = estimator  # an accepted retraining: the twin runs it from now on

    # ------------------------------------------------------------------ the loop
    def run(
        self, duration: float | None = None, *, resume: bool = True, progress: bool | None = None
    ) -> TwinRun:
        """Run (or resume) to the end and return the record.

        Parameters
        ----------
        duration : float, optional
            Override the configured duration, s.
        resume : bool, default=True
            Resume an unfinished run with the same configuration from the store.
        progress : bool or None, default=None
            Live progress display (tqdm on stderr): ``None`` shows it only on a
            terminal.

        Returns
        -------
        TwinRun
        """
        if duration is not None and not self._started:
            self.config = replace(self.config, duration=float(duration))
        if not self._started:
            self.start(resume=resume)
        bar = self._progress(progress)
        try:
            every = max(1, self.config.n_samples // 200)
            while self._k < self.config.n_samples:
                st = self.step()
                if bar is not None and (st.k % every == 0 or self._k == self.config.n_samples):
                    bar.update(self._k - bar.n)
                    fit = "-" if math.isnan(st.fit) else f"{st.fit:.1f}%"
                    bar.set_postfix_str(f"t={st.t:.1f}s {st.phase} v{st.version} fit={fit}",
                                        refresh=False)
        finally:
            if bar is not None:
                bar.close()
        return self.finish()

    def _progress(self, progress: bool | None) -> Any:
        if progress is False:
            return None
        from tqdm.auto import tqdm

        return tqdm(
            total=self.config.n_samples, initial=self._k, unit="sample",
            desc=f"twin {self.config.plant}", disable=None if progress is None else False,
            dynamic_ncols=True, leave=True,
        )

    def finish(self, status: str | None = None) -> TwinRun:
        """Commit what is pending, mark the run and return its record.

        Parameters
        ----------
        status : str, optional
            Final status; ``'finished'`` when every sample was processed,
            else the run stays ``'running'`` (resumable).

        Returns
        -------
        TwinRun
        """
        if not self._started:
            raise TwinError("call start() (or run()) first")
        complete = self._k >= self.config.n_samples
        final = status if status is not None else ("finished" if complete else "running")
        self._record.finish(final)
        return self.result(final)

    def result(self, status: str = "running") -> TwinRun:
        """The record of the samples processed so far.

        Parameters
        ----------
        status : str, default='running'

        Returns
        -------
        TwinRun
        """
        counts = dict(self._sanitizer.counts)
        counts.update(late_ticks=self._late_ticks, mpc_failures=self._mpc_failures)
        if self.updater is not None:
            uc = self.updater.counts
            counts.update(reidentification_attempts=uc["attempts"],
                          reidentifications_accepted=uc["accepted"])
        return self._record.result(
            self.config, self.plant.name, self._k, self._k_cl, counts, self._replay.summary(),
            time.perf_counter() - self._wall0, status,
        )

    def close(self) -> None:
        """Stop the workers, close the plant and the store if the twin opened it.

        A background re-identification still running is cancelled (its
        result is dropped); so is a background optimization job: what has
        not started is cancelled, a running part (a weight retuning, an
        estimator retraining) cannot be interrupted and is waited for, and
        the worker thread is joined.  Call :meth:`finish` first to commit
        the run.
        """
        for upd in (self.updater, self.static):
            if upd is not None:
                upd.close()
        if self._birth is not None:
            self._birth.close()
        if self._versions is not None:
            self._versions.close()
        self.plant.close()
        if self._owns_history:
            self.history.close()

    def __enter__(self) -> DigitalTwin:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"DigitalTwin(plant={self.plant.name!r}, k={self.k}/{self.config.n_samples}, "
            f"version={self._versions.version if self._versions else 0}, store={self.store!r})"
        )
