r"""Reports of a twin run: ``metrics.json``, ``report.md`` and the plots.

:func:`compute_metrics` turns a :class:`~kautztwin.twin.runtime.TwinRun`
into the metrics of the run (synchronisation of the updating and the static
twin, tracking, constraints, timings, sample sanitation); :func:`write_report`
writes them with the plots:

* ``outputs.png``: plant output against the twins' predictions, drift events
  and model versions marked (:func:`plot_outputs`);
* ``sync_fit.png``: rolling synchronisation fit over time with the threshold,
  the recovery windows, drift and re-identification events (:func:`plot_sync_fit`);
* ``tracking.png``: MPC tracking with the output, input and rate limits
  (:func:`plot_tracking`);
* ``timings.png``: MPC solve and update times (:func:`plot_timings`).

The rolling fit is the one of the synchronisation monitor: the fit percent
of the twin's monitored prediction over windows of ``monitor_window``
closed-loop samples every ``monitor_stride`` samples (samples flagged by the
sanitiser left out),

.. math:: \mathrm{fit} = 100\Big(1 - \frac{\|y - \hat y\|}{\|y - \bar y\|}\Big).

Size: over 600 lines because the metrics, the four plots and the Markdown
report of a run are written together and share their helpers.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from .._json import to_jsonable
from ..metrics import fit_percent_or_nan
from .runtime import TwinRun

if TYPE_CHECKING:  # pragma: no cover - typing only
    from matplotlib.axes import Axes

__all__ = [
    "compute_metrics",
    "plot_outputs",
    "plot_sync_fit",
    "plot_timings",
    "plot_tracking",
    "rolling_fit",
    "write_report",
]

_ACCEPTED = ("model-update",)


def rolling_fit(
    y: NDArray[np.float64], y_pred: NDArray[np.float64], window: int, stride: int, start: int = 0
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Fit percent of the windows ``[end - window, end)``, ``end = start + window, ... + stride``.

    Parameters
    ----------
    y, y_pred : ndarray of shape (n_samples,)
        Measured output (NaN where not usable) and prediction.
    window, stride : int
        Window length and spacing, samples.
    start : int, default=0
        First sample of the first window.

    Returns
    -------
    ends : ndarray of int
        Index one past the last sample of each window.
    fits : ndarray
        Fit percent of each window (NaN with fewer than 3 usable samples or no spread).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.report import rolling_fit
    >>> y = np.sin(np.arange(100) / 5.0)
    >>> ends, fits = rolling_fit(y, y + 0.01, 50, 25)
    >>> ends.tolist(), bool(np.all(fits > 98))
    ([50, 75, 100], True)
    """
    y = np.asarray(y, dtype=float)
    p = np.asarray(y_pred, dtype=float)
    ends, fits = [], []
    for end in range(start + window, y.size + 1, stride):
        a, b = y[end - window:end], p[end - window:end]
        fit = math.nan
        if np.count_nonzero(np.isfinite(a) & np.isfinite(b)) >= 3:
            fit = fit_percent_or_nan(a, b)
        ends.append(end)
        fits.append(fit)
    return np.asarray(ends, dtype=np.int64), np.asarray(fits, dtype=float)


def _stats(x: NDArray[np.float64]) -> dict[str, float | None]:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if not x.size:
        return {"median": None, "p99": None, "max": None, "n": 0}
    return {"median": float(np.median(x)), "p99": float(np.percentile(x, 99)),
            "max": float(np.max(x)), "n": int(x.size)}


def _num(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _fits(run: TwinRun) -> dict[str, Any]:
    cfg = run.config
    a = run.arrays
    k0 = run.k_closed_loop
    ends, f_twin = rolling_fit(a["y_clean"], a["y_pred"], cfg.monitor_window,
                               cfg.monitor_stride, k0)
    _, f_static = rolling_fit(a["y_clean"], a["y_pred_static"], cfg.monitor_window,
                              cfg.monitor_stride, k0)
    t_end = np.array([a["t"][e - 1] for e in ends]) if ends.size else np.zeros(0)
    return {"ends": ends, "t_end": t_end, "twin": f_twin, "static": f_static}


def _recovery_mask(t_end: NDArray, events: tuple[float, ...], window: float) -> NDArray[np.bool_]:
    mask = np.zeros(t_end.size, dtype=bool)
    for e in events:
        mask |= (t_end > e) & (t_end <= e + window)
    return mask


def compute_metrics(run: TwinRun) -> dict[str, Any]:
    """Metrics of a twin run (the content of ``metrics.json``).

    Parameters
    ----------
    run : TwinRun
        The record of the run.

    Returns
    -------
    dict
        JSON-ready.  Synchronisation: ``sync_fit_mean``, ``sync_fit_min``,
        ``sync_fit_min_after_recovery`` (outside the recovery windows),
        ``sync_fit_min_before_drift``, ``static_twin_sync_fit_mean``,
        ``static_twin_sync_fit_mean_after_drift``, ``recovery_s`` (per drift
        event: how long the fit stayed below the threshold).  Model:
        ``reidentifications`` (accepted new versions after the initial one),
        ``reidentification_attempts``, ``model_version``.  Control:
        ``tracking_iae`` (integral of ``|y - setpoint|`` over the closed loop),
        ``tracking_iae_reference`` (against the filtered reference),
        ``settled_error_max`` (largest mean error over the second half of a
        set-point segment), ``constraint_violations``, ``max_violation``,
        ``mpc_failures``.  Timings: ``mpc_solve_ms`` and ``update_ms`` (fast
        path only) with ``median``, ``p99``, ``max``; ``reidentification_ms``.
        Samples: counts of dropouts, outliers, late samples and more.
        ``acceptance``: the checks of the issue, each ``True``/``False``.
    """
    cfg = run.config
    a = run.arrays
    k0 = run.k_closed_loop
    n = run.n_done
    dt = cfg.dt
    fits = _fits(run)
    t_end, f_twin, f_static = fits["t_end"], fits["twin"], fits["static"]
    events = tuple(e for e in cfg.drift_events if e < (n * dt))
    rec = _recovery_mask(t_end, events, cfg.recovery_window)
    ok = np.isfinite(f_twin)
    outside = ok & ~rec
    before = ok & (t_end <= (events[0] if events else math.inf))
    after_drift = np.isfinite(f_static) & (t_end > (events[0] if events else math.inf))
    recovery = []
    bounds = (*events, math.inf)
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        sel = ok & (t_end > lo) & (t_end <= hi) & (f_twin < cfg.monitor_threshold)
        recovery.append(float(t_end[sel].max() - lo) if sel.any() else 0.0)

    def mean(x: NDArray, m: NDArray) -> float | None:
        return _num(float(np.mean(x[m]))) if m.any() else None

    def minimum(x: NDArray, m: NDArray) -> float | None:
        return _num(float(np.min(x[m]))) if m.any() else None

    static_ok = np.isfinite(f_static)
    out: dict[str, Any] = {
        "plant": cfg.plant, "plant_name": run.plant_name, "run_id": run.run_id,
        "status": run.status, "n_samples": n, "duration_s": n * dt, "dt": dt,
        "closed_loop_start_s": k0 * dt, "quick": cfg.quick,
        "sync_fit_mean": mean(f_twin, ok),
        "sync_fit_min": minimum(f_twin, ok),
        "sync_fit_min_after_recovery": minimum(f_twin, outside),
        "sync_fit_mean_after_recovery": mean(f_twin, outside),
        "sync_fit_min_before_drift": minimum(f_twin, before) if events else None,
        "static_twin_sync_fit_mean": mean(f_static, static_ok) if cfg.static_twin else None,
        "static_twin_sync_fit_min": minimum(f_static, static_ok) if cfg.static_twin else None,
        "static_twin_sync_fit_mean_after_drift": (
            mean(f_static, after_drift) if cfg.static_twin and events else None),
        "sync_threshold": cfg.monitor_threshold,
        "sync_window_s": cfg.monitor_window * dt,
        "recovery_window_s": cfg.recovery_window,
        "drift_events_s": list(events),
        "recovery_s": recovery[: len(events)],
    }
    accepted = [v for v in run.versions if v["version"] > 1]
    attempts = [e for e in run.events if e.kind in ("model-update", "model-rejected")
                and "elapsed" in e.payload]
    out.update({
        "reidentifications": len(accepted),
        "reidentification_attempts": int(run.counts.get("reidentification_attempts", 0)),
        "model_version": int(a["version"][-1]) if n else 0,
        "model_versions": [dict(v) for v in run.versions],
        "reidentification_ms": _stats(np.array([1e3 * e.payload["elapsed"] for e in attempts])),
        "estimator_retrainings": {
            "accepted": sum(e.kind == "estimator-update" for e in run.events),
            "rejected": sum(e.kind == "estimator-rejected" for e in run.events),
        },
    })
    # control
    cl = np.arange(n) >= k0
    if cfg.controlled and cl.any():
        mpc = cfg.mpc
        assert mpc is not None
        y, sp, ref, u = a["y_clean"], a["setpoint"], a["reference"], a["u"]
        err = np.abs(y - sp)
        out["tracking_iae"] = _num(float(np.nansum(err[cl])) * dt)
        out["tracking_iae_reference"] = _num(float(np.nansum(np.abs(y - ref)[cl])) * dt)
        settled = []
        values = cfg.setpoints
        for i, (ts, v) in enumerate(values):
            te = values[i + 1][0] if i + 1 < len(values) else n * dt
            ts = max(ts, k0 * dt)
            sel = cl & (a["t"] >= ts + 0.5 * (te - ts)) & (a["t"] < te)
            if sel.sum() > 2 and np.isfinite(y[sel]).any():
                settled.append(float(abs(np.nanmean(y[sel]) - v)))
        out["settled_error_max"] = max(settled) if settled else None
        tol = 1e-9
        du = np.diff(u, prepend=u[k0 - 1] if k0 > 0 else u[0])
        bad_u = (u > mpc.u_max + tol) | (u < mpc.u_min - tol)
        bad_du = np.abs(du) > mpc.du_max + tol
        bad_y = (y > mpc.y_max + tol) | (y < mpc.y_min - tol)
        viol = cl & (bad_u | bad_du | np.nan_to_num(bad_y, nan=False).astype(bool))
        over = np.concatenate([
            np.maximum(u - mpc.u_max, mpc.u_min - u)[cl], (np.abs(du) - mpc.du_max)[cl],
            np.nan_to_num(np.maximum(y - mpc.y_max, mpc.y_min - y), nan=-np.inf)[cl],
        ])
        out["constraint_violations"] = int(viol.sum())
        out["max_violation"] = _num(max(0.0, float(np.max(over)))) if over.size else 0.0
        out["limits"] = mpc.to_dict()
        out["mpc_failures"] = int(run.counts.get("mpc_failures", 0))
        out["controller_rebuilds"] = sum(e.kind == "controller" for e in run.events)
        out["controller_rejections"] = sum(e.kind == "controller-rejected" for e in run.events)
        out["mpc_weight_r"] = [t["r"] for t in run.tunings]
    else:
        out.update(tracking_iae=None, tracking_iae_reference=None, settled_error_max=None,
                   constraint_violations=0, max_violation=0.0, mpc_failures=0)
    out["mpc_solve_ms"] = _stats(a["mpc_ms"])
    out["update_ms"] = _stats(a["update_ms"])
    c = run.counts
    out["samples"] = {
        "total": int(c.get("total", n)), "clean": int(c.get("ok", 0)),
        "dropouts": int(c.get("dropout", 0)), "outliers": int(c.get("outlier", 0)),
        "clipped": int(c.get("clipped", 0)), "late": int(c.get("late", 0)),
        "skipped": int(c.get("held", 0)), "level_shifts": int(c.get("level_shift", 0)),
        "late_ticks": int(c.get("late_ticks", 0)),
    }
    out["identification"] = {key: v for key, v in run.identification.items()}
    out["resume"] = dict(run.resume)
    out["wall_time_s"] = run.wall_time
    out["store"] = run.store
    # acceptance checks of the issue
    acc: dict[str, Any] = {}
    if events and cfg.static_twin:
        smin = out["sync_fit_min_after_recovery"]
        acc["sync_fit_min_after_recovery_ge_95"] = smin is not None and smin >= 95.0
        st = out["static_twin_sync_fit_mean"]
        acc["static_twin_clearly_below"] = (
            st is not None and out["sync_fit_mean"] is not None
            and st < min(95.0, out["sync_fit_mean"] - 10.0))
        acc["recovery_within_window"] = all(r <= cfg.recovery_window for r in out["recovery_s"])
    if cfg.controlled:
        acc["zero_constraint_violations"] = out["constraint_violations"] == 0
    med = out["mpc_solve_ms"]["median"]
    if med is not None:
        acc["mpc_solve_median_lt_1ms"] = med < 1.0
    med = out["update_ms"]["median"]
    if med is not None:
        acc["update_median_lt_5ms"] = med < 5.0
    out["acceptance"] = acc
    return to_jsonable(out)


# --------------------------------------------------------------------------- plots
def _new_axes(ax: Axes | None, n: int = 1, height: float = 3.2) -> list[Axes]:
    if ax is not None:
        return [ax]
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, height * n), layout="constrained")
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    return list(axes)


def _mark_events(ax: Axes, run: TwinRun, *, label: bool = True) -> None:
    first_d = first_v = label
    for e in run.config.drift_events:
        if e <= run.n_done * run.config.dt:
            ax.axvline(e, color="tab:red", ls="--", lw=1.0,
                       label="drift event" if first_d else None)
            first_d = False
    for v in run.versions:
        if v["version"] > 1:
            ax.axvline(v["t"], color="tab:green", ls=":", lw=1.2,
                       label="new model version" if first_v else None)
            first_v = False


def plot_outputs(run: TwinRun, ax: Axes | None = None) -> Axes:
    """Plant output against the predictions of the updating and the static twin.

    Parameters
    ----------
    run : TwinRun
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    (ax,) = _new_axes(ax)
    a = run.arrays
    t = a["t"]
    ax.plot(t, a["y"], color="0.2", lw=0.8, label="plant (measured)")
    ax.plot(t, a["y_pred"], color="tab:blue", lw=0.8, label="updating twin")
    if run.config.static_twin:
        ax.plot(t, a["y_pred_static"], color="tab:orange", lw=0.8, alpha=0.8,
                label="static twin")
    y = a["y_clean"][np.isfinite(a["y_clean"])]
    if y.size:
        lo, hi = np.percentile(y, [0.5, 99.5])
        pad = 0.25 * (hi - lo) + 1e-9
        ax.set_ylim(lo - pad, hi + pad)
    ax.axvspan(t[0] if t.size else 0, run.k_closed_loop * run.config.dt, color="0.9",
               label="identification")
    _mark_events(ax, run)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("output")
    ax.set_title(f"{run.plant_name}: plant vs twin (monitored prediction)")
    ax.legend(fontsize="small", loc="best", ncols=2)
    return ax


def plot_sync_fit(run: TwinRun, ax: Axes | None = None) -> Axes:
    """Rolling synchronisation fit over time, recovery windows and events marked.

    Parameters
    ----------
    run : TwinRun
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    (ax,) = _new_axes(ax)
    cfg = run.config
    fits = _fits(run)
    t_end = fits["t_end"]
    ax.plot(t_end, fits["twin"], "o-", ms=2.5, color="tab:blue", label="updating twin")
    if cfg.static_twin:
        ax.plot(t_end, fits["static"], "s-", ms=2.0, color="tab:orange", label="static twin")
    ax.axhline(cfg.monitor_threshold, color="k", lw=0.8, label=f"{cfg.monitor_threshold:g} %")
    first = True
    for e in cfg.drift_events:
        if cfg.recovery_window > 0 and e <= run.n_done * cfg.dt:
            ax.axvspan(e, e + cfg.recovery_window, color="tab:red", alpha=0.08,
                       label="recovery window" if first else None)
            first = False
    _mark_events(ax, run)
    finite = np.concatenate([fits["twin"][np.isfinite(fits["twin"])], [cfg.monitor_threshold]])
    lo = max(float(np.min(finite)) - 5.0, -100.0)
    ax.set_ylim(lo, 101.0)
    ax.set_xlabel("time (end of window) [s]")
    ax.set_ylabel("fit [%]")
    ax.set_title(f"rolling fit over {cfg.monitor_window * cfg.dt:g} s windows "
                 "(values below the axis are clipped)")
    ax.legend(fontsize="small", loc="lower left", ncols=3)
    return ax


def plot_tracking(run: TwinRun, ax: Axes | None = None) -> Axes:
    """MPC tracking: output with set-point and limits, input and rate with limits.

    With ``ax`` only the output panel is drawn there; without, a figure with
    three panels (output, input, input change) is made and its first axes returned.

    Parameters
    ----------
    run : TwinRun
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    cfg = run.config
    axes = _new_axes(ax, 1 if ax is not None else 3, 2.6)
    a = run.arrays
    k0 = run.k_closed_loop
    t = a["t"]
    mpc = cfg.mpc
    ax0 = axes[0]
    ax0.plot(t, a["y"], color="0.2", lw=0.7, label="output")
    if cfg.controlled:
        ax0.plot(t[k0:], a["setpoint"][k0:], color="tab:red", lw=1.2, label="set-point")
        ax0.plot(t[k0:], a["reference"][k0:], color="tab:purple", lw=0.8, ls="--",
                 label="reference (filtered)")
        assert mpc is not None
        for lim in (mpc.y_min, mpc.y_max):
            if math.isfinite(lim):
                ax0.axhline(lim, color="k", ls="-.", lw=0.8)
    y = a["y_clean"][np.isfinite(a["y_clean"])]
    if y.size:
        lo, hi = np.percentile(y, [0.5, 99.5])
        pad = 0.3 * (hi - lo) + 1e-9
        ax0.set_ylim(lo - pad, hi + pad)
    ax0.set_ylabel("output")
    ax0.set_title("MPC tracking (limits dash-dotted)")
    ax0.legend(fontsize="small", loc="best", ncols=3)
    if len(axes) == 3:
        ax1, ax2 = axes[1], axes[2]
        ax1.plot(t, a["u"], color="tab:blue", lw=0.7, label="applied input u = v + dither")
        if cfg.controlled:
            ax1.plot(t[k0:], a["command"][k0:], color="tab:green", lw=0.9, label="MPC command v")
            assert mpc is not None
            ax1.axhline(mpc.u_min, color="k", ls="-.", lw=0.8, label="input limits")
            ax1.axhline(mpc.u_max, color="k", ls="-.", lw=0.8)
        ax1.set_ylabel("input")
        ax1.legend(fontsize="small", loc="best", ncols=3)
        du = np.diff(a["u"], prepend=a["u"][0]) if a["u"].size else a["u"]
        ax2.plot(t, du, color="tab:blue", lw=0.7, label="input change per sample")
        if cfg.controlled:
            assert mpc is not None
            ax2.axhline(mpc.du_max, color="k", ls="-.", lw=0.8, label="rate limits")
            ax2.axhline(-mpc.du_max, color="k", ls="-.", lw=0.8)
        ax2.set_ylabel("delta u")
        ax2.set_xlabel("time [s]")
        ax2.legend(fontsize="small", loc="best")
    else:
        ax0.set_xlabel("time [s]")
    return ax0


def plot_timings(run: TwinRun, ax: Axes | None = None) -> Axes:
    """Distribution of the MPC solve times and of the update (fast path) times.

    Parameters
    ----------
    run : TwinRun
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    (ax,) = _new_axes(ax, 1, 3.6)
    a = run.arrays
    for name, label, color in (("mpc_ms", "MPC solve", "tab:blue"),
                               ("update_ms", "update (fast path)", "tab:orange")):
        x = a[name][np.isfinite(a[name])]
        x = x[x > 0]
        if not x.size:
            continue
        bins = np.logspace(np.log10(x.min()), np.log10(x.max()) + 1e-9, 50)
        med = float(np.median(x))
        ax.hist(x, bins=bins, alpha=0.6, color=color,
                label=f"{label}: median {med:.3f} ms, p99 {np.percentile(x, 99):.3f} ms")
        ax.axvline(med, color=color, lw=1.2)
    ax.set_xscale("log")
    ax.set_xlabel("time per sample [ms]")
    ax.set_ylabel("samples")
    ax.set_title("computation per sample")
    ax.legend(fontsize="small", loc="best")
    return ax


# --------------------------------------------------------------------------- files
def _fmt(x: Any, digits: int = 2) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.{digits}f}"
    return str(x)


def _markdown(metrics: dict[str, Any], run: TwinRun, plots: dict[str, str],
              command: str | None) -> str:
    cfg = run.config
    m = metrics
    lines = [f"# Digital twin run: {run.plant_name}", ""]
    if command:
        lines += ["```bash", command, "```", ""]
    lines += [
        f"- status: **{run.status}**, {m['n_samples']} samples of {cfg.dt:g} s "
        f"({m['duration_s']:.1f} s); closed loop from {m['closed_loop_start_s']:.1f} s",
        f"- history store: `{run.store}` (run {run.run_id})",
        f"- wall time of this process: {m['wall_time_s']:.1f} s",
    ]
    res = m["resume"]
    if res.get("resumed"):
        lines.append(f"- **resumed** after {res['resume_k']} committed samples (replayed; "
                     f"{res['replay_mismatches']} mismatches with the store)")
    ident = m.get("identification") or {}
    if ident:
        poles = ", ".join(f"{p:.3g}" for p in ident.get("continuous_poles", []))
        lines.append(f"- initial identification: fit {_fmt(ident.get('fit_percent'))} % on "
                     f"{ident.get('n_samples')} samples, poles {poles} 1/s")
    lines += ["", "## Acceptance checks", "", "| check | result |", "|---|---|"]
    for key, val in m["acceptance"].items():
        lines.append(f"| {key.replace('_', ' ')} | {'PASS' if val else 'FAIL'} |")
    lines += ["", "## Metrics", "", "| metric | value |", "|---|---|"]
    rows = [
        ("sync fit mean (updating twin) [%]", m["sync_fit_mean"]),
        ("sync fit min outside recovery windows [%]", m["sync_fit_min_after_recovery"]),
        ("static twin sync fit mean [%]", m["static_twin_sync_fit_mean"]),
        ("static twin sync fit mean after the first drift [%]",
         m["static_twin_sync_fit_mean_after_drift"]),
        ("recovery window [s]", m["recovery_window_s"]),
        ("drift events [s]", ", ".join(f"{e:g}" for e in m["drift_events_s"]) or "none"),
        ("time below threshold after each event [s]",
         ", ".join(f"{r:.2f}" for r in m["recovery_s"]) or "n/a"),
        ("re-identifications (accepted versions)", m["reidentifications"]),
        ("re-identification attempts", m["reidentification_attempts"]),
        ("tracking IAE", m["tracking_iae"]),
        ("tracking IAE against the filtered reference", m["tracking_iae_reference"]),
        ("largest settled set-point error", m["settled_error_max"]),
        ("constraint violations", m["constraint_violations"]),
        ("MPC solve median / p99 [ms]",
         f"{_fmt(m['mpc_solve_ms']['median'], 3)} / {_fmt(m['mpc_solve_ms']['p99'], 3)}"),
        ("update (fast path) median / p99 [ms]",
         f"{_fmt(m['update_ms']['median'], 3)} / {_fmt(m['update_ms']['p99'], 3)}"),
    ]
    for name, val in rows:
        lines.append(f"| {name} | {_fmt(val)} |")
    s = m["samples"]
    lines += [
        "", "## Samples", "",
        f"{s['total']} samples: {s['clean']} clean, {s['dropouts']} dropouts (NaN), "
        f"{s['outliers']} outliers ({s['clipped']} clipped), {s['late']} late, "
        f"{s['skipped']} skipped, {s['level_shifts']} level shifts, "
        f"{s['late_ticks']} late clock ticks.  A skipped or outlying sample is not used by "
        "the update module; the controller uses the twin's prediction in its place.",
        "", "## Events", "",
    ]
    shown = ("phase", "drift", "resume", "model-version", "controller", "controller-rejected")
    last_sync = None
    for e in run.events:
        if e.kind in ("desync", "resync"):
            if e.kind == last_sync:
                continue
            last_sync = e.kind
        elif e.kind not in shown:
            continue
        lines.append(f"- {e.t:9.2f} s  **{e.kind}**: {e.message}")
    lines += ["", "## Plots", ""]
    for title, name in plots.items():
        lines += [f"### {title}", "", f"![{title}]({name})", ""]
    lines += [
        "## Notes", "",
        "- The sync fit is the fit percent of each twin's monitored prediction "
        f"(parameters frozen over {cfg.monitor_stride} samples, no output feedback) over "
        f"windows of {cfg.monitor_window} samples every {cfg.monitor_stride} samples of the "
        "closed loop; the static twin is the initial model run on the same samples with "
        "its updates disabled.",
        f"- Recovery window: {cfg.recovery_window:g} s from the start of each drift event; "
        "the minimum fit outside these windows is `sync_fit_min_after_recovery`.",
        f"- The controller's command carries a binary excitation dither of +-{cfg.dither:g} "
        "(its predicted response is removed from the controller's feedback) so that the twin "
        "stays identifiable in closed loop; the tracking IAE includes its ripple.",
        "",
    ]
    return "\n".join(lines)


def write_report(
    run: TwinRun, out_dir: str | os.PathLike[str], *, command: str | None = None,
    plots: bool = True, dpi: int = 110,
) -> dict[str, Path]:
    """Write ``metrics.json``, ``report.md`` and the plots of a run.

    Parameters
    ----------
    run : TwinRun
        The record of the run.
    out_dir : str or os.PathLike
        Folder (created if missing).
    command : str, optional
        The command line that made the run (quoted in the report).
    plots : bool, default=True
        Write the four PNG plots.
    dpi : int, default=110
        Resolution of the plots.

    Returns
    -------
    dict of str to Path
        ``metrics``, ``report`` and one entry per plot.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = compute_metrics(run)
    paths: dict[str, Path] = {}
    names: dict[str, str] = {}
    if plots:
        for key, title, func in (
            ("outputs", "Plant vs twin output", plot_outputs),
            ("sync_fit", "Synchronisation fit over time", plot_sync_fit),
            ("tracking", "MPC tracking with constraints", plot_tracking),
            ("timings", "Solve and update times", plot_timings),
        ):
            ax = func(run)
            path = out / f"{key}.png"
            ax.figure.savefig(path, dpi=dpi)
            paths[key] = path
            names[title] = path.name
    metrics_path = out / "metrics.json"
    metrics_path.write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n",
                            encoding="utf-8")
    report_path = out / "report.md"
    report_path.write_text(_markdown(metrics, run, names, command), encoding="utf-8")
    paths["metrics"] = metrics_path
    paths["report"] = report_path
    return paths
