"""A fleet of twins as a long-running service: the batched Fleet on the wall clock, one HTTP API.

:class:`FleetService` (``kautztwin fleet serve``) builds a simulated fleet
(:func:`~kautztwin.twin.fleet.simulate.hydraulic_fleet`), steps its batched
:class:`~kautztwin.twin.fleet.Fleet` every ``dt / speed`` wall-clock seconds
(the runtime's real-time :class:`~kautztwin.twin.physical.Clock`) until it is
asked to stop, its wall-clock duration ends or the horizon is reached, and
serves every asset over one HTTP API (:mod:`.fleet_api`:
``/assets/{id}/...``).  Its history is one SQLite store (``OUT/history.sqlite``);
a restart with the same options resumes the unfinished run (the committed
samples are recomputed, set-points written through the API replayed).

:class:`~kautztwin.service.fleet_view.FleetView` (its own module) is what the API
sees: the latest step of every asset and the queue of jobs the loop runs between steps.

The settings go through the single service's configuration
(:func:`~kautztwin.service.config.load_service_config`): the same ``--http``,
token (``KAUTZTWIN_HTTP_TOKEN``) and rate-limit rules, the same speed check.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

from .._json import to_jsonable
from ..exceptions import DataError
from .config import load_service_config
from .fleet_view import FleetView

__all__ = ["FleetService", "FleetView"]  # FleetView re-exported from .fleet_view

_logger = logging.getLogger("kautztwin.service")

#: default horizon of a served fleet, plant seconds
DEFAULT_DURATION = 600.0


def _log(event: str, **fields: Any) -> None:
    _logger.info(event, extra={"event": event, "fields": fields})


class FleetService:
    """A simulated fleet's twins on the wall clock, served over one HTTP API.

    Parameters
    ----------
    n_assets : int
        Assets of the fleet.
    out : str or Path
        Folder of the store (``history.sqlite``) and ``summary.json``.
    plant : {'hydraulic'}, default='hydraulic'
        Plant type.
    speed : float, default=1.0
        Plant seconds per wall-clock second.
    duration : float, optional
        Horizon of the run, plant s (600 when omitted).
    wall_duration : float, optional
        Stop after this many wall-clock seconds (default: at the horizon or a stop request).
    http : str, optional
        ``HOST:PORT`` (or ``PORT``) of the HTTP API; none when omitted.
    token : str, optional
        API token (bearer) of the writes; ``KAUTZTWIN_HTTP_TOKEN`` when omitted;
        needed off the loopback interface.
    rate_limit : float, default=60
        Writes a minute per client (0: no limit).
    seed, spread, drift_spread, noise
        The simulated fleet (:func:`~kautztwin.twin.fleet.simulate.hydraulic_fleet`).
    workers : int, default=1
        Processes of the fleet's pool (identifications, re-identifications).
    resume : bool, default=True
        Continue an unfinished run of the same options in the store.
    estimator : object, optional
        A trained neural estimator for the update module (see :class:`~kautztwin.twin.fleet.Fleet`).

    Attributes
    ----------
    fleet : Fleet
        Built by :meth:`build`.
    clock : Clock
        The real-time clock of the loop.
    api : FleetApiServer or None
    summary : dict
        What :meth:`run` returned.

    Raises
    ------
    DataError
        On a bad option (one line): the same rules as ``twin serve`` for
        ``http``, ``token``, ``rate_limit`` and ``speed``.
    """

    def __init__(
        self, n_assets: int, out: str | Path, *, plant: str = "hydraulic", speed: float = 1.0,
        duration: float | None = None, wall_duration: float | None = None,
        http: str | None = None, token: str | None = None, rate_limit: float = 60.0,
        seed: int = 0, spread: float = 0.05, drift_spread: float = 0.3, noise: float = 0.01,
        workers: int = 1, resume: bool = True, estimator: Any = None,
    ) -> None:
        from .._validation import check_int

        if plant != "hydraulic":
            raise DataError(f"plant must be 'hydraulic' (the simulated fleet), got {plant!r}")
        self.n_assets = check_int(n_assets, "n_assets", 1)
        overrides: dict[str, Any] = {"plant.kind": "hydraulic", "service.out": str(out),
                                     "plant.speed": float(speed),
                                     "http.rate_limit": float(rate_limit)}
        if wall_duration is not None:
            overrides["service.duration"] = float(wall_duration)
        if http is not None:
            overrides["http.bind"] = str(http)
        if token is not None:
            overrides["http.token"] = str(token)
        cfg = load_service_config(None, overrides)  # the single service's rules
        self.out = cfg.out
        self.speed = float(cfg.plant["speed"])
        self.wall_duration = cfg.values["service"]["duration"]
        self.http = dict(cfg.values["http"])
        if duration is not None and not (math.isfinite(duration) and duration > 0):
            raise DataError(f"duration must be a positive number of plant seconds, got "
                            f"{duration!r}")
        self.duration = DEFAULT_DURATION if duration is None else float(duration)
        if isinstance(workers, bool) or int(workers) < 1:
            raise DataError(f"workers must be a positive integer, got {workers!r}")
        self.options = {"seed": int(seed), "spread": float(spread),
                        "drift_spread": float(drift_spread), "noise": float(noise)}
        self.workers = int(workers)
        self.resume = bool(resume)
        self.estimator = estimator
        self.stop_event = threading.Event()
        self.fleet: Any = None
        self.assets: list[dict[str, float]] = []
        self.clock: Any = None
        self.api: Any = None
        self.summary: dict[str, Any] = {}

    @property
    def history_path(self) -> Path:
        """The fleet's SQLite store."""
        return self.out / "history.sqlite"

    def build(self) -> None:
        """Draw the fleet, open the store and make the HTTP server (not started yet)."""
        from ..twin.fleet import Fleet, FleetStore
        from ..twin.fleet.simulate import hydraulic_fleet
        from ..twin.physical import Clock
        from ..twin.runtime import TwinConfig

        cfg = TwinConfig.for_plant("hydraulic", duration=self.duration, quick=True,
                                   static_twin=False, retune=False, seed=self.options["seed"])
        plant, self.assets = hydraulic_fleet(self.n_assets, cfg, record=False, **self.options)
        self.out.mkdir(parents=True, exist_ok=True)
        store = FleetStore(str(self.history_path))
        self.fleet = Fleet(plant, cfg, store=store, workers=self.workers, record=False,
                           estimator=self.estimator)
        self.clock = Clock.real_time(self.speed, tolerance=cfg.dt)
        if self.http["bind"] is not None:
            from .fleet_api import FleetApiServer

            self.api = FleetApiServer(self, bind=self.http["bind"], token=self.http["token"],
                                      rate_limit=self.http["rate_limit"])

    def request_stop(self) -> None:
        """Ask the loop to stop after the step in progress (safe from a signal handler)."""
        self.stop_event.set()

    def run(self) -> dict[str, Any]:
        """Step the fleet on the wall clock until stopped, out of time or at the horizon.

        Builds the service first if :meth:`build` was not called.  On the way
        out the pending samples are committed (the run stays resumable unless
        its horizon was reached) and ``summary.json`` is written.

        Returns
        -------
        dict
            :attr:`summary`.
        """
        from ..twin.fleet.simulate import summarize

        if self.fleet is None:
            self.build()
        fleet, clock, api = self.fleet, self.clock, self.api
        n_s = fleet.config.n_samples
        dt = fleet.config.dt
        try:
            if api is not None:
                api.start()
            fleet.start(resume=self.resume)
            k0 = fleet.resumed_at
            _log("start", assets=fleet.n_assets, run_id=fleet.run_id, resumed=k0 > 0, k=k0,
                 horizon=n_s, speed=self.speed, store=str(self.history_path),
                 url=None if api is None else api.url)
            wall0 = time.monotonic()
            deadline = math.inf if self.wall_duration is None else wall0 + self.wall_duration
            reason = "horizon reached"
            clock.start()
            while fleet.k < n_s:
                if self.stop_event.is_set():
                    reason = "stop requested"
                    break
                if time.monotonic() >= deadline:
                    reason = "duration reached"
                    break
                if fleet.k >= k0:  # committed samples are recomputed at once
                    clock.wait_until((fleet.k - k0) * dt)
                fleet.step()
                if api is not None:
                    api.view.after_step(fleet)
            run = fleet.finish()
            wall = time.monotonic() - wall0
            summary = summarize(run, self.assets)
            summary.update(reason=reason, run_id=fleet.run_id, resumed_at=k0, wall_s=wall,
                           steps_per_s=(run.n_done - k0) / max(wall, 1e-9),
                           late_steps=int(clock.n_late), store=str(self.history_path))
            self.summary = summary
            (self.out / "summary.json").write_text(
                json.dumps(to_jsonable(summary), indent=2, allow_nan=False))
            _log("stop", reason=reason, n_samples=run.n_done, wall_s=round(wall, 3),
                 late_steps=int(clock.n_late))
        finally:
            if api is not None:
                api.stop()
            fleet.close()
        return self.summary

