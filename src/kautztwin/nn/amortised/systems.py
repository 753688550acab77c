"""Random stable systems on a normalised time axis: the training records of the amortised estimator.

Time is measured in units of the record length ``T``: a record is sampled on
``tau = t / T`` in ``[0, 1]``, so a pole at ``s`` (1/s) on a record of length ``T``
is the normalised pole ``s T``.  One draw is a strictly proper stable system of order
``1 .. max_order`` with real poles and lightly to heavily damped complex pairs spread
over about a decade and a half of decay rates, real zeros on either side of the imaginary axis
(relative degree at least one), an optional input delay, a random sign, and white or AR(1)
noise scaled to the record's peak.  The impulse response is the sum of its modes
(residues at distinct poles), exact to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from ..._validation import check_int

__all__ = ["SystemDraws", "random_systems"]

# the distribution (normalised units: rates times the record length)
_SLOWEST_RATE = (2.0, 40.0)  # slowest decay rate: 2 .. 40 time constants per record
_RATE_SPREAD = 15.0  # every other decay rate is within this factor above the slowest
_ZETA = (0.08, 1.0)  # damping ratio of a complex pair (log-uniform)
_ZERO_RANGE = (0.3, 20.0)  # |zero| relative to the slowest rate (log-uniform)
_RHP_ZERO = 0.2  # probability that a zero is in the right half plane
_DELAY = (0.25, 0.05)  # probability of a delay, largest delay (share of the record)
_NOISE_FREE = 0.1  # probability of a noise-free record
_NOISE = 0.1  # largest noise level (share of the record's peak)
_WHITE = 0.4  # probability of white (else AR(1)) noise
_AR1 = (0.5, 0.97)  # AR(1) pole of coloured noise (per sample, uniform)


@dataclass(frozen=True, eq=False)
class SystemDraws:
    """Records of random stable systems on the normalised grid.

    Parameters
    ----------
    tau : ndarray of shape (n_samples,)
        Normalised sample times, ``linspace(0, 1, n_samples)``.
    clean : ndarray of shape (n, n_samples)
        Noise-free impulse responses, peak ``1`` in absolute value.
    responses : ndarray of shape (n, n_samples)
        ``clean`` plus noise.
    poles : ndarray of complex, shape (n, max_order)
        Normalised poles of each system, padded with ``nan`` past its order.
    order : ndarray of int, shape (n,)
        Order of each system.
    delay : ndarray of shape (n,)
        Input delay of each system (share of the record).
    """

    tau: NDArray[np.float64]
    clean: NDArray[np.float64]
    responses: NDArray[np.float64]
    poles: NDArray[np.complex128]
    order: NDArray[np.int64]
    delay: NDArray[np.float64]


def _log_uniform(rng: np.random.Generator, lo: float, hi: float, size=None) -> NDArray:
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size))


def _one_system(rng: np.random.Generator, max_order: int) -> tuple[NDArray, NDArray, float]:
    """Poles (normalised), real zeros and delay of one random system."""
    order = int(rng.choice(np.arange(1, max_order + 1), p=_order_weights(max_order)))
    n_pairs = int(rng.integers(0, order // 2 + 1))
    slowest = _log_uniform(rng, *_SLOWEST_RATE)
    n_modes = order - n_pairs
    rates = slowest * _log_uniform(rng, 1.0, _RATE_SPREAD, n_modes)
    rates[rng.integers(n_modes)] = slowest  # one mode sits at the slowest rate
    poles: list[complex] = []
    for i, rate in enumerate(rates):
        if i < n_pairs:
            zeta = _log_uniform(rng, *_ZETA)
            omega = rate * np.sqrt(1.0 / zeta**2 - 1.0)
            poles += [complex(-rate, omega), complex(-rate, -omega)]
        else:
            poles.append(complex(-rate, 0.0))
    n_zeros = int(rng.integers(0, order))
    zeros = slowest * _log_uniform(rng, *_ZERO_RANGE, n_zeros)
    zeros *= np.where(rng.random(n_zeros) < _RHP_ZERO, 1.0, -1.0)
    delay = rng.uniform(0.0, _DELAY[1]) if rng.random() < _DELAY[0] else 0.0
    return np.array(poles), zeros, float(delay)


def _order_weights(max_order: int) -> NDArray[np.float64]:
    """Higher orders are drawn more often (weight proportional to the order)."""
    w = np.arange(1, max_order + 1, dtype=float)
    return w / w.sum()


def _impulse(poles: NDArray, zeros: NDArray, delay: float, tau: NDArray) -> NDArray[np.float64]:
    """Impulse response of ``prod(s - z) / prod(s - p)`` delayed by ``delay`` (residues)."""
    s = tau - delay
    h = np.zeros(tau.size)
    on = s >= 0
    for i, p in enumerate(poles):
        others = np.delete(poles, i)
        r = np.prod(p - zeros) / np.prod(p - others)
        h[on] += np.real(r * np.exp(p * s[on]))
    return h


def random_systems(
    n: int,
    n_samples: int,
    rng: np.random.Generator,
    *,
    max_order: int = 5,
) -> SystemDraws:
    """Draw random stable systems and their noisy impulse records (normalised time).

    Parameters
    ----------
    n : int
        Number of records, ``>= 1``.
    n_samples : int
        Samples per record, ``>= 16``.
    rng : numpy.random.Generator
        Source of every draw.
    max_order : int, default=5
        Largest system order.

    Returns
    -------
    SystemDraws

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.nn.amortised import random_systems
    >>> d = random_systems(8, 200, np.random.default_rng(0), max_order=3)
    >>> d.clean.shape, float(np.abs(d.clean).max(axis=1).min())
    ((8, 200), 1.0)
    """
    n = check_int(n, "n", minimum=1)
    n_samples = check_int(n_samples, "n_samples", minimum=16)
    max_order = check_int(max_order, "max_order", minimum=1)
    tau = np.linspace(0.0, 1.0, n_samples)
    clean = np.empty((n, n_samples))
    poles = np.full((n, max_order), np.nan, dtype=complex)
    order = np.empty(n, dtype=np.int64)
    delay = np.empty(n)
    for i in range(n):
        while True:
            p, z, d = _one_system(rng, max_order)
            h = _impulse(p, z, d, tau)
            peak = np.abs(h).max()
            if np.isfinite(peak) and peak > 0 and np.ptp(h) > 0:
                break
        clean[i] = h / peak * (1.0 if rng.random() < 0.5 else -1.0)
        poles[i, : p.size] = p
        order[i] = p.size
        delay[i] = d
    level = np.where(rng.random(n) < _NOISE_FREE, 0.0, rng.uniform(0.0, _NOISE, n))
    w = rng.standard_normal((n, n_samples))
    a = np.where(rng.random(n) < _WHITE, 0.0, rng.uniform(*_AR1, n))
    noise = np.empty_like(w)
    for i in range(n):  # stationary AR(1) with unit variance (white for a = 0)
        g = np.sqrt(1.0 - a[i] ** 2)
        e0 = w[i].copy()
        e0[0] /= g
        noise[i] = scipy.signal.lfilter([g], [1.0, -a[i]], e0)
    responses = clean + level[:, None] * noise
    return SystemDraws(tau=tau, clean=clean, responses=responses, poles=poles, order=order,
                       delay=delay)
