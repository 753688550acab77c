r"""Synchronisation metrics of a fleet: the sample sanitiser and the sync monitor as arrays.

:class:`FleetSanitizer` is :class:`~kautztwin.twin.SampleSanitizer`
(``outlier_action='clip'``, level shifts, no timestamps) for every asset at
once, and :class:`FleetMonitor` is :class:`~kautztwin.twin.SyncMonitor` (the
rolling fit percent of the twin's prediction and the ``'desync'`` /
``'resync'`` logic) for every asset at once; both give the flags, fits and
events that the scalar classes give on the same samples (``tests/test_fleet.py``
compares them).

The sanitiser's rolling median and MAD cost a partition of the window per
asset and sample; a cheap exact screen skips them: with ``s >= min_scale``
and the median inside ``[min(window), max(window)]``, a value within
``threshold * min_scale`` of both window extremes cannot be an outlier.
Only the assets that fail the screen get the median and MAD.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..physical.sanitize import SampleFlag

__all__ = ["FleetMonitor", "FleetSanitizer", "fit_percent_rows"]

_MAD_TO_SIGMA = 1.482602218505602  # as in SampleSanitizer


def fit_percent_rows(y: NDArray, y_hat: NDArray) -> NDArray[np.float64]:
    """Fit percent of each row (all samples finite), NaN for a constant row.

    The row-wise form of :func:`kautztwin.metrics.fit_percent_or_nan` for
    complete windows.

    Parameters
    ----------
    y, y_hat : ndarray of shape (n_rows, n_samples)

    Returns
    -------
    ndarray of shape (n_rows,)
    """
    spread = np.linalg.norm(y - y.mean(axis=1, keepdims=True), axis=1)
    err = np.linalg.norm(y - y_hat, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 100.0 * (1.0 - err / spread)
    return np.where(spread == 0.0, np.nan, out)


class FleetSanitizer:
    """Outlier and dropout flags of every asset's sample (the fleet's SampleSanitizer).

    Parameters
    ----------
    n_assets : int
    threshold, window, min_samples, min_scale, max_consecutive
        As :class:`~kautztwin.twin.SampleSanitizer` (``outlier_action='clip'``).
    """

    def __init__(
        self, n_assets: int, *, threshold: float, window: int, min_samples: int = 15,
        min_scale: float = 0.0, max_consecutive: int | None = 5,
    ) -> None:
        self.threshold = float(threshold)
        self.window = int(window)
        self.min_samples = int(min_samples)
        self.min_scale = float(min_scale)
        self.max_consecutive = max_consecutive
        self.buf = np.zeros((n_assets, self.window))
        self.count = np.zeros(n_assets, dtype=np.int64)
        self.pos = np.zeros(n_assets, dtype=np.int64)
        self.runs: dict[int, tuple[int, list[float]]] = {}
        self.counts = dict.fromkeys(("dropout", "outlier", "clipped", "level_shift"), 0)

    def _append(self, rows: NDArray[np.intp], x: NDArray) -> None:
        self.buf[rows, self.pos[rows]] = x
        self.pos[rows] = (self.pos[rows] + 1) % self.window
        self.count[rows] = np.minimum(self.count[rows] + 1, self.window)

    def process(self, y: NDArray) -> NDArray[np.int64]:
        """Flags of one sample of every asset (the windows advance).

        Parameters
        ----------
        y : ndarray of shape (n_assets,)

        Returns
        -------
        ndarray of int of shape (n_assets,)
            :class:`~kautztwin.twin.SampleFlag` bits.
        """
        n = y.size
        flags = np.zeros(n, dtype=np.int64)
        finite = np.isfinite(y)
        flags[~finite] = int(SampleFlag.DROPOUT | SampleFlag.HELD)
        self.counts["dropout"] += int((~finite).sum())
        judged = finite & (self.count >= self.min_samples)
        suspect = np.zeros(n, dtype=bool)
        if judged.any():
            if (self.count >= self.window).all():
                lo, hi = self.buf.min(axis=1), self.buf.max(axis=1)
            else:  # windows still filling (the first samples of a run)
                held = np.arange(self.window)[None, :] < self.count[:, None]
                lo = np.where(held, self.buf, np.inf).min(axis=1)
                hi = np.where(held, self.buf, -np.inf).max(axis=1)
            bound = self.threshold * self.min_scale
            safe = (np.abs(y - lo) <= bound) & (np.abs(y - hi) <= bound) if bound > 0 else (
                np.zeros(n, dtype=bool))
            suspect = judged & ~safe
        plain = finite & ~suspect
        self._clear_runs(np.flatnonzero(plain))
        self._append(np.flatnonzero(plain), y[plain])
        for i in np.flatnonzero(suspect):
            flags[i] = self._exact(int(i), float(y[i]))
        return flags

    def _clear_runs(self, rows: NDArray[np.intp]) -> None:
        if self.runs:
            for i in rows.tolist():
                self.runs.pop(i, None)

    def _exact(self, i: int, x: float) -> int:
        """One sample of asset ``i`` through the scalar rules (median, MAD, level shift)."""
        w = self.buf[i, : self.count[i]] if self.count[i] < self.window else self.buf[i]
        med = float(np.median(w))
        scale = max(_MAD_TO_SIGMA * float(np.median(np.abs(w - med))), self.min_scale)
        dev = x - med
        if scale > 0 and abs(dev) > self.threshold * scale:
            sign = 1 if dev > 0 else -1
            run_sign, run = self.runs.get(i, (0, []))
            if sign != run_sign:
                run = []
            run.append(x)
            self.runs[i] = (sign, run)
            if self.max_consecutive is None or len(run) < self.max_consecutive:
                self.counts["outlier"] += 1
                self.counts["clipped"] += 1
                return int(SampleFlag.OUTLIER | SampleFlag.CLIPPED)
            self.counts["level_shift"] += 1
            self.runs.pop(i, None)
            vals = run[-self.window:]
            self.buf[i] = 0.0
            self.buf[i, : len(vals)] = vals
            self.count[i] = len(vals)
            self.pos[i] = len(vals) % self.window
            return 0
        self.runs.pop(i, None)
        self._append(np.array([i]), np.array([x]))
        return 0

    @property
    def nbytes(self) -> int:
        """Bytes held in the arrays."""
        return int(self.buf.nbytes + self.count.nbytes + self.pos.nbytes)


class FleetMonitor:
    """Rolling fit and desync/resync detection of every asset (the fleet's SyncMonitor).

    Parameters
    ----------
    n_assets : int
    window, stride, threshold, n_consecutive, resync_margin
        As :class:`~kautztwin.twin.SyncMonitor`.

    Attributes
    ----------
    fit : ndarray of shape (n_assets,)
        Latest window fit (NaN before the first).
    in_sync : ndarray of bool
    n_bad : ndarray of int
    """

    def __init__(
        self, n_assets: int, *, window: int, stride: int, threshold: float, n_consecutive: int,
        resync_margin: float = 0.0,
    ) -> None:
        self.window, self.stride = int(window), int(stride)
        self.threshold, self.n_consecutive = float(threshold), int(n_consecutive)
        self.resync_margin = float(resync_margin)
        self.y = np.zeros((n_assets, self.window))
        self.yp = np.zeros((n_assets, self.window))
        self.count = np.zeros(n_assets, dtype=np.int64)
        self.since = np.zeros(n_assets, dtype=np.int64)
        self.pos = np.zeros(n_assets, dtype=np.int64)
        self.fit = np.full(n_assets, math.nan)
        self.in_sync = np.ones(n_assets, dtype=bool)
        self.n_bad = np.zeros(n_assets, dtype=np.int64)

    def clear_window(self, i: int) -> None:
        """Empty asset ``i``'s window (after a model change); fits and state stay."""
        self.count[i] = 0
        self.since[i] = 0
        self.pos[i] = 0
        self.n_bad[i] = 0

    def update(
        self, y: NDArray, y_pred: NDArray, valid: NDArray[np.bool_],
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
        """Add one pair per asset (where ``valid``); the assets with a new fit and events.

        Parameters
        ----------
        y, y_pred : ndarray of shape (n_assets,)
        valid : ndarray of bool of shape (n_assets,)
            Pairs to add (the monitor ignores non-finite ones too).

        Returns
        -------
        evaluated : ndarray of int
            Assets whose window fit was computed at this sample.
        desync, resync : ndarray of int
            Assets with a ``'desync'`` / ``'resync'`` event.
        fits : ndarray
            The fits of ``evaluated``.
        """
        ok = valid & np.isfinite(y) & np.isfinite(y_pred)
        rows = np.flatnonzero(ok)
        p = self.pos[rows]
        self.y[rows, p] = y[rows]
        self.yp[rows, p] = y_pred[rows]
        self.pos[rows] = (p + 1) % self.window
        self.count[rows] = np.minimum(self.count[rows] + 1, self.window)
        self.since[rows] += 1
        due = rows[(self.count[rows] >= self.window) & (self.since[rows] >= self.stride)]
        empty = np.zeros(0, dtype=np.intp)
        if due.size == 0:
            return empty, empty, empty, np.zeros(0)
        self.since[due] = 0
        fits = fit_percent_rows(self.y[due], self.yp[due])
        good_fit = np.isfinite(fits)
        due, fits = due[good_fit], fits[good_fit]
        self.fit[due] = fits
        bad = fits < self.threshold
        b = due[bad]
        self.n_bad[b] += 1
        fire = b[self.n_bad[b] % self.n_consecutive == 0]
        self.in_sync[fire] = False
        g = due[~bad]
        self.n_bad[g] = 0
        back = g[~self.in_sync[g]]
        back = back[self.fit[back] >= self.threshold + self.resync_margin]  # the hysteresis
        self.in_sync[back] = True
        return due, fire, back, fits

    @property
    def nbytes(self) -> int:
        """Bytes held in the arrays."""
        return int(sum(a.nbytes for a in (self.y, self.yp, self.count, self.since, self.pos,
                                          self.fit, self.in_sync, self.n_bad)))
