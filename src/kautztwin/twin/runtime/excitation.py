"""Seeded signals of a run: the identification excitation, the dither and the sensor faults."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .config import TwinConfig

__all__ = ["FaultPlan", "binary_signal", "continued_excitation", "excitation"]


def binary_signal(rng: np.random.Generator, n: int, amp: float, hold: tuple[int, int]) -> NDArray:
    """Random binary signal: +-amp, switching sign after each random hold time."""
    out: list[float] = []
    sign = float(rng.choice([-1.0, 1.0]))
    while len(out) < n:
        out += [amp * sign] * int(rng.integers(hold[0], hold[1]))
        sign = -sign
    return np.asarray(out[:n], dtype=float)


def excitation(config: TwinConfig) -> tuple[NDArray, NDArray]:
    """``(u_ident, dither)``: the identification input and the closed-loop dither of a run."""
    cfg = config
    n = cfg.n_samples
    rng = np.random.default_rng(cfg.seed)
    u_ident = cfg.ident_level + binary_signal(rng, cfg.n_ident, cfg.ident_amplitude,
                                              cfg.ident_hold)
    d = binary_signal(rng, n, cfg.dither, cfg.dither_hold) if cfg.dither > 0 else np.zeros(n)
    return u_ident, d


def continued_excitation(config: TwinConfig) -> NDArray:
    """The identification excitation's continuation: ``n_ident`` more samples of it.

    What a live plant gets while its twin identifies in the background
    (:mod:`.birth`): the same binary signal (level, amplitude, holds), seeded
    apart from :func:`excitation`'s signals, which it therefore leaves unchanged.

    Parameters
    ----------
    config : TwinConfig

    Returns
    -------
    ndarray of shape (n_ident,)
    """
    cfg = config
    rng = np.random.default_rng([cfg.seed, 104729])
    return cfg.ident_level + binary_signal(rng, cfg.n_ident, cfg.ident_amplitude, cfg.ident_hold)


@dataclass(frozen=True, eq=False)
class FaultPlan:
    """The sensor faults of every sample of a run, drawn once (after the identification phase).

    Parameters
    ----------
    dropout, outlier, late : ndarray of bool
        Samples that read NaN, carry a gross error, or arrive late (never two in a row).
    sign : ndarray
        Sign of each sample's gross error.
    outlier_size : float
        Size of a gross error, output units.
    dt : float
        Sampling period: a late reading carries the previous sample's time.
    """

    dropout: NDArray[np.bool_]
    outlier: NDArray[np.bool_]
    late: NDArray[np.bool_]
    sign: NDArray[np.float64]
    outlier_size: float
    dt: float

    @classmethod
    def for_config(cls, config: TwinConfig) -> FaultPlan:
        """The plan of ``config.faults``, seeded by ``config.seed``."""
        n = config.n_samples
        f = config.faults
        rng = np.random.default_rng([config.seed, 7919])
        a, b, c, s = rng.random(n), rng.random(n), rng.random(n), rng.random(n)
        active = np.arange(n) >= config.n_ident
        drop = active & (a < f.dropout)
        out = active & (b < f.outlier) & ~drop
        late = active & (c < f.late) & ~drop & ~out
        late[1:] &= ~late[:-1]
        return cls(drop, out, late, np.where(s < 0.5, -1.0, 1.0), f.outlier_size, config.dt)

    def apply(self, k: int, t: float, y: float) -> tuple[float, float]:
        """The reading ``(t, y)`` of sample ``k`` as the faults deliver it."""
        if self.dropout[k]:
            y = math.nan
        elif self.outlier[k]:
            y += self.sign[k] * self.outlier_size
        if self.late[k]:
            t -= self.dt
        return t, y
