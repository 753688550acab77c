"""Shared pieces of the commands: flag parsing, data loading, output (no numerics)."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..exceptions import DataError, KautzTwinError, PoleError

__all__ = [
    "CLIError",
    "Record",
    "add_data_arguments",
    "check_output",
    "format_pole",
    "join_option_values",
    "load_record",
    "parse_number",
    "parse_poles",
    "parse_span",
    "print_json",
    "stop_on_signals",
]

#: flags whose values may start with "-" (negative poles); see join_option_values
VALUE_FLAGS = ("--poles", "--laguerre", "--span")

_MANTISSA = r"(?:[^+\-±eE]|[eE](?=[+-]?\d)[+-]?)+?"  # a number; 'e-9' exponents allowed
_PAIR = re.compile(
    rf"^(?P<re>[+-]?{_MANTISSA})(?:\+-|\+/-|±)(?P<im>(?:[^+\-±eE]|[eE][+-]?)+)$"
)


class CLIError(KautzTwinError, ValueError):
    """Invalid command-line input (exit status 2)."""


def join_option_values(argv: list[str]) -> list[str]:
    """Glue ``--poles -1,-2`` into ``--poles=-1,-2`` so argparse takes it as a value.

    argparse reads a value that starts with ``-`` (and is not a plain negative
    number) as an option; pole lists always start with ``-``.

    Parameters
    ----------
    argv : list of str
        Command-line arguments without the program name.

    Returns
    -------
    list of str
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg in VALUE_FLAGS and i + 1 < len(argv) and not argv[i + 1].startswith("--"):
            out.append(f"{arg}={argv[i + 1]}")
            i += 2
            continue
        out.append(arg)
        i += 1
    return out


def _number(token: str, flag: str, text: str) -> complex:
    s = re.sub(r"[iI]$", "j", token)
    try:
        return complex(s)
    except ValueError:
        raise PoleError(
            f"{flag}: cannot read {token!r} in {text!r} as a number; write poles like "
            "-1.5 or -0.5+1.9j (or the pair -0.5+-1.9j)"
        ) from None


def parse_poles(text: str, flag: str = "--poles") -> list[complex]:
    """Read a comma-separated pole list such as ``"-1,-3,-0.5+1.94j,-0.5-1.94j"``.

    Entries are Python-style numbers; ``i`` may stand for ``j``, spaces are
    ignored, and ``a+-bj`` (or ``a±bj``) is shorthand for the conjugate pair
    ``a+bj, a-bj``.  Stability and pairing are checked by the library
    (:class:`~kautztwin.KautzBasis`), not here.

    Parameters
    ----------
    text : str
        The flag's value.
    flag : str, default='--poles'
        Flag name for error messages.

    Returns
    -------
    list of complex

    Raises
    ------
    PoleError
        If an entry is empty or not a number.

    Examples
    --------
    >>> from kautztwin.cli._common import parse_poles
    >>> parse_poles("-1, -0.5+-2i")
    [(-1+0j), (-0.5+2j), (-0.5-2j)]
    """
    tokens = text.split(",")
    poles: list[complex] = []
    for k, raw in enumerate(tokens, start=1):
        token = re.sub(r"\s+", "", raw)
        if not token:
            raise PoleError(
                f"{flag}: entry {k} of {text!r} is empty; separate poles by single commas"
            )
        pair = _PAIR.match(token)
        if pair:
            re_part = _number(pair["re"], flag, text).real
            im_text = pair["im"] if pair["im"][-1] in "jJiI" else pair["im"] + "j"
            im_part = _number(im_text, flag, text).imag
            poles += [complex(re_part, im_part), complex(re_part, -im_part)]
        else:
            poles.append(_number(token, flag, text))
    return poles


def parse_number(text: str, flag: str) -> complex:
    """Read one number (real or complex) given to ``flag``.

    Parameters
    ----------
    text : str
    flag : str

    Returns
    -------
    complex
    """
    return _number(re.sub(r"\s+", "", text), flag, text)


def parse_span(text: str) -> tuple[float, float]:
    """Read ``--span LO:HI`` (two factors, ``0 < LO < HI``).

    Parameters
    ----------
    text : str

    Returns
    -------
    (float, float)

    Raises
    ------
    CLIError
        If the value is not two increasing positive numbers.
    """
    parts = text.split(":")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise CLIError(
            f"--span must be LO:HI, two positive factors such as 0.2:3; got {text!r}"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
        raise CLIError(f"--span needs 0 < LO < HI (finite); got {text!r}")
    return lo, hi


#: largest relative spread (max - min over |median|) of an --input column that is still one step
STEP_INPUT_TOLERANCE = 0.01


@dataclass(frozen=True)
class Record:
    """One sampled response and where it came from.

    Attributes
    ----------
    t : ndarray
        Sample times.
    y : ndarray
        The response per unit input (already divided by ``amplitude``).
    source : str
        Where the record came from, for the report.
    amplitude : float
        The input's size the measured response was divided by (1 for a unit input).
    amplitude_source : str
        How ``amplitude`` was found (``'--amplitude'``, ``"column 'u'"``), empty for 1.
    """

    t: NDArray[np.float64]
    y: NDArray[np.float64]
    source: str
    amplitude: float = 1.0
    amplitude_source: str = ""


def add_data_arguments(parser: Any, *, noise: bool) -> None:
    """Add DATA, --time, --response, --kind, --amplitude, --input (and --noise/--seed).

    Parameters
    ----------
    parser : argparse.ArgumentParser or argument group
        Where the arguments go.
    noise : bool
        Also add ``--noise`` and ``--seed`` (built-in reference only).
    """
    parser.add_argument(
        "data", nargs="?", metavar="DATA.csv",
        help="CSV file with a header row (comma, semicolon, tab or whitespace separated). "
        "Omit it to use the built-in reference system G(s) = 6/((s+1)(s+3)(s^2+s+4)) "
        "sampled at 900 points on [0, 20] s.",
    )
    parser.add_argument("--time", default="t", metavar="COLUMN",
                        help="name of the time column in DATA (default: %(default)s)")
    parser.add_argument("--response", default="h", metavar="COLUMN",
                        help="name of the response column in DATA (default: %(default)s)")
    parser.add_argument(
        "--kind", choices=("impulse", "step"), default="impulse",
        help="what the response is: an impulse response, or a step response from rest; a "
        "unit impulse or step unless --amplitude or --input gives its size (default: "
        "%(default)s)",
    )
    parser.add_argument(
        "--amplitude", type=float, default=None, metavar="A",
        help="DATA only: size of the input that produced the response (the step's height, or "
        "the impulse's area); the response is divided by A, so coefficients and DC gain are "
        "per unit input (default: 1)",
    )
    parser.add_argument(
        "--input", default=None, metavar="COLUMN",
        help="DATA only, --kind step: read the step's height from this input column (constant "
        "from t = 0, as in 'kautztwin simulate' records) instead of giving --amplitude",
    )
    if noise:
        parser.add_argument(
            "--noise", type=float, default=None, metavar="FRACTION",
            help="built-in reference only: add white Gaussian noise with this standard deviation, "
            "as a fraction of the response's peak (0.1 = 10%%; default: 0)",
        )
        parser.add_argument("--seed", type=int, default=None,
                            help="built-in reference only: seed of the noise (default: 0)")


def load_record(args: argparse.Namespace) -> Record:
    """The response to work on: the CSV columns, or the built-in reference response.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags of a command that used :func:`add_data_arguments`.

    Returns
    -------
    Record
        Its response is per unit input: divided by ``--amplitude`` or by the
        step height read from the ``--input`` column.

    Raises
    ------
    DataError
        From the CSV reader (missing file or column, NaN, ...) or on a time
        column that is not strictly increasing.
    CLIError
        On flags that contradict each other, or an ``--input`` column that is
        not one constant step.
    """
    from .._validation import check_time
    from ..data import reference_response
    from ..data.csv import read_columns

    _check_input_flags(args)
    noise = getattr(args, "noise", None)
    seed = getattr(args, "seed", None)
    if args.data is None:
        if noise is not None and not (math.isfinite(noise) and noise >= 0):
            raise CLIError(f"--noise must be a fraction >= 0, got {noise}")
        t, y = reference_response(kind=args.kind, noise=noise or 0.0,
                                  random_state=0 if seed is None else seed)
        extra = f", noise {noise:g} of peak (seed {0 if seed is None else seed})" if noise else ""
        return Record(t, y, f"built-in reference system, {args.kind} response{extra}")
    if noise is not None or seed is not None:
        raise CLIError("--noise and --seed apply to the built-in reference only; drop them or DATA")
    if args.time == args.response:
        raise CLIError(f"--time and --response name the same column {args.time!r}")
    input_column = getattr(args, "input", None)
    names = [args.time, args.response]
    if input_column is not None:
        if input_column in names:
            raise CLIError(f"--input names the {input_column!r} column that is already "
                           f"--{'time' if input_column == args.time else 'response'}")
        names.append(input_column)
    cols = read_columns(args.data, names)
    t = cols[args.time]
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1  # 0-based index of the offending sample
        raise DataError(
            f"{args.data}: time column {args.time!r} must be strictly increasing, but row {k + 1} "
            f"({args.time} = {t[k]:g}) does not come after row {k} ({args.time} = {t[k - 1]:g})"
        )
    t = check_time(t, name=f"time column {args.time!r}")
    source = f"{args.data} (columns {args.time}, {args.response})"
    amplitude, how = _input_size(args, cols.get(input_column) if input_column else None)
    if amplitude == 1.0:
        return Record(t, cols[args.response], source)
    return Record(t, cols[args.response] / amplitude, source, amplitude, how)


def _check_input_flags(args: argparse.Namespace) -> None:
    """Reject --amplitude / --input where they do not apply (before any data is read)."""
    amplitude = getattr(args, "amplitude", None)
    input_column = getattr(args, "input", None)
    if amplitude is None and input_column is None:
        return
    if amplitude is not None and input_column is not None:
        raise CLIError("give only one of --amplitude A and --input COLUMN (the step's size)")
    if args.data is None:
        raise CLIError("--amplitude and --input apply to DATA only; the built-in reference "
                       "response is already per unit input")
    if input_column is not None and args.kind != "step":
        raise CLIError("--input applies to --kind step; give an impulse's area with --amplitude")
    if amplitude is not None and not (math.isfinite(amplitude) and amplitude != 0):
        raise CLIError(f"--amplitude must be a finite nonzero number, got {amplitude:g}")


def _input_size(args: argparse.Namespace, u: NDArray[np.float64] | None) -> tuple[float, str]:
    """The size of the input (and how it was found): --amplitude, the --input column, or 1."""
    amplitude = getattr(args, "amplitude", None)
    if amplitude is not None:
        return float(amplitude), "--amplitude"
    if u is None:
        return 1.0, ""
    level = float(np.median(u))
    spread = float(np.max(u) - np.min(u))
    if level == 0 or spread > STEP_INPUT_TOLERANCE * abs(level):
        raise CLIError(
            f"--input {args.input}: not one step from rest at t = 0 (the column ranges from "
            f"{np.min(u):g} to {np.max(u):g}); approx needs a constant input after the step "
            "(give its height with --amplitude), or use 'kautztwin identify' for any input"
        )
    return level, f"column {args.input!r}"


def check_output(path: str, flag: str) -> Path:
    """Fail early (before any computation) if a figure cannot be written to ``path``.

    Parameters
    ----------
    path : str
    flag : str

    Returns
    -------
    pathlib.Path

    Raises
    ------
    CLIError
        If the folder is missing, ``path`` is a folder, or matplotlib cannot
        write the format its extension asks for.
    """
    from matplotlib.backend_bases import FigureCanvasBase

    out = Path(path)
    if out.is_dir():
        raise CLIError(f"{flag} {path}: is a directory; give a file name such as fig.png")
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise CLIError(f"{flag} {path}: directory {str(parent)!r} does not exist")
    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = out.suffix[1:].lower()
    if suffix and suffix not in formats:
        raise CLIError(
            f"{flag} {path}: unknown figure format {suffix!r}; "
            f"use one of {', '.join(sorted(formats))}"
        )
    return out


def format_pole(p: complex) -> str:
    """Short text of a pole: ``-1`` or ``-0.5+1.93649j``."""
    p = complex(p)
    if p.imag == 0:
        return f"{p.real:.6g}"
    return f"{p.real:.6g}{p.imag:+.6g}j"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (complex, np.complexfloating)):
        return [_jsonable(obj.real), _jsonable(obj.imag)]
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        value = float(obj)
        return value if math.isfinite(value) else None
    return obj


def print_json(obj: dict[str, Any]) -> None:
    """Print one JSON object to stdout: a key per line, NaN/inf as null, complex as [re, im]."""
    data = _jsonable(obj)
    items = [
        f"  {json.dumps(key)}: {json.dumps(value, allow_nan=False)}" for key, value in data.items()
    ]
    sys.stdout.write("{\n" + ",\n".join(items) + "\n}\n")


@contextlib.contextmanager
def stop_on_signals(stop: Callable[[], Any]) -> Iterator[None]:
    """Call ``stop()`` on SIGINT or SIGTERM while the block runs; restore the handlers after.

    Signal handlers can only be set from the main thread; elsewhere (a command run
    from a worker thread, as some tests do) the block runs with the handlers unchanged.

    Parameters
    ----------
    stop : callable
        Called without arguments when either signal arrives (a request to stop).
    """
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop())
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
