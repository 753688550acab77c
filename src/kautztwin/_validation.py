"""Input checks shared by the public functions (validate once, at the boundary)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .exceptions import DataError, DimensionError

__all__ = ["check_dt", "check_finite", "check_records", "check_time"]


def check_finite(x: NDArray, name: str) -> None:
    """Raise :class:`DataError` if ``x`` holds NaN or inf, naming the first bad index."""
    bad = ~np.isfinite(x)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        where = idx[0] if len(idx) == 1 else idx
        raise DataError(f"{name} contains a non-finite value ({float(x[idx])}) at index {where}")


def check_time(t: ArrayLike, name: str = "t", *, min_samples: int = 2) -> NDArray[np.float64]:
    """Return ``t`` as a strictly increasing 1-D float array, or raise."""
    t = np.asarray(t, dtype=float)
    if t.ndim != 1:
        raise DimensionError(f"{name} must be 1-D, got an array of shape {t.shape}")
    if t.size < min_samples:
        raise DimensionError(f"{name} needs at least {min_samples} samples, got {t.size}")
    check_finite(t, name)
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise DataError(
            f"{name} must be strictly increasing, but {name}[{k + 1}] = {t[k + 1]:g} "
            f"<= {name}[{k}] = {t[k]:g}"
        )
    return t


def check_records(y: ArrayLike, n_samples: int, name: str = "h") -> NDArray[np.float64]:
    """Return ``y`` as float array of shape ``(n_samples,)`` or ``(n_records, n_samples)``."""
    y = np.asarray(y, dtype=float)
    if y.ndim not in (1, 2):
        raise DimensionError(
            f"{name} must be 1-D (one record) or 2-D (n_records, n_samples), got shape {y.shape}"
        )
    if y.shape[-1] != n_samples:
        raise DimensionError(f"{name} has {y.shape[-1]} samples per record but t has {n_samples}")
    check_finite(y, name)
    return y


def check_dt(dt: float) -> float:
    """Return ``dt`` as float; ``0`` means continuous time, ``> 0`` a sampling period."""
    dt = float(dt)
    if not np.isfinite(dt) or dt < 0:
        raise DataError(f"dt must be 0 (continuous time) or a positive sampling period, got {dt}")
    return dt
