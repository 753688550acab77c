"""Plant construction from a command-line name: :func:`make_plant` (hydraulic, tclab, replay)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ...exceptions import DataError
from .base import Plant
from .replay import ReplayPlant
from .simulated import HydraulicPlant
from .tclab import TCLabPlant

__all__ = ["make_plant"]


def make_plant(
    spec: str,
    *,
    drift: float = 0.0,
    drift_events: Sequence[float] = (),
    seed: int = 0,
    noise: float | None = None,
) -> Plant:
    """Build a plant from its command-line name.

    Parameters
    ----------
    spec : str
        ``'hydraulic'``, ``'tclab'`` (the emulator) or ``'replay:FILE'``.
    drift : float, default=0.0
        Hydraulic only: total relative drift of the dominant pole over ``drift_events``.
    drift_events : sequence of float, default=()
        Hydraulic only: start times of the drift steps, s.
    seed : int, default=0
        Seed of the sensor noise.
    noise : float, optional
        Sensor noise (plant default when omitted: 0.01 rad/s, tclab's 0.043 °C).

    Returns
    -------
    Plant

    Raises
    ------
    DataError
        On an unknown name, a drift for another plant, or an unreadable record.
    """
    kind, _, arg = spec.partition(":")
    kind = kind.strip().lower()
    if kind != "hydraulic" and drift:
        raise DataError(f"drift applies to the hydraulic plant only, not to {spec!r}")
    if kind == "hydraulic":
        kwargs: dict[str, Any] = dict(dt=0.02, noise=0.01 if noise is None else noise,
                                      random_state=seed + 1)
        if drift:
            if not drift_events:
                raise DataError("a drift needs at least one event time")
            return HydraulicPlant.with_pole_drift(
                drift, events=tuple(drift_events), ramp_time=2.0, base_temperature=20.0, **kwargs
            )
        return HydraulicPlant(temperature=20.0, **kwargs)
    if kind == "tclab":
        kwargs = {} if noise is None else {"noise": noise}
        return TCLabPlant(dt=1.0, random_state=seed, **kwargs)
    if kind == "replay":
        if not arg:
            raise DataError("replay needs a file: --plant replay:FILE.csv")
        return ReplayPlant.from_csv(arg)
    raise DataError(f"unknown plant {spec!r}; use hydraulic, tclab or replay:FILE")
