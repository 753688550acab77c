"""The paper's sample system ``G(s) = 6/((s+1)(s+3)(s^2+s+4))`` and its sampled responses."""

from __future__ import annotations

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from ..exceptions import DataError

__all__ = ["reference_poles", "reference_response", "reference_system"]


def reference_poles() -> NDArray[np.complex128]:
    """Poles of the reference system: ``-1, -3, -1/2 +- j sqrt(15)/2``.

    Returns
    -------
    ndarray of complex, shape (4,)
    """
    w = np.sqrt(15.0) / 2.0
    return np.array([-1.0, -3.0, -0.5 + 1j * w, -0.5 - 1j * w])


def reference_system() -> scipy.signal.TransferFunction:
    """The reference system ``6 / ((s+1)(s+3)(s^2+s+4))`` (kautz-math.md 9.2).

    Returns
    -------
    scipy.signal.TransferFunction
        Continuous-time, static gain 0.5.

    Examples
    --------
    >>> from kautztwin.data import reference_system
    >>> reference_system().den
    array([ 1.,  5., 11., 19., 12.])
    """
    den = np.polymul(np.polymul([1.0, 1.0], [1.0, 3.0]), [1.0, 1.0, 4.0])
    return scipy.signal.TransferFunction([6.0], den)


def reference_response(
    *,
    kind: str = "impulse",
    n_samples: int = 900,
    t_end: float = 20.0,
    noise: float = 0.0,
    random_state: int | None = 0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sampled impulse or unit-step response of :func:`reference_system`.

    Parameters
    ----------
    kind : {'impulse', 'step'}, default='impulse'
    n_samples : int, default=900
        Samples on ``[0, t_end]`` (the paper: 900).
    t_end : float, default=20.0
        Record length in seconds.
    noise : float, default=0.0
        White Gaussian noise, standard deviation as a fraction of the
        noise-free response's peak (0.1 = 10 %).
    random_state : int or None, default=0
        Seed of the noise.

    Returns
    -------
    t, y : ndarray of shape (n_samples,)
    """
    if kind not in ("impulse", "step"):
        raise DataError(f"kind must be 'impulse' or 'step', got {kind!r}")
    t = np.linspace(0.0, t_end, n_samples)
    sys = reference_system()
    if kind == "impulse":
        _, y = scipy.signal.impulse(sys, T=t)
    else:
        _, y = scipy.signal.step(sys, T=t)
    if noise:
        rng = np.random.default_rng(random_state)
        y = y + noise * np.max(np.abs(y)) * rng.standard_normal(t.size)
    return t, y
