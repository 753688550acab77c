"""The twins born at the end of the identification phase: the updating twin and the static one.

:func:`identify_initial` identifies the first model from the open-loop
samples; :func:`make_twins` builds on it the update module the twin runs
(:class:`~kautztwin.twin.Updater`) and, for comparison, the **static twin**:
the same initial model with its updates disabled, stepped on the same
samples, whose predictions and rolling fit show what the updates gain.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...exceptions import DataError
from ..physical import SampleSanitizer
from ..update import OutputErrorFit, SyncMonitor, Updater, identify_output_error
from .config import TwinConfig
from .protocols import TwinError

__all__ = [
    "catch_up",
    "identification_info",
    "identify_initial",
    "make_monitor",
    "make_sanitizer",
    "make_twins",
]

_STATIC_OPTIONS = ("buffer_size", "burn_in", "reid_samples")


def make_sanitizer(config: TwinConfig) -> SampleSanitizer:
    """The sample sanitiser of the configuration."""
    return SampleSanitizer(
        threshold=config.sanitizer_threshold, window=config.sanitizer_window,
        min_scale=config.sensor_scale,
    )


def make_monitor(config: TwinConfig) -> SyncMonitor:
    """The synchronisation monitor of the configuration."""
    cfg = config
    return SyncMonitor(window=cfg.monitor_window, stride=cfg.monitor_stride,
                       threshold=cfg.monitor_threshold, n_consecutive=cfg.monitor_consecutive,
                       resync_margin=cfg.monitor_resync_margin)


def identify_initial(config: TwinConfig, u: NDArray, y: NDArray) -> OutputErrorFit:
    """The initial model from the identification samples ``u, y`` (NaN where unusable).

    Raises
    ------
    TwinError
        If the identification fails.
    """
    cfg = config
    try:
        return identify_output_error(
            u, y, cfg.n_poles, dt=cfg.dt, input_offset=cfg.operating_input,
            min_rate=cfg.min_rate,
        )
    except (DataError, ValueError) as exc:
        raise TwinError(f"the initial identification failed: {exc}") from exc


def make_twins(
    fit: OutputErrorFit, config: TwinConfig, *, background: bool, estimator: Any = None
) -> tuple[Updater, Updater | None, NDArray[np.float64]]:
    """The updating twin, the static twin (``None`` unless ``config.static_twin``) and the rates.

    Parameters
    ----------
    fit : OutputErrorFit
        The initial identification.
    config : TwinConfig
        The run.
    background : bool
        Re-identify in the update module's worker thread.
    estimator : object, optional
        The DNN estimator of the update module's step-test fast path.

    Returns
    -------
    updater : Updater
    static : Updater or None
    rates : ndarray
        Continuous-time rates ``log|p| / dt`` of the identified poles, 1/s.
    """
    cfg = config
    rates = np.log(np.maximum(np.abs(fit.model.poles), 1e-12)) / cfg.dt
    slowest = float(np.max(rates))
    extra = [cfg.extra_pole_factor * slowest] if cfg.extra_pole_factor > 0 else None
    kw = dict(cfg.updater)
    kw.setdefault("min_rate", cfg.min_rate if cfg.min_rate is not None else -0.5 * slowest)
    kw["background"] = background
    if estimator is not None:
        kw["estimator"] = estimator
    updater = Updater.from_fit(
        fit, dt=cfg.dt, forgetting=cfg.forgetting, extra_poles=extra,
        monitor=make_monitor(cfg), sanitizer=make_sanitizer(cfg), **kw,
    )
    static = None
    if cfg.static_twin:
        static = Updater.from_fit(
            fit, dt=cfg.dt, fast_update=False, reidentify=False,
            monitor=make_monitor(cfg), sanitizer=make_sanitizer(cfg),
            **{key: val for key, val in kw.items() if key in _STATIC_OPTIONS},
        )
    return updater, static, rates


def catch_up(
    updater: Updater, static: Updater | None, arrays: dict[str, NDArray[Any]], k: int,
    start: int = 0,
) -> None:
    """Step both twins through the samples ``start .. k-1`` (their predictions kept).

    At the twin's birth, the samples before it (``start=0``); a live plant's
    twin born in the background takes them a slice at a time (:mod:`.birth`).
    """
    a = arrays
    for j in range(start, k):
        r = updater.step(a["u"][j], a["y"][j], a["t"][j])
        a["y_pred"][j] = r.y_pred_frozen
        if static is not None:
            rs = static.step(a["u"][j], a["y"][j], a["t"][j])
            a["y_pred_static"][j] = rs.y_pred_frozen


def identification_info(
    fit: OutputErrorFit, rates: NDArray[np.float64], k: int, start: float,
    k_twin: int | None = None, tuning_point: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """The ``identification`` of a TwinRun.

    ``k``: the samples identified; ``start``: ``time.perf_counter()`` when the
    fit started; ``k_twin``: the sample at which the twin was built (``k``
    unless a live plant's twin was built in the background, see :mod:`.birth`),
    and then ``tuning_point``: the ``(u_op, y_op)`` its first controller was
    tuned at.
    """
    info = {
        "fit_percent": fit.fit_percent, "offset": fit.offset,
        "poles": [[float(p.real), float(p.imag)] for p in fit.model.poles],
        "continuous_poles": [float(r) for r in np.sort(rates)],
        "n_samples": int(k), "k_twin": int(k if k_twin is None else k_twin),
        "elapsed": time.perf_counter() - start,
    }
    if tuning_point is not None:
        info["tuning_point"] = [float(tuning_point[0]), float(tuning_point[1])]
    return info
