"""Reading named numeric columns from CSV (or whitespace-separated) text files.

The reader is deliberately strict: every problem with the file is reported as a
one-line :class:`~kautztwin.exceptions.DataError` that names the file, the
column and the row, so that the command-line interface can show it as it is.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..exceptions import DataError

__all__ = ["read_columns"]


def read_columns(
    path: str | os.PathLike[str], columns: list[str]
) -> dict[str, NDArray[np.float64]]:
    """Read named numeric columns from a text file with a header row.

    The first non-blank line names the columns (a leading ``#``, as written by
    ``numpy.savetxt(..., header=...)``, is ignored); every later line is one
    row.  The separator is found from the header: a comma, else a semicolon,
    else a tab, else any run of whitespace.  Blank lines and lines starting
    with ``#`` below the header are skipped.  Columns that are not asked for
    are ignored, and so is an unnamed first index column (as
    ``pandas.DataFrame.to_csv`` writes it: an empty first header field, or one
    field more in every row than the header names).  In semicolon-separated
    files a decimal comma (``0,5``) is accepted.

    Parameters
    ----------
    path : str or os.PathLike
        The file, UTF-8 text (a byte-order mark is allowed).
    columns : list of str
        Names of the columns to read, as written in the header.

    Returns
    -------
    dict of str to ndarray of shape (n_rows,)
        One float64 array per requested column, in the order asked for.

    Raises
    ------
    DataError
        If the file is missing or unreadable, is empty, has no header row (the
        first line is numeric) or no data rows, lacks a requested column (the
        message lists the available ones), or holds an empty, non-numeric or
        non-finite (NaN, inf) value in a requested column (the message names
        the column and the row).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kautztwin.data.csv import read_columns
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = pathlib.Path(tmp) / "step.csv"
    ...     _ = path.write_text("t,u,y\\n0,1,0.0\\n0.5,1,0.4\\n1.0,1,0.7\\n")
    ...     data = read_columns(path, ["t", "y"])
    >>> data["y"]
    array([0. , 0.4, 0.7])
    """
    if isinstance(columns, str):
        columns = [columns]
    columns = list(columns)
    if not columns:
        raise DataError("columns must name at least one column to read")
    name = str(path)
    lines = _read_lines(Path(path), name)

    numbered = [(i + 1, line) for i, line in enumerate(lines) if line.strip()]
    if not numbered:
        raise DataError(f"{name} is empty")
    header_line = numbered[0][1].strip()
    if header_line.startswith("#"):
        header_line = header_line.lstrip("#").strip()
    delimiter = _delimiter(header_line)
    header = [field.strip() for field in _split(header_line, delimiter)]
    if all(_is_number(field) for field in header if field) and any(header):
        raise DataError(
            f"{name} has no header row: its first line {numbered[0][1].strip()!r} is numeric; "
            "the first line must name the columns (for example 't,h')"
        )

    index = _column_index(header, columns, name)
    rows = [(lineno, line) for lineno, line in numbered[1:] if not line.lstrip().startswith("#")]
    if not rows:
        raise DataError(f"{name} has a header but no data rows")

    values = {col: np.empty(len(rows)) for col in columns}
    n_header = len(header)
    for row, (lineno, line) in enumerate(rows, start=1):
        fields = _split(line, delimiter)
        if len(fields) == n_header + 1:
            fields = fields[1:]  # an unnamed leading index column
        elif len(fields) > n_header + 1:
            raise DataError(
                f"{name}, line {lineno}: {len(fields)} fields but the header names "
                f"{n_header} columns"
            )
        for col, j in index.items():
            text = fields[j].strip() if j < len(fields) else ""
            values[col][row - 1] = _parse_value(text, col, row, lineno, name, delimiter)
    return values


def _read_lines(path: Path, name: str) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise DataError(f"{name} is a directory, not a data file") from None
    except UnicodeDecodeError:
        raise DataError(f"{name} is not a UTF-8 text file") from None
    except OSError as exc:
        raise DataError(f"cannot read {name}: {exc.strerror or exc}") from None
    return text.splitlines()


def _delimiter(header: str) -> str | None:
    for candidate in (",", ";", "\t"):
        if candidate in header:
            return candidate
    return None  # any whitespace


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return next(csv.reader([line], delimiter=delimiter, skipinitialspace=True), [])


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _column_index(header: list[str], columns: list[str], name: str) -> dict[str, int]:
    index: dict[str, int] = {}
    for col in columns:
        hits = [j for j, field in enumerate(header) if field == col]
        if not hits:
            available = ", ".join(repr(field) for field in header if field) or "none"
            raise DataError(f"{name} has no column {col!r}; available columns: {available}")
        if len(hits) > 1:
            raise DataError(f"{name} names column {col!r} {len(hits)} times in its header")
        index[col] = hits[0]
    return index


def _parse_value(
    text: str, col: str, row: int, lineno: int, name: str, delimiter: str | None
) -> float:
    where = f"{name}: column {col!r}, row {row} (line {lineno})"
    if not text:
        raise DataError(f"{where} is empty; every row needs a value")
    try:
        value = float(text)
    except ValueError:
        value = None
        if delimiter == ";" and "," in text and "." not in text:
            try:  # decimal comma
                value = float(text.replace(",", "."))
            except ValueError:
                value = None
        if value is None:
            raise DataError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise DataError(f"{where} is {text!r}; values must be finite (no NaN or inf)")
    return value
