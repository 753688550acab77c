"""Records returned by the hydraulic simulator: linearisation, response, step-test session."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import scipy.integrate
import scipy.optimize
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..._validation import (
    check_time,
)
from .parameters import HydraulicParameters

__all__ = ["Linearization", "PlantResponse", "StepTestRecords"]


def _readonly(a: ArrayLike, dtype: Any = float) -> NDArray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class Linearization:
    r"""Small-signal model of the drive around an equilibrium.

    The transfer function from a change of the valve command :math:`\Delta u`
    to the change of shaft speed :math:`\Delta\omega` (rad/s per unit command)
    is

    .. math:: G(s) = \frac{b_0}{(s - p_1)(s - p_2)(s - p_3)}

    (no zeros: the command reaches the speed only through the spool and the
    pressure).

    Parameters
    ----------
    num, den : ndarray
        Transfer-function coefficients in descending powers of ``s``; ``den``
        is monic.
    poles : ndarray of complex, shape (3,)
        Roots of ``den``, slowest (closest to the imaginary axis) first.
    A, B, C, D : ndarray
        State-space matrices of the deviations of the physical states
        ``(x_v [m], p_L [Pa], omega [rad/s])``, shapes (3, 3), (3, 1), (1, 3), (1, 1).
    u0 : float
        Valve command of the operating point.
    x0 : ndarray of shape (3,)
        Equilibrium state ``(x_v, p_L, omega)`` in m, Pa, rad/s.
    temperature : float
        Oil temperature, °C.

    See Also
    --------
    HydraulicServoDrive.linearize : Builds this object.
    """

    num: NDArray[np.float64]
    den: NDArray[np.float64]
    poles: NDArray[np.complex128]
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    D: NDArray[np.float64]
    u0: float
    x0: NDArray[np.float64]
    temperature: float

    def __post_init__(self) -> None:
        for name in ("num", "den", "A", "B", "C", "D", "x0"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))
        object.__setattr__(self, "poles", _readonly(self.poles, complex))

    @property
    def y0(self) -> float:
        """Shaft speed of the operating point, rad/s."""
        return float(self.x0[2])

    @property
    def dc_gain(self) -> float:
        """Static gain ``G(0)``: rad/s per unit of valve command."""
        return float(self.num[-1] / self.den[-1])

    @property
    def is_real(self) -> bool:
        """Whether all poles are real (relative imaginary part below 1e-9)."""
        return bool(np.all(np.abs(self.poles.imag) <= 1e-9 * np.abs(self.poles)))

    def to_scipy(self) -> scipy.signal.TransferFunction:
        """The transfer function as a :class:`scipy.signal.TransferFunction`.

        Returns
        -------
        scipy.signal.TransferFunction
        """
        return scipy.signal.TransferFunction(self.num, self.den)

    def step(self, t: ArrayLike, amplitude: float = 1.0) -> NDArray[np.float64]:
        """Speed change for a command step of ``amplitude`` at ``t[0]``, from the equilibrium.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Increasing sample times, s.
        amplitude : float, default=1.0
            Size of the command step.

        Returns
        -------
        ndarray of shape (n_samples,)
            :math:`\\Delta\\omega(t)` in rad/s (add :attr:`y0` for the absolute speed).
        """
        t = check_time(t)
        _, y = scipy.signal.step(self.to_scipy(), T=t - t[0])
        return amplitude * np.asarray(y, dtype=float)


@dataclass(frozen=True, eq=False)
class PlantResponse:
    """Sampled response of the drive to a command signal.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Sample times, s.
    u : ndarray of shape (n_samples,)
        Valve command (fraction of the rated input), held between samples.
    y : ndarray of shape (n_samples,)
        Measured shaft speed, rad/s: ``y_true`` plus sensor noise, quantised.
    y_true : ndarray of shape (n_samples,)
        Noise-free shaft speed, rad/s.
    x : ndarray of shape (n_samples, 3)
        States ``(x_v [m], p_L [Pa], omega [rad/s])``; ``x[-1]`` continues a
        simulation (pass it as ``x0``).
    temperature : ndarray of shape (n_samples,)
        Oil temperature at the samples, °C.
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    y_true: NDArray[np.float64]
    x: NDArray[np.float64]
    temperature: NDArray[np.float64]

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, _readonly(getattr(self, f.name)))


@dataclass(frozen=True, eq=False)
class StepTestRecords:
    """A session of step tests: one response per record, oil warming between records.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Common sample times, s.
    u : ndarray of shape (n_records, n_samples)
        Valve command of each record.
    y : ndarray of shape (n_records, n_samples)
        Measured shaft speed (with noise), rad/s.
    y_true : ndarray of shape (n_records, n_samples)
        Noise-free shaft speed, rad/s.
    temperature : ndarray of shape (n_records,)
        Oil temperature of each record, °C.
    amplitude : float
        Step size of the valve command.
    noise : float
        Noise standard deviation as a fraction of each record's peak.
    parameters : HydraulicParameters
        Parameters of the simulated drive.
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    y_true: NDArray[np.float64]
    temperature: NDArray[np.float64]
    amplitude: float
    noise: float
    parameters: HydraulicParameters = field(default_factory=HydraulicParameters)

    def __post_init__(self) -> None:
        for name in ("t", "u", "y", "y_true", "temperature"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))

    @property
    def n_records(self) -> int:
        """Number of step responses."""
        return int(self.y.shape[0])

    @property
    def n_samples(self) -> int:
        """Samples per response."""
        return int(self.t.size)
