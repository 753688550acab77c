"""Reading a MIMO input/output record (several input and output columns) from a text file."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...exceptions import DataError
from ..records import _read_table

__all__ = ["MIMORecord", "load_mimo_record"]


@dataclass(frozen=True, eq=False)
class MIMORecord:
    """A uniformly sampled MIMO record read by :func:`load_mimo_record`.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Sample times, s.
    u : ndarray of shape (n_samples, n_inputs)
    y : ndarray of shape (n_samples, n_outputs)
    dt : float
        Sampling period, s.
    inputs, outputs : tuple of str
        Column names.
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    dt: float
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


def load_mimo_record(
    path: str | os.PathLike[str],
    *,
    inputs: list[str],
    outputs: list[str],
    time: str | None = None,
    dt: float | None = None,
) -> MIMORecord:
    """Read input and output columns of one uniformly sampled record.

    Parameters
    ----------
    path : path
        CSV (or whitespace-separated) file; with a header row columns are named, without
        one they are 1-based numbers (as :func:`~kautztwin.ident.load_records` reads them).
    inputs, outputs : list of str
        Input and output columns.
    time : str, optional
        Time column, s: the samples must be uniformly spaced (to 1e-6 of a period).
    dt : float, optional
        Sampling period when there is no time column.  Give exactly one of ``time``, ``dt``.

    Returns
    -------
    MIMORecord

    Raises
    ------
    DataError
        On a missing file or column, a repeated column, non-finite values, or a time
        column that is not uniformly increasing.
    """
    if (time is None) == (dt is None):
        raise DataError("give exactly one of time (a column) and dt (a sampling period)")
    cols = [*([time] if time is not None else []), *inputs, *outputs]
    if len(set(cols)) != len(cols):
        raise DataError(f"the time, input and output columns must differ; got {cols}")
    data = _read_table(path, cols)
    u = np.column_stack([data[c] for c in inputs])
    y = np.column_stack([data[c] for c in outputs])
    if time is None:
        if not (np.isfinite(dt) and dt > 0):
            raise DataError(f"dt must be a positive sampling period, got {dt}")
        step = float(dt)
        t = np.arange(u.shape[0]) * step
    else:
        t = data[time]
        d = np.diff(t)
        step = float(np.median(d)) if d.size else 0.0
        if d.size == 0 or step <= 0 or np.max(np.abs(d - step)) > 1e-6 * step:
            raise DataError(
                f"{path}: the time column {time!r} must increase in equal steps (a MIMO "
                "record is uniformly sampled); resample it or give --dt"
            )
    return MIMORecord(t, u, y, step, tuple(inputs), tuple(outputs))
