"""What follows each update: log its events, ask the optimizer, optimise new model versions.

:class:`ModelVersions` follows the model versions of a run.  After each
update it logs the update's events; a ``'resync'`` asks the optimizer to
re-optimise the poles or, failing that, to consolidate the fast path into
a new version; every new version is stored, and its estimator retraining
and controller retuning run synchronously or are queued for the
background worker (:class:`~kautztwin.twin.optimization.background.OptimizationWorker`).
The controller switch itself is :class:`~.control.ControllerVersions`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from ...approx.model import KautzModel
from ...exceptions import KautzTwinError
from ..digital import DigitalModel
from ..optimization import EstimatorRetraining
from ..optimization.background import OptimizationJob, OptimizationWorker
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
            context=self.control.context,
        )
        self._on_estimator = on_estimator

    # ------------------------------------------------------------------ the first version
    def first(self, updater: Updater, k: int, t: float, *, u_op: float, offload: bool) -> None:
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
            Tune in the background worker.
        """
        cfg = self.config
        rec = self.record
        self.updater = updater
        dm = updater.digital_model
        self.version = dm.version
        rec.store_version(dm, k, t, updater.offset)
        if cfg.controlled and offload:
            # the first controller runs on the configured weights until the tuning ends
            assert cfg.mpc is not None
            self.control.rebuild(dm.model, cfg.mpc, k)
            self._offload(dm, k, t, u_op, initial=True)
            rec.event("phase", k, t, "closed loop: MPC tracking with twin updates", {})
        elif cfg.controlled:
            self._retune_controller(k, t, u_op, initial=True)
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
        if resync and self.config.retune and k >= self.config.n_ident:
            mu = self.optimizer.retune_model(upd)
            if mu is not None:
                self._log_model_update(mu, k, t, kind="pole re-optimisation")
            if (mu is None or not mu.accepted) and upd.digital_model.version == self.version:
                self._consolidate(k, t)
        dm = upd.digital_model
        if dm.version != self.version:
            self._new_version(dm, k, t, u_op, offload)

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

    def _retune_controller(self, k: int, t: float, u_op: float, *, initial: bool = False) -> None:
        cfg = self.config
        assert self.updater is not None and cfg.mpc is not None
        model, version, u_op, y_op = self._tuning_point(k, u_op)
        tuning = self.optimizer.tune_controller(
            model, cfg.mpc, step=cfg.tuning_step(), u_op=u_op, y_op=y_op
        )
        self.control.apply_tuning(tuning, model, version, k, t, initial=initial)

    def _offload(
        self, dm: DigitalModel, k: int, t: float, u_op: float, *, initial: bool = False
    ) -> None:
        """Queue the optimisation of a new version for the worker; it supersedes older ones."""
        cfg = self.config
        assert self.updater is not None
        self.worker.supersede(f"version {dm.version} superseded it", k, t)
        estimator = None if initial else self.updater.dnn
        if not cfg.controlled and estimator is None:
            return
        model, version, u_op, y_op = self._tuning_point(k, u_op)
        self.worker.queue(OptimizationJob(version, k, t, model, initial, u_op, y_op,
                                          cfg.controlled, estimator), k)
