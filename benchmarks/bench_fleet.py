"""Batched fleet runtime vs looped scalar twins: asset-steps per second per core, memory, store.

Measures the closed-loop phase (identification, tuning and re-identification
are one-off or rare and reported apart).  The scalar path is
``DigitalTwin.step`` (plant by LSODA, the DAQP MPC, the updater) on a few
assets, scaled per asset-step; the batched path is ``Fleet.step`` with the
batched plant (RK4 array simulation), the batched QP solver and the array
updater.  A fleet of N assets is built from ``K`` identified template assets
tiled to N (the step's cost does not depend on the values; identifying
10 000 assets would take about an hour on this machine).  "MPC off" keeps the
command at its last value in both paths (the QPs are skipped).  Everything
runs in one process with one BLAS thread: the rates are per core.

Run::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_fleet.py

and it writes ``benchmarks/results/fleet.json``.  ``--quick`` measures fewer steps.
``--ray N`` runs only the Ray check (N assets on 2 local workers against one process,
merged into the JSON as ``ray_N``); ``--ray 2000 --kill`` is issue #15's acceptance check
(one worker killed mid-run).  The Ray check runs ``--duration`` plant seconds (default 40:
the quick hydraulic profile's own run, 8 s of identification, so that every drift event
has the profile's 15 s recovery window inside the run); the processes import a snapshot of
the package taken at the start, so that the shard restarted after the kill runs the same
code on a tree that is being edited.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from kautztwin.twin import HydraulicPlant
from kautztwin.twin.fleet import Fleet, FleetStore
from kautztwin.twin.fleet.simulate import hydraulic_fleet
from kautztwin.twin.runtime import DigitalTwin, TwinConfig

OUT = Path(__file__).parent / "results" / "fleet.json"


def _config() -> TwinConfig:
    return TwinConfig.for_plant("hydraulic", duration=120.0, quick=True, static_twin=False,
                                retune=False)


def scalar_rate(n_assets: int, n_steps: int, mpc: bool) -> dict[str, float]:
    """Asset-steps per second of looped DigitalTwins in the closed loop."""
    cfg = _config()
    twins = []
    for i in range(n_assets):
        plant = HydraulicPlant(dt=cfg.dt, temperature=20.0 + i, noise=0.01, random_state=i)
        tw = DigitalTwin(plant, replace(cfg, seed=i))
        tw.start(resume=False)
        while tw.k <= cfg.n_ident + 5:
            tw.step()
        if not mpc:
            def solve(y: float, ref: float, v_prev: float, **kw: Any) -> Any:
                return SimpleNamespace(u_next=v_prev, success=True, solve_time=0.0)
            tw.controller.solve = solve  # type: ignore[method-assign]
        twins.append(tw)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        for tw in twins:
            tw.step()
    dt = time.perf_counter() - t0
    for tw in twins:
        tw.close()
    return {"assets": n_assets, "steps": n_steps, "seconds": dt,
            "asset_steps_per_s": n_assets * n_steps / dt}


def _tile(obj: Any, n0: int, reps: int) -> None:
    """Repeat every per-asset array / list attribute of ``obj`` ``reps`` times."""
    for name, val in list(vars(obj).items()):
        new = val
        if isinstance(val, np.ndarray) and val.ndim >= 1 and val.shape[0] == n0:
            new = np.tile(val, (reps,) + (1,) * (val.ndim - 1))
        elif isinstance(val, list) and len(val) == n0:
            new = val * reps
        elif isinstance(val, dict) and val and all(
                isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == n0
                for v in val.values()):
            new = {k: np.tile(v, (reps,) + (1,) * (v.ndim - 1)) for k, v in val.items()}
        if new is not val:
            object.__setattr__(obj, name, new)


def template_fleet(k: int) -> Fleet:
    """``k`` identified assets (batched plants, constant temperatures) in the closed loop."""
    cfg = _config()
    plant, _ = hydraulic_fleet(k, cfg, drift_spread=0.0, noise=0.01, seed=1, record=False)
    fleet = Fleet(plant, cfg, workers=1, record=False)
    fleet.start()
    while fleet._k <= cfg.n_ident + 5:
        fleet.step()
    return fleet


def tiled(template: Fleet, n: int) -> Fleet:
    """A copy of ``template`` with its assets repeated to ``n``."""
    k0 = template.n_assets
    reps = -(-n // k0)
    f = copy.copy(template)
    f.plant = copy.copy(template.plant)
    f.plant.batch = copy.copy(template.plant.batch)
    parts = [f, f.plant, f.plant.batch]
    for attr in ("updater", "sanitizer", "controller", "signals"):
        setattr(f, attr, copy.copy(getattr(template, attr)))
        parts.append(getattr(f, attr))
    f.updater.monitor = copy.copy(template.updater.monitor)
    parts.append(f.updater.monitor)
    for p in parts:
        _tile(p, k0, reps)
    f.updater.counts = {k: np.tile(v, reps) for k, v in template.updater.counts.items()}
    f.counts = {k: np.tile(v, reps) for k, v in template.counts.items()}
    f.plant.batch._coef = {k: np.tile(v, reps) for k, v in template.plant.batch._coef.items()}
    f.plant.batch._params = {k: np.tile(v, reps) for k, v in template.plant.batch._params.items()}
    f._command = np.tile(template._command, (reps, 1))
    n_all = k0 * reps
    for obj in (f, f.plant, f.updater):
        obj.n_assets = n_all
    f.plant.batch.n_drives = n_all
    f.seeds = np.arange(n_all)
    f._mpc_cache = {}
    f.store = None
    return f


def fleet_rate(template: Fleet, n: int, n_steps: int, mpc: bool,
               store: FleetStore | None = None) -> dict[str, Any]:
    f = tiled(template, n)
    f._solve_mpc = mpc
    f.store = store
    if store is not None:
        f.run_id = store.start_run({"bench": n})
    f._timings = {}
    f.step()  # warm
    f._timings = {}
    t0 = time.perf_counter()
    for _ in range(n_steps):
        f.step()
    dt = time.perf_counter() - t0
    if store is not None:
        t1 = time.perf_counter()
        store.commit()
        f._timings["store"] = f._timings.get("store", 0.0) + time.perf_counter() - t1
    n_all = f.n_assets
    return {"assets": n_all, "steps": n_steps, "seconds": dt,
            "asset_steps_per_s": n_all * n_steps / dt,
            "timings_s": {k: round(v, 4) for k, v in f._timings.items()},
            "mpc_fallbacks": int(f.counts["mpc_fallbacks"].sum()),
            "state_bytes_per_asset": f.nbytes_per_asset,
            "history_bytes_per_asset_per_sample": 9}


def memory_per_asset(n: int) -> dict[str, float]:
    """Traced memory of a real (not tiled) fleet of ``n`` assets in the closed loop, per asset."""
    import gc
    import tracemalloc

    cfg = _config()
    gc.collect()
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    plant, _ = hydraulic_fleet(n, cfg, drift_spread=0.0, noise=0.01, seed=3, record=False)
    fleet = Fleet(plant, cfg, workers=1, record=False)
    fleet.start()
    while fleet._k <= cfg.n_ident + 5:
        fleet.step()
    gc.collect()
    now = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    from kautztwin.twin.fleet.step import history_length

    return {"assets": n, "run_samples": cfg.n_samples,
            "traced_bytes_per_asset": (now - base) / n,
            "array_state_bytes_per_asset": fleet.nbytes_per_asset,
            "command_history_bytes_per_asset": 8.0 * history_length(cfg),
            "dither_bits_bytes_per_asset": float(np.ceil(cfg.n_samples / 8))}


def ray_check(n: int, duration: float, kill: bool = False) -> dict[str, Any]:
    """A 2-worker local Ray run of ``n`` assets against the single-process run: same metrics?

    With ``kill`` the shards write their stores and the first shard's worker
    process is killed (``SIGKILL``) once it has committed about half the run;
    the report then says at which sample the shard resumed, how many recomputed
    samples differed from the stored ones, and whether every stored sample is
    there exactly once.
    """
    import pickle
    import signal
    import sqlite3
    import subprocess

    import ray

    from kautztwin.twin.fleet.shards import make_actors, merge_runs
    from kautztwin.twin.fleet.simulate import summarize

    cfg = TwinConfig.for_plant("hydraulic", duration=duration, quick=True, static_twin=False,
                               retune=False)
    out: dict[str, Any] = {"assets": n, "duration_s": duration}
    # Ray lowers its workers' priority by 15 (to nice 19 under a driver at nice 10), which
    # starves the shards on a shared machine: they run at the driver's priority instead
    os.environ.setdefault("RAY_worker_niceness", "0")
    with tempfile.TemporaryDirectory() as tmp:
        # The reference, the shards and a shard restarted after the kill import a snapshot of
        # the package taken now: on a tree that others edit meanwhile, a restarted shard
        # would otherwise recompute its committed samples with other code.
        import shutil

        import kautztwin

        snap = Path(tmp) / "src"
        shutil.copytree(Path(kautztwin.__file__).parent, snap / "kautztwin",
                        ignore=shutil.ignore_patterns("__pycache__"))
        os.environ["PYTHONPATH"] = os.pathsep.join(
            [str(snap)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
        # the single-process reference runs beside the shards, in a process of its own
        ref = Path(tmp) / "single.pkl"
        proc = subprocess.Popen([sys.executable, __file__, "--ray-single", str(n),
                                 "--duration", str(duration), "--save", str(ref)])
        t0 = time.perf_counter()
        try:
            actors = make_actors(n, cfg, n_shards=2, seed=7, drift_spread=0.3,
                                 store_dir=tmp if kill else None)
            pids = ray.get([a.pid.remote() for a in actors])

            @ray.remote(num_cpus=0)  # the shards hold the CPUs
            def package_path() -> str:
                import kautztwin as kt

                return str(kt.__file__)

            out["workers_import"] = ray.get(package_path.remote())
            print(f"  Ray workers import {out['workers_import']}", flush=True)
            refs = [a.run.remote() for a in actors]
            if kill:
                shard0 = (n + 1) // 2
                k_kill = cfg.n_ident + (cfg.n_samples - cfg.n_ident) // 2
                db = Path(tmp) / "shard_0.sqlite"
                # a commit writes whole steps (every asset of a sample), so asset 0's last
                # stored k tells the progress: an index look-up, not a count of the rows
                poll = ("SELECT MAX(k) FROM fleet_samples WHERE asset = 0 AND run_id = "
                        "(SELECT MAX(run_id) FROM fleet_runs)")
                steps = 0
                while steps < k_kill:
                    time.sleep(2.0)
                    try:
                        with sqlite3.connect(db) as con:
                            last = con.execute(poll).fetchone()[0]
                        steps = 0 if last is None else int(last) + 1
                    except sqlite3.Error:
                        steps = 0
                os.kill(pids[0], signal.SIGKILL)
                with sqlite3.connect(db) as con:
                    committed = con.execute("SELECT COUNT(*) FROM fleet_samples").fetchone()[0]
                out["killed_after_committed_rows"] = int(committed)
                out["killed_after_committed_steps"] = int(committed) // shard0
                out["killed_at_s"] = time.perf_counter() - t0
                print(f"  killed shard 0 after {committed} committed rows", flush=True)
            parts = ray.get(refs)
        finally:
            ray.shutdown()
        if kill:
            rows = {}
            for j in range(2):
                with sqlite3.connect(Path(tmp) / f"shard_{j}.sqlite") as con:
                    total, distinct = con.execute(
                        "SELECT COUNT(*), COUNT(DISTINCT asset * 100000 + k) FROM fleet_samples"
                    ).fetchone()
                rows[f"shard_{j}"] = {"rows": int(total), "distinct": int(distinct)}
            out["store_rows"] = rows
            out["every_sample_exactly_once"] = all(
                r["rows"] == r["distinct"] == len(p["indices"]) * cfg.n_samples
                for r, p in zip(rows.values(), sorted(parts, key=lambda p: int(p["indices"][0])),
                                strict=True))
        t_sharded = time.perf_counter() - t0
        print(f"  sharded: {t_sharded:.0f} s", flush=True)
        if proc.wait() != 0:
            raise RuntimeError("the single-process reference run failed")
        with open(ref, "rb") as fh:
            single, assets, t_single = pickle.load(fh)
        single = replace(single, config=cfg)  # sent without it (a mapping proxy does not pickle)
    out["single_process_wall_s"] = t_single
    sharded = merge_runs(cfg, parts)
    assets_s: list[dict[str, float]] = []
    for p in sorted(parts, key=lambda p: int(p["indices"][0])):
        assets_s += p["assets"]
    s1, s2 = summarize(single, assets), summarize(sharded, assets_s)
    keys = ("sync_fit_last", "sync_fit_mean", "sync_fit_min", "desync_events",
            "reidentification", "mpc", "violations", "tracking_rms")
    same = {k: s1[k] == s2[k] for k in keys}
    diff = {name: float(np.nanmax(np.abs(single.arrays[name] - sharded.arrays[name])))
            for name in ("y", "u", "y_pred")}
    out["shard_timings_s"] = [p["timings"] for p in
                              sorted(parts, key=lambda p: int(p["indices"][0]))]
    out.update({"ray_2_workers_wall_s": t_sharded, "metrics_equal": same,
                "max_abs_difference": diff, "resume": dict(sharded.resume), "summary": s1})
    return out


def single_reference(n: int, duration: float, path: str) -> None:
    """The single-process run of :func:`ray_check` (pool of 2), pickled to ``path``."""
    import pickle

    cfg = TwinConfig.for_plant("hydraulic", duration=duration, quick=True, static_twin=False,
                               retune=False)
    import kautztwin

    print(f"  single process imports {kautztwin.__file__}", flush=True)
    t0 = time.perf_counter()
    plant, assets = hydraulic_fleet(n, cfg, seed=7, drift_spread=0.3)
    with Fleet(plant, cfg, workers=2) as fleet:
        single = fleet.run(progress=False)
    t_single = time.perf_counter() - t0
    print(f"  single process: {t_single:.0f} s", flush=True)
    with open(path, "wb") as fh:
        pickle.dump((replace(single, config=None), assets, t_single), fh)


def rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--ray", type=int, default=0, metavar="N",
                    help="only the Ray check: N assets on 2 local workers vs one process "
                    "(merged into the existing JSON)")
    ap.add_argument("--kill", action="store_true",
                    help="with --ray: kill one worker mid-run (it resumes from its store)")
    ap.add_argument("--ray-single", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--duration", type=float, default=40.0,
                    help="with --ray: plant seconds of the run (default 40: the quick hydraulic "
                    "profile's own length, 8 s identification; every drift event then has the "
                    "profile's 15 s recovery window inside the run)")
    ap.add_argument("--json", default="", help="with --ray: the JSON file to merge into "
                    "(default benchmarks/results/fleet.json)")
    ap.add_argument("--save", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.ray_single:
        single_reference(args.ray_single, args.duration, args.save)
        return
    if args.ray:
        out = Path(args.json) if args.json else OUT
        old = json.loads(out.read_text()) if out.exists() else {}
        key = f"ray_{args.ray}" + ("_kill" if args.kill else "")
        old[key] = ray_check(args.ray, args.duration, kill=args.kill)
        old[key]["command"] = " ".join(["benchmarks/bench_fleet.py", *sys.argv[1:]])
        print(json.dumps(old[key]["metrics_equal"]), old[key]["max_abs_difference"],
              old[key].get("resume"), old[key].get("every_sample_exactly_once"))
        out.write_text(json.dumps(old, indent=2, default=float))
        return
    steps = 20 if args.quick else 60
    results: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpu": platform.processor(),
                    "threads": os.environ.get("OPENBLAS_NUM_THREADS", "unset")},
        "note": __doc__.split("Run::")[0].strip(),
    }
    print("scalar path (looped DigitalTwins) ...")
    results["scalar"] = {
        "mpc_on": scalar_rate(4, 2 * steps, True), "mpc_off": scalar_rate(4, 2 * steps, False)}
    for key, r in results["scalar"].items():
        print(f"  {key}: {r['asset_steps_per_s']:.0f} asset-steps/s")
    t0 = time.perf_counter()
    template = template_fleet(4)
    results["template_setup_s"] = time.perf_counter() - t0
    results["batched"] = {}
    rss0 = rss_mib()
    for n in (1, 100, 1000, 10000):
        for mpc in (True, False):
            n_steps = steps if n < 10000 else max(10, steps // 3)
            r = fleet_rate(template, n, n_steps, mpc) if n > 1 else fleet_rate(
                _single(template), 1, n_steps, mpc)
            base = results["scalar"]["mpc_on" if mpc else "mpc_off"]["asset_steps_per_s"]
            r["speedup_vs_scalar"] = r["asset_steps_per_s"] / base
            key = f"N={n} mpc={'on' if mpc else 'off'}"
            results["batched"][key] = r
            print(f"  {key}: {r['asset_steps_per_s']:.0f} asset-steps/s, "
                  f"x{r['speedup_vs_scalar']:.1f}, {r['timings_s']}")
    # the scalar path again (the machine's load drifts): speed-ups against the mean of both
    after = {"mpc_on": scalar_rate(4, 2 * steps, True),
             "mpc_off": scalar_rate(4, 2 * steps, False)}
    results["scalar_after"] = after
    for key, r in results["batched"].items():
        mode = "mpc_on" if key.endswith("on") else "mpc_off"
        base = 0.5 * (results["scalar"][mode]["asset_steps_per_s"]
                      + after[mode]["asset_steps_per_s"])
        r["speedup_vs_scalar"] = r["asset_steps_per_s"] / base
    print("  speed-ups vs the mean scalar rate:",
          {k: round(r["speedup_vs_scalar"], 1) for k, r in results["batched"].items()})
    results["memory"] = memory_per_asset(16 if args.quick else 40)
    print(f"  memory: {results['memory']}")
    results["rss_peak_mib"] = rss_mib()
    results["rss_growth_mib_during_batched"] = rss_mib() - rss0
    # the store: does one SQLite file keep up with the fleet?
    results["store"] = {}
    for n in (1000, 10000):
        with tempfile.TemporaryDirectory() as tmp:
            store = FleetStore(os.path.join(tmp, "fleet.sqlite"))
            n_steps = 50 if n < 10000 else 20
            r = fleet_rate(template, n, n_steps, True, store=store)
            t_store = r["timings_s"].get("store", 0.0)
            rows = n * n_steps
            r["store_rows_per_s"] = rows / t_store if t_store else float("inf")
            r["store_fraction_of_step_time"] = t_store / r["seconds"]
            r["keeps_up"] = bool(r["store_rows_per_s"] >= r["asset_steps_per_s"])
            store.close()
            results["store"][f"N={n}"] = r
            print(f"  store N={n}: {r['store_rows_per_s']:.0f} rows/s, "
                  f"{100 * r['store_fraction_of_step_time']:.0f} % of the step time")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    if OUT.exists():  # the Ray checks (--ray N) are kept from earlier runs
        old = json.loads(OUT.read_text())
        results.update({k: v for k, v in old.items() if k.startswith("ray_")})
    OUT.write_text(json.dumps(results, indent=2, default=float))
    print(f"wrote {OUT}")


def _single(template: Fleet) -> Fleet:
    """A one-asset fleet: the template's first asset."""
    f = tiled(template, template.n_assets)
    keep = 1
    n0 = f.n_assets
    for obj in (f, f.plant, f.plant.batch, f.updater, f.updater.monitor, f.sanitizer,
                f.controller, f.signals):
        for name, val in list(vars(obj).items()):
            if isinstance(val, np.ndarray) and val.ndim >= 1 and val.shape[0] == n0:
                object.__setattr__(obj, name, val[:keep].copy())
            elif isinstance(val, list) and len(val) == n0:
                object.__setattr__(obj, name, val[:keep])
    f.updater.counts = {k: v[:keep].copy() for k, v in f.updater.counts.items()}
    f.counts = {k: v[:keep].copy() for k, v in f.counts.items()}
    f.plant.batch._coef = {k: v[:keep].copy() for k, v in f.plant.batch._coef.items()}
    f.plant.batch._params = {k: v[:keep].copy() for k, v in f.plant.batch._params.items()}
    f._command = f._command[:keep].copy()
    for obj in (f, f.plant, f.updater):
        obj.n_assets = keep
    f.plant.batch.n_drives = keep
    f.seeds = f.seeds[:keep]
    return f


if __name__ == "__main__":
    main()
