r"""Judging a candidate model: held-out validation against the live model, the acceptance rule.

Every candidate of the update module - a re-identification (synchronous or
from the background worker), a step test, a DNN estimate, the runtime's pole
re-optimisation - is judged the same way: the candidate and the live fast-path
model predict the held-out samples at the end of a data window, and the
candidate wins only if

* its fit percent beats the live model's by more than ``min_improvement``
  (or the live model's fit is not finite), and
* it reaches ``min_candidate_fit`` (when that floor is set).

:func:`candidate_verdict` is that rule with its reason; :class:`CandidateJudging`
(a base class of :class:`~kautztwin.twin.update.Updater`) computes the fits,
records the :class:`~kautztwin.twin.update.ModelUpdate` and hands a winner to
the updater's ``_adopt``; its public :meth:`~CandidateJudging.judge_candidate`
is the entry for candidates built outside the updater.
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_int
from ...approx.model import KautzModel
from ...exceptions import DataError
from ...ident.kautz_oe import filter_states
from ...metrics import fit_percent_or_nan
from ..digital import DigitalModel
from .records import ModelUpdate
from .recursive import RecursiveKautzEstimator

__all__ = ["CandidateJudging", "candidate_verdict"]


def candidate_verdict(
    fit_candidate: float,
    fit_current: float,
    n_val: int,
    *,
    min_improvement: float,
    min_candidate_fit: float | None,
) -> tuple[bool, str]:
    """The acceptance rule of the update module: does a candidate replace the current model?

    Parameters
    ----------
    fit_candidate : float
        Fit percent of the candidate on the held-out samples (NaN: not computable).
    fit_current : float
        Fit percent of the current (live) model on the same samples.
    n_val : int
        Number of held-out samples (for the reason).
    min_improvement : float
        Fit percent by which the candidate must beat the current model.
    min_candidate_fit : float or None
        Floor of the candidate's fit percent; ``None``: no floor.

    Returns
    -------
    accepted : bool
        Whether the candidate wins.
    reason : str
        Why, in the words logged with the :class:`~kautztwin.twin.update.ModelUpdate`.

    Examples
    --------
    >>> from kautztwin.twin.update.judging import candidate_verdict
    >>> candidate_verdict(95.0, 80.0, 60, min_improvement=0.0, min_candidate_fit=50.0)
    (True, 'candidate fit 95.00 % beats the current 80.00 % on 60 held-out samples')
    >>> candidate_verdict(45.0, 20.0, 60, min_improvement=0.0, min_candidate_fit=50.0)[0]
    False
    """
    fit_c, fit_m = fit_candidate, fit_current
    better = math.isfinite(fit_c) and (
        not math.isfinite(fit_m) or fit_c > fit_m + min_improvement
    )
    if not better:
        return False, (
            f"candidate fit {fit_c:.2f} % does not beat the current {fit_m:.2f} % "
            f"on {n_val} held-out samples"
        )
    floor = min_candidate_fit
    if floor is not None and not fit_c >= floor:
        return False, (
            f"candidate fit {fit_c:.2f} % on {n_val} held-out samples is below "
            f"min_candidate_fit = {floor:g} % (the current model has {fit_m:.2f} %)"
        )
    return True, (
        f"candidate fit {fit_c:.2f} % beats the current {fit_m:.2f} % on {n_val} held-out "
        "samples"
    )


class CandidateJudging:
    """Base class of :class:`~kautztwin.twin.update.Updater`: judges candidates, records attempts.

    Not used on its own.  What it reads from the updater is declared below
    (set by ``Updater.__init__``); a winner is handed to the updater's
    ``_adopt`` (a new model version, the fast path restarted from it), every
    outcome is logged through its ``_log``.
    """

    # set by Updater.__init__
    estimator_: RecursiveKautzEstimator
    input_offset: float
    min_improvement: float
    min_candidate_fit: float | None
    model_updates: list[ModelUpdate]
    _k: int
    _u: deque[float]
    _counts: dict[str, int]

    def count_attempt(self) -> None:
        """Count one update attempt that was made outside the updater.

        The updater counts its own attempts (``counts['attempts']``); a
        caller that builds a candidate itself (the runtime's pole
        re-optimisation) counts each of its attempts here, also one whose
        fit failed and that never reaches :meth:`judge_candidate`.
        """
        self._counts["attempts"] += 1

    def judge_candidate(
        self,
        model: KautzModel,
        offset: float,
        u: ArrayLike,
        y: ArrayLike,
        n_val: int,
        *,
        kind: str,
        k_window: int | None = None,
        k_submitted: int | None = None,
        start: float | None = None,
        from_live: bool = False,
    ) -> ModelUpdate:
        """Judge a candidate built elsewhere with the updater's rules, and adopt it when it wins.

        The candidate and the live fast-path model predict the last ``n_val``
        samples of ``u, y`` (the filters run from the first sample of ``u``:
        samples before the held-out ones settle them); the candidate replaces
        the current model if it beats it by more than ``min_improvement`` and
        reaches ``min_candidate_fit`` (:func:`candidate_verdict`).  A winner
        becomes a new :class:`~kautztwin.twin.DigitalModel` version and the
        fast path continues from it, exactly as after an accepted
        re-identification.  The attempt is recorded in ``model_updates`` and
        logged either way; it is not counted (see :meth:`count_attempt`).

        Parameters
        ----------
        model : KautzModel
            The candidate on the twin's delayed discrete basis (period ``dt``;
            see :func:`~kautztwin.twin.update.discretize_model`).
        offset : float
            Its output offset.
        u, y : array-like of shape (n_samples,)
            Inputs and outputs of the validation window (NaN outputs are left
            out of the fits), usually a window of :meth:`recent_samples`.
        n_val : int
            Held-out samples at the end of ``u, y``.
        kind : {'reidentification', 'dnn-update', 'step-test'}
            What produced the candidate (the provenance of an accepted version).
        k_window : int, optional
            The updater's sample counter (:attr:`k`) when the window ended,
            for a window taken from the buffer at an earlier sample: an
            accepted candidate then starts from its filter state over the
            input from the window's first sample up to now.  Omitted: the
            window ends now (or is not from the buffer) and the candidate
            starts from its state at the end of ``u``.
        k_submitted : int, optional
            Sample at which the attempt's data were frozen, for the record
            (:attr:`ModelUpdate.k_submitted`); the current sample when omitted.
        start : float, optional
            :func:`time.perf_counter` value at which the attempt started,
            for :attr:`ModelUpdate.elapsed`; now when omitted.
        from_live : bool, default=False
            Whether the candidate re-expresses the live model (a pole
            re-optimisation of its step response): a winner's version is the
            candidate, but the fast path continues from the live model
            projected onto the candidate's basis, not from the candidate's
            coefficients (which fit the step response, not the one-step
            predictions).

        Returns
        -------
        ModelUpdate
            Accepted or not, with both validation fits.

        Raises
        ------
        DataError
            If ``u`` and ``y`` are not 1-D of one length or ``n_val`` is not
            between 1 and that length.
        """
        if start is None:
            start = time.perf_counter()
        uu = np.asarray(u, dtype=float)
        yy = np.asarray(y, dtype=float)
        if uu.ndim != 1 or uu.shape != yy.shape:
            raise DataError(
                f"u and y must be 1-D of one length, got shapes {uu.shape} and {yy.shape}"
            )
        n_val = check_int(n_val, "n_val", 1)
        if n_val > uu.size:
            raise DataError(f"n_val must be at most len(u) = {uu.size}, got {n_val}")
        u_now = None if k_window is None else self._inputs_since(uu.size, k_window)
        return self._judge(kind, start, model, offset, uu, yy, n_val, u_now=u_now,
                           k_submitted=k_submitted, from_live=from_live)

    def _inputs_since(self, n_window: int, k_window: int) -> NDArray | None:
        """The input from the first sample of a window that ended at ``k_window`` up to now.

        ``n_window`` samples long when it ended; ``None`` when no sample has
        arrived since.  Starts later when the buffer no longer holds the
        window's first sample.
        """
        if self._k <= k_window:
            return None
        n_now = min(n_window + (self._k - k_window), len(self._u))
        return np.asarray(self._u, dtype=float)[len(self._u) - n_now:]

    def _validate(
        self, model: KautzModel, offset: float, u: NDArray, y: NDArray, n_val: int
    ) -> tuple[float, float, NDArray]:
        """Fits of a candidate and of the live model on the last ``n_val`` samples of ``u, y``."""
        v = u - self.input_offset
        Xc = filter_states(model.basis, v)
        yc = Xc[:-1] @ model.coefficients + offset
        ym = self.estimator_.simulate(u)
        sl = slice(u.size - n_val, u.size)
        return fit_percent_or_nan(y[sl], yc[sl]), fit_percent_or_nan(y[sl], ym[sl]), Xc[-1]

    def _judge(
        self, kind: str, start: float, model: KautzModel, offset: float, u: NDArray,
        y: NDArray, n_val: int, *, u_now: NDArray | None = None, k_submitted: int | None = None,
        band: tuple[float, float] = (math.nan, math.nan), from_live: bool = False,
    ) -> ModelUpdate:
        """Validate a candidate on the last ``n_val`` samples of ``u, y`` and maybe adopt it.

        ``u_now``: the input from the first sample of ``u`` (or a later one,
        when the buffer no longer holds it) up to now, when samples arrived
        after the window (a background attempt); an accepted candidate
        starts from its filter state at the end of ``u_now``.  ``from_live``:
        see :meth:`judge_candidate`.
        """
        fit_c, fit_m, state = self._validate(model, offset, u, y, n_val)
        accepted, reason = candidate_verdict(
            fit_c, fit_m, n_val, min_improvement=self.min_improvement,
            min_candidate_fit=self.min_candidate_fit,
        )
        dm = (self._adopt(kind, model, offset, fit_c, u, state, u_now, from_live)
              if accepted else None)
        return self._finish(kind, start, accepted, reason, model, offset, fit_c, fit_m, dm,
                            k_submitted=k_submitted, band=band)

    def _finish(
        self, kind: str, start: float, accepted: bool, reason: str, model: KautzModel | None,
        offset: float, fit_c: float, fit_m: float, dm: DigitalModel | None,
        *, k_submitted: int | None = None, band: tuple[float, float] = (math.nan, math.nan),
    ) -> ModelUpdate:
        """Record and log the outcome of an attempt."""
        mu = ModelUpdate(
            kind, self._k, accepted, reason, model, offset, fit_c, fit_m, dm,
            time.perf_counter() - start, k_submitted, *band,
        )
        self.model_updates.append(mu)
        self._log(
            "model-update" if accepted else "model-rejected", reason, self._k, None, mu.payload()
        )
        return mu
