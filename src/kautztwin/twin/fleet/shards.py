r"""A simulated fleet sharded over a Ray cluster: one batched fleet per actor, one store per shard.

:func:`run_sharded` splits the assets of a simulated hydraulic fleet
(:func:`~.simulate.hydraulic_fleet`) into ``n_shards`` contiguous shards and
runs each as a :class:`~.step.Fleet` inside a Ray actor.  A shard is the
same computation as the corresponding assets of a single-process fleet: the
assets' draws, seeds and sensor noise do not depend on the sharding, and
every asset's twin is independent of the others, so the merged record equals
the single-process one.

**What is shared.**  Nothing but the driver's arguments: each actor builds
its plants, twins and worker pool itself and writes its own SQLite store
``store_dir/shard_<j>.sqlite`` (WAL; its rows number the shard's assets ``0 .. n_j - 1``:
row asset ``i`` of shard ``j`` is the fleet's asset ``shard_indices(n, S)[j][i]``).  On a
multi-node cluster ``store_dir`` must be a path every node can write (a
shared file system), or each node keeps its shards' files on its own disk.

**Recovery.**  The actors are created with ``max_restarts`` and
``max_task_retries``: when a worker process dies (killed, out of memory,
node lost), Ray restarts the actor and retries its ``run`` call; the new
:class:`~.step.Fleet` finds its unfinished run in the shard's store,
recomputes the committed samples without storing them again (the run is
deterministic; a recomputed sample that differs is counted as a replay
mismatch) and continues.  A sample committed before the kill is stored
exactly once; the samples after the last commit are recomputed.

Ray is optional (``pip install ray``); it is imported only here.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ...exceptions import DataError
from ..runtime import TwinConfig
from .assets import config_state
from .step import FleetRun

__all__ = ["make_actors", "merge_runs", "run_sharded", "shard_indices"]


def _ray() -> Any:
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError("sharding a fleet over Ray needs ray: pip install 'ray==2.60.0'") from exc
    return ray


def shard_indices(n_assets: int, n_shards: int) -> list[np.ndarray]:
    """Contiguous, nearly equal shards of ``0 .. n_assets - 1``.

    Parameters
    ----------
    n_assets, n_shards : int

    Returns
    -------
    list of ndarray of int

    Examples
    --------
    >>> from kautztwin.twin.fleet.shards import shard_indices
    >>> [s.tolist() for s in shard_indices(5, 2)]
    [[0, 1, 2], [3, 4]]
    """
    if n_shards < 1 or n_shards > n_assets:
        raise DataError(f"n_shards must lie in [1, {n_assets}] for {n_assets} assets, "
                        f"got {n_shards}")
    return [a for a in np.array_split(np.arange(n_assets), n_shards)]


class _ShardActor:
    """One shard: a batched fleet of its assets, its store, its run (inside a Ray actor)."""

    def __init__(self, shard: int, indices: np.ndarray, n_assets: int, state: dict[str, Any],
                 sim: dict[str, Any], store_path: str | None, workers: int) -> None:
        from .simulate import hydraulic_fleet
        from .step import Fleet
        from .store import FleetStore

        self.shard = shard
        self.indices = np.asarray(indices)
        cfg = TwinConfig(**state)
        plant, self.assets = hydraulic_fleet(n_assets, cfg, indices=self.indices, **sim)
        store = FleetStore(store_path) if store_path else None
        self.fleet = Fleet(plant, cfg, seeds=cfg.seed + self.indices, store=store,
                           workers=workers, record=True)

    def pid(self) -> int:
        return os.getpid()

    def run(self, until: int | None = None) -> dict[str, Any]:
        f = self.fleet
        if not getattr(f, "_started", False):
            f.start(resume=True)
        r = f.run(progress=False, until=until)
        if until is None and f.store is not None:
            f.store.close()
        return {"indices": self.indices, "n_done": r.n_done, "arrays": r.arrays, "fits": r.fits,
                "events": r.events, "counts": r.counts, "wall_time": r.wall_time,
                "timings": r.timings, "resume": r.resume, "k_closed_loop": r.k_closed_loop,
                "fit_stats": r.fit_stats, "assets": self.assets}


def merge_runs(config: TwinConfig, parts: list[dict[str, Any]]) -> FleetRun:
    """One :class:`~.step.FleetRun` of the whole fleet from the shards' records.

    Parameters
    ----------
    config : TwinConfig
    parts : list of dict
        What each shard's ``run`` returned.

    Returns
    -------
    FleetRun
        Asset ``i`` is the fleet's asset ``i``; ``resume`` holds the latest
        sample a shard resumed at, the number of resumed shards and the sum of
        their replay mismatches; ``wall_time`` is the slowest shard's.
    """
    idx = np.concatenate([p["indices"] for p in parts])
    n = idx.size
    order = np.argsort(idx)
    arrays = {}
    for name in parts[0]["arrays"]:
        stacked = np.concatenate([p["arrays"][name] for p in parts], axis=0)
        arrays[name] = stacked[order]
    fits: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    events = []
    for p in parts:
        glob = p["indices"]
        for k, a, f in p["fits"]:
            fits.setdefault(k, []).append((glob[a], f))
        events += [(int(glob[a]), k, kind, msg) for a, k, kind, msg in p["events"]]
    fit_list = []
    for k in sorted(fits):
        a = np.concatenate([x[0] for x in fits[k]])
        f = np.concatenate([x[1] for x in fits[k]])
        o = np.argsort(a)
        fit_list.append((k, a[o], f[o]))
    events.sort(key=lambda e: (e[1], e[0]))
    counts = {}
    for name in parts[0]["counts"]:
        counts[name] = np.concatenate([p["counts"][name] for p in parts])[order]
    timings: dict[str, float] = {}
    for p in parts:
        for key, v in p["timings"].items():
            timings[key] = max(timings.get(key, 0.0), v)
    resume = {"resumed_at": max(p["resume"].get("resumed_at", 0) for p in parts),
              "shards_resumed": sum(p["resume"].get("resumed_at", 0) > 0 for p in parts),
              "replay_mismatches": sum(p["resume"].get("replay_mismatches", 0) for p in parts)}
    seeds = config.seed + np.arange(n)
    stats = {key: np.concatenate([p["fit_stats"][key] for p in parts])[order]
             for key in parts[0]["fit_stats"]}
    return FleetRun(config, seeds, min(p["n_done"] for p in parts), parts[0]["k_closed_loop"],
                    arrays, fit_list, events, counts, max(p["wall_time"] for p in parts),
                    timings, resume, stats)


def run_sharded(
    n_assets: int, config: TwinConfig, *, n_shards: int = 2, store_dir: str | None = None,
    address: str | None = None, workers_per_shard: int = 1, max_restarts: int = 3,
    spread: float = 0.05, drift_spread: float = 0.3, noise: float = 0.01, seed: int = 0,
    actors: list[Any] | None = None,
) -> tuple[FleetRun, list[dict[str, float]]]:
    """Run a simulated hydraulic fleet sharded over Ray actors and merge the records.

    Parameters
    ----------
    n_assets : int
    config : TwinConfig
    n_shards : int, default=2
        Ray actors (one CPU each).
    store_dir : str, optional
        Folder of the shards' SQLite stores (none when omitted: no recovery).
    address : str, optional
        Ray cluster to join (``'auto'``, ``'ray://host:10001'``, ``'host:6379'``);
        a local Ray instance when omitted (started here unless one is running).
    workers_per_shard : int, default=1
        Worker processes of each shard's pool.
    max_restarts : int, default=3
        Restarts of a killed shard actor (and retries of its run).
    spread, drift_spread, noise, seed
        The fleet (see :func:`~.simulate.hydraulic_fleet`).
    actors : list, optional
        Shard actors made by :func:`make_actors` (tests use it to kill one).

    Returns
    -------
    run : FleetRun
    assets : list of dict
        What each asset drew.
    """
    ray = _ray()
    if actors is None:
        actors = make_actors(n_assets, config, n_shards=n_shards, store_dir=store_dir,
                             address=address, workers_per_shard=workers_per_shard,
                             max_restarts=max_restarts, spread=spread,
                             drift_spread=drift_spread, noise=noise, seed=seed)
    parts = ray.get([a.run.remote() for a in actors])
    assets: list[dict[str, float]] = []
    for p in sorted(parts, key=lambda p: int(p["indices"][0])):
        assets += p["assets"]
    return merge_runs(config, parts), assets


def make_actors(
    n_assets: int, config: TwinConfig, *, n_shards: int = 2, store_dir: str | None = None,
    address: str | None = None, workers_per_shard: int = 1, max_restarts: int = 3,
    spread: float = 0.05, drift_spread: float = 0.3, noise: float = 0.01, seed: int = 0,
) -> list[Any]:
    """Start Ray (or join ``address``) and create the shard actors (see :func:`run_sharded`).

    Returns
    -------
    list
        Ray actor handles with ``run.remote(until=None)`` and ``pid.remote()``.
    """
    ray = _ray()
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=max(n_shards, os.cpu_count() or 1), include_dashboard=False,
                     log_to_driver=False)
    if store_dir is not None:
        Path(store_dir).mkdir(parents=True, exist_ok=True)
    Actor = ray.remote(num_cpus=1, max_restarts=max_restarts,
                       max_task_retries=max_restarts)(_ShardActor)
    sim = {"spread": spread, "drift_spread": drift_spread, "noise": noise, "seed": seed,
           "record": True}
    state = config_state(config)
    out = []
    for j, idx in enumerate(shard_indices(n_assets, n_shards)):
        path = None if store_dir is None else str(Path(store_dir) / f"shard_{j}.sqlite")
        out.append(Actor.remote(j, idx, n_assets, state, sim, path, workers_per_shard))
    return out
