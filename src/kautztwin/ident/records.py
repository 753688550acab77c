r"""Measured records for identification: normalisation, step detection, offsets, jitter.

A :class:`Record` is one experiment: sample times, input and output.  Real
files need some care before they can be fitted, and :meth:`Record.from_data`
does it once, at the boundary:

* **Repeated time stamps** (a step logged as two rows with the same time, as in
  ``data/tclab_step_tests/step-test-data.csv``) are merged into one sample: the
  output is averaged and the input takes the *last* value, the one that acts
  from that instant on.  The first row still tells the input level before the
  step.  The merged sample keeps the number of rows as its weight, so the
  least-squares fit and the fit percent are those of the rows as logged.
* **Jittered or non-uniform time stamps** are kept as they are: the simulation
  (:mod:`kautztwin.ident.simulate`) is exact on any grid.  :attr:`Record.jitter`
  says how far the stamps are from a uniform grid.
* **Step records** (``kind='step'``): the step instant, the level before it
  and its height are read from the input column.  An input that never changes
  means the record starts at the step, from ``u_before`` (0 unless given).
* **Impulse records** (``kind='impulse'``): the pulse in the input gives the
  impulse instant and its area (the pulse integrated as held between samples).
* **Offsets**: the output level before the experiment is *not* taken from the
  file; the estimator fits one offset per record (and, for ``kind='io'``,
  optionally the initial state).

Decreasing time stamps, NaN and too few samples are errors.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_finite
from ..exceptions import DataError, DimensionError

__all__ = ["KINDS", "MIN_SAMPLES", "Record", "load_records"]

#: the kinds of experiment a record can hold
KINDS = ("io", "step", "impulse")
#: fewest samples a record may have
MIN_SAMPLES = 4
_STEP_TOL = 0.05  # input ripple allowed around a step, as a fraction of its height


def _readonly(x: ArrayLike) -> NDArray[np.float64]:
    a = np.array(x, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Record:
    r"""One identification experiment: sampled input and output, and what it was.

    Build records with :meth:`from_data` (from raw columns, which normalises
    them), :meth:`step_response` or :meth:`impulse_response`; the constructor
    only validates.  Records are immutable.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times in seconds (uniform or not).
    u : array-like of shape (n_samples,)
        Input samples (for ``kind='io'`` held or interpolated between samples).
    y : array-like of shape (n_samples,)
        Measured output samples.
    kind : {'io', 'step', 'impulse'}, default='io'
        ``'io'``: general input/output record.  ``'step'``: an ideal step of
        height ``amplitude`` at ``start``, from the level ``u_before``.
        ``'impulse'``: a Dirac impulse of area ``amplitude`` at ``start``.
    u_before : float, default=0.0
        Input level before the record (``'io'``: the equilibrium level the
        input is measured from) or before the step.
    start : float, optional
        Instant of the step or impulse; ``t[0]`` when omitted.
    amplitude : float, optional
        Step height or impulse area (required for ``'step'`` and ``'impulse'``).
    name : str, default=''
        Where the record came from (file name), used in reports.
    weights : array-like of shape (n_samples,), optional
        Positive weight of each sample in the least-squares fit and the fit
        percent; :meth:`from_data` gives a merged sample the number of rows it
        stands for, so fitting the record equals fitting the rows as logged.
        All ones when omitted.

    Attributes
    ----------
    n_samples : int
        Number of samples.
    jitter : float
        Largest deviation of ``t`` from the uniform grid through its end points,
        as a fraction of the mean sampling period (0 for a uniform grid).

    Raises
    ------
    DataError
        On NaN, non-increasing ``t``, an unknown kind, a missing or zero
        amplitude, a start outside the record, or an ``'io'`` input that is
        constant at ``u_before`` (no excitation).
    DimensionError
        If ``t``, ``u`` and ``y`` differ in shape, are not 1-D, or have fewer
        than 4 samples.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import Record
    >>> t = [0.0, 0.0, 1.0, 2.0, 3.0]                 # step logged twice at t = 0
    >>> u = [0.0, 50.0, 50.0, 50.0, 50.0]
    >>> y = [20.0, 20.0, 20.5, 21.3, 22.0]
    >>> rec = Record.from_data(t, u, y, kind="step")
    >>> rec.n_samples, rec.start, rec.u_before, rec.amplitude
    (4, 0.0, 0.0, 50.0)
    """

    t: NDArray[np.float64]
    u: NDArray[np.float64]
    y: NDArray[np.float64]
    kind: str = "io"
    u_before: float = 0.0
    start: float | None = None
    amplitude: float | None = None
    name: str = ""
    weights: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        t, u, y = (np.asarray(a, dtype=float) for a in (self.t, self.u, self.y))
        label = f"record {self.name!r}" if self.name else "record"
        if self.kind not in KINDS:
            raise DataError(f"kind must be one of {', '.join(map(repr, KINDS))}; got {self.kind!r}")
        for nm, a in (("t", t), ("u", u), ("y", y)):
            if a.ndim != 1:
                raise DimensionError(f"{label}: {nm} must be 1-D, got shape {a.shape}")
            check_finite(a, f"{label}: {nm}")
        if not t.size == u.size == y.size:
            raise DimensionError(
                f"{label}: t, u and y must have the same length; got {t.size}, {u.size}, {y.size}"
            )
        if t.size < MIN_SAMPLES:
            raise DimensionError(
                f"{label} is too short: {t.size} samples, at least {MIN_SAMPLES} are needed"
            )
        steps = np.diff(t)
        if np.any(steps <= 0):
            k = int(np.argmax(steps <= 0)) + 1
            raise DataError(
                f"{label}: t must be strictly increasing, but t[{k}] = {t[k]:g} <= "
                f"t[{k - 1}] = {t[k - 1]:g} (use Record.from_data to merge repeated stamps)"
            )
        if not np.isfinite(self.u_before):
            raise DataError(f"{label}: u_before must be finite, got {self.u_before}")
        start = float(t[0]) if self.start is None else float(self.start)
        if self.kind == "io":
            if np.ptp(u) == 0 and u[0] == self.u_before:
                raise DataError(
                    f"{label}: the input is constant ({u[0]:g}) and equals the level before the "
                    "record: there is no excitation (use kind='step' for a step from u_before)"
                )
            amplitude = None
            start = float(t[0])
        else:
            if self.amplitude is None or not np.isfinite(self.amplitude) or self.amplitude == 0:
                what = "step height" if self.kind == "step" else "impulse area"
                raise DataError(f"{label}: the {what} (amplitude) must be finite and nonzero; "
                                f"got {self.amplitude}")
            amplitude = float(self.amplitude)
            if not t[0] <= start <= t[-1]:
                raise DataError(
                    f"{label}: the {self.kind} at t = {start:g} lies outside the record "
                    f"[{t[0]:g}, {t[-1]:g}]"
                )
        w = np.ones(t.size) if self.weights is None else np.asarray(self.weights, dtype=float)
        if w.shape != t.shape or not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise DataError(f"{label}: weights must be {t.size} finite positive numbers")
        object.__setattr__(self, "weights", _readonly(w))
        object.__setattr__(self, "t", _readonly(t))
        object.__setattr__(self, "u", _readonly(u))
        object.__setattr__(self, "y", _readonly(y))
        object.__setattr__(self, "u_before", float(self.u_before))
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "amplitude", amplitude)
        object.__setattr__(self, "name", str(self.name))

    # ------------------------------------------------------------------ properties
    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return int(self.t.size)

    @property
    def duration(self) -> float:
        """``t[-1] - t[0]`` in seconds."""
        return float(self.t[-1] - self.t[0])

    @property
    def sampling_period(self) -> float:
        """Median interval between samples."""
        return float(np.median(np.diff(self.t)))

    @property
    def jitter(self) -> float:
        """Largest distance of a time stamp from the nominal grid ``t[0] + k * period``.

        In sampling periods (the median interval); missing samples (gaps of whole
        periods) do not count as jitter.
        """
        step = self.sampling_period
        k = np.round((self.t - self.t[0]) / step)
        return float(np.max(np.abs(self.t - self.t[0] - k * step)) / step)

    # ------------------------------------------------------------------ builders
    @classmethod
    def from_data(
        cls,
        t: ArrayLike,
        u: ArrayLike,
        y: ArrayLike,
        *,
        kind: str = "io",
        u_before: float | None = None,
        name: str = "",
    ) -> Record:
        """Build a record from raw columns: merge repeated stamps, detect the step or pulse.

        Parameters
        ----------
        t : array-like of shape (n_rows,)
            Non-decreasing time stamps; equal stamps are merged (output averaged,
            last input kept; the first row's input is the level before the record).
        u, y : array-like of shape (n_rows,)
            Input and output columns.
        kind : {'io', 'step', 'impulse'}, default='io'
            What the experiment was.
        u_before : float, optional
            Input level before the record.  Default: the first input value for
            ``'io'`` and ``'impulse'``; for ``'step'`` the level before the
            detected step, or 0 when the input never changes (the record then
            starts at the step).
        name : str, default=''
            Label for reports.

        Returns
        -------
        Record

        Raises
        ------
        DataError
            On NaN, decreasing time stamps, a ``'step'`` input that changes more
            than once, an ``'impulse'`` input without a pulse, or an input with
            no excitation at all.
        DimensionError
            On columns of different lengths or fewer than 4 distinct times.
        """
        if kind not in KINDS:
            raise DataError(f"kind must be one of {', '.join(map(repr, KINDS))}; got {kind!r}")
        t, u, y = (np.asarray(a, dtype=float).reshape(-1) for a in (t, u, y))
        label = f"record {name!r}" if name else "record"
        if not t.size == u.size == y.size:
            raise DimensionError(
                f"{label}: t, u and y must have the same length; got {t.size}, {u.size}, {y.size}"
            )
        for nm, a in (("t", t), ("u", u), ("y", y)):
            check_finite(a, f"{label}: {nm}")
        steps = np.diff(t)
        if np.any(steps < 0):
            k = int(np.argmax(steps < 0)) + 1
            raise DataError(
                f"{label}: time stamps must not decrease, but t[{k}] = {t[k]:g} < "
                f"t[{k - 1}] = {t[k - 1]:g}"
            )
        tm, um, ym, wm = _merge_repeated(t, u, y)
        if tm.size < MIN_SAMPLES:
            raise DimensionError(
                f"{label} is too short: {tm.size} distinct sample times, at least "
                f"{MIN_SAMPLES} are needed"
            )
        if kind == "io":
            ub = float(u[0]) if u_before is None else float(u_before)
            return cls(tm, um, ym, kind="io", u_before=ub, name=name, weights=wm)
        if kind == "step":
            start, before, height = _detect_step(t, u, u_before, label)
            return cls(tm, um, ym, kind="step", u_before=before, start=start,
                       amplitude=height, name=name, weights=wm)
        start, area, base = _detect_pulse(t, u, u_before, label)
        return cls(tm, um, ym, kind="impulse", u_before=base, start=start, amplitude=area,
                   name=name, weights=wm)

    @classmethod
    def step_response(
        cls,
        t: ArrayLike,
        y: ArrayLike,
        *,
        amplitude: float = 1.0,
        start: float | None = None,
        u_before: float = 0.0,
        name: str = "",
    ) -> Record:
        """A step record without an input column: a step of ``amplitude`` at ``start``.

        Parameters
        ----------
        t, y : array-like of shape (n_samples,)
            Strictly increasing times and the measured output (any offset).
        amplitude : float, default=1.0
            Step height.
        start : float, optional
            Step instant (default ``t[0]``).
        u_before : float, default=0.0
            Input level before the step.
        name : str, default=''

        Returns
        -------
        Record
        """
        t = np.asarray(t, dtype=float)
        t0 = float(t.reshape(-1)[0]) if start is None and t.size else start
        u = np.where(t >= (t0 or 0.0), u_before + amplitude, u_before)
        return cls(t, u, y, kind="step", u_before=u_before, start=t0, amplitude=amplitude,
                   name=name)

    @classmethod
    def impulse_response(
        cls,
        t: ArrayLike,
        y: ArrayLike,
        *,
        amplitude: float = 1.0,
        start: float | None = None,
        name: str = "",
    ) -> Record:
        """An impulse record without an input column: a Dirac of area ``amplitude`` at ``start``.

        Parameters
        ----------
        t, y : array-like of shape (n_samples,)
        amplitude : float, default=1.0
            Impulse area.
        start : float, optional
            Impulse instant (default ``t[0]``).
        name : str, default=''

        Returns
        -------
        Record
        """
        t = np.asarray(t, dtype=float)
        return cls(t, np.zeros(t.shape), y, kind="impulse", start=start, amplitude=amplitude,
                   name=name)

    def select(self, mask: ArrayLike) -> Record:
        """The record restricted to the samples where ``mask`` is true (same kind and step).

        Parameters
        ----------
        mask : array-like of bool, shape (n_samples,)

        Returns
        -------
        Record
        """
        m = np.asarray(mask, dtype=bool)
        return Record(self.t[m], self.u[m], self.y[m], kind=self.kind, u_before=self.u_before,
                      start=self.start if self.kind != "io" else None,
                      amplitude=self.amplitude, name=self.name, weights=self.weights[m])


# --------------------------------------------------------------------------- normalisation
def _merge_repeated(
    t: NDArray, u: NDArray, y: NDArray
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """One sample per distinct time: mean output, last input, weight = number of rows."""
    tm, first, counts = np.unique(t, return_index=True, return_counts=True)
    if tm.size == t.size:
        return t, u, y, np.ones(t.size)
    last = first + counts - 1
    ym = np.add.reduceat(y, first) / counts
    return tm, u[last], ym, counts.astype(float)


def _detect_step(
    t: NDArray, u: NDArray, u_before: float | None, label: str
) -> tuple[float, float, float]:
    """``(start, level before, height)`` of the single step in ``u``."""
    span = float(np.ptp(u))
    if span <= 1e-12 * max(1.0, float(np.max(np.abs(u)))):
        before = 0.0 if u_before is None else float(u_before)
        height = float(u[0]) - before
        if height == 0:
            raise DataError(
                f"{label}: the input is constant at {u[0]:g} and equals the level before the "
                f"step ({before:g}): there is no step to identify from"
            )
        return float(t[0]), before, height
    k = int(np.argmax(np.abs(np.diff(u)))) + 1
    lo, hi = float(np.median(u[:k])), float(np.median(u[k:]))
    height = hi - lo
    ripple = max(np.max(np.abs(u[:k] - lo)), np.max(np.abs(u[k:] - hi)))
    if ripple > _STEP_TOL * abs(height):
        later = k + int(np.argmax(np.abs(u[k:] - hi) > _STEP_TOL * abs(height)))
        where = f"t = {t[later]:g}" if later < t.size else "before the step"
        raise DataError(
            f"{label}: the input is not a single step (it jumps at t = {t[k]:g} and changes again "
            f"at {where}); use kind='io' for a general input"
        )
    before = lo if u_before is None else float(u_before)
    return float(t[k]), before, hi - before


def _detect_pulse(
    t: NDArray, u: NDArray, u_before: float | None, label: str
) -> tuple[float, float, float]:
    """``(start, area, base level)`` of the pulse in ``u`` (held between samples)."""
    base = float(u[0]) if u_before is None else float(u_before)
    dev = u - base
    scale = float(np.max(np.abs(dev)))
    if scale == 0:
        raise DataError(
            f"{label}: an impulse record needs a pulse in the input, but the input is constant "
            f"({base:g}); give the impulse with Record.impulse_response(t, y, amplitude=...)"
        )
    active = np.flatnonzero(np.abs(dev) > 1e-9 * scale)
    tt, first, counts = np.unique(t, return_index=True, return_counts=True)
    held = np.zeros(t.size)
    # the value that acts from each distinct time on is the last row with that time
    last = first + counts - 1
    widths = np.diff(tt, append=tt[-1] + (tt[-1] - tt[-2] if tt.size > 1 else 1.0))
    held[last] = widths
    area = float(np.sum(dev[active] * held[active]))
    if area == 0:
        raise DataError(f"{label}: the pulse in the input has zero area")
    return float(t[active[0]]), area, base


# --------------------------------------------------------------------------- files
def _first_line(path: Path) -> str:
    try:
        with path.open(encoding="utf-8-sig") as fh:
            for line in fh:
                if line.strip():
                    return line.strip()
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DataError(f"{path} is a directory, not a data file") from None
    except UnicodeDecodeError:
        raise DataError(f"{path} is not a UTF-8 text file") from None
    return ""


def _headerless(line: str) -> bool:
    fields = [f for f in line.replace(",", " ").replace(";", " ").split() if f]
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return bool(fields)


def _read_numbered(path: Path, columns: list[str]) -> dict[str, NDArray[np.float64]]:
    """Columns of a file without a header, addressed by 1-based number."""
    numbers = []
    for col in columns:
        if not col.isdigit() or int(col) < 1:
            raise DataError(
                f"{path} has no header row, so columns must be given by number (1, 2, ...); "
                f"got {col!r}"
            )
        numbers.append(int(col) - 1)
    text = path.read_text(encoding="utf-8-sig").replace(",", " ").replace(";", " ")
    rows = [ln.split() for ln in text.splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]
    width = min(len(r) for r in rows)
    out: dict[str, NDArray[np.float64]] = {}
    for col, j in zip(columns, numbers, strict=True):
        if j >= width:
            raise DataError(f"{path} has no column {j + 1}; its rows have {width} columns")
        values = np.empty(len(rows))
        for i, r in enumerate(rows):
            try:
                values[i] = float(r[j])
            except ValueError:
                raise DataError(f"{path}: column {j + 1}, row {i + 1}: {r[j]!r} is not a number"
                                ) from None
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(f"{path}: column {j + 1}, row {i + 1} is {rows[i][j]!r}; "
                            "values must be finite (no NaN or inf)")
        out[col] = values
    return out


def _read_table(path: str | os.PathLike[str], columns: list[str]) -> dict[str, NDArray[np.float64]]:
    """Named columns of a CSV file with a header, or numbered (1-based) columns without one."""
    from ..data.csv import read_columns

    p = Path(path)
    if _headerless(_first_line(p)):
        return _read_numbered(p, columns)
    return read_columns(p, columns)


def load_records(
    paths: str | os.PathLike[str] | list[str | os.PathLike[str]],
    *,
    input: str,
    output: str,
    time: str | None = None,
    dt: float | None = None,
    record: str | None = None,
    kind: str = "io",
) -> list[Record]:
    """Read identification records from text files (one per file, or split by a column).

    Parameters
    ----------
    paths : path or list of paths
        CSV (or whitespace-separated) files.  With a header row the columns are
        named; files without one (all-numeric first line, e.g. DaISy ``.dat``
        files) take 1-based column numbers (``input='1'``).  An unnamed index
        column, as pandas writes it, is ignored.
    input, output : str
        Input and output columns.
    time : str, optional
        Time column (seconds).  Give exactly one of ``time`` and ``dt``.
    dt : float, optional
        Sampling period for files without a time column: ``t = k * dt``.
    record : str, optional
        Column whose value labels the record of each row (one long file holding
        several experiments); rows keep their order within a record.
    kind : {'io', 'step', 'impulse'}, default='io'
        What every record is (see :meth:`Record.from_data`).

    Returns
    -------
    list of Record

    Raises
    ------
    DataError
        From the file reader (missing file or column, NaN, text), on a bad
        ``dt``, decreasing time stamps, or an input without excitation.
    DimensionError
        If a record has fewer than 4 distinct sample times.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> from kautztwin.ident import load_records
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = pathlib.Path(tmp) / "steps.csv"
    ...     _ = path.write_text("t,u,y,run\\n0,0,1,1\\n0,2,1,1\\n1,2,2,1\\n2,2,3,1\\n3,2,3,1\\n"
    ...                         "0,1,5,2\\n1,1,6,2\\n2,1,7,2\\n3,1,7,2\\n")
    ...     recs = load_records(path, time="t", input="u", output="y", record="run",
    ...                         kind="step")
    >>> [(r.n_samples, r.amplitude) for r in recs]
    [(4, 2.0), (4, 1.0)]
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    if (time is None) == (dt is None):
        raise DataError("give exactly one of time (a column) and dt (a sampling period)")
    if dt is not None and not (np.isfinite(dt) and dt > 0):
        raise DataError(f"dt must be a positive sampling period, got {dt}")
    cols = [c for c in (time, input, output, record) if c is not None]
    if len(set(cols)) != len(cols):
        raise DataError(f"the time, input, output and record columns must differ; got {cols}")
    out: list[Record] = []
    for path in paths:
        data = _read_table(path, cols)
        n = data[input].size
        t = data[time] if time is not None else np.arange(n) * float(dt)
        if record is None:
            out.append(Record.from_data(t, data[input], data[output], kind=kind,
                                        name=str(path)))
            continue
        labels = data[record]
        _, first = np.unique(labels, return_index=True)
        for value in labels[np.sort(first)]:
            m = labels == value
            tag = f"{path} [{record} = {value:g}]"
            tr = t[m] if time is not None else np.arange(int(m.sum())) * float(dt)
            out.append(Record.from_data(tr, data[input][m], data[output][m], kind=kind,
                                        name=tag))
    return out
