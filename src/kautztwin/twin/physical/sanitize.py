"""Sample sanitising of the plant signal: dropouts, outliers and late samples.

A live sensor stream is messy: values go missing (NaN, ``None``, garbage),
spike, or arrive out of order.  :class:`SampleSanitizer` turns each raw sample
into a usable value plus a :class:`SampleFlag` bitmask, never raises on bad
samples, and counts what it saw so the run report can show it.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from enum import IntFlag
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_choice, check_int, check_nonnegative, to_float_or_nan
from ...exceptions import DataError

__all__ = ["SampleFlag", "SampleSanitizer", "SanitizedSample"]

_MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4): MAD of a normal sample -> sigma


def _median_sorted(values: list[float]) -> float:
    """Median of sorted ``values`` (as ``numpy.median``: the mean of the middle two when even)."""
    n = len(values)
    mid = n // 2
    return values[mid] if n % 2 else (values[mid - 1] + values[mid]) / 2.0
_OUTLIER_ACTIONS = ("clip", "skip")


class SampleFlag(IntFlag):
    """Bitmask of what happened to a sample; stored as ``flags`` in the history.

    Attributes
    ----------
    NONE : 0
        A clean sample, used as is.
    DROPOUT : 1
        The value was missing: NaN, inf, ``None`` or not a number.
    OUTLIER : 2
        The value lay more than ``threshold`` robust standard deviations from
        the rolling median.
    LATE : 4
        The timestamp was bad: not increasing (out of order or duplicate), not
        finite, or (with :attr:`GAP`) after a gap longer than the tolerance.
    CLIPPED : 8
        The value was replaced by the nearest outlier bound.
    HELD : 16
        The value was replaced by the last good value (the sample was skipped).
    GAP : 32
        The time since the previous sample exceeded ``max_gap`` (set with
        :attr:`LATE`; the value itself is used).
    """

    NONE = 0
    DROPOUT = 1
    OUTLIER = 2
    LATE = 4
    CLIPPED = 8
    HELD = 16
    GAP = 32


@dataclass(frozen=True)
class SanitizedSample:
    """One sample after :meth:`SampleSanitizer.process`.

    Parameters
    ----------
    value : float
        The value to use: the raw value, a clipped value, or the last good
        value (``fill_value`` before any good value was seen).
    flags : SampleFlag
        What happened to the sample.
    raw : float
        The raw value as a float (NaN when it was not a number).

    See Also
    --------
    SampleSanitizer : Produces these.
    """

    value: float
    flags: SampleFlag
    raw: float

    @property
    def skipped(self) -> bool:
        """Whether the raw sample was discarded (``value`` is a held value).

        A skipped sample should not be used to update or re-identify the model.
        """
        return bool(self.flags & SampleFlag.HELD)


class SampleSanitizer:
    r"""Flag, clean and count dropouts, outliers and late samples of one channel.

    The sanitizer is stateful (last good value, last timestamp, a rolling
    window and counters) and never raises on a bad sample.  Each call to
    :meth:`process` handles one sample in this order:

    1. **Late** (only when a timestamp is given): a timestamp that is not
       finite or not greater than the last accepted one marks the sample
       ``LATE | HELD``; it is skipped and the last good value is returned.  A
       timestamp more than ``max_gap`` after the last one is flagged
       ``LATE | GAP`` and the sample is processed normally.
    2. **Dropout**: a value that is not a finite number (NaN, inf, ``None``, a
       string, an array of several elements...) is flagged ``DROPOUT | HELD``
       and the last good value is returned.
    3. **Outlier**: once the window holds ``min_samples`` good values, a value
       with robust score :math:`|x - m| / s > \text{threshold}` is an outlier,
       where :math:`m` is the window median and
       :math:`s = \max(1.4826\,\mathrm{MAD}, \text{min\_scale})`.  With
       ``outlier_action='clip'`` it is replaced by :math:`m \pm
       \text{threshold}\cdot s` (``OUTLIER | CLIPPED``); with ``'skip'`` by
       the last good value (``OUTLIER | HELD``).  Outliers do not enter the
       window.  When :math:`s = 0` (a constant window and ``min_scale=0``)
       there is no spread to judge against and no sample is flagged.

    A genuine level shift would otherwise be clipped forever; so the
    ``max_consecutive``-th outlier in a row on the same side of the median is
    accepted as a level shift: the window restarts from that run of values
    and the sample is used unflagged (counted as ``level_shift``).

    Parameters
    ----------
    threshold : float, default=5.0
        Outlier threshold in robust standard deviations.
    window : int, default=50
        Number of recent good values in the rolling window (>= 3).
    min_samples : int, default=15
        Good values needed in the window before outliers are detected (>= 3,
        <= ``window``).
    outlier_action : {'clip', 'skip'}, default='clip'
        Replace an outlier by the nearest bound or by the last good value.
    min_scale : float, default=0.0
        Lower bound of the robust scale :math:`s`; set it to the sensor
        resolution for quantised sensors, whose MAD is often 0.
    max_gap : float or None, default=None
        Largest accepted time between consecutive samples, in the units of
        the timestamps; ``None`` disables the gap check.
    max_consecutive : int or None, default=5
        Consecutive same-side outliers that count as a level shift; ``None``
        disables level-shift detection.
    fill_value : float, default=nan
        Value returned for a skipped sample before any good value was seen.

    Raises
    ------
    DataError
        If a parameter is out of range.

    Attributes
    ----------
    counts : dict of str to int
        See :attr:`counts`.

    See Also
    --------
    SampleFlag : The flag bits.
    kautztwin.twin.HistoryStore.append_measurements : Stores the flags with each sample.

    Notes
    -----
    The robust score is the Hampel identifier: median and median absolute
    deviation (MAD) of a rolling window, with

    .. math::

        s = 1.4826\,\operatorname{median}_i |x_i - m|,

    which equals the standard deviation for normal data.

    References
    ----------
    .. [1] F. R. Hampel, "The influence curve and its role in robust
       estimation", J. Amer. Statist. Assoc. 69 (1974), 383-393.

    Examples
    --------
    >>> from kautztwin.twin import SampleFlag, SampleSanitizer
    >>> s = SampleSanitizer(min_samples=5, min_scale=0.1)
    >>> for k, v in enumerate([1.0, 1.1, 0.9, 1.0, 1.05, 0.95]):
    ...     _ = s.process(v, t=k)
    >>> out = s.process(float("nan"), t=6)
    >>> out.value, out.flags == SampleFlag.DROPOUT | SampleFlag.HELD
    (0.95, True)
    >>> out = s.process(1e6, t=7)
    >>> bool(out.flags & SampleFlag.CLIPPED), round(out.value, 3)
    (True, 1.5)
    >>> s.process(1.0, t=7).flags == SampleFlag.LATE | SampleFlag.HELD
    True
    >>> s.counts["dropout"], s.counts["outlier"], s.counts["late"]
    (1, 1, 1)
    """

    def __init__(
        self,
        *,
        threshold: float = 5.0,
        window: int = 50,
        min_samples: int = 15,
        outlier_action: str = "clip",
        min_scale: float = 0.0,
        max_gap: float | None = None,
        max_consecutive: int | None = 5,
        fill_value: float = math.nan,
    ) -> None:
        threshold = float(threshold)
        if not math.isfinite(threshold) or threshold <= 0:
            raise DataError(f"threshold must be a positive number, got {threshold}")
        window = check_int(window, "window", 3)
        min_samples = check_int(min_samples, "min_samples", 3)
        if min_samples > window:
            raise DataError(f"min_samples must be <= window = {window}, got {min_samples}")
        check_choice(outlier_action, "outlier_action", _OUTLIER_ACTIONS)
        min_scale = check_nonnegative(min_scale, "min_scale")
        if max_gap is not None:
            max_gap = float(max_gap)
            if not math.isfinite(max_gap) or max_gap <= 0:
                raise DataError(f"max_gap must be a positive number or None, got {max_gap}")
        if max_consecutive is not None:
            try:
                max_consecutive = check_int(max_consecutive, "max_consecutive", 1)
            except DataError:  # worded "an integer >= 1", not "a positive integer"
                raise DataError(
                    f"max_consecutive must be an integer >= 1, got {max_consecutive!r}"
                ) from None
        self.threshold = threshold
        self.window = window
        self.min_samples = min_samples
        self.outlier_action = outlier_action
        self.min_scale = min_scale
        self.max_gap = max_gap
        self.max_consecutive = max_consecutive
        self.fill_value = float(fill_value)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the window, the last value and timestamp, and zero the counters."""
        self._window: deque[float] = deque(maxlen=self.window)
        self._sorted: list[float] = []  # the window's values in order (median without a sort)
        self._last_good = self.fill_value
        self._last_t: float | None = None
        self._run: list[float] = []
        self._run_sign = 0
        self._counts = dict.fromkeys(
            ("total", "ok", "dropout", "outlier", "clipped", "held", "late", "gap", "level_shift"),
            0,
        )

    @property
    def counts(self) -> dict[str, int]:
        """Counters since construction or :meth:`reset` (a copy).

        Keys: ``total`` (samples processed), ``ok`` (used unflagged),
        ``dropout``, ``outlier``, ``clipped``, ``held`` (skipped samples),
        ``late`` (every ``LATE`` sample, gaps included), ``gap`` and
        ``level_shift``.
        """
        return dict(self._counts)

    @property
    def last_value(self) -> float:
        """The last good value (``fill_value`` before the first one)."""
        return self._last_good

    @property
    def last_time(self) -> float | None:
        """The last accepted timestamp, or ``None``."""
        return self._last_t

    # ------------------------------------------------------------------ processing
    def process(self, value: Any, t: Any = None) -> SanitizedSample:
        """Sanitise one sample; never raises on a bad value or timestamp.

        Parameters
        ----------
        value : Any
            The raw sample; anything that is not a finite real scalar is a dropout.
        t : Any, default=None
            Its timestamp; ``None`` skips the time checks.

        Returns
        -------
        SanitizedSample
            The value to use, its flags and the raw value.
        """
        c = self._counts
        c["total"] += 1
        x = to_float_or_nan(value)
        flags = SampleFlag.NONE
        if t is not None:
            tf = to_float_or_nan(t)
            if not math.isfinite(tf) or (self._last_t is not None and tf <= self._last_t):
                c["late"] += 1
                return self._hold(SampleFlag.LATE, x)
            if self._last_t is not None and self.max_gap is not None:
                if tf - self._last_t > self.max_gap:
                    flags |= SampleFlag.LATE | SampleFlag.GAP
                    c["late"] += 1
                    c["gap"] += 1
            self._last_t = tf
        if not math.isfinite(x):
            c["dropout"] += 1
            return self._hold(flags | SampleFlag.DROPOUT, x)
        if len(self._window) >= self.min_samples:
            med = _median_sorted(self._sorted)
            mad = _median_sorted(sorted([abs(v - med) for v in self._sorted]))
            scale = max(_MAD_TO_SIGMA * mad, self.min_scale)
            dev = x - med
            if scale > 0 and abs(dev) > self.threshold * scale:
                sign = 1 if dev > 0 else -1
                if sign != self._run_sign:
                    self._run, self._run_sign = [], sign
                self._run.append(x)
                if self.max_consecutive is None or len(self._run) < self.max_consecutive:
                    c["outlier"] += 1
                    flags |= SampleFlag.OUTLIER
                    if self.outlier_action == "skip":
                        return self._hold(flags, x)
                    c["clipped"] += 1
                    bound = med + sign * self.threshold * scale
                    return SanitizedSample(bound, flags | SampleFlag.CLIPPED, x)
                # a run of same-side outliers: the level has shifted
                c["level_shift"] += 1
                self._window.clear()
                self._window.extend(self._run)
                self._sorted = sorted(self._window)
                self._run, self._run_sign = [], 0
                self._last_good = x
                if not flags:
                    c["ok"] += 1
                return SanitizedSample(x, flags, x)
        self._run, self._run_sign = [], 0
        if len(self._window) == self._window.maxlen:
            del self._sorted[bisect.bisect_left(self._sorted, self._window[0])]
        self._window.append(x)
        bisect.insort(self._sorted, x)
        self._last_good = x
        if not flags:
            c["ok"] += 1
        return SanitizedSample(x, flags, x)

    def process_many(
        self, values: ArrayLike, t: ArrayLike | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Sanitise a sequence of samples in order (for replay and tests).

        Parameters
        ----------
        values : array-like of shape (n_samples,)
            Raw samples; elements may be anything :meth:`process` accepts.
        t : array-like of shape (n_samples,) or None, default=None
            Timestamps, or ``None`` for no time checks.

        Returns
        -------
        values : ndarray of shape (n_samples,)
            The values to use.
        flags : ndarray of int64, shape (n_samples,)
            The :class:`SampleFlag` bitmasks.

        Raises
        ------
        DataError
            If ``t`` is given with a different length than ``values``.
        """
        vals = list(values) if not isinstance(values, np.ndarray) else list(values.ravel())
        times = [None] * len(vals) if t is None else list(np.asarray(t, dtype=object).ravel())
        if len(times) != len(vals):
            raise DataError(f"t has {len(times)} samples but values has {len(vals)}")
        out = np.empty(len(vals))
        flags = np.empty(len(vals), dtype=np.int64)
        for i, (v, ti) in enumerate(zip(vals, times, strict=True)):
            s = self.process(v, ti)
            out[i], flags[i] = s.value, int(s.flags)
        return out, flags

    def _hold(self, flags: SampleFlag, raw: float) -> SanitizedSample:
        self._counts["held"] += 1
        return SanitizedSample(self._last_good, flags | SampleFlag.HELD, raw)

    def __repr__(self) -> str:
        return (
            f"SampleSanitizer(threshold={self.threshold}, window={self.window}, "
            f"outlier_action={self.outlier_action!r}, counts={self._counts})"
        )
