r"""The batched fleet runtime: :class:`Fleet` steps N twins of one type as array operations.

A :class:`Fleet` runs, for each of its assets, what
:class:`~kautztwin.twin.runtime.DigitalTwin` runs for one plant with the
same :class:`~kautztwin.twin.runtime.TwinConfig` and the asset's seed -
restricted to the configurations listed under *Scope* - but every sample
of all assets at once:

1. the plants are stepped together (:mod:`.plants`);
2. the sanitiser flags every asset's sample (:class:`~.sync.FleetSanitizer`);
3. identification phase: the seeded binary excitation; at its end the
   initial identifications run in a worker pool, the updaters catch up on
   the samples so far (batched), and the first controllers are tuned and
   built in the pool;
4. closed loop: the reference filters, the MPC's QPs
   (:mod:`.mpc_batch`, DAQP for the few it leaves), the dither and the
   input limits, the controllers' filter states;
5. the update module (:class:`~.update.FleetUpdater`): recursive least
   squares, the monitored prediction, the sync monitor and the recovery
   policy; the re-identifications due at a sample run in the pool and an
   accepted model rebuilds that asset's controller (in the pool too);
6. the store (:class:`~.store.FleetStore`) commits every
   ``commit_every`` samples of all assets in one transaction.

**Scope** (what a DigitalTwin can do that the fleet does not):
``static_twin``, ``retune`` (pole re-optimisation, consolidation and the
weight retuning of later versions; the first version's tuning is done),
injected ``faults``, background threads, real-time pacing and live links.
:class:`Fleet` refuses such a configuration with a one-line
:class:`~kautztwin.exceptions.DataError`.  A trained neural ``estimator``
is the fleet's own option (no DigitalTwin counterpart in the recovery
path): the due re-identifications then take its fast path, one estimator
call for all the assets due at a sample (:meth:`.FleetUpdater.dnn_update`).
Per-asset set-points (:meth:`Fleet.set_setpoint`) override the
configuration's schedule from the next sample (the service's
``POST /assets/{id}/setpoint``; ``kautztwin.service.fleet_service``
steps a fleet on the wall clock).

Size: :class:`Fleet` is the sample loop and its phases (the runtime's
``DigitalTwin.step`` and ``_begin_twin`` as array operations); the
arithmetic lives in :mod:`.update`, :mod:`.sync` and :mod:`.mpc_batch`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...exceptions import DataError
from ..physical import SampleFlag
from ..prediction import MPCSettings
from ..prediction.settings import build_mpc
from ..runtime import TwinConfig
from ..runtime.twins import make_twins
from .assets import ControllerBuild, FleetSignals, controller_job, identify_job, unpack_fit
from .mpc_batch import BatchedController
from .plants import FleetPlant
from .store import FleetStore
from .sync import FleetMonitor, FleetSanitizer
from .update import FleetUpdater, ReidOutcome, estimator_grid

__all__ = ["Fleet", "FleetRun", "history_length"]

_RECORDED = ("y", "u", "command", "reference", "y_pred", "flags", "version")


@dataclass(frozen=True, eq=False)
class FleetRun:
    """The record of a fleet run.

    Parameters
    ----------
    config : TwinConfig
        The fleet's configuration (each asset's with its seed).
    seeds : ndarray of int
    n_done : int
        Samples processed.
    k_closed_loop : int
    arrays : dict of str to ndarray of shape (n_assets, n_done)
        ``y, u, command, reference, y_pred, flags, version`` (with ``record=True``).
    fits : list of (int, ndarray, ndarray)
        ``(k, assets, fits)``: the window fits computed at sample ``k`` (with
        ``record=True``; empty otherwise).
    events : list of (int, int, str, str)
        ``(asset, k, kind, message)``.
    counts : dict of str to ndarray of shape (n_assets,)
        ``reidentification_attempts``, ``reidentifications_accepted``,
        ``mpc_failures``, ``mpc_fallbacks``, ``flagged`` per asset.
    wall_time : float
        Seconds of the run.
    timings : dict of str to float
        Seconds spent in each part (plant, mpc, update, reidentification, store, setup).
    resume : dict
        ``resumed_at`` (samples recomputed from a resumed run, not stored again)
        and ``replay_mismatches`` (recomputed samples that differ from the stored ones).
    fit_stats : dict of str to ndarray of shape (n_assets,)
        Closed-loop window fits of each asset: ``last``, ``mean``, ``min`` and
        their number ``n`` (kept without ``record`` too).
    """

    config: TwinConfig
    seeds: NDArray[np.int64]
    n_done: int
    k_closed_loop: int
    arrays: dict[str, NDArray[Any]]
    fits: list[tuple[int, NDArray[np.intp], NDArray[np.float64]]]
    events: list[tuple[int, int, str, str]]
    counts: dict[str, NDArray[np.int64]]
    wall_time: float
    timings: dict[str, float]
    resume: dict[str, int] = field(default_factory=dict)
    fit_stats: dict[str, NDArray[Any]] = field(default_factory=dict)

    def fit_history(self, asset: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Sample indices and window fits of one asset.

        Parameters
        ----------
        asset : int

        Returns
        -------
        k, fit : ndarray
        """
        ks, fs = [], []
        for k, idx, f in self.fits:
            hit = np.flatnonzero(idx == asset)
            if hit.size:
                ks.append(k)
                fs.append(float(f[hit[0]]))
        return np.asarray(ks, dtype=np.int64), np.asarray(fs, dtype=float)


def history_length(config: TwinConfig) -> int:
    """Samples of command history a fleet keeps per asset to rebuild controllers.

    The runtime rebuilds a controller's filter states from rest over the
    whole history.  Every pole of the twin's models is at least as fast as
    the updater's ``min_rate`` (the identification's floor), so inputs older
    than ``46 / (min_rate dt)`` samples weigh less than ``exp(-46) = 1e-20``
    in the states: the fleet keeps that many (all of them without a
    ``min_rate``).

    Parameters
    ----------
    config : TwinConfig

    Returns
    -------
    int
    """
    floors = (config.updater.get("min_rate", config.min_rate), config.min_rate)
    if any(r is None or not r > 0 for r in floors):
        return config.n_samples
    rate = min(float(r) for r in floors)  # type: ignore[arg-type]
    return int(min(config.n_samples, max(config.n_ident + 1,
                                          math.ceil(46.0 / (float(rate) * config.dt)))))


def _check_config(config: TwinConfig) -> None:
    if not isinstance(config, TwinConfig):
        raise DataError(f"config must be a TwinConfig, got {type(config).__name__}")
    if not config.controlled:
        raise DataError("the fleet runs controlled plants (the configuration has no MPC)")
    out = [name for name, on in (("static_twin", config.static_twin), ("retune", config.retune),
                                 ("faults", config.faults.any)) if on]
    if config.updater.get("background"):
        out.append("updater background")
    if out:
        raise DataError(
            f"the fleet does not run {', '.join(out)}; set static_twin=False, retune=False and "
            "no faults (see docs/fleet.md, Scope)")


class Fleet:
    r"""N digital twins of one type stepped together (the batched fleet runtime).

    Parameters
    ----------
    plant : FleetPlant
        The assets' plants (:class:`~kautztwin.twin.fleet.HydraulicFleetPlant`,
        :class:`~kautztwin.twin.fleet.LoopedFleetPlant`).
    config : TwinConfig
        The configuration every asset runs (see *Scope* in the module notes).
    seeds : array-like of int, optional
        Each asset's seed (its excitation and dither); ``config.seed + i`` when omitted.
    store : FleetStore, str or None, default=None
        One history store for the fleet (a path opens a SQLite file); none when omitted.
    workers : int, default=1
        Processes of the pool for identification, tuning, re-identification
        and controller builds (1: in this process).
    record : bool, default=True
        Keep the per-sample arrays of every asset in memory (for tests and
        plots; off for large fleets).
    estimator : object, optional
        A trained neural estimator of step responses
        (:class:`~kautztwin.nn.AdaptivePoleEstimator`) whose basis size plus
        the extra fast-path poles is the twins': the due re-identification
        attempts use it, one ``predict_models`` call per sample for all the
        due assets (:meth:`.FleetUpdater.dnn_update`), instead of the
        output-error fits.

    Attributes
    ----------
    last : dict
        The latest step: ``k``, ``t`` and the arrays over the assets ``y``,
        ``u``, ``command``, ``y_pred``, ``flags``, ``reference``, ``version``
        (new arrays every step; what the fleet service's API reads).
    counts : dict of str to ndarray
        Per asset: ``mpc_failures``, ``mpc_fallbacks``, ``flagged`` and the
        closed-loop samples outside the output, input and rate limits
        (``output_violations``, ``input_violations``, ``rate_violations``).

    Raises
    ------
    DataError
        If the configuration is out of scope, the seeds do not match the
        plants, or ``dt`` differs.

    Examples
    --------
    >>> from kautztwin.twin import HydraulicPlant
    >>> from kautztwin.twin.fleet import Fleet, LoopedFleetPlant
    >>> from kautztwin.twin.runtime import TwinConfig
    >>> plants = [HydraulicPlant(temperature=20.0, noise=0.01, random_state=s) for s in (1, 2)]
    >>> cfg = TwinConfig.for_plant("hydraulic", duration=10.0, quick=True, static_twin=False,
    ...                            retune=False)
    >>> run = Fleet(LoopedFleetPlant(plants), cfg, seeds=[1, 2]).run(progress=False)
    >>> run.arrays["y"].shape
    (2, 500)
    """

    def __init__(
        self, plant: FleetPlant, config: TwinConfig, seeds: ArrayLike | None = None, *,
        store: FleetStore | str | None = None, workers: int = 1, record: bool = True,
        estimator: Any = None,
    ) -> None:
        _check_config(config)
        n = int(plant.n_assets)
        if abs(float(plant.dt) - config.dt) > 1e-9 * config.dt:
            raise DataError(
                f"the configuration has dt = {config.dt:g} s but the plants sample at "
                f"{plant.dt:g} s")
        seeds_a = (config.seed + np.arange(n) if seeds is None
                   else np.asarray(seeds, dtype=np.int64).reshape(-1))
        if seeds_a.size != n:
            raise DataError(f"seeds has {seeds_a.size} entries for {n} assets")
        if isinstance(workers, bool) or int(workers) < 1:
            raise DataError(f"workers must be a positive integer, got {workers!r}")
        self.plant = plant
        self.config = config
        self.seeds = seeds_a
        self.n_assets = n
        self.workers = int(workers)
        self.record = bool(record)
        self.store = FleetStore(store) if isinstance(store, str) else store
        self._started = False
        self._pool: ProcessPoolExecutor | None = None
        self._solve_mpc = True
        if estimator is not None:
            estimator_grid(estimator, config.dt)  # a one-line error now, not after identifying
        self.estimator = estimator

    # ------------------------------------------------------------------ pool
    def _map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
        if self.workers == 1 or len(items) < 2:
            return [fn(x) for x in items]
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.workers)
        chunk = max(1, len(items) // (4 * self.workers))
        return list(self._pool.map(fn, items, chunksize=chunk))

    @contextmanager
    def _timed(self, part: str) -> Iterator[None]:
        t0 = time.perf_counter()
        yield
        self._timings[part] = self._timings.get(part, 0.0) + time.perf_counter() - t0

    # ------------------------------------------------------------------ start
    def start(self, *, resume: bool = True) -> None:
        """Draw the signals, reset the plants and open the run in the store.

        Parameters
        ----------
        resume : bool, default=True
            Continue an unfinished run with the same configuration in the
            store: its committed samples are recomputed (the run is
            deterministic: same plants, seeds and code) but not stored again,
            and the run goes on after them.  A recomputed input or output
            that differs from the stored one is counted in ``replay_mismatches``.
        """
        if self._started:
            raise DataError("the fleet run has already been started")
        cfg = self.config
        N, n_s = self.n_assets, cfg.n_samples
        self._timings: dict[str, float] = {}
        self._wall0 = time.perf_counter()
        with self._timed("setup"):
            self.signals = FleetSignals.draw(cfg, self.seeds)
        self._k = 0
        self._k_cl = cfg.n_ident
        self._v_prev = np.full(N, cfg.operating_input)
        self._ref = np.full(N, math.nan)
        self._setpoint = np.full(N, math.nan)  # per-asset overrides (NaN: the schedule)
        self._hist_len = history_length(cfg)
        self._command = np.zeros((N, self._hist_len))
        self._ident_y = np.zeros((N, cfg.n_ident))
        self._ident_clean = np.zeros((N, cfg.n_ident), dtype=bool)
        self.sanitizer = FleetSanitizer(N, threshold=cfg.sanitizer_threshold,
                                        window=cfg.sanitizer_window, min_scale=cfg.sensor_scale)
        self.updater: FleetUpdater | None = None
        self.controller: BatchedController | None = None
        self.settings: list[MPCSettings] = []
        self.models: list[Any] = []
        self.fits: list[tuple[int, NDArray[np.intp], NDArray[np.float64]]] = []
        self.fit_stats = {"last": np.full(N, math.nan), "sum": np.zeros(N),
                          "n": np.zeros(N, dtype=np.int64), "min": np.full(N, math.inf)}
        self.events: list[tuple[int, int, str, str]] = []
        self.outcomes: list[ReidOutcome] = []
        self.counts = {name: np.zeros(N, dtype=np.int64) for name in (
            "mpc_failures", "mpc_fallbacks", "flagged", "output_violations",
            "input_violations", "rate_violations")}
        self._u_last = np.full(N, math.nan)
        self.last: dict[str, Any] = {}
        self.arrays: dict[str, NDArray[Any]] = {}
        if self.record:
            for name in _RECORDED:
                dtype = np.int64 if name in ("flags", "version") else float
                self.arrays[name] = np.full((N, n_s), 0 if dtype is np.int64 else math.nan,
                                            dtype=dtype)
        self._version = np.zeros(N, dtype=np.int64)
        self._mpc_cache: dict[int, tuple[int, Any]] = {}
        self._y = np.asarray(self.plant.reset(), dtype=float)
        self.run_id = None
        self._resume_k = 0
        self.replay_mismatches = 0
        self._stored: dict[str, NDArray[Any]] | None = None
        self._replay_setpoints: list[tuple[int, int, float]] = []
        if self.store is not None:
            run_cfg = {"twin": cfg.to_dict(), "n_assets": N, "seeds": self.seeds.tolist()}
            found = self.store.find_run(run_cfg) if resume else None
            if found is not None:
                self.run_id = found
                self._resume_k = self.store.committed_steps(found)
                st = self.store.samples(found)
                if st["k"].size != N * self._resume_k:
                    raise DataError(
                        f"run {found} in {self.store.path} holds {st['k'].size} samples, not "
                        f"{N} assets x {self._resume_k} steps; it cannot be resumed")
                self._stored = {name: st[name].reshape(N, self._resume_k) for name in ("u", "y")}
                # set-points written to the run (the service's API) are replayed at their sample
                self._replay_setpoints = self.store.setpoints(found)
            else:
                self.run_id = self.store.start_run(run_cfg)
        self._started = True

    # ------------------------------------------------------------------ one sample
    def step(self) -> int:
        """Process the next sample of every asset.

        Returns
        -------
        int
            The index of the sample processed.

        Raises
        ------
        DataError
            If the run was not started or is complete.
        """
        if not self._started:
            raise DataError("call start() (or run()) first")
        cfg = self.config
        k = self._k
        if k >= cfg.n_samples:
            raise DataError(f"the run is complete ({cfg.n_samples} samples)")
        t_k = k * cfg.dt
        while self._replay_setpoints and self._replay_setpoints[0][0] <= k:
            _, asset, value = self._replay_setpoints.pop(0)
            self._setpoint[asset] = value
        y_raw = self._y
        flags = self.sanitizer.process(y_raw)
        clean = (flags & int(SampleFlag.HELD | SampleFlag.OUTLIER)) == 0
        self.counts["flagged"] += flags != 0
        if k < self._k_cl:
            u = self.signals.u_ident(k)
            v = u
            self._ident_y[:, k] = y_raw
            self._ident_clean[:, k] = clean
        else:
            if k == self._k_cl:
                self._begin_twin(k, y_raw, clean)
            with self._timed("mpc"):
                u, v = self._track(k, t_k, y_raw, clean)
            self._violations(y_raw, u)
        self._u_last = u
        self._command[:, k % self._hist_len] = v
        self._v_prev = v
        y_pred = np.full(self.n_assets, math.nan)
        if self.updater is not None:
            with self._timed("update"):
                y_pred = self._update(k, t_k, u, y_raw, clean)
        if self.record:
            a = self.arrays
            a["y"][:, k], a["u"][:, k], a["command"][:, k] = y_raw, u, v
            a["flags"][:, k], a["y_pred"][:, k], a["version"][:, k] = flags, y_pred, self._version
            if k >= self._k_cl:
                a["reference"][:, k] = self._ref
        if self.store is not None and k < self._resume_k:
            self._check_replay(k, u, y_raw)
        elif self.store is not None:
            with self._timed("store"):
                self.store.add_samples(self.run_id, k, t_k, u, y_raw, y_pred, flags)
                if (k + 1) % cfg.commit_every == 0 or k + 1 == cfg.n_samples:
                    self.store.commit()
        self.last = {"k": k, "t": t_k, "y": y_raw, "u": u, "command": v, "y_pred": y_pred,
                     "flags": flags, "reference": self._ref.copy(),
                     "version": self._version.copy()}
        if k + 1 < cfg.n_samples:
            with self._timed("plant"):
                self._y = np.asarray(self.plant.step(u), dtype=float)
        self._k = k + 1
        return k

    def _violations(self, y: NDArray, u: NDArray) -> None:
        """Count the closed-loop samples outside the output, input and rate limits."""
        m = self.config.mpc
        assert m is not None
        tol = 1e-9  # as summarize() counts them from the records
        c = self.counts
        c["output_violations"] += (y < m.y_min) | (y > m.y_max)
        c["input_violations"] += (u < m.u_min - tol) | (u > m.u_max + tol)
        c["rate_violations"] += np.abs(u - self._u_last) > m.du_max + tol

    def _add_fits(self, k: int, assets: NDArray[np.intp], fits: NDArray[np.float64]) -> None:
        """Record window fits: every one with ``record``, closed-loop statistics always."""
        if self.record:
            self.fits.append((k, assets, fits.copy()))
        if k >= self._k_cl:
            st = self.fit_stats
            st["last"][assets] = fits
            st["sum"][assets] += fits
            st["n"][assets] += 1
            st["min"][assets] = np.minimum(st["min"][assets], fits)

    def _check_replay(self, k: int, u: NDArray, y: NDArray) -> None:
        """Compare a recomputed committed sample with the stored one."""
        st = self._stored
        assert st is not None
        bad = ~(np.isclose(st["u"][:, k], u, rtol=1e-9, atol=0, equal_nan=True)
                & np.isclose(st["y"][:, k], y, rtol=1e-9, atol=0, equal_nan=True))
        self.replay_mismatches += int(bad.sum())
        if k + 1 == self._resume_k:
            self._stored = None

    def _track(
        self, k: int, t_k: float, y_raw: NDArray, clean: NDArray
    ) -> tuple[NDArray, NDArray]:
        """``(u, v)``: MPC tracking of the filtered set-point (the runtime's ``_track``)."""
        cfg = self.config
        assert self.updater is not None and self.controller is not None and cfg.mpc is not None
        y_fb = np.where(clean, y_raw, self.updater.predict())
        first = np.isnan(self._ref)
        self._ref[first] = y_fb[first]
        sp: Any = cfg.setpoint(t_k)
        if not np.isnan(self._setpoint).all():
            sp = np.where(np.isnan(self._setpoint), sp, self._setpoint)
        if cfg.reference_tau > 0:
            alpha = 1.0 - math.exp(-cfg.dt / cfg.reference_tau)
            self._ref += alpha * (sp - self._ref)
        else:
            self._ref[:] = sp
        ctl = self.controller
        x = ctl.state(y_fb)
        v_prev = self._v_prev
        if not self._solve_mpc:  # benchmarks only: the loop without the QPs
            v, status = v_prev.copy(), np.ones(self.n_assets, dtype=np.int64)
        else:
            v, status = ctl.solve(x, self._ref, v_prev, np.arange(self.n_assets))
        for i in np.flatnonzero(status != 1).tolist():
            res = self._problem(i).solve(x[i], float(self._ref[i]), u_prev=float(v_prev[i]))
            v[i] = float(res.u_next)
            self.counts["mpc_fallbacks"][i] += 1
            if not res.success:
                self.counts["mpc_failures"][i] += 1
        d = self.signals.d(k)
        u = np.clip(v + d, cfg.mpc.u_min, cfg.mpc.u_max)
        ctl.advance(v, d)
        return u, v

    def _problem(self, i: int) -> Any:
        """Asset ``i``'s MPC problem for the scalar fallback (built on demand, cached)."""
        hit = self._mpc_cache.get(i)
        if hit is None or hit[0] != self._version[i]:
            problem = build_mpc(self.models[i], self.settings[i])
            hit = (int(self._version[i]), problem)
            self._mpc_cache[i] = hit
        return hit[1]

    def _update(
        self, k: int, t_k: float, u: NDArray, y_raw: NDArray, clean: NDArray
    ) -> NDArray[np.float64]:
        upd = self.updater
        assert upd is not None
        before = upd.reid_seconds
        y_frozen, _, outcomes, ev, desync, resync = upd.step(u, y_raw, clean)
        spent = upd.reid_seconds - before
        self._timings["update"] = self._timings.get("update", 0.0) - spent
        self._timings["reidentification"] = self._timings.get("reidentification", 0.0) + spent
        if ev.size:
            self._add_fits(k, ev, upd.monitor.fit[ev])
        for i in desync.tolist():
            self.events.append((i, k, "desync", f"fit {upd.monitor.fit[i]:.2f} %"))
        for i in resync.tolist():
            self.events.append((i, k, "resync", f"fit {upd.monitor.fit[i]:.2f} %"))
        if outcomes:
            with self._timed("reidentification"):
                self._after_reid(outcomes, k, t_k)
        return y_frozen

    def _after_reid(self, outcomes: list[ReidOutcome], k: int, t_k: float) -> None:
        """Log the attempts; an accepted model rebuilds its asset's controller (in the pool)."""
        upd = self.updater
        assert upd is not None
        self.outcomes.extend(outcomes)
        new = []
        for o in outcomes:
            self.events.append((o.asset, k, "model-update" if o.accepted else "model-rejected",
                                o.reason))
            if o.accepted:
                self._version[o.asset] = o.version
                new.append(o.asset)
                if self.store is not None:
                    self.store.add_version(self.run_id, o.asset, upd.digital_models[o.asset], k)
        if not new:
            return
        # the command of sample k is in (the runtime's history_length)
        jobs = [(upd.digital_models[i].model.to_dict(), self.settings[i], False, 0.0, 0.0, 0.0,
                 *self._histories(i, k + 1), self.config.operating_input) for i in new]
        for i, build in zip(new, self._map(controller_job, jobs), strict=True):
            if isinstance(build, str):
                self.events.append((i, k, "controller-rejected",
                                    f"kept the controller: the MPC on version "
                                    f"{self._version[i]} cannot be set up ({build})"))
                continue
            self._install(i, build, upd.digital_models[i].model)
            self.events.append((i, k, "controller", f"MPC rebuilt on version {self._version[i]}"))

    def _histories(self, i: int, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Asset ``i``'s commands and dither of samples ``n - h .. n - 1`` (the last ``h`` kept).

        The runtime rebuilds a controller's filter states from rest over the
        whole command history; the fleet keeps the last ``h`` samples
        (:func:`history_length`), whose start state differs from the full
        history's by a factor below ``1e-20`` of the slowest pole's decay.
        """
        h = self._hist_len
        first = max(0, n - h)
        ks = np.arange(first, n)
        v = self._command[i, ks % h].copy()
        d = self.signals.dither_history(i, first, n)
        d[ks < self._k_cl] = 0.0  # no dither in the identification phase
        return v, d

    def _inputs(self, i: int, first: int, n: int) -> NDArray[np.float64]:
        """Asset ``i``'s plant inputs of samples ``first .. n - 1`` (the last ``h`` kept).

        Rebuilt from the command history exactly as :meth:`step` formed them:
        the excitation in the identification phase (stored as the command),
        ``clip(v + d, u_min, u_max)`` in the closed loop.  The update module's
        buffer reads its inputs here instead of keeping a copy.
        """
        h = self._hist_len
        if n - first > h:
            raise DataError(f"only the last {h} inputs are kept, {n - first} were asked for")
        ks = np.arange(first, n)
        u = self._command[i, ks % h].copy()
        cl = ks >= self._k_cl
        if cl.any():
            mpc = self.config.mpc
            assert mpc is not None
            d = self.signals.dither_history(i, first, n)
            u[cl] = np.clip(u[cl] + d[cl], mpc.u_min, mpc.u_max)
        return u

    def set_setpoint(self, assets: ArrayLike, value: float) -> int:
        """Hold ``value`` as the set-point of ``assets`` from the next sample on.

        The override replaces the rest of the configuration's schedule for
        those assets (as ``POST /setpoint`` does for one twin); the reference
        filter moves towards it as towards a scheduled step.

        Parameters
        ----------
        assets : array-like of int
        value : float

        Returns
        -------
        int
            The first sample that uses it (after the recomputed samples of a
            resumed run).

        Raises
        ------
        DataError
            If an asset index is out of range or ``value`` is not finite.
        """
        if not self._started:
            raise DataError("call start() (or run()) first")
        idx = np.asarray(assets, dtype=np.intp).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_assets):
            raise DataError(f"asset indices must lie in [0, {self.n_assets})")
        v = float(value)
        if not math.isfinite(v):
            raise DataError(f"the set-point must be a finite number, got {value!r}")
        # while a resumed run recomputes its stored samples, a new set-point waits for the
        # first sample after them (the recomputed ones must stay those stored)
        k_from = max(self._k, self._resume_k)
        if k_from > self._k:
            self._replay_setpoints = sorted(
                self._replay_setpoints + [(k_from, int(a), v) for a in idx.tolist()],
                key=lambda e: e[0])
        else:
            self._setpoint[idx] = v
        if self.store is not None and self.run_id is not None:
            self.store.add_setpoints(self.run_id, idx, k_from, k_from * self.config.dt, v)
        return k_from

    @property
    def k(self) -> int:
        """Samples processed so far (the next sample's index)."""
        return int(getattr(self, "_k", 0))

    @property
    def started(self) -> bool:
        """Whether :meth:`start` has run."""
        return bool(self._started)

    @property
    def resumed_at(self) -> int:
        """Committed samples of the resumed run (recomputed, not stored again); 0 for a new run."""
        return int(getattr(self, "_resume_k", 0))

    @property
    def k_closed_loop(self) -> int:
        """The first closed-loop sample (the end of the identification phase)."""
        return int(getattr(self, "_k_cl", self.config.n_ident))

    def setpoints(self, t: float) -> NDArray[np.float64]:
        """Every asset's set-point in force at plant time ``t`` from now on.

        Parameters
        ----------
        t : float

        Returns
        -------
        ndarray of shape (n_assets,)
        """
        sp = float(self.config.setpoint(t))
        over = getattr(self, "_setpoint", None)
        if over is None:
            return np.full(self.n_assets, sp)
        return np.where(np.isnan(over), sp, over)

    def _install(self, i: int, build: ControllerBuild, model: Any) -> None:
        assert self.controller is not None
        self.controller.install(i, build.qp, build.A, build.B, build.c, build.xv, build.xv_prev,
                                build.xd)
        self.settings[i] = build.settings
        self.models[i] = model
        self._mpc_cache.pop(i, None)

    # ------------------------------------------------------------------ identification
    def _begin_twin(self, k: int, y_now: NDArray, clean_now: NDArray) -> None:
        """End of the identification phase: identify, build the updaters and the controllers."""
        cfg = self.config
        N = self.n_assets
        with self._timed("setup"):
            u_id = np.stack([self.signals.u_ident(j) for j in range(k)], axis=1)
            ident = {"n_poles": cfg.n_poles, "dt": cfg.dt,
                     "operating_input": cfg.operating_input, "min_rate": cfg.min_rate}
            y_clean = np.where(self._ident_clean, self._ident_y, np.nan)
            fits = self._map(identify_job, [(ident, u_id[i].copy(), y_clean[i].copy())
                                            for i in range(N)])
            bad = [i for i, f in enumerate(fits) if isinstance(f, str)]
            if bad:
                raise DataError(f"asset {bad[0]}: {fits[bad[0]]}")
            fits = [unpack_fit(f) for f in fits]
            updaters = [make_twins(f, cfg, background=False)[0] for f in fits]
            mon = FleetMonitor(N, window=cfg.monitor_window, stride=cfg.monitor_stride,
                               threshold=cfg.monitor_threshold,
                               n_consecutive=cfg.monitor_consecutive,
                               resync_margin=cfg.monitor_resync_margin)
            # the command ring gives every input of the last h samples (all of them when h is
            # the run's length): the update module's buffer needs no copy of its own
            span = self._hist_len if self._hist_len < cfg.n_samples else None
            self.updater = upd = FleetUpdater(updaters, mon, map_fn=self._map,
                                              inputs=self._inputs, inputs_span=span,
                                              estimator=self.estimator)
            del updaters
            # the twins catch up on the identification samples (their own sanitiser sees
            # the same samples as the loop's: the same flags)
            for j in range(k):
                y_frozen, _, outcomes, ev, _, _ = upd.step(
                    u_id[:, j], self._ident_y[:, j], self._ident_clean[:, j])
                if self.record:
                    self.arrays["y_pred"][:, j] = y_frozen
                if ev.size:
                    self._add_fits(j, ev, upd.monitor.fit[ev])
                self.outcomes.extend(outcomes)
            self._version = np.array([dm.version for dm in upd.digital_models], dtype=np.int64)
            upd.enter_new_regime()  # the closed loop's start (as DigitalTwin's)
            u_op = self._v_prev
            y_op = np.where(clean_now, y_now, upd.predict())
            del self._ident_y, self._ident_clean
            assert cfg.mpc is not None
            jobs = [(upd.digital_models[i].model.to_dict(), cfg.mpc, True, cfg.tuning_step(),
                     float(u_op[i]), float(y_op[i]), *self._histories(i, k),
                     cfg.operating_input) for i in range(N)]
            builds = self._map(controller_job, jobs)
            bad = [i for i, b in enumerate(builds) if isinstance(b, str)]
            if bad:
                raise DataError(f"asset {bad[0]}: the first MPC cannot be set up: {builds[bad[0]]}")
            n_states = builds[0].A.shape[0]
            nv, m = builds[0].qp.Einv.shape[0], builds[0].qp.n_rows
            self.controller = BatchedController(N, n_states, nv, m, cfg.operating_input)
            self.settings = [b.settings for b in builds]
            self.models = [dm.model for dm in upd.digital_models]
            for i, b in enumerate(builds):
                self._install(i, b, upd.digital_models[i].model)
            if self.store is not None:
                for i in range(N):
                    self.store.add_version(self.run_id, i, upd.digital_models[i], k)
            for i in range(N):
                self.events.append((i, k, "phase", "closed loop: MPC tracking with twin updates"))

    # ------------------------------------------------------------------ the loop
    def run(
        self, *, progress: bool | None = None, resume: bool = True, until: int | None = None,
    ) -> FleetRun:
        """Run (or resume) every sample, or up to ``until``, and return the record.

        Parameters
        ----------
        progress : bool or None, default=None
            A tqdm bar on stderr (``None``: only on a terminal).
        resume : bool, default=True
            See :meth:`start`.
        until : int, optional
            Stop before this sample (the run stays resumable).

        Returns
        -------
        FleetRun
        """
        if not self._started:
            self.start(resume=resume)
        stop = self.config.n_samples if until is None else min(int(until), self.config.n_samples)
        bar = None
        if progress is not False:
            from tqdm.auto import tqdm

            bar = tqdm(total=self.config.n_samples, initial=self._k, unit="sample",
                       desc=f"fleet of {self.n_assets}",
                       disable=None if progress is None else False, dynamic_ncols=True)
        try:
            while self._k < stop:
                self.step()
                if bar is not None:
                    bar.update(1)
                    if self._k % 50 == 0 and self.updater is not None:
                        fit = self.updater.monitor.fit
                        med = float(np.nanmedian(fit)) if np.isfinite(fit).any() else math.nan
                        bar.set_postfix_str(f"median fit {med:.1f}%", refresh=False)
        finally:
            if bar is not None:
                bar.close()
        return self.finish()

    def finish(self) -> FleetRun:
        """Commit what is pending, stop the pool and return the record.

        Returns
        -------
        FleetRun
        """
        if self.store is not None:
            done = self._k >= self.config.n_samples
            if done:
                self.store.log_events(self.run_id, self.events)
            self.store.finish_run(self.run_id, "finished" if done else "running")
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        counts = dict(self.counts)
        if self.updater is not None:
            counts["reidentification_attempts"] = self.updater.counts["attempts"].copy()
            counts["reidentifications_accepted"] = self.updater.counts["accepted"].copy()
        arrays = {name: a[:, : self._k].copy() for name, a in self.arrays.items()}
        st = self.fit_stats
        with np.errstate(invalid="ignore", divide="ignore"):
            stats = {"last": st["last"].copy(), "n": st["n"].copy(),
                     "mean": np.where(st["n"] > 0, st["sum"] / st["n"], math.nan),
                     "min": np.where(st["n"] > 0, st["min"], math.nan)}
        return FleetRun(self.config, self.seeds, self._k, self._k_cl, arrays, list(self.fits),
                        list(self.events), counts, time.perf_counter() - self._wall0,
                        dict(self._timings), {"resumed_at": self._resume_k,
                                              "replay_mismatches": self.replay_mismatches},
                        stats)

    def close(self) -> None:
        """Stop the pool and close the store."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self.store is not None:
            self.store.close()

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def nbytes_per_asset(self) -> float:
        """Bytes of array state per asset (the per-sample records and the command history excluded).

        Returns
        -------
        float
        """
        total = self.sanitizer.nbytes
        if self.updater is not None:
            total += self.updater.nbytes + self.updater.monitor.nbytes
        if self.controller is not None:
            total += self.controller.nbytes
        total += (self._v_prev.nbytes + self._ref.nbytes + self._version.nbytes
                  + self._setpoint.nbytes)
        return total / self.n_assets

    def __repr__(self) -> str:
        return f"Fleet(n_assets={self.n_assets}, k={getattr(self, '_k', 0)})"
