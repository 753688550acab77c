r"""A simulated fleet of hydraulic drives: parameter spread, individual drift, summary, plots.

:func:`hydraulic_fleet` draws ``n_assets`` drives around the nominal
:class:`~kautztwin.simulators.hydraulic.HydraulicParameters` (each of
inertia, leakage, bulk modulus, oil volume, valve time constant and load
damping scaled by a log-normal factor of standard deviation ``spread``), an
initial oil temperature, and a drift of the dominant pole by a fraction
drawn uniformly from ``[0, drift_spread]`` starting at a random time of the
closed-loop phase (a 2 s temperature ramp).  :func:`summarize` turns a
:class:`~.step.FleetRun` into fleet metrics; :func:`plot_fleet` draws them.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._validation import check_int, check_memory, check_nonnegative
from ...exceptions import DataError
from ...simulators.hydraulic import HydraulicParameters
from ..physical import HydraulicPlant, TemperatureSchedule
from ..physical.simulated import temperature_for_pole_ratio
from ..runtime import TwinConfig
from .plants import HydraulicFleetPlant
from .step import FleetRun

__all__ = ["bytes_per_asset", "distribution", "hydraulic_fleet", "plot_fleet", "summarize"]

_SPREAD_FIELDS = ("inertia", "leakage", "bulk_modulus", "volume", "valve_time_constant",
                  "load_damping")


def bytes_per_asset(config: TwinConfig, *, record: bool) -> float:
    """Estimated memory of one asset of a fleet run (state, histories, records), bytes.

    Parameters
    ----------
    config : TwinConfig
    record : bool
        Whether the per-sample arrays are kept.

    Returns
    -------
    float
    """
    from .step import history_length

    n_s = config.n_samples
    state = 40_000.0  # QP rows, filters, RLS, monitor and sanitiser windows, buffers, objects
    history = 8.0 * history_length(config) + n_s + 16.0 * config.n_ident  # commands, dither
    return state + history + (7 * 8.0 * n_s if record else 0.0)


def hydraulic_fleet(
    n_assets: int, config: TwinConfig, *, spread: float = 0.05, drift_spread: float = 0.3,
    noise: float = 0.01, seed: int = 0, looped: bool = False, record: bool = True,
    indices: Any = None,
) -> tuple[Any, list[dict[str, float]]]:
    """The plants of a simulated hydraulic fleet and each asset's drawn parameters.

    Parameters
    ----------
    n_assets : int
        Number of drives (``>= 1``).
    config : TwinConfig
        The run (its duration and closed-loop phase place the drifts).
    spread : float, default=0.05
        Log-normal standard deviation of the parameter factors.
    drift_spread : float, default=0.3
        Largest relative drift of an asset's dominant pole (uniform in ``[0, drift_spread]``).
    noise : float, default=0.01
        Sensor noise, rad/s.
    seed : int, default=0
        Seed of the draw and of the noise.
    looped : bool, default=False
        Scalar :class:`~kautztwin.twin.HydraulicPlant` objects in a loop
        (:class:`~.plants.LoopedFleetPlant`) instead of the batched simulation.
    record : bool, default=True
        Only for the memory check: whether the run keeps its per-sample arrays.
    indices : array-like of int, optional
        Build only these assets of the fleet (a shard): their draws, plants
        and noise are those they have in the whole fleet.

    Returns
    -------
    plant : HydraulicFleetPlant or LoopedFleetPlant
    assets : list of dict
        ``temperature``, ``drift``, ``drift_time`` and the parameter factors per asset.

    Raises
    ------
    DataError
        If ``n_assets`` is not a positive integer, a spread is negative or
        ``drift_spread >= 0.9``, or the fleet would not fit in memory.
    """
    n = check_int(n_assets, "n_assets", 1)
    spread = check_nonnegative(spread, "spread")
    drift_spread = check_nonnegative(drift_spread, "drift_spread")
    if drift_spread >= 0.9:
        raise DataError(f"drift_spread must be < 0.9, got {drift_spread:g}")
    n_sel = n if indices is None else int(np.size(indices))
    check_memory(n_sel * bytes_per_asset(config, record=record), f"--assets {n_sel}")
    sel = np.arange(n) if indices is None else np.asarray(indices, dtype=np.intp).reshape(-1)
    if sel.size == 0 or sel.min() < 0 or sel.max() >= n or np.unique(sel).size != sel.size:
        raise DataError(f"indices must select distinct assets in [0, {n})")
    wanted = set(sel.tolist())
    rng = np.random.default_rng([seed, 4242])
    params: list[HydraulicParameters] = []
    temps: list[Any] = []
    info: list[dict[str, float]] = []
    t_cl, t_end = config.ident_duration, config.duration
    nominal = HydraulicParameters()
    ratio_cache: dict[tuple[float, float], float] = {}
    for i in range(n):
        factors = np.exp(spread * rng.standard_normal(len(_SPREAD_FIELDS)))
        p = replace(nominal, **{f: getattr(nominal, f) * float(x)
                                for f, x in zip(_SPREAD_FIELDS, factors, strict=True)})
        T0 = float(np.round(rng.uniform(20.0, 30.0), 1))
        drift = float(np.round(rng.uniform(0.0, drift_spread), 2)) if drift_spread else 0.0
        t_d = float(np.round(rng.uniform(t_cl + 0.1 * (t_end - t_cl), t_cl + 0.5 * (t_end - t_cl))))
        if i not in wanted:
            continue
        params.append(p)
        if drift > 0:
            key = (T0, drift)
            if key not in ratio_cache:
                ratio_cache[key] = temperature_for_pole_ratio(1.0 - drift, base_temperature=T0)
            temps.append(TemperatureSchedule.steps([t_d], [T0, ratio_cache[key]], ramp_time=2.0))
        else:
            temps.append(T0)
        info.append({"temperature": T0, "drift": drift, "drift_time": t_d if drift else math.nan,
                     **{f: float(x) for f, x in zip(_SPREAD_FIELDS, factors, strict=True)}})
    pos = {i: j for j, i in enumerate(sorted(wanted))}  # the draws came in index order
    params = [params[pos[i]] for i in sel.tolist()]
    temps = [temps[pos[i]] for i in sel.tolist()]
    info = [info[pos[i]] for i in sel.tolist()]
    if looped:
        from ...simulators.hydraulic import HydraulicServoDrive
        from .plants import LoopedFleetPlant

        plants = [HydraulicPlant(HydraulicServoDrive(p), dt=config.dt, temperature=T,
                                 noise=noise, random_state=seed + int(i))
                  for i, p, T in zip(sel, params, temps, strict=True)]
        return LoopedFleetPlant(plants), info
    return HydraulicFleetPlant(params, temps, dt=config.dt, noise=noise, random_state=seed,
                               noise_index=sel, noise_size=n), info


def distribution(x: NDArray[np.float64]) -> dict[str, float | int]:
    """Count, extremes, percentiles (5, 25, 50, 75, 95) and mean of the finite values.

    Parameters
    ----------
    x : ndarray

    Returns
    -------
    dict
        ``{"n": 0}`` when none is finite.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.fleet.simulate import distribution
    >>> distribution(np.array([1.0, np.nan, 3.0]))["median"]
    2.0
    """
    f = np.asarray(x, dtype=float)
    f = f[np.isfinite(f)]
    if f.size == 0:
        return {"n": 0}
    q = np.percentile(f, [5, 25, 50, 75, 95])
    return {"n": int(f.size), "min": float(f.min()), "p5": float(q[0]), "p25": float(q[1]),
            "median": float(q[2]), "p75": float(q[3]), "p95": float(q[4]),
            "max": float(f.max()), "mean": float(f.mean())}


def summarize(run: FleetRun, assets: list[dict[str, float]] | None = None) -> dict[str, Any]:
    """Fleet metrics of a run: fit distribution, re-identifications, violations, tracking.

    Parameters
    ----------
    run : FleetRun
    assets : list of dict, optional
        What :func:`hydraulic_fleet` drew (summarised alongside).

    Returns
    -------
    dict
        JSON-ready.
    """
    n = run.seeds.size
    cfg = run.config
    if run.fit_stats:
        last, mean, low = (run.fit_stats[key] for key in ("last", "mean", "min"))
    else:  # a merged or hand-made record: from the window fits
        last, mean, low = (np.full(n, math.nan) for _ in range(3))
        per: dict[int, list[float]] = {}
        for k, idx, f in run.fits:
            if k >= run.k_closed_loop:
                for i, v in zip(idx.tolist(), f.tolist(), strict=True):
                    per.setdefault(i, []).append(v)
        for i, vals in per.items():
            arr = np.asarray(vals)
            last[i], mean[i], low[i] = arr[-1], arr.mean(), arr.min()
    desync = np.zeros(n, dtype=np.int64)
    for a, k, kind, _ in run.events:
        if kind == "desync" and k >= run.k_closed_loop:
            desync[a] += 1

    dist = distribution
    out: dict[str, Any] = {
        "n_assets": int(n), "n_samples": int(run.n_done), "dt": cfg.dt,
        "k_closed_loop": int(run.k_closed_loop),
        "sync_fit_last": dist(last), "sync_fit_mean": dist(mean), "sync_fit_min": dist(low),
        "desync_events": {"total": int(desync.sum()), "assets": int((desync > 0).sum())},
        "reidentification": {
            "attempts": int(run.counts.get("reidentification_attempts", np.zeros(1)).sum()),
            "accepted": int(run.counts.get("reidentifications_accepted", np.zeros(1)).sum()),
            "assets_with_new_model": int(
                (run.counts.get("reidentifications_accepted", np.zeros(1)) > 0).sum()),
        },
        "mpc": {"failures": int(run.counts["mpc_failures"].sum()),
                "fallbacks_to_daqp": int(run.counts["mpc_fallbacks"].sum())},
        "flagged_samples": int(run.counts["flagged"].sum()),
        "wall_time_s": run.wall_time, "timings_s": dict(run.timings),
    }
    a = run.arrays
    if a and cfg.mpc is not None:
        cl = slice(run.k_closed_loop, run.n_done)
        y, u = a["y"][:, cl], a["u"][:, cl]
        du = np.diff(a["u"][:, run.k_closed_loop - 1: run.n_done], axis=1)
        tol = 1e-9
        y_out = (y < cfg.mpc.y_min) | (y > cfg.mpc.y_max)
        u_out = (u < cfg.mpc.u_min - tol) | (u > cfg.mpc.u_max + tol)
        du_out = np.abs(du) > cfg.mpc.du_max + tol
        err = y - a["reference"][:, cl]
        out["violations"] = {
            "output_samples": int(y_out.sum()), "input_samples": int(u_out.sum()),
            "rate_samples": int(du_out.sum()),
            "assets_with_any": int((y_out | u_out | du_out).any(axis=1).sum()),
        }
        out["tracking_rms"] = dist(np.sqrt(np.nanmean(err**2, axis=1)))
    elif "output_violations" in run.counts:  # no records: the counts kept during the run
        c = run.counts
        any_v = (c["output_violations"] + c["input_violations"] + c["rate_violations"]) > 0
        out["violations"] = {
            "output_samples": int(c["output_violations"].sum()),
            "input_samples": int(c["input_violations"].sum()),
            "rate_samples": int(c["rate_violations"].sum()),
            "assets_with_any": int(any_v.sum()),
        }
    if assets:
        out["drift"] = dist(np.array([d["drift"] for d in assets]))
    return out


def plot_fleet(run: FleetRun, path: str, *, max_traces: int = 20) -> None:
    """Plot a fleet run: fit distribution over time, final fits, a few outputs.

    Parameters
    ----------
    run : FleetRun
    path : str
        PNG file.
    max_traces : int, default=20
        Assets whose outputs are drawn.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 9))
    dt = run.config.dt
    ks = sorted({k for k, _, _ in run.fits if k >= run.k_closed_loop})
    by_k = {k: f for k, _, f in run.fits}
    if ks:
        t = np.array(ks) * dt
        q = np.array([np.percentile(by_k[k], [5, 50, 95]) for k in ks])
        ax = axes[0]
        ax.fill_between(t, q[:, 0], q[:, 2], alpha=0.3, label="5-95 %")
        ax.plot(t, q[:, 1], label="median")
        ax.axhline(run.config.monitor_threshold, color="k", ls="--", lw=0.8, label="threshold")
        ax.set_ylim(max(-100.0, float(np.nanmin(q[:, 0])) - 5), 101)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("sync fit [%]")
        ax.legend(loc="lower left")
    last = {}
    for _, idx, f in run.fits:
        for i, v in zip(idx.tolist(), f.tolist(), strict=True):
            last[i] = v
    if last:
        axes[1].hist(np.clip(list(last.values()), -100, 100), bins=30)
        axes[1].set_xlabel("last sync fit per asset [%]")
        axes[1].set_ylabel("assets")
    if run.arrays:
        y = run.arrays["y"]
        t = np.arange(y.shape[1]) * dt
        for i in range(min(max_traces, y.shape[0])):
            axes[2].plot(t, y[i], lw=0.6)
        axes[2].plot(t, run.arrays["reference"][0], "k--", lw=0.8, label="reference (asset 0)")
        axes[2].set_xlabel("t [s]")
        axes[2].set_ylabel("speed [rad/s]")
        axes[2].legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
