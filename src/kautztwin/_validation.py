"""Input checks shared by the whole package (validate once, at the boundary).

Every argument check lives here: modules import these instead of writing private copies, so
one kind of bad input gets one wording everywhere.
"""

from __future__ import annotations

import functools
import math
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .exceptions import DataError, DimensionError

__all__ = [
    "check_choice",
    "check_dt",
    "check_finite",
    "check_int",
    "check_memory",
    "check_nonnegative",
    "check_number",
    "check_positive",
    "check_records",
    "check_time",
    "format_bytes",
    "memory_limit",
    "to_float_or_nan",
    "total_memory",
]

#: the share of the machine's memory one array-building step may ask for
MEMORY_FRACTION = 0.5


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


def _read_int(path: str) -> int | None:
    try:
        with open(path, encoding="ascii") as fh:
            text = fh.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


@functools.lru_cache(maxsize=1)
def total_memory() -> int | None:
    """The machine's physical memory in bytes (a container's limit if smaller), or ``None``.

    Read from ``os.sysconf`` (``SC_PAGE_SIZE * SC_PHYS_PAGES``), else ``/proc/meminfo``;
    a cgroup memory limit (``/sys/fs/cgroup/memory.max`` or the v1
    ``memory.limit_in_bytes``) lowers the figure when it is smaller.  Read once per
    process: every basis checks its size against it, and the reads cost 8 % of an
    identification's time when they were repeated.

    Returns
    -------
    int or None
        Bytes, or ``None`` where none of these sources can be read.
    """
    total: int | None = None
    try:
        total = int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        total = None
    if not total or total <= 0:
        try:
            with open("/proc/meminfo", encoding="ascii") as fh:
                for line in fh:
                    if line.startswith("MemTotal:"):
                        total = int(line.split()[1]) * 1024
                        break
        except (OSError, ValueError, IndexError):
            total = None
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        limit = _read_int(path)
        if limit and (total is None or limit < total):
            total = limit
    return total if total and total > 0 else None


def memory_limit() -> tuple[float, int | None]:
    """The most bytes one step may allocate, and the total it is derived from.

    Returns
    -------
    limit : float
        ``MEMORY_FRACTION`` (half) of :func:`total_memory`; ``inf`` when the total is unknown.
    total : int or None
        :func:`total_memory`.
    """
    total = total_memory()
    return (math.inf if total is None else MEMORY_FRACTION * total), total


def format_bytes(n_bytes: float) -> str:
    """A byte count as short text: ``'373 GiB'``, ``'1.5 MiB'``, ``'512 B'``.

    Parameters
    ----------
    n_bytes : float

    Returns
    -------
    str

    Examples
    --------
    >>> from kautztwin._validation import format_bytes
    >>> format_bytes(4e11), format_bytes(1536 * 1024), format_bytes(512)
    ('373 GiB', '1.5 MiB', '512 B')
    """
    value = float(n_bytes)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if value < 1024 or unit == "PiB":
            if unit == "B":
                return f"{value:.0f} B"
            return f"{value:.3g} {unit}"
        value /= 1024
    raise AssertionError("unreachable")  # pragma: no cover


def check_memory(n_bytes: float, what: str) -> float:
    """Refuse, before any work, a step whose arrays would not fit in this machine's memory.

    The limit is half the machine's memory (:func:`memory_limit`), so that the
    step and its temporaries fit beside everything else.

    Parameters
    ----------
    n_bytes : float
        The estimated size of the arrays the step builds, in bytes (computed
        from the requested shape before anything is allocated; may exceed the
        int range).
    what : str
        The request in the user's terms, e.g. ``"--records 100000 x --samples 900"``.

    Returns
    -------
    float
        ``n_bytes``.

    Raises
    ------
    DataError
        ``"<what> would need 373 GiB; at most 11.8 GiB with this machine's 23.5 GiB of
        memory"`` when ``n_bytes`` exceeds the limit (or is not a finite number).

    Examples
    --------
    >>> from kautztwin._validation import check_memory
    >>> check_memory(8 * 900 * 30, "30 records")
    216000
    """
    limit, total = memory_limit()
    if not (isinstance(n_bytes, int | float | np.integer | np.floating) and n_bytes >= 0):
        raise DataError(f"{what}: cannot size the request ({n_bytes!r} bytes)")
    if not math.isfinite(float(n_bytes)) or n_bytes > limit:
        need = "more than any machine has" if not math.isfinite(float(n_bytes)) else (
            f"{format_bytes(n_bytes)}"
        )
        raise DataError(
            f"{what} would need {need}; at most {format_bytes(limit)} with this machine's "
            f"{format_bytes(total or 0)} of memory"
        )
    return n_bytes
