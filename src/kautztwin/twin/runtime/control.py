"""Which controller the loop runs: rebuilt on validated model versions and tunings, else kept.

:class:`ControllerVersions` applies the outcome of a weight retuning (or a
new model version without one) to the running
:class:`~kautztwin.twin.prediction.MPCController`: it rebuilds the
controller on the new version with the validated weights, keeps the
running controller when the QP of a new version cannot be set up, and
remembers the last validated ``(model, settings)`` so that background mode
can return to it after an interim controller.  The controllers are built
here from the command histories of the run record, or installed from the
ones the background worker prepared.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ...approx.model import KautzModel
from ...exceptions import DataError
from ..optimization import ControllerTuning
from ..optimization.background import TuningContext, _Prepared, prepared_for
from ..prediction import MPCController, MPCSettings
from ..prediction.controller import _PreparedController
from .config import TwinConfig
from .record import RunRecord

__all__ = ["ControllerVersions"]


class ControllerVersions:
    """The controller's life cycle over the model versions of a run.

    Parameters
    ----------
    controller : MPCController
        The running controller.
    record : RunRecord
        The run's arrays (command histories), events and tunings.
    config : TwinConfig
        The run.
    k_closed_loop : int
        First sample of the closed loop.

    Attributes
    ----------
    validated : (KautzModel, MPCSettings) or None
        The last controller that was built on a validated version and tuning.
    """

    def __init__(
        self, controller: MPCController, record: RunRecord, config: TwinConfig,
        k_closed_loop: int,
    ) -> None:
        self.controller = controller
        self.record = record
        self.config = config
        self.k_closed_loop = k_closed_loop
        self.validated: tuple[KautzModel, MPCSettings] | None = None

    # ------------------------------------------------------------------ histories
    def history_length(self, k: int) -> int:
        """Samples of the command history that the controller state covers at sample ``k``."""
        a = self.record.arrays
        if k >= self.k_closed_loop and a["command"][k] == a["command"][k]:  # command is in
            return k + 1
        return k

    def rebuild(self, model: KautzModel, settings: MPCSettings, k: int) -> None:
        """Build the controller; the histories end with the sample being processed."""
        a = self.record.arrays
        n = self.history_length(k)
        self.controller.rebuild(model, settings, a["command"][:n], a["dither"][:n])

    def install(self, prepared: _PreparedController, k: int) -> None:
        """Run on a controller the worker prepared, advanced to sample ``k``."""
        a = self.record.arrays
        n = self.history_length(k)
        self.controller._install(prepared, a["command"][prepared.n:n], a["dither"][prepared.n:n])

    def context(self, k: int) -> TuningContext:
        """What the background worker reads for a retuning at sample ``k`` (copies only)."""
        cfg = self.config
        assert cfg.mpc is not None
        a = self.record.arrays
        n = self.history_length(k)
        return TuningContext(
            cfg.mpc, self.controller.settings or cfg.mpc, cfg.tuning_step(),
            self.controller.input_offset, self.validated, a["command"][:n].copy(),
            a["dither"][:n].copy(),
        )

    # ------------------------------------------------------------------ tunings
    def apply_tuning(
        self, tuning: ControllerTuning, model: KautzModel, version: int, k: int, t: float, *,
        initial: bool, prepared: Sequence[_Prepared] | None = None,
        extra: Mapping[str, Any] | None = None,
    ) -> None:
        """Rebuild the controller on a validated tuning, or keep the running one.

        ``prepared`` (background mode): the controllers the worker built for
        the outcome; without it the controller is built here.
        """
        rec = {"k": int(k), "t": float(t), "version": version, **tuning.payload(),
               **(extra or {})}
        self.record.tunings.append(rec)
        if tuning.accepted or initial or self.controller.problem is None:
            settings = tuning.settings if tuning.accepted else (
                self.controller.settings or self.config.mpc)
            if not self.rebuild_or_keep(model, settings, k, t, rec, prepared):
                self._restore_validated(k, prepared)
                return
            self.record.event("controller", k, t,
                              f"MPC rebuilt on version {version}: {tuning.reason}", rec)
        else:
            self._restore_validated(k, prepared)
            self.record.event("controller-rejected", k, t,
                              f"kept the controller: {tuning.reason}", rec)

    def rebuild_or_keep(
        self, model: KautzModel, settings: MPCSettings, k: int, t: float, rec: dict[str, Any],
        prepared: Sequence[_Prepared] | None = None,
    ) -> bool:
        """Rebuild on a new version; keep the running controller if its QP cannot be set up.

        A model version that passed validation can still give a QP that the
        solver refuses (e.g. DAQP's setup on a nearly input-independent
        output row); the loop must not stop for it.  Only the first build
        (no controller yet) raises.
        """
        if self.controller.problem is None:
            self._build(model, settings, k, prepared)
            self.validated = (model, settings)
            return True
        try:
            self._build(model, settings, k, prepared)
        except DataError as exc:
            self.record.event("controller-rejected", k, t,
                              f"kept the controller: the MPC on version {rec.get('version')} "
                              f"cannot be set up ({exc})", rec)
            return False
        self.validated = (model, settings)
        return True

    def _build(
        self, model: KautzModel, settings: MPCSettings, k: int,
        prepared: Sequence[_Prepared] | None,
    ) -> None:
        """Run the controller on ``(model, settings)``: built here, or prepared by the worker."""
        if prepared is not None:
            ctl = self.controller
            if ctl.model is model and ctl.settings == settings:
                return  # the interim controller of this version already runs it
            p = prepared_for(prepared, model, settings)
            if isinstance(p, DataError):
                raise p
            if p is not None:
                self.install(p, k)
                return
        self.rebuild(model, settings, k)

    def _restore_validated(self, k: int, prepared: Sequence[_Prepared] | None) -> None:
        """Background mode: back to the last validated controller after the interim one.

        Synchronously the running controller is always the validated one.
        """
        if prepared is None or self.validated is None:
            return
        model, settings = self.validated
        try:
            self._build(model, settings, k, prepared)
        except DataError:  # pragma: no cover - it was built before
            pass
