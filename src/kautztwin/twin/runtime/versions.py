"""What follows each update: log its events, ask the optimizer, optimise new model versions.

:class:`ModelVersions` follows the model versions of a run.  After each
update it logs the update's events; a ``'resync'`` asks the optimizer to
re-optimise the poles or, failing that, to consolidate the fast path into
a new version; every new version is stored, and its estimator retraining
and controller retuning run synchronously or are queued for the
background worker (:class:`~kautztwin.twin.optimization.background.OptimizationWorker`).
The controller switch itself is :class:`~.control.ControllerVersions`.

**The resync pole re-optimisation against a live plant** (``offload``) runs off
the sample thread (:mod:`kautztwin.twin.optimization.poles`): at the resync the
virtual step test is frozen, a ``'pole-retune'`` event logs the submission,
the worker (thread or process, as the updater's re-identification) fits the
candidate while the loop runs on the current version, and the first update
that finds it finished judges it with the updater's rules, on the validation
window frozen at the resync, as a background re-identification is judged (a
``'model-update'`` / ``'model-rejected'`` event "pole re-optimisation: ...",
``k_submitted`` the resync; a rejection then tries the consolidation, as the
synchronous path does at once).  One job at a time: a resync meanwhile is
logged and skipped; a new version (a re-identification) makes the job stale
("discarded").  A resumed run replays the same decisions: the candidate is a
pure function of the frozen step test, computed synchronously in the replay
and judged at the sample the stored event names (at the first live sample when
the run was killed before the judgement).  Offline runs keep the synchronous
call (their numbers are unchanged).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from ...approx.model import KautzModel
from ...exceptions import KautzTwinError
from ..digital import DigitalModel
from ..optimization import ControllerTuning, EstimatorRetraining
from ..optimization.background import OptimizationJob, OptimizationWorker
from ..optimization.poles import (
    PendingPoles,
    PoleWorker,
    judge_pole_candidate,
    pole_candidate,
    pole_job,
)
from ..prediction import MPCController
from ..update import ModelUpdate, Updater, UpdateResult
from .config import TwinConfig
from .control import ControllerVersions
from .protocols import TwinOptimizer
from .record import RunRecord

__all__ = ["ModelVersions"]


class ModelVersions:
    """The model versions of a run, and the optimisation of each.

    Parameters
    ----------
    config : TwinConfig
        The run.
    optimizer : TwinOptimizer
        The optimization module.
    record : RunRecord
        Where events, versions and tunings are recorded.
    controller : MPCController
        The running controller.
    on_estimator : callable
        Called with an accepted retrained estimator (the twin runs it from then on).

    Attributes
    ----------
    version : int
        The running version (0 before the identification).
    updater : Updater or None
        The update module (from :meth:`first` on).
    control : ControllerVersions
        The controller switch.
    worker : OptimizationWorker
        The background optimisation worker.
    """

    def __init__(
        self, config: TwinConfig, optimizer: TwinOptimizer, record: RunRecord,
        controller: MPCController, *, on_estimator: Callable[[Any], None],
    ) -> None:
        self.config = config
        self.optimizer = optimizer
        self.record = record
        self.version = 0
        self.updater: Updater | None = None
        self.control = ControllerVersions(controller, record, config, config.n_ident)
        self.worker = OptimizationWorker(
            optimizer, event=record.event, install=self.control.install,
            apply_tuning=self.control.apply_tuning, apply_retraining=self.apply_retraining,
            context=self.control.context, kind=str(config.updater.get("worker", "thread")),
        )
        self._on_estimator = on_estimator
        self.poles: PoleWorker | None = None  # the worker of the live pole re-optimisation
        self._pending_poles: PendingPoles | None = None
        self._stored_poles: dict[int, int] | None = None  # replay: resync k -> judged at

    # ------------------------------------------------------------------ the first version
    def first(self, updater: Updater, k: int, t: float, *, u_op: float, offload: bool,
              y_op: float | None = None, tuning: ControllerTuning | None = None) -> None:
        """The identified version: store it and build the first controller on it.

        Parameters
        ----------
        updater : Updater
            The update module, just built on the identified model.
        k, t : int, float
            The first closed-loop sample.
        u_op : float
            The command in force (where a weight retuning starts).
        offload : bool
            Later versions are optimised in the background worker (the first
            controller is tuned before the closed loop starts: here, or given).
        y_op : float, optional
            The output the tuning starts from (sample ``k``'s when omitted).
        tuning : ControllerTuning, optional
            The first controller's tuning, made already at ``(u_op, y_op)`` (a
            live plant's twin built in the background, see
            :mod:`kautztwin.twin.runtime.birth`); tuned here when omitted.
        """
        cfg = self.config
        rec = self.record
        self.updater = updater
        if offload and self._pole_async(updater, k, True) and self.poles is None:
            self.poles = PoleWorker(updater.worker)
            if updater.worker == "process":
                self.poles.prestart()  # its interpreter starts while the twin runs
        dm = updater.digital_model
        self.version = dm.version
        rec.store_version(dm, k, t, updater.offset)
        if cfg.controlled:
            # tuned before the first closed-loop sample, live runs too: their loop stalls
            # for the identification anyway, with the plant parked at the excitation's
            # centre, and an untuned first controller (the configured weights) would run
            # the closed loop's first seconds while a worker tuned it
            self._retune_controller(k, t, u_op, initial=True, y_op=y_op, tuning=tuning)
            rec.event("phase", k, t, "closed loop: MPC tracking with twin updates", {})
        else:
            rec.event("phase", k, t, "monitoring: the twin follows the recorded plant", {})

    # ------------------------------------------------------------------ after each update
    def after_update(
        self, r: UpdateResult, k: int, t: float, *, u_op: float, offload: bool
    ) -> None:
        """Log the update's events; a resync asks the optimizer, a new version is optimised.

        Parameters
        ----------
        r : UpdateResult
            The update of sample ``k``.
        k, t : int, float
            The sample.
        u_op : float
            The command in force (where a weight retuning starts).
        offload : bool
            Optimise a new version in the background worker.
        """
        upd = self.updater
        assert upd is not None
        if r.model_update is not None:
            self._log_model_update(r.model_update, k, t)
        resync = False
        for ev in r.events:
            self.record.event(ev.kind, k, t, ev.message, ev.payload())
            resync |= ev.kind == "resync"
        if self._pending_poles is not None:
            self._poll_poles(k, t, offload)
        if resync and self.config.retune and k >= self.config.n_ident:
            if self._pending_poles is not None:
                self.record.event("pole-retune", k, t, "resync while a pole re-optimisation "
                                  f"(resync at sample {self._pending_poles.job.k}) runs: "
                                  "skipped", {"k_submitted": self._pending_poles.job.k})
            elif self._pole_async(upd, k, offload):
                self._submit_poles(upd, k, t, offload)
            else:
                mu = self.optimizer.retune_model(upd)
                if mu is not None:
                    self._log_model_update(mu, k, t, kind="pole re-optimisation")
                if (mu is None or not mu.accepted) and upd.digital_model.version == self.version:
                    self._consolidate(k, t)
        dm = upd.digital_model
        if dm.version != self.version:
            self._new_version(dm, k, t, u_op, offload)

    # ------------------------------------------------------------------ live pole re-optimisation
    def prestart_poles(self, kind: str) -> None:
        """Start the process worker of the live pole re-optimisation now (a thread: at first use).

        A child process takes seconds to start and import on a loaded host; started with
        the run, it is ready by the first resync of the closed loop.
        """
        if self.poles is None and kind == "process" and getattr(
                self.optimizer, "retune_poles", False):
            self.poles = PoleWorker(kind)
            self.poles.prestart()

    def resumed(self) -> None:
        """A resumed run: read back where the stored run judged its live pole re-optimisations."""
        rec = self.record
        self._stored_poles = {}
        if rec.run_id is None:
            return
        for ev in rec.history.events(rec.run_id):
            p = ev.payload or {}
            if ev.kind == "pole-retune" and "submitted" in p:
                self._stored_poles.setdefault(int(p["k_submitted"]), -1)
            elif (ev.kind in ("model-update", "model-rejected") and ev.k is not None
                  and ev.message.startswith("pole re-optimisation")
                  and p.get("k_submitted") is not None):
                self._stored_poles[int(p["k_submitted"])] = int(ev.k)

    def _pole_async(self, upd: Updater, k: int, offload: bool) -> bool:
        """Whether the resync at ``k`` runs its pole re-optimisation in the worker (or replays one).

        Live runs (``offload``) without a DNN estimator and with an optimizer whose
        pole re-optimisation is on; a replay exactly where the stored run did.
        """
        if upd.dnn is not None or not getattr(self.optimizer, "retune_poles", False):
            return False
        if offload:
            return hasattr(self.optimizer, "max_step_samples")
        return self._stored_poles is not None and k in self._stored_poles

    def _submit_poles(self, upd: Updater, k: int, t: float, offload: bool) -> None:
        """Freeze the step test and start its candidate (in a replay: compute it now)."""
        job = pole_job(self.optimizer, upd, k)
        assert job is not None
        self.record.event("pole-retune", k, t, f"pole re-optimisation of version "
                          f"{job.version} submitted to the worker",
                          {"k_submitted": k, "version": job.version, "submitted": True})
        if offload:
            if self.poles is None:
                self.poles = PoleWorker(upd.worker)
            self._pending_poles = self.poles.submit(job)
            return
        assert self._stored_poles is not None
        at = self._stored_poles.get(k, -1)
        self._pending_poles = PendingPoles(job, outcome=pole_candidate(job),
                                           judge_at=None if at < 0 else at)

    def _poll_poles(self, k: int, t: float, offload: bool) -> None:
        """Judge the pending candidate once it is there (a replay: at the stored sample)."""
        p = self._pending_poles
        upd = self.updater
        assert p is not None and upd is not None
        if upd.digital_model.version != p.job.version:
            self._pending_poles = None
            self.record.event("model-rejected", k, t, "pole re-optimisation: discarded: "
                              f"version {upd.digital_model.version} superseded version "
                              f"{p.job.version}", {"k_submitted": p.job.k, "discarded": True})
            return
        if p.future is None:  # computed in a replay
            if not (p.judge_at is not None and k >= p.judge_at
                    or p.judge_at is None and offload):
                return
        elif self.poles is None or not self.poles.done(p):
            return
        out = p.outcome if p.future is None or self.poles is None else self.poles.outcome(p)
        assert out is not None
        self._pending_poles = None
        mu = judge_pole_candidate(upd, p.job, out)
        if mu is not None:
            payload = {key: val for key, val in mu.payload().items() if key != "model"}
            payload["worker_s"] = out.elapsed
            self.record.event("model-update" if mu.accepted else "model-rejected", k, t,
                              f"pole re-optimisation: {mu.reason}", payload)
        else:
            self.record.event("model-rejected", k, t, "pole re-optimisation: no candidate "
                              f"({out.error or 'the fit failed'})",
                              {"k_submitted": p.job.k, "worker_s": out.elapsed})
        if (mu is None or not mu.accepted) and upd.digital_model.version == self.version:
            self._consolidate(k, t)

    def close(self) -> None:
        """Stop the optimisation workers (the pending pole re-optimisation is dropped)."""
        self._pending_poles = None
        if self.poles is not None:
            self.poles.close()
        self.worker.close()

    def _consolidate(self, k: int, t: float) -> None:
        """A new version from the fast path if it predicts recent data clearly better."""
        upd = self.updater
        assert upd is not None
        a = self.record.arrays
        current = upd.digital_model.model
        offset = self.record.version_offset.get(self.version, upd.offset)
        better, f_live, f_cur = self.optimizer.consolidate(
            upd, current, offset, a["u"][: k + 1], a["y_clean"][: k + 1]
        )
        payload = {"fit_live": f_live, "fit_current": f_cur}
        if better:
            upd.snapshot("rls-consolidation")
            self.record.event("model-update", k, t,
                              f"consolidated the fast path: fit {f_live:.2f} % vs the "
                              f"current version's {f_cur:.2f} %", payload)
        else:
            self.record.event("model-rejected", k, t,
                              f"kept the current version: fast path {f_live:.2f} % vs "
                              f"{f_cur:.2f} %", payload)

    def _new_version(
        self, dm: DigitalModel, k: int, t: float, u_op: float, offload: bool
    ) -> None:
        """Store a new model version; retrain the estimator and retune the controller on it."""
        cfg = self.config
        upd = self.updater
        assert upd is not None
        self.version = dm.version
        self.record.store_version(dm, k, t, upd.offset)
        if offload:
            self._offload(dm, k, t, u_op)
            return
        if cfg.retune and upd.dnn is not None:
            self._retrain_estimator(dm, k, t)
        if cfg.controlled and cfg.retune:
            self._retune_controller(k, t, u_op)
        elif cfg.controlled:
            self.control.rebuild_or_keep(
                dm.model, self.control.controller.settings or cfg.mpc, k, t,
                {"k": int(k), "t": float(t), "version": dm.version},
            )

    def _log_model_update(self, mu: ModelUpdate, k: int, t: float, kind: str = "") -> None:
        what = kind or mu.kind
        payload = {key: val for key, val in mu.payload().items() if key != "model"}
        self.record.event("model-update" if mu.accepted else "model-rejected", k, t,
                          f"{what}: {mu.reason}", payload)

    # ------------------------------------------------------------------ estimator
    def _retrain_estimator(self, dm: DigitalModel, k: int, t: float) -> None:
        """Fine-tune the DNN around the new version; keep the old one unless the new one wins."""
        upd = self.updater
        assert upd is not None
        try:
            rt: EstimatorRetraining | KautzTwinError = self.optimizer.retrain_estimator(
                upd.dnn, dm.model)
        except KautzTwinError as exc:  # e.g. the estimator has another number of functions
            rt = exc
        self.apply_retraining(rt, dm.version, k, t)

    def apply_retraining(
        self, rt: EstimatorRetraining | KautzTwinError, version: int, k: int, t: float,
        extra: Mapping[str, Any] | None = None,
    ) -> None:
        """Log a retraining (or why there is none) and run on an accepted candidate."""
        upd = self.updater
        assert upd is not None
        if isinstance(rt, KautzTwinError):
            self.record.event("estimator-rejected", k, t, f"estimator not retrained: {rt}",
                              {**(extra or {})})
            return
        self.record.event("estimator-update" if rt.accepted else "estimator-rejected", k, t,
                          f"estimator retraining for version {version}: {rt.reason}",
                          {**rt.payload(), **(extra or {})})
        if rt.accepted:
            upd.dnn = rt.estimator
            self._on_estimator(rt.estimator)

    # ------------------------------------------------------------------ controller
    def _tuning_point(self, k: int, u_op: float) -> tuple[KautzModel, int, float, float]:
        """``(model, version, u_op, y_op)``: where the weight retuning of sample ``k`` starts."""
        upd = self.updater
        assert upd is not None
        y_clean = self.record.arrays["y_clean"]
        y_op = float(y_clean[k]) if math.isfinite(y_clean[k]) else (
            float(upd.estimator_.predict()))
        return upd.digital_model.model, upd.digital_model.version, u_op, y_op

    def _retune_controller(
        self, k: int, t: float, u_op: float, *, initial: bool = False, y_op: float | None = None,
        tuning: ControllerTuning | None = None,
    ) -> None:
        cfg = self.config
        assert self.updater is not None and cfg.mpc is not None
        model, version, u_op, y_k = self._tuning_point(k, u_op)
        if tuning is None:
            tuning = self.optimizer.tune_controller(
                model, cfg.mpc, step=cfg.tuning_step(), u_op=u_op,
                y_op=y_k if y_op is None else y_op,
            )
        self.control.apply_tuning(tuning, model, version, k, t, initial=initial)

    def _offload(self, dm: DigitalModel, k: int, t: float, u_op: float) -> None:
        """Queue the optimisation of a new version for the worker; it supersedes older ones."""
        cfg = self.config
        assert self.updater is not None
        self.worker.supersede(f"version {dm.version} superseded it", k, t)
        estimator = self.updater.dnn
        if not cfg.controlled and estimator is None:
            return
        model, version, u_op, y_op = self._tuning_point(k, u_op)
        self.worker.queue(OptimizationJob(version, k, t, model, u_op, y_op,
                                          cfg.controlled, estimator), k)
