"""Pacing of a plant: real time (optionally sped up) or as fast as possible (simulated time)."""

from __future__ import annotations

import math
import time

from ..._validation import check_positive
from ...exceptions import DataError

__all__ = ["Clock"]


class Clock:
    """Paces a plant in real time, or lets it run as fast as possible.

    With ``realtime=True`` :meth:`wait_until` sleeps until the wall-clock time
    (``time.monotonic``) of a plant time has come, ``speedup`` plant seconds per
    wall-clock second; with ``realtime=False`` the time is simulated and
    nothing waits.

    Parameters
    ----------
    realtime : bool, default=False
        Pace in real time (``True``) or run as fast as possible.
    speedup : float, default=1.0
        Plant seconds per wall-clock second in real-time mode (``> 0``).
    tolerance : float, default=inf
        A target reached more than this many plant seconds late counts as a
        late tick (:attr:`n_late`).

    Raises
    ------
    DataError
        If ``speedup`` is not positive or ``tolerance`` is negative.

    Attributes
    ----------
    n_late : int
        Targets that were already more than ``tolerance`` in the past.
    max_lateness : float
        Largest lateness seen, plant seconds.

    Examples
    --------
    >>> from kautztwin.twin.physical import Clock
    >>> clock = Clock()          # simulated time: never sleeps
    >>> clock.start()
    >>> clock.wait_until(10.0), clock.now()
    (0.0, 10.0)
    """

    def __init__(
        self, realtime: bool = False, *, speedup: float = 1.0, tolerance: float = math.inf
    ) -> None:
        speedup = check_positive(speedup, "speedup")
        tolerance = float(tolerance)
        if math.isnan(tolerance) or tolerance < 0:
            raise DataError(f"tolerance must be >= 0 s, got {tolerance}")
        self.realtime = bool(realtime)
        self.speedup = speedup
        self.tolerance = tolerance
        self.start()

    @classmethod
    def real_time(cls, speedup: float = 1.0, *, tolerance: float = math.inf) -> Clock:
        """A real-time clock (``speedup`` plant seconds per wall-clock second).

        Parameters
        ----------
        speedup : float, default=1.0
            Plant seconds per wall-clock second.
        tolerance : float, default=inf
            Lateness that counts as a late tick, plant seconds.

        Returns
        -------
        Clock
        """
        return cls(True, speedup=speedup, tolerance=tolerance)

    def start(self) -> None:
        """Set plant time 0 to now and clear the lateness counters."""
        self._origin = time.monotonic()
        self._t = 0.0
        self.n_late = 0
        self.max_lateness = 0.0

    def now(self) -> float:
        """Plant time since :meth:`start`, s (simulated: the last target)."""
        if self.realtime:
            return (time.monotonic() - self._origin) * self.speedup
        return self._t

    def wait_until(self, t: float) -> float:
        """Wait until plant time ``t`` (real time) or jump to it (simulated).

        Parameters
        ----------
        t : float
            Target plant time, s since :meth:`start`.

        Returns
        -------
        float
            How late the target was reached, plant seconds (0 when on time or simulated).
        """
        self._t = float(t)
        if not self.realtime:
            return 0.0
        delay = self._origin + self._t / self.speedup - time.monotonic()
        if delay > 0:
            time.sleep(delay)
            return 0.0
        late = -delay * self.speedup
        self.max_lateness = max(self.max_lateness, late)
        if late > self.tolerance:
            self.n_late += 1
        return late

    def __repr__(self) -> str:
        mode = f"real time x{self.speedup:g}" if self.realtime else "as fast as possible"
        return f"Clock({mode})"
