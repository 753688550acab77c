"""The physical side of a fleet: ``n_assets`` plants stepped together (batched or looped).

A fleet plant has ``n_assets``, ``dt``, ``reset() -> y`` and ``step(u) -> y``
on ``(n_assets,)`` arrays.  :class:`HydraulicFleetPlant` simulates N
hydraulic drives as one array
(:class:`~kautztwin.simulators.hydraulic.batch.HydraulicDriveBatch`);
:class:`LoopedFleetPlant` steps N ordinary
:class:`~kautztwin.twin.physical.Plant` objects one after the other (the
reference for the same-numbers test: the very plants a
:class:`~kautztwin.twin.runtime.DigitalTwin` would run).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...exceptions import DataError
from ...simulators.hydraulic import HydraulicParameters
from ...simulators.hydraulic.batch import HydraulicDriveBatch
from ..physical import Plant

__all__ = ["FleetPlant", "HydraulicFleetPlant", "LoopedFleetPlant"]


@runtime_checkable
class FleetPlant(Protocol):
    """What a fleet needs from its plants."""

    n_assets: int
    dt: float

    def reset(self) -> NDArray[np.float64]:
        """Start a run at ``t = 0``; the first outputs."""

    def step(self, u: NDArray[np.float64]) -> NDArray[np.float64]:
        """Hold ``u`` for one period; the next outputs."""


class LoopedFleetPlant:
    """N scalar plants behind the fleet-plant interface, stepped in a Python loop.

    Parameters
    ----------
    plants : sequence of Plant
        Plants of one sampling period.

    Raises
    ------
    DataError
        If the list is empty or the periods differ.

    Examples
    --------
    >>> from kautztwin.twin import HydraulicPlant
    >>> from kautztwin.twin.fleet import LoopedFleetPlant
    >>> fp = LoopedFleetPlant([HydraulicPlant(temperature=T) for T in (20.0, 40.0)])
    >>> fp.reset().shape, fp.step([0.5, 0.5]).shape
    ((2,), (2,))
    """

    def __init__(self, plants: Sequence[Plant]) -> None:
        self.plants = list(plants)
        if not self.plants:
            raise DataError("a fleet needs at least one plant")
        self.dt = float(self.plants[0].dt)
        if any(abs(float(p.dt) - self.dt) > 1e-12 * self.dt for p in self.plants):
            raise DataError("every plant of a fleet must sample at the same dt")
        self.n_assets = len(self.plants)
        self.drift_events = tuple(getattr(self.plants[0], "drift_events", ()))

    def reset(self) -> NDArray[np.float64]:
        """Reset every plant; the first outputs."""
        return np.array([float(p.reset().y) for p in self.plants])

    def step(self, u: ArrayLike) -> NDArray[np.float64]:
        """Step every plant with its input; the next outputs."""
        uu = np.asarray(u, dtype=float)
        return np.array([float(p.step(float(v)).y) for p, v in zip(self.plants, uu, strict=True)])

    def close(self) -> None:
        """Close every plant."""
        for p in self.plants:
            p.close()


class HydraulicFleetPlant:
    """N hydraulic drives simulated as one array (the fleet's batched physical side).

    Parameters
    ----------
    parameters : sequence of HydraulicParameters
        One per asset (their spread).
    temperature : sequence of float or callable
        Each asset's oil temperature, °C, constant or ``T(t)`` (e.g. a
        :class:`~kautztwin.twin.physical.TemperatureSchedule` for its drift).
    dt : float, default=0.02
    noise : float, default=0.0
        Sensor noise, rad/s.
    initial_command : float, default=0.5
    random_state : int or None, default=None
    n_substeps : int, default=8
        Runge-Kutta steps per period.
    drift_events : sequence of float, default=()
        Start times of drift events (for the metrics).
    noise_index, noise_size
        A shard of a larger fleet: the positions of these drives in it and
        its size (each drive gets the noise it gets in the whole fleet).
    """

    def __init__(
        self, parameters: Sequence[HydraulicParameters],
        temperature: Sequence[float | Callable[[float], float]], *, dt: float = 0.02,
        noise: float = 0.0, initial_command: float = 0.5, random_state: int | None = None,
        n_substeps: int = 8, drift_events: Sequence[float] = (),
        noise_index: ArrayLike | None = None, noise_size: int | None = None,
    ) -> None:
        self.batch = HydraulicDriveBatch(
            parameters, temperature, dt=dt, initial_command=initial_command, noise=noise,
            random_state=random_state, n_substeps=n_substeps, noise_index=noise_index,
            noise_size=noise_size)
        self.n_assets = self.batch.n_drives
        self.dt = self.batch.dt
        self.drift_events = tuple(float(e) for e in drift_events)

    def reset(self) -> NDArray[np.float64]:
        """Back to the equilibria at ``t = 0``; the first outputs."""
        return self.batch.reset()

    def step(self, u: ArrayLike) -> NDArray[np.float64]:
        """Hold the commands (clipped to ``[-1, 1]``) for one period; the next outputs."""
        return self.batch.step(np.clip(np.asarray(u, dtype=float), -1.0, 1.0))

    def close(self) -> None:
        """Nothing to release."""
