"""Records of the update module: an update attempt (ModelUpdate), a sample (UpdateResult).

:class:`~kautztwin.twin.update.Updater` returns an :class:`UpdateResult` from
every :meth:`~kautztwin.twin.update.Updater.step` and a :class:`ModelUpdate`
from every accurate-path, step-test or pole re-optimisation attempt (logged in
the history store as :meth:`ModelUpdate.payload`).  Both are re-exported by
:mod:`kautztwin.twin.update`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ...approx.model import KautzModel
from ..digital import DigitalModel
from .sync import SyncEvent

__all__ = ["ModelUpdate", "UpdateResult"]


@dataclass(frozen=True, eq=False)
class ModelUpdate:
    """Outcome of one accurate-path or step-test update attempt of :class:`Updater`.

    Parameters
    ----------
    kind : {'reidentification', 'dnn-update', 'step-test'}
        What produced the candidate.
    k : int
        Sample index (the updater's next sample) at which it was decided.
    accepted : bool
        Whether the candidate replaced the current model.
    reason : str
        Why it was accepted or rejected.
    candidate : KautzModel or None
        The candidate model (delayed discrete basis), ``None`` if none was built.
    offset : float
        The candidate's output offset.
    fit_candidate : float
        Fit percent of the candidate on the held-out validation samples.
    fit_current : float
        Fit percent of the current model on the same samples.
    digital_model : DigitalModel or None
        The new version when accepted.
    elapsed : float
        Seconds of computation the attempt took (in a background attempt:
        the worker's fit plus the validation in :meth:`Updater.step`).
    k_submitted : int or None, default=None
        Sample index at which the attempt's data window ended; ``k`` for a
        synchronous attempt, earlier for a background one (which is judged
        at ``k``, when its result was ready).  ``None`` means ``k``.
    relative_width : float, default=nan
        Uncertainty of a DNN candidate: the RMS half-width of its confidence
        band over the RMS of its response
        (:attr:`~kautztwin.nn.ResponseEstimate.relative_width`, the level in
        ``confidence``); NaN when the candidate came without one (an
        estimator without ``estimate``, pole optimisation, re-identification).
    confidence : float, default=nan
        Level of the band of ``relative_width`` (0.9 for the estimators' default).
    """

    kind: str
    k: int
    accepted: bool
    reason: str
    candidate: KautzModel | None
    offset: float
    fit_candidate: float
    fit_current: float
    digital_model: DigitalModel | None
    elapsed: float
    k_submitted: int | None = None
    relative_width: float = math.nan
    confidence: float = math.nan

    def __post_init__(self) -> None:
        if self.k_submitted is None:
            object.__setattr__(self, "k_submitted", self.k)

    def payload(self) -> dict[str, Any]:
        """JSON-ready summary (for the history store).

        Returns
        -------
        dict
        """
        return {
            "kind": self.kind, "k": self.k, "k_submitted": self.k_submitted,
            "accepted": self.accepted, "reason": self.reason,
            "offset": self.offset, "fit_candidate": _json_float(self.fit_candidate),
            "fit_current": _json_float(self.fit_current), "elapsed": self.elapsed,
            "version": None if self.digital_model is None else self.digital_model.version,
            "model": None if self.candidate is None else self.candidate.to_dict(),
            "relative_width": _json_float(self.relative_width),
            "confidence": _json_float(self.confidence),
        }


def _json_float(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """What :meth:`Updater.step` did with one sample.

    Parameters
    ----------
    k : int
        Sample index.
    t : float or None
        Sample time, if given.
    y_pred : float
        A-priori prediction of this sample with the current parameters.
    y_pred_frozen : float
        Prediction with the parameters frozen at the start of the current
        prediction horizon (what the monitor judges).
    y : float
        The measured value used, NaN when the sample was skipped.
    flags : int
        :class:`~kautztwin.twin.SampleFlag` bits of the output sample.
    input_held : bool
        Whether the input was missing and the last one was held.
    fit : float
        Latest rolling fit of the monitor, percent (NaN before the first window).
    events : tuple of SyncEvent
        Monitor events raised by this sample.
    model_update : ModelUpdate or None
        An accurate-path attempt decided at this sample (in background mode:
        one submitted earlier whose result was judged now).
    version : int
        Version of the digital model after this sample.
    elapsed : float
        Wall-clock seconds spent in :meth:`Updater.step`.
    """

    k: int
    t: float | None
    y_pred: float
    y_pred_frozen: float
    y: float
    flags: int
    input_held: bool
    fit: float
    events: tuple[SyncEvent, ...]
    model_update: ModelUpdate | None
    version: int
    elapsed: float
