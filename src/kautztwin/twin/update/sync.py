r"""Synchronisation metric of the twin: the rolling fit of its prediction and desync detection.

:class:`SyncMonitor` computes the fit percent of the twin's predicted output
against the measured one over a rolling window and turns a run of bad windows
into ``'desync'`` :class:`SyncEvent` objects (the trigger of the update
module's accurate path) and the recovery into ``'resync'``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._validation import check_int, check_nonnegative, check_number, to_float_or_nan
from ...metrics import fit_percent_or_nan

__all__ = ["FitHistory", "SyncEvent", "SyncMonitor"]


def _finite_or_nan(value: Any) -> float:
    """``value`` as a finite float, NaN for anything else (garbage, inf); never raises."""
    out = to_float_or_nan(value)
    return out if math.isfinite(out) else math.nan


@dataclass(frozen=True)
class SyncEvent:
    """A synchronisation event of :class:`SyncMonitor`.

    Parameters
    ----------
    kind : {'desync', 'resync'}
        ``'desync'``: the rolling fit stayed below the threshold for
        ``n_consecutive`` windows (a re-identification trigger; repeated every
        further ``n_consecutive`` bad windows).  ``'resync'``: the fit is back
        above the threshold (plus the monitor's ``resync_margin``).
    k : int or None
        Sample index that completed the window.
    t : float or None
        Its time.
    fit : float
        Rolling fit of that window, percent.
    n_bad : int
        Consecutive windows below the threshold (0 for ``'resync'``).
    message : str
        Human-readable text.
    """

    kind: str
    k: int | None
    t: float | None
    fit: float
    n_bad: int
    message: str

    def payload(self) -> dict[str, Any]:
        """JSON-ready dictionary of the event.

        Returns
        -------
        dict
        """
        return {"kind": self.kind, "k": self.k, "t": self.t, "fit": self.fit, "n_bad": self.n_bad}


@dataclass(frozen=True, eq=False)
class FitHistory:
    """Rolling fits computed by :class:`SyncMonitor`.

    Parameters
    ----------
    k : ndarray of int, shape (n_windows,)
        Sample index that completed each window (-1 when unknown).
    t : ndarray of shape (n_windows,)
        Its time (NaN when unknown).
    fit : ndarray of shape (n_windows,)
        Fit percent of each window.
    """

    k: NDArray[np.int64]
    t: NDArray[np.float64]
    fit: NDArray[np.float64]


class SyncMonitor:
    r"""Rolling fit of the twin's prediction and desynchronisation detection.

    Every ``stride`` valid samples, once ``window`` valid samples have been
    seen, the fit percent of the last ``window`` pairs is computed,

    .. math:: \mathrm{fit} = 100\Big(1 - \frac{\|y - \hat y\|}{\|y - \bar y\|}\Big),

    (a window with a constant ``y`` has no defined fit and is skipped).  A fit
    below ``threshold`` for ``n_consecutive`` windows in a row emits a
    ``'desync'`` :class:`SyncEvent` (the trigger for re-identification); it is
    emitted again after every further ``n_consecutive`` bad windows while the
    fit stays low, and a ``'resync'`` event follows the first window whose fit
    reaches ``threshold + resync_margin``.  With a margin this is a
    hysteresis: a window between the two ends a run of bad windows but not the
    desynchronisation, so a twin that has only just climbed back over the
    threshold stays desynchronised, and its recovery goes on, until its fit is
    clearly good again.

    Parameters
    ----------
    window : int, default=100
        Samples per rolling window (``>= 3``).
    stride : int, optional
        Samples between evaluations; ``window // 4`` when omitted.
    threshold : float, default=95.0
        Fit percent below which a window is bad.
    n_consecutive : int, default=3
        Bad windows in a row that make a desynchronisation.
    resync_margin : float, default=0.0
        Fit points above ``threshold`` that a desynchronised twin's window must
        reach to resynchronise (``>= 0``).

    Raises
    ------
    DataError
        If a parameter is out of range.

    Attributes
    ----------
    fit : float
        The latest window fit (NaN before the first).
    in_sync : bool
        False between a ``'desync'`` and the next ``'resync'``.
    n_bad : int
        Current run of consecutive bad windows.

    See Also
    --------
    Updater : Feeds the monitor and acts on its events.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.update import SyncMonitor
    >>> mon = SyncMonitor(window=20, stride=10, threshold=90.0, n_consecutive=2)
    >>> y = np.sin(np.arange(100) / 3.0)
    >>> y_pred = y + np.where(np.arange(100) > 50, 0.5, 0.0)  # the twin drifts off at k = 51
    >>> events = [e for k in range(100) for e in mon.update(y[k], y_pred[k], k=k)]
    >>> [(e.kind, e.k) for e in events]
    [('desync', 69), ('desync', 89)]
    """

    def __init__(
        self,
        *,
        window: int = 100,
        stride: int | None = None,
        threshold: float = 95.0,
        n_consecutive: int = 3,
        resync_margin: float = 0.0,
    ) -> None:
        window = check_int(window, "window", 3)
        stride = max(1, window // 4) if stride is None else check_int(stride, "stride", 1)
        threshold = check_number(threshold, "threshold")
        self.window = window
        self.stride = stride
        self.threshold = threshold
        self.n_consecutive = check_int(n_consecutive, "n_consecutive", 1)
        self.resync_margin = check_nonnegative(resync_margin, "resync_margin")
        self.reset()

    def clear_window(self) -> None:
        """Empty the rolling window (after a model change) but keep the fits and the state.

        The next fit is computed once ``window`` new samples have arrived, so it
        judges the new model only; the run of bad windows restarts at 0.
        """
        self._y.clear()
        self._yp.clear()
        self._since = 0
        self.n_bad = 0

    def reset(self) -> None:
        """Forget the window, the fits and the state (back in sync)."""
        self._y: deque[float] = deque(maxlen=self.window)
        self._yp: deque[float] = deque(maxlen=self.window)
        self._since = 0
        self._k: list[int] = []
        self._t: list[float] = []
        self._fits: list[float] = []
        self.fit = math.nan
        self.in_sync = True
        self.n_bad = 0

    def update(
        self, y: float, y_pred: float, *, k: int | None = None, t: float | None = None
    ) -> tuple[SyncEvent, ...]:
        """Add one measured/predicted pair; NaN pairs are ignored.

        Parameters
        ----------
        y : float
            Measured output.
        y_pred : float
            The twin's prediction of it.
        k : int, optional
            Sample index (reported in events).
        t : float, optional
            Sample time (reported in events).

        Returns
        -------
        tuple of SyncEvent
            Events raised by this sample (usually none).
        """
        yf, pf = _finite_or_nan(y), _finite_or_nan(y_pred)
        if math.isnan(yf) or math.isnan(pf):
            return ()
        self._y.append(yf)
        self._yp.append(pf)
        self._since += 1
        if len(self._y) < self.window or self._since < self.stride:
            return ()
        self._since = 0
        fit = fit_percent_or_nan(
            np.asarray(self._y, dtype=float), np.asarray(self._yp, dtype=float)
        )
        if math.isnan(fit):
            return ()
        self.fit = fit
        self._k.append(-1 if k is None else int(k))
        self._t.append(math.nan if t is None else float(t))
        self._fits.append(fit)
        if fit < self.threshold:
            self.n_bad += 1
            if self.n_bad % self.n_consecutive == 0:
                first = self.in_sync
                self.in_sync = False
                what = "desynchronised" if first else "still desynchronised"
                return (
                    SyncEvent(
                        "desync", k, t, fit, self.n_bad,
                        f"twin {what}: fit {fit:.2f} % < {self.threshold:g} % for "
                        f"{self.n_bad} windows",
                    ),
                )
            return ()
        self.n_bad = 0
        if not self.in_sync and fit >= self.threshold + self.resync_margin:
            self.in_sync = True
            return (
                SyncEvent("resync", k, t, fit, 0, f"twin resynchronised: fit {fit:.2f} %"),
            )
        return ()

    @property
    def n_fits(self) -> int:
        """Number of window fits computed so far."""
        return len(self._fits)

    @property
    def history(self) -> FitHistory:
        """All window fits so far.

        Returns
        -------
        FitHistory
        """
        return FitHistory(
            np.asarray(self._k, dtype=np.int64), np.asarray(self._t, dtype=float),
            np.asarray(self._fits, dtype=float),
        )

    def __repr__(self) -> str:
        return (
            f"SyncMonitor(window={self.window}, stride={self.stride}, threshold={self.threshold:g},"
            f" n_consecutive={self.n_consecutive}, resync_margin={self.resync_margin:g},"
            f" fit={self.fit:.2f})"
        )

