r"""Many hydraulic drives as one array simulation: :class:`HydraulicDriveBatch`.

A fleet of drives of one type (each with its own :class:`HydraulicParameters`
and oil-temperature schedule) is integrated together: the states of all
drives form one ``(n_drives, 3)`` array and one classical fourth-order
Runge-Kutta step with ``n_substeps`` sub-steps per sampling period advances
them all.  The equations are those of :class:`HydraulicServoDrive` (the scaled
model of :mod:`.drive`); this module holds their array form, because the
scalar right-hand side there branches on Python floats:

* :func:`coefficient_arrays` is :class:`~kautztwin.simulators.hydraulic.drive._Coefficients`
  for arrays of parameters and temperatures (``tests/test_fleet.py`` checks
  it against the scalar class to rounding);
* :func:`rhs_batch` is the scaled right-hand side ``_rhs`` for arrays of
  states, reusing the regularised orifice law ``_orifice`` of :mod:`.drive`.

Equilibria (the initial states) come from the scalar drive
(:meth:`HydraulicServoDrive.equilibrium`).  The scalar plant integrates with
LSODA at ``rtol = 1e-8``; the fixed-step integrator here agrees with it to
about ``1e-6`` rad/s at the default ``n_substeps = 8`` on ``dt = 0.02`` s
(the fastest pole of the drive is about 40 /s, so ``h |p|`` stays near 0.1).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_int, check_nonnegative, check_positive
from ...exceptions import DataError, DimensionError
from .drive import HydraulicServoDrive, _orifice
from .parameters import TEMPERATURE_RANGE, HydraulicParameters, walther_viscosity

__all__ = ["HydraulicDriveBatch", "coefficient_arrays", "rhs_batch"]

_FIELDS = ("tau", "kq", "lam", "m", "b", "c", "wc", "eps2")


def _param_arrays(params: Sequence[HydraulicParameters]) -> dict[str, NDArray[np.float64]]:
    names = HydraulicParameters.__dataclass_fields__
    return {n: np.array([float(getattr(p, n)) for p in params]) for n in names}


def coefficient_arrays(
    params: Sequence[HydraulicParameters] | dict[str, NDArray[np.float64]],
    temperature: ArrayLike,
) -> dict[str, NDArray[np.float64]]:
    """Coefficients of the scaled drive model for arrays of drives and temperatures.

    The array form of the scalar model's coefficients (:mod:`.drive`): the
    same formulas (:meth:`HydraulicParameters.at_temperature`, Walther
    viscosity) evaluated for every drive at once.

    Parameters
    ----------
    params : sequence of HydraulicParameters, or dict of arrays
        One parameter set per drive (or their fields as arrays of shape ``(n,)``).
    temperature : array-like of shape (n,) or float
        Oil temperature of each drive, °C.

    Returns
    -------
    dict of str to ndarray of shape (n,)
        ``tau, kq, lam, m, b, c, wc, eps2`` (rates in 1/s).

    Raises
    ------
    DataError
        If a temperature is outside the model's range.
    """
    p = params if isinstance(params, dict) else _param_arrays(params)
    T = np.broadcast_to(np.asarray(temperature, dtype=float), p["inertia"].shape)
    lo, hi = TEMPERATURE_RANGE
    if not np.all((T >= lo) & (T <= hi)):
        raise DataError(f"temperatures must lie in [{lo:g}, {hi:g}] °C")
    v40, v100 = p["viscosity_40"], p["viscosity_100"]
    nu = np.empty_like(T)
    for a, b in {(float(x), float(y)) for x, y in zip(v40, v100, strict=True)}:
        sel = (v40 == a) & (v100 == b)
        nu[sel] = walther_viscosity(T[sel], a, b)
    ratio = nu / v40
    leakage = p["leakage"] / ratio
    damping = p["viscous_friction"] * ratio + p["load_damping"]
    bulk = p["bulk_modulus"] * (1 - p["bulk_modulus_slope"] * (T - 40.0))
    qmax = p["discharge_coefficient"] * p["area_gradient"] * p["spool_stroke"] * np.sqrt(
        p["supply_pressure"] / p["density"])
    w_nl = qmax / p["displacement"]
    return {
        "tau": p["valve_time_constant"].copy(),
        "kq": 4.0 * bulk * qmax / (p["volume"] * p["supply_pressure"]),
        "lam": leakage * p["supply_pressure"] / qmax,
        "m": p["displacement"] * p["supply_pressure"] / (p["inertia"] * w_nl),
        "b": damping / p["inertia"],
        "c": p["coulomb_friction"] / (p["inertia"] * w_nl),
        "wc": p["coulomb_speed"] / w_nl,
        "eps2": (p["transition_pressure"] / p["supply_pressure"]) ** 2,
    }


def rhs_batch(
    z: NDArray[np.float64], v: NDArray[np.float64], c: dict[str, NDArray[np.float64]]
) -> NDArray[np.float64]:
    """Time derivative of the scaled states of many drives (the array form of ``_rhs``).

    Parameters
    ----------
    z : ndarray of shape (n, 3)
        Scaled states ``(xi, pi, w)``.
    v : ndarray of shape (n,)
        Saturated valve commands.
    c : dict of ndarray
        :func:`coefficient_arrays`.

    Returns
    -------
    ndarray of shape (n, 3)
    """
    xi, pi, w = z[:, 0], z[:, 1], z[:, 2]
    f, _ = _orifice(1.0 - np.sign(xi) * pi, c["eps2"])
    out = np.empty_like(z)
    out[:, 0] = (v - xi) / c["tau"]
    out[:, 1] = c["kq"] * (xi * f - w - c["lam"] * pi)
    fric = c["c"] * np.tanh(w / c["wc"])
    out[:, 2] = c["m"] * pi - c["b"] * w - fric
    return out


def _piecewise(
    temps: Sequence[object], idx: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]] | None:
    """Padded breakpoints of piecewise-linear schedules (``times``/``temperatures``), else None."""
    if idx.size == 0:
        return None
    sched = [temps[i] for i in idx]
    if not all(hasattr(s, "times") and hasattr(s, "temperatures") for s in sched):
        return None
    n = max(len(s.times) for s in sched)  # type: ignore[attr-defined]
    times = np.full((idx.size, n), np.inf)
    values = np.empty((idx.size, n))
    for r, s in enumerate(sched):
        ts = np.asarray(s.times, dtype=float)  # type: ignore[attr-defined]
        vs = np.asarray(s.temperatures, dtype=float)  # type: ignore[attr-defined]
        times[r, : ts.size] = ts
        values[r, : ts.size] = vs
        values[r, ts.size :] = vs[-1]
    return idx, times, values


def _interp_rows(t: float, times: NDArray, values: NDArray) -> NDArray[np.float64]:
    """``np.interp(t, times[i], values[i])`` for every row (rows padded with ``inf`` times)."""
    rows = np.arange(times.shape[0])
    j = np.sum(times <= t, axis=1) - 1
    out = np.where(j < 0, values[:, 0], values[rows, np.maximum(j, 0)])
    inner = (j >= 0) & (j + 1 < times.shape[1])
    jj = np.minimum(np.maximum(j, 0) + 1, times.shape[1] - 1)
    t1 = times[rows, jj]
    inner &= np.isfinite(t1)
    if inner.any():
        j0 = np.maximum(j, 0)
        x0, f0, f1 = times[rows, j0], values[rows, j0], values[rows, jj]
        slope = (f1[inner] - f0[inner]) / (t1[inner] - x0[inner])
        out[inner] = slope * (t - x0[inner]) + f0[inner]
    return out


class HydraulicDriveBatch:
    r"""``n`` hydraulic drives, each with its parameters and temperature, stepped as one array.

    Each :meth:`step` holds every drive's valve command for one period
    ``dt`` and integrates all drives together with ``n_substeps`` classical
    Runge-Kutta steps; the oil temperatures are evaluated at the middle of
    each sub-step.

    Parameters
    ----------
    parameters : sequence of HydraulicParameters
        One per drive.
    temperature : sequence of callables or floats
        Oil temperature of each drive, °C: a constant or a function ``T(t)``
        (e.g. a :class:`~kautztwin.twin.physical.TemperatureSchedule`).
    dt : float, default=0.02
        Sampling period, s.
    initial_command : float, default=0.5
        Every drive starts at the equilibrium of this command at its initial temperature.
    noise : float, default=0.0
        Standard deviation of the white sensor noise, rad/s.
    random_state : int or None, default=None
        Seed of the noise: one generator draws ``noise_size`` values per
        sample, and drive ``i`` takes value ``noise_index[i]``.
    n_substeps : int, default=8
        Runge-Kutta steps per period.
    noise_index : array-like of int, optional
        Each drive's position in a larger batch (``0 .. n - 1`` when omitted):
        a shard of a fleet gets the noise its drives get in the whole fleet.
    noise_size : int, optional
        Size of that larger batch (``n`` when omitted).

    Raises
    ------
    DimensionError
        If ``parameters`` and ``temperature`` differ in length or are empty.
    DataError
        On invalid values.

    Examples
    --------
    >>> from kautztwin.simulators.hydraulic import HydraulicParameters
    >>> from kautztwin.simulators.hydraulic.batch import HydraulicDriveBatch
    >>> batch = HydraulicDriveBatch([HydraulicParameters()] * 3, [20.0, 30.0, 40.0])
    >>> y0 = batch.reset()
    >>> y1 = batch.step([0.6, 0.6, 0.6])
    >>> y1.shape, bool((y1 > y0).all())
    ((3,), True)
    """

    def __init__(
        self,
        parameters: Sequence[HydraulicParameters],
        temperature: Sequence[float | Callable[[float], float]],
        *,
        dt: float = 0.02,
        initial_command: float = 0.5,
        noise: float = 0.0,
        random_state: int | None = None,
        n_substeps: int = 8,
        noise_index: ArrayLike | None = None,
        noise_size: int | None = None,
    ) -> None:
        params = list(parameters)
        temps = list(temperature)
        if not params or len(params) != len(temps):
            raise DimensionError(
                f"parameters and temperature need one entry per drive, got {len(params)} and "
                f"{len(temps)}"
            )
        self.n_drives = len(params)
        self.dt = check_positive(dt, "dt")
        self.noise = check_nonnegative(noise, "noise")
        self.n_substeps = check_int(n_substeps, "n_substeps", 1)
        self.initial_command = float(initial_command)
        self.random_state = random_state
        self.noise_size = self.n_drives if noise_size is None else check_int(
            noise_size, "noise_size", 1)
        self.noise_index = (np.arange(self.n_drives) if noise_index is None
                            else np.asarray(noise_index, dtype=np.intp).reshape(-1))
        if self.noise_index.shape != (self.n_drives,) or (
                self.noise_index.size and not (0 <= self.noise_index.min()
                                               and self.noise_index.max() < self.noise_size)):
            raise DimensionError(
                f"noise_index needs one index in [0, {self.noise_size}) per drive")
        self._params = _param_arrays(params)
        self._drives = [HydraulicServoDrive(p) for p in params]
        self._const = np.array([not callable(T) for T in temps])
        self._temps = temps
        self._T_const = np.array([float(T) if not callable(T) else np.nan for T in temps])
        self._callable_idx = np.flatnonzero(~self._const)
        self._pw = _piecewise(temps, self._callable_idx)
        self._scale = np.stack([
            self._params["spool_stroke"], self._params["supply_pressure"],
            np.array([d.parameters.no_load_speed for d in self._drives]),
        ], axis=1)
        self.reset()

    def temperatures(self, t: float) -> NDArray[np.float64]:
        """Oil temperature of every drive at time ``t``, °C.

        Parameters
        ----------
        t : float

        Returns
        -------
        ndarray of shape (n_drives,)
        """
        T = self._T_const.copy()
        if self._pw is not None:
            idx, times, values = self._pw
            T[idx] = _interp_rows(float(t), times, values)
            return T
        for i in self._callable_idx:
            T[i] = float(self._temps[i](t))
        return T

    def reset(self) -> NDArray[np.float64]:
        """Back to ``t = 0`` at the equilibria; the first (noisy) outputs.

        Returns
        -------
        ndarray of shape (n_drives,)
        """
        T0 = self.temperatures(0.0)
        self._z = np.stack([
            d.equilibrium(self.initial_command, float(T)) for d, T in zip(
                self._drives, T0, strict=True)
        ]) / self._scale
        self._k = 0
        self._rng = np.random.default_rng(self.random_state)
        self._coef_T = T0
        self._coef = coefficient_arrays(self._params, T0)
        return self._measure()

    @property
    def t(self) -> float:
        """Time of the current state, s."""
        return self._k * self.dt

    @property
    def y_true(self) -> NDArray[np.float64]:
        """Noise-free speeds, rad/s."""
        return self._z[:, 2] * self._scale[:, 2]

    def _coefficients(self, t: float) -> dict[str, NDArray[np.float64]]:
        if self._callable_idx.size == 0:
            return self._coef
        T = self.temperatures(t)
        if not np.array_equal(T, self._coef_T):
            self._coef_T = T
            self._coef = coefficient_arrays(self._params, T)
        return self._coef

    def step(self, u: ArrayLike) -> NDArray[np.float64]:
        """Hold the valve commands ``u`` for one period; the next (noisy) outputs.

        Parameters
        ----------
        u : array-like of shape (n_drives,)
            Valve commands (saturated at ``|u| = 1`` like the spool).

        Returns
        -------
        ndarray of shape (n_drives,)

        Raises
        ------
        DimensionError
            If ``u`` has the wrong shape.
        DataError
            If ``u`` is not finite.
        """
        v = np.asarray(u, dtype=float)
        if v.shape != (self.n_drives,):
            raise DimensionError(f"u must have shape ({self.n_drives},), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise DataError("u contains NaN or inf")
        v = np.clip(v, -1.0, 1.0)
        h = self.dt / self.n_substeps
        t0 = self._k * self.dt
        z = self._z
        for j in range(self.n_substeps):
            c = self._coefficients(t0 + (j + 0.5) * h)
            k1 = rhs_batch(z, v, c)
            k2 = rhs_batch(z + 0.5 * h * k1, v, c)
            k3 = rhs_batch(z + 0.5 * h * k2, v, c)
            k4 = rhs_batch(z + h * k3, v, c)
            z = z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        self._z = z
        self._k += 1
        return self._measure()

    def _measure(self) -> NDArray[np.float64]:
        y = self.y_true
        if self.noise:
            draw = self._rng.standard_normal(self.noise_size)
            y = y + self.noise * draw[self.noise_index]
        q = np.array([d.sensor_resolution for d in self._drives[:1]])[0]
        return q * np.round(y / q) if q > 0 else y

    def __repr__(self) -> str:
        return (f"HydraulicDriveBatch(n_drives={self.n_drives}, dt={self.dt:g}, "
                f"n_substeps={self.n_substeps})")
