"""Replay of a recorded ``t, u, y`` run (array or CSV file) as a twin plant."""

from __future__ import annotations

import csv
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...exceptions import DataError, DimensionError, KautzTwinError
from .base import Reading
from .clock import Clock

__all__ = ["ReplayExhaustedError", "ReplayInputWarning", "ReplayPlant"]


class ReplayInputWarning(UserWarning):
    """A replayed record was asked to follow an input other than the recorded one."""


class ReplayExhaustedError(KautzTwinError, EOFError):
    """:meth:`ReplayPlant.step` was called after the last recorded sample."""


# --------------------------------------------------------------------------- replay
def _read_replay_csv(path: Path, columns: tuple[str, str, str]) -> dict[str, NDArray]:
    """Read three named columns; empty cells and ``nan`` in u and y become NaN."""
    name = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"cannot read {name}: {exc.strerror or exc}") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip()]
    if not lines:
        raise DataError(f"{name} is empty")
    header_line = lines[0][1].lstrip("#").strip()
    delimiter = next((d for d in (",", ";", "\t") if d in header_line), None)

    def split(line: str) -> list[str]:
        if delimiter is None:
            return line.split()
        return [c.strip() for c in next(csv.reader([line], delimiter=delimiter))]

    header = split(header_line)
    index = {}
    for col in columns:
        if col not in header:
            raise DataError(f"{name} has no column {col!r}; columns are {', '.join(header)}")
        index[col] = header.index(col)
    out: dict[str, list[float]] = {c: [] for c in columns}
    for lineno, line in lines[1:]:
        if line.lstrip().startswith("#"):
            continue
        cells = split(line)
        for col in columns:
            j = index[col]
            cell = cells[j] if j < len(cells) else ""
            try:
                value = float(cell) if cell else math.nan
            except ValueError:
                raise DataError(
                    f"{name}, line {lineno}: column {col!r} holds {cell!r}, not a number"
                ) from None
            out[col].append(value)
    return {c: np.asarray(v, dtype=float) for c, v in out.items()}


class ReplayPlant:
    """Replay of a recorded run ``t, u, y`` as a plant.

    :meth:`reset` returns the first recorded sample; each :meth:`step`
    returns the next one.  The recorded output cannot react to another input:
    the input passed to :meth:`step` is ignored (pass ``None`` to follow the
    record), and one :class:`ReplayInputWarning` per run says so when it
    differs from the recorded input by more than ``input_tolerance``.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times, s.
    u : array-like of shape (n_samples,)
        Recorded input (``u[k]`` was applied from ``t[k]`` on); NaN allowed.
    y : array-like of shape (n_samples,)
        Recorded output; NaN (a recorded dropout) allowed.
    clock : Clock, optional
        Pacing; as fast as possible when omitted.  A real-time clock replays
        at the recorded pace.
    input_tolerance : float, default=1e-9
        Largest difference from the recorded input that is not warned about.
    name : str, default='replay'
        Name of the plant.

    Raises
    ------
    DimensionError
        If the arrays are not 1-D of one length ``>= 2``.
    DataError
        If ``t`` is not finite and strictly increasing.

    Attributes
    ----------
    dt : float
        Median sampling period of the record, s.
    input_limits : tuple of float
        Range of the recorded input (``(-inf, inf)`` if it holds no finite value).
    n_samples : int
        Number of recorded samples.

    See Also
    --------
    ReplayPlant.from_csv : Read the record from a file.

    Notes
    -----
    ``meta`` holds ``u`` (the recorded input of the period that ended at
    ``t``), ``k`` and ``u_requested`` (what :meth:`step` was given).

    Examples
    --------
    >>> from kautztwin.twin.physical import ReplayPlant
    >>> plant = ReplayPlant([0.0, 0.1, 0.2], [1.0, 1.0, 0.0], [0.0, 0.5, 0.8])
    >>> plant.reset().y, plant.step(None).y, plant.step(None).y
    (0.0, 0.5, 0.8)
    """

    def __init__(
        self,
        t: ArrayLike,
        u: ArrayLike,
        y: ArrayLike,
        *,
        clock: Clock | None = None,
        input_tolerance: float = 1e-9,
        name: str = "replay",
    ) -> None:
        arrays = [np.array(a, dtype=float, copy=True) for a in (t, u, y)]
        for label, a in zip("tuy", arrays, strict=True):
            if a.ndim != 1:
                raise DimensionError(f"{label} must be 1-D, got shape {a.shape}")
        if not arrays[0].size == arrays[1].size == arrays[2].size:
            raise DimensionError(
                f"t, u and y must have one length, got {arrays[0].size}, {arrays[1].size} "
                f"and {arrays[2].size}"
            )
        if arrays[0].size < 2:
            raise DimensionError(f"a replay needs at least 2 samples, got {arrays[0].size}")
        tt = arrays[0]
        if not np.all(np.isfinite(tt)) or np.any(np.diff(tt) <= 0):
            raise DataError("t must be finite and strictly increasing")
        for a in arrays:
            a.setflags(write=False)
        self.t, self.u, self.y = arrays
        self.dt = float(np.median(np.diff(tt)))
        finite = self.u[np.isfinite(self.u)]
        self.input_limits = (
            (float(finite.min()), float(finite.max())) if finite.size else (-math.inf, math.inf)
        )
        self.clock = clock if clock is not None else Clock()
        self.input_tolerance = float(input_tolerance)
        self.name = str(name)
        self.reset()

    @classmethod
    def from_csv(
        cls,
        path: str | os.PathLike[str],
        *,
        columns: tuple[str, str, str] = ("t", "u", "y"),
        **kwargs: Any,
    ) -> ReplayPlant:
        """Read a record from a CSV (or whitespace-separated) file with a header row.

        Parameters
        ----------
        path : str or os.PathLike
            The file.  The first non-blank line names the columns (a leading
            ``#`` is ignored); the separator is a comma, a semicolon, a tab or
            whitespace.  Empty cells and ``nan`` in ``u`` and ``y`` are dropouts.
        columns : (str, str, str), default=('t', 'u', 'y')
            Names of the time, input and output columns.
        **kwargs
            Further arguments of :class:`ReplayPlant`.

        Returns
        -------
        ReplayPlant

        Raises
        ------
        DataError
            If the file is missing, empty, lacks a column or holds a
            non-numeric value.
        """
        data = _read_replay_csv(Path(path), tuple(columns))
        tc, uc, yc = columns
        kwargs.setdefault("name", Path(path).stem)
        return cls(data[tc], data[uc], data[yc], **kwargs)

    @property
    def n_samples(self) -> int:
        """Number of recorded samples."""
        return int(self.t.size)

    @property
    def remaining(self) -> int:
        """Steps left before the record ends."""
        return self.n_samples - 1 - self._k

    def reset(self) -> Reading:
        """Rewind to the first sample and return it.

        Returns
        -------
        Reading
        """
        self._k = 0
        self._warned = False
        self.clock.start()
        return Reading(self.t[0], self.y[0], {"u": math.nan, "k": 0, "u_requested": math.nan})

    def step(self, u: float | None = None) -> Reading:
        """Return the next recorded sample; ``u`` is only compared with the record.

        Parameters
        ----------
        u : float or None, default=None
            The input the caller wanted to apply; ``None`` follows the record.

        Returns
        -------
        Reading

        Raises
        ------
        ReplayExhaustedError
            After the last recorded sample.
        """
        if self._k + 1 >= self.n_samples:
            raise ReplayExhaustedError(
                f"the record {self.name!r} ends after {self.n_samples} samples"
            )
        recorded = float(self.u[self._k])
        requested = math.nan if u is None else float(u)
        if u is not None and not self._warned:
            same = (math.isnan(requested) and math.isnan(recorded)) or (
                abs(requested - recorded) <= self.input_tolerance
            )
            if not same:
                self._warned = True
                warnings.warn(
                    f"{self.name}: a replay cannot follow another input; u = {requested:g} "
                    f"was asked at t = {self.t[self._k]:g} s but {recorded:g} was recorded "
                    "(warned once per run)",
                    ReplayInputWarning,
                    stacklevel=2,
                )
        self._k += 1
        self.clock.wait_until(self.t[self._k] - self.t[0])
        return Reading(
            self.t[self._k], self.y[self._k],
            {"u": recorded, "k": self._k, "u_requested": requested},
        )

    def close(self) -> None:
        """Nothing to release for a replay."""

    def __repr__(self) -> str:
        return f"ReplayPlant({self.name!r}, n_samples={self.n_samples}, dt={self.dt:g})"
