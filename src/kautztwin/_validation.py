"""Input checks shared by the whole package (validate once, at the boundary).

Every argument check lives here: modules import these instead of writing private copies, so
one kind of bad input gets one wording everywhere.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .exceptions import DataError, DimensionError

__all__ = [
    "check_choice",
    "check_dt",
    "check_finite",
    "check_int",
    "check_nonnegative",
    "check_number",
    "check_positive",
    "check_records",
    "check_time",
    "to_float_or_nan",
]


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


def _integer_phrase(minimum: int | None) -> str:
    if minimum is None:
        return "an integer"
    if minimum == 0:
        return "a non-negative integer"
    if minimum == 1:
        return "a positive integer"
    return f"an integer >= {minimum}"


def check_int(value: Any, name: str, minimum: int | None = None) -> int:
    """Return ``value`` as a Python ``int`` (bools refused), at least ``minimum``, or raise.

    The message names the argument and the accepted range in one line, e.g.
    ``"n must be a positive integer, got 0"``.
    """
    if (
        isinstance(value, bool | np.bool_)
        or not isinstance(value, int | np.integer)
        or (minimum is not None and value < minimum)
    ):
        raise DataError(f"{name} must be {_integer_phrase(minimum)}, got {value!r}")
    return int(value)


def check_number(value: Any, name: str) -> float:
    """Return ``value`` as a finite float, or raise naming ``name``."""
    if isinstance(value, bool | np.bool_):
        raise DataError(f"{name} must be a number, got {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise DataError(f"{name} must be finite, got {out}")
    return out


def check_positive(value: Any, name: str) -> float:
    """Return ``value`` as a finite float ``> 0``, or raise naming ``name``."""
    if isinstance(value, bool | np.bool_):
        raise DataError(f"{name} must be a positive number, got {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(out) and out > 0):
        raise DataError(f"{name} must be a finite number > 0, got {value!r}")
    return out


def check_nonnegative(value: Any, name: str) -> float:
    """Return ``value`` as a finite float ``>= 0``, or raise naming ``name``."""
    if isinstance(value, bool | np.bool_):
        raise DataError(f"{name} must be a number >= 0, got {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{name} must be a number >= 0, got {value!r}") from None
    if not (math.isfinite(out) and out >= 0):
        raise DataError(f"{name} must be a finite number >= 0, got {out}")
    return out


def check_choice(value: Any, name: str, choices: tuple[str, ...]) -> str:
    """Return ``value`` if it is one of ``choices``, else raise listing them."""
    if value not in choices:
        raise DataError(f"{name} must be one of {', '.join(map(repr, choices))}; got {value!r}")
    return value


def to_float_or_nan(value: Any) -> float:
    """``value`` as a float, NaN when it is not a real scalar; never raises or warns.

    For samples arriving from a plant: garbage of any kind (``None``, text, a bool, an array
    of several values, an int beyond the float range) is a dropout, not an exception.
    ``inf`` stays ``inf`` (callers that want it as a dropout test ``math.isfinite``).
    """
    if isinstance(value, bool | np.bool_):
        return math.nan
    if not isinstance(value, float | int | np.floating | np.integer):
        try:
            a = np.asarray(value)
        except Exception:  # garbage of any kind is a dropout
            return math.nan
        if a.size != 1 or a.dtype.kind not in "iuf":
            return math.nan
        value = a.reshape(())[()]
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError):
        return math.nan
    return out
