"""The set-point in force at each sample of a stored run.

A run's set-points come from its configured schedule (``config['twin']['setpoints']``),
from set-points written through the HTTP API while it ran (``api-setpoint`` events) and
from restarts (a ``resume`` event brings the configured schedule back).  Both readers of
a store, :func:`~kautztwin.twin.history.read_run` (``kautztwin twin history``) and the
service's ``GET /history``, rebuild the set-point column with these functions, so they
agree with each other and with the loop.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["control_start", "setpoint_segments", "setpoints_at"]


def control_start(config: Any) -> tuple[float, int]:
    """The sampling period and the first sample under control of a stored run.

    Parameters
    ----------
    config : dict
        The run's stored configuration (``{"twin": TwinConfig.to_dict(), ...}``).

    Returns
    -------
    dt : float
        Sampling period, s (0 when the configuration does not say).
    k_control : int
        The first sample after the identification phase (0 without one).

    Examples
    --------
    >>> control_start({"twin": {"dt": 0.02, "ident_duration": 5.0}})
    (0.02, 250)
    """
    twin = config.get("twin", {}) if isinstance(config, dict) else {}
    dt = float(twin.get("dt") or 0.0)
    k_control = (int(round(float(twin["ident_duration"]) / dt))
                 if dt > 0 and twin.get("ident_duration") is not None else 0)
    return dt, k_control


def setpoint_segments(config: Any, events: Any) -> list[tuple[int, NDArray[np.float64],
                                                                NDArray[np.float64]]]:
    """The set-point schedules of a run and the first sample each one is in force from.

    The configured schedule (``config['twin']['setpoints']``) holds from sample 0.  An
    ``api-setpoint`` event (``POST /setpoint``) replaces it from the event's ``k_from`` on as
    its job did in the loop: the entries before ``t - dt/2`` are kept and the new value holds
    from there.  A ``resume`` event (a restart, logged at the last committed sample) brings
    the configured schedule back: a set-point from the API lives in the running twin only.

    Parameters
    ----------
    config : dict
        The run's stored configuration (``{"twin": TwinConfig.to_dict(), ...}``).
    events : iterable of (str, int or None, float or None, object)
        ``(kind, k, t, payload)`` of the run's events in logging order; other kinds are
        ignored.

    Returns
    -------
    list of (int, ndarray, ndarray)
        ``(k_from, times, values)`` in increasing ``k_from``; empty schedules for a run
        without set-points.

    Examples
    --------
    >>> cfg = {"twin": {"dt": 0.5, "setpoints": [[0.0, 1.0], [10.0, 2.0]]}}
    >>> segs = setpoint_segments(cfg, [("api-setpoint", 4, 2.0, {"value": 5.0, "k_from": 4}),
    ...                                ("resume", 9, 123.4, {"last_k": 9})])
    >>> [(k, t.tolist(), v.tolist()) for k, t, v in segs]
    [(0, [0.0, 10.0], [1.0, 2.0]), (4, [0.0, 1.75], [1.0, 5.0]), (10, [0.0, 10.0], [1.0, 2.0])]
    >>> k = np.arange(12)
    >>> setpoints_at(segs, k, 0.5 * k, 0.5).tolist()
    [1.0, 1.0, 1.0, 1.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 1.0, 1.0]
    """
    twin = config.get("twin", {}) if isinstance(config, dict) else {}
    dt = float(twin.get("dt") or 0.0)
    base = sorted((float(t), float(v)) for t, v in (twin.get("setpoints") or []))
    schedule = list(base)
    segments = [(0, schedule)]
    for kind, k, t, payload in events:
        p = payload if isinstance(payload, dict) else {}
        if kind == "api-setpoint" and "value" in p and t is not None:
            k_from = int(p.get("k_from", k if k is not None else 0))
            t_from = float(t) - 0.5 * dt
            schedule = [e for e in schedule if e[0] < t_from] + [(t_from, float(p["value"]))]
            segments.append((k_from, schedule))
        elif kind == "resume":
            schedule = list(base)
            segments.append((0 if k is None else int(k) + 1, schedule))
    return [(k0, np.array([e[0] for e in sch], dtype=float),
             np.array([e[1] for e in sch], dtype=float)) for k0, sch in segments]


def setpoints_at(segments: list[tuple[int, NDArray[np.float64], NDArray[np.float64]]],
                 k: NDArray[Any], t: NDArray[np.float64], dt: float,
                 k_control: int = 0) -> NDArray[np.float64]:
    """The set-point in force at samples ``k`` (times ``t``), NaN without a schedule.

    Parameters
    ----------
    segments : list of (int, ndarray, ndarray)
        From :func:`setpoint_segments`.
    k : ndarray of int
        Sample indices.
    t : ndarray of float
        Their times, s.
    dt : float
        Sampling period, s (a schedule time within ``1e-9 dt`` after a sample counts as
        reached, as in :meth:`TwinConfig.setpoint <kautztwin.twin.runtime.TwinConfig.setpoint>`).
    k_control : int, default=0
        The first sample under control (the identification phase has no set-point: NaN).

    Returns
    -------
    ndarray of float
    """
    out = np.full(np.shape(t), math.nan)
    k = np.asarray(k)
    starts = np.array([s[0] for s in segments])
    which = np.searchsorted(starts, k, side="right") - 1
    for i, (_, times, values) in enumerate(segments):
        sel = (which == i) & (k >= k_control)
        if not values.size or not sel.any():
            continue
        j = np.searchsorted(times, t[sel] + 1e-9 * dt, side="right") - 1
        out[sel] = values[np.maximum(j, 0)]
    return out
