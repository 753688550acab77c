"""The plant interface of the twin: a reading, the :class:`Plant` protocol and open-loop runs.

The twin talks to the physical system through the small :class:`Plant`
protocol: it reads the output, applies an input for one sampling period and
reads again.

Timing convention
-----------------
:meth:`Plant.reset` returns the reading at ``t = 0`` (the first sample).
:meth:`Plant.step` holds ``u`` constant over one sampling period
``[t_k, t_k + dt)`` (zero-order hold, as a D/A converter does) and returns the
reading at ``t_{k+1}``.  The plants are strictly proper: ``y(t_{k+1})`` depends
on ``u`` up to ``u_k``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_number
from ...exceptions import DimensionError

__all__ = ["Plant", "PlantRun", "Reading", "run_open_loop"]


# --------------------------------------------------------------------------- readings
@dataclass(frozen=True, eq=False)
class Reading:
    """One measurement of a plant.

    Parameters
    ----------
    t : float
        Sample time in seconds since :meth:`Plant.reset` (a replay keeps the
        recorded times).
    y : float
        Measured output (NaN when a replayed record holds a dropout).
    meta : mapping, optional
        Plant-specific extras, read-only; every plant stores ``'u'``, the
        input applied over the period that ended at ``t`` (NaN for the
        reading of :meth:`Plant.reset`), and ``'k'``, the sample index.

    See Also
    --------
    Plant : The interface that produces readings.

    Examples
    --------
    >>> from kautztwin.twin.physical import Reading
    >>> r = Reading(0.5, 21.3, {"u": 40.0, "k": 1})
    >>> r.t, r.y, r.meta["u"]
    (0.5, 21.3, 40.0)
    """

    t: float
    y: float
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", float(self.t))
        object.__setattr__(self, "y", float(self.y))
        object.__setattr__(self, "meta", MappingProxyType(dict(self.meta)))


@runtime_checkable
class Plant(Protocol):
    """Interface of a physical system (simulated, emulated, real or replayed).

    Attributes
    ----------
    dt : float
        Sampling period, s.
    name : str
        Short human-readable name (for logs and reports).
    input_limits : tuple of float
        ``(low, high)`` bounds of the input; plants clip to them.

    See Also
    --------
    HydraulicPlant, TCLabPlant, ReplayPlant : The implementations.
    run_open_loop : Drive any plant with a known input sequence.
    """

    dt: float
    name: str
    input_limits: tuple[float, float]

    def reset(self) -> Reading:
        """Restart the run and return the reading at ``t = 0``.

        Returns
        -------
        Reading
        """
        ...

    def step(self, u: float | None) -> Reading:
        """Hold ``u`` for one sampling period and return the next reading.

        Parameters
        ----------
        u : float or None
            Input, clipped to :attr:`input_limits`; ``None`` is allowed only
            where a plant defines it (a replay follows its record).

        Returns
        -------
        Reading
        """
        ...

    def close(self) -> None:
        """Release the plant (a real device: heaters off, port closed)."""
        ...


def clip_input(u: Any, limits: tuple[float, float], name: str) -> float:
    """Return the input ``u`` of plant ``name`` as a finite float clipped to ``limits``.

    Parameters
    ----------
    u : Any
        The requested input.
    limits : (float, float)
        ``(low, high)`` input bounds of the plant.
    name : str
        Name of the plant, for the error message.

    Returns
    -------
    float

    Raises
    ------
    DataError
        If ``u`` is not a finite number.
    """
    value = check_number(u, f"u for {name}")
    return min(limits[1], max(limits[0], value))


# --------------------------------------------------------------------------- open loop
@dataclass(frozen=True, eq=False)
class PlantRun:
    """Samples of an open-loop run of a plant (see :func:`run_open_loop`).

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Sample times, s.
    u : ndarray of shape (n_samples,)
        Input applied from ``t[k]`` on (the last one is NaN: never applied).
    y : ndarray of shape (n_samples,)
        Measured output.
    readings : tuple of Reading
        The readings themselves (with their ``meta``).
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    readings: tuple[Reading, ...]

    def __post_init__(self) -> None:
        for name in ("t", "u", "y"):
            a = np.array(getattr(self, name), dtype=float, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def meta(self, key: str) -> NDArray[np.float64]:
        """One numeric ``meta`` entry of every reading as an array (NaN where missing).

        Parameters
        ----------
        key : str
            The entry, for example ``'y_true'`` or ``'temperature'``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return np.array([float(r.meta.get(key, math.nan)) for r in self.readings])


def run_open_loop(plant: Plant, u: ArrayLike) -> PlantRun:
    """Reset a plant, drive it with a known input sequence and collect the readings.

    Parameters
    ----------
    plant : Plant
        Any plant.
    u : array-like of shape (n_steps,)
        Finite inputs, one per step.

    Returns
    -------
    PlantRun
        ``n_steps + 1`` samples: the reading of :meth:`Plant.reset` and one per step.

    Raises
    ------
    DimensionError
        If ``u`` is not 1-D.

    Examples
    --------
    >>> from kautztwin.twin.physical import HydraulicPlant, run_open_loop
    >>> run = run_open_loop(HydraulicPlant(dt=0.05), [0.5] * 10)
    >>> run.y.shape
    (11,)
    """
    u = np.atleast_1d(np.asarray(u, dtype=float))
    if u.ndim != 1:
        raise DimensionError(f"u must be 1-D, got shape {u.shape}")
    readings = [plant.reset()]
    readings += [plant.step(float(v)) for v in u]
    return PlantRun(
        t=np.array([r.t for r in readings]),
        u=np.append(u, math.nan),
        y=np.array([r.y for r in readings]),
        readings=tuple(readings),
    )
