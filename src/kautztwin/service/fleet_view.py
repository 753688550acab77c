"""What the fleet service's HTTP API sees: the latest fleet step and a job queue.

:class:`FleetView` holds the latest step of every asset (references to the arrays the
fleet made for it, no copies) and the queue of jobs (set-points) that the service's loop
runs between two steps, so nothing of the fleet is touched by two threads at once.  It is
the single twin's :class:`~kautztwin.service.twin_view.TwinView` (job queue, event
buffer, loop timing) fed by a fleet step instead of a twin sample.  Used by
:mod:`.fleet_service` (which feeds it) and :mod:`.fleet_api` (which reads it).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .twin_view import TwinView, _num

__all__ = ["FleetView"]


class FleetView(TwinView):
    """Thread-safe window on a running :class:`FleetService` for the HTTP API.

    Parameters
    ----------
    service : FleetService
        The service whose loop feeds the view.
    event_capacity : int, default=500
        Events kept for the live buffer.

    Attributes
    ----------
    seq : int
        Steps seen so far.
    running : bool
        Whether the loop is stepping the fleet.
    """

    def __init__(self, service: Any, *, event_capacity: int = 500) -> None:
        super().__init__(service, capacity=1, event_capacity=event_capacity)
        self._step: dict[str, Any] = {}

    def after_step(self, fleet: Any) -> None:
        """Record the step the fleet just made and run the queued jobs (the loop's thread).

        Parameters
        ----------
        fleet : Fleet
        """
        now = time.perf_counter()
        last = dict(fleet.last)
        upd = fleet.updater
        mon = None if upd is None else upd.monitor
        n = fleet.n_assets
        closed = last["k"] >= fleet.k_closed_loop
        last.update(
            fit=np.full(n, math.nan) if mon is None else mon.fit.copy(),
            in_sync=np.ones(n, dtype=bool) if mon is None else mon.in_sync.copy(),
            setpoint=fleet.setpoints(last["t"]) if closed else np.full(n, math.nan),
            phase="closed-loop" if closed else "identification")
        with self._lock:
            if self._last_sample is not None:
                self._intervals.append(now - self._last_sample)
            self._last_sample = now
            self.seq += 1
            self._step = last
        self.running = True
        self.run_jobs()

    def step(self) -> dict[str, Any]:
        """The latest step: ``k, t, y, u, command, y_pred, flags, reference, version, fit,
        in_sync, setpoint`` (arrays over the assets) and ``phase`` (empty before the first).

        Returns
        -------
        dict
        """
        with self._lock:
            return dict(self._step)

    def asset(self, i: int) -> dict[str, Any]:
        """The latest sample of asset ``i`` as JSON-ready numbers (empty before the first).

        Parameters
        ----------
        i : int

        Returns
        -------
        dict
        """
        st = self.step()
        if not st:
            return {}
        out: dict[str, Any] = {"k": int(st["k"]), "t": _num(st["t"]), "phase": st["phase"]}
        for key in ("y", "u", "command", "y_pred", "reference", "setpoint", "fit"):
            out[key] = _num(st[key][i])
        out.update(version=int(st["version"][i]), flags=int(st["flags"][i]),
                   in_sync=bool(st["in_sync"][i]))
        return out

    def loop_timing(self) -> dict[str, Any]:
        """How regularly the loop steps the fleet (``/health``'s ``loop``).

        Returns
        -------
        dict
            As :meth:`TwinView.loop_timing`, with the fleet's clock.
        """
        with self._lock:
            iv = np.array(self._intervals) * 1e3
        out: dict[str, Any] = {"samples": int(iv.size)}
        if iv.size:
            p50, p99 = np.percentile(iv, [50, 99])
            out.update(interval_ms_p50=round(float(p50), 3), interval_ms_p99=round(float(p99), 3),
                       interval_ms_max=round(float(iv.max()), 3))
        clock = getattr(self.service, "clock", None)
        fleet = getattr(self.service, "fleet", None)
        if clock is not None and fleet is not None:
            out.update(period_ms=round(fleet.config.dt / clock.speedup * 1e3, 3),
                       late=int(clock.n_late),
                       behind_ms_max=round(clock.max_lateness / clock.speedup * 1e3, 3))
        return out
