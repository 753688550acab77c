"""Entry point of the ``kautztwin`` command (also ``python -m kautztwin``).

Exit status: 0 success, 1 failure (an unexpected internal error), 2 bad input
or usage (a :class:`~kautztwin.exceptions.KautzTwinError`, ``ValueError`` or
``OSError``).  Errors print one line ``kautztwin: error: <message>`` to stderr;
``--debug`` adds the traceback.
"""

from __future__ import annotations

import argparse
import sys
import traceback
import warnings
from collections.abc import Sequence

from .. import __version__
from ..exceptions import KautzTwinError
from . import (
    _approx,
    _basis,
    _export,
    _fleet,
    _identify,
    _plant,
    _reproduce,
    _sensitivity,
    _simulate,
    _train,
    _twin,
)
from ._common import CLIError, join_option_values

__all__ = ["build_parser", "main"]

PROG = "kautztwin"

DESCRIPTION = """\
kautztwin: digital twins of dynamic systems on orthonormal Kautz functions and
neural networks: approximation, identification, DNN estimators, MPC, the twin.

basis, approx and sensitivity run without data files: leave out DATA.csv and the
built-in reference system G(s) = 6/((s+1)(s+3)(s^2+s+4)) of the paper is used.
Poles are written as comma-separated numbers, e.g. "-1,-3,-0.5+1.9365j,-0.5-1.9365j";
each complex pole is listed with its conjugate (or written a+-bj for both).
"""

EPILOG = """\
examples:
  kautztwin basis --poles "-1.1,-0.8,-2.1" --out fig2.png
  kautztwin approx --poles "-1,-3,-0.5+1.9365j,-0.5-1.9365j"
  kautztwin approx examples/measured.csv --time t --response h --optimize-poles 4 --json
  kautztwin sensitivity --poles "-1,-3,-0.5+-1.9365j" --out fig3.png
  kautztwin identify data/tclab_step_tests/step-test-data.csv --time Time --input Q1 \\
      --output T1 --kind step --order 2
  kautztwin reproduce simulation --quick --out sim
  kautztwin twin run --plant hydraulic --duration 90 --drift 0.4 --out twin
  kautztwin twin history twin --start 42 --end 42.1

exit status: 0 success, 1 unexpected failure, 2 bad input or usage.
Run 'kautztwin COMMAND --help' for the flags of a command.
"""


class _UsageError(CLIError):
    """A command line that argparse rejects."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one-line exceptions instead of usage + exit."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise _UsageError(f"{message} (see '{self.prog} --help')")


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser of the ``kautztwin`` command.

    Returns
    -------
    argparse.ArgumentParser
        Parser with the subcommands ``basis``, ``approx`` and ``sensitivity``;
        its ``error`` raises instead of exiting.

    Examples
    --------
    >>> from kautztwin.cli.main import build_parser
    >>> build_parser().parse_args(["basis", "--poles=-1,-2", "--out", "f.png"]).command
    'basis'
    """
    parser = _Parser(
        prog=PROG, description=DESCRIPTION, epilog=EPILOG, allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                        help="print the version and exit")
    debug_help = "on an error, print the full traceback as well as the one-line message"
    parser.add_argument("--debug", action="store_true", help=debug_help)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=debug_help)
    sub = parser.add_subparsers(dest="command", title="commands", metavar="COMMAND")
    _basis.register(sub, common)
    _approx.register(sub, common)
    _sensitivity.register(sub, common)
    _simulate.register(sub, common)
    _train.register(sub, common)
    _reproduce.register(sub, common)
    _identify.register(sub, common)
    _export.register(sub, common)
    _twin.register(sub, common)
    _fleet.register(sub, common)
    _plant.register(sub, common)
    return parser


def _command_names(parser: argparse.ArgumentParser) -> list[str]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    return []  # pragma: no cover


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def _fail(exc: BaseException, code: int, debug: bool) -> int:
    if debug:
        traceback.print_exception(exc, file=sys.stderr)
    message = _one_line(exc)
    if code == 1:
        message = f"unexpected {type(exc).__name__}: {message}"
        if not debug:
            message += " (rerun with --debug for the traceback)"
    sys.stderr.write(f"{PROG}: error: {message}\n")
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``kautztwin`` command line.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; ``sys.argv[1:]`` when omitted.

    Returns
    -------
    int
        Exit status: 0 success, 1 unexpected failure, 2 bad input or usage.
        ``--help`` and ``--version`` return 0.

    Examples
    --------
    >>> from kautztwin.cli.main import main
    >>> main(["approx"])  # neither --poles nor --optimize-poles: one line on stderr
    2
    """
    args_list = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args_list
    parser = build_parser()
    try:
        args = parser.parse_args(join_option_values(args_list))
    except SystemExit as exc:  # --help and --version
        return exc.code if isinstance(exc.code, int) else 0
    except CLIError as exc:
        return _fail(exc, 2, debug=False)
    if args.command is None:
        sys.stderr.write(
            f"{PROG}: error: missing command; choose one of {', '.join(_command_names(parser))} "
            f"(see '{PROG} --help')\n"
        )
        return 2
    debug = bool(args.debug)
    error: tuple[BaseException, int] | None = None
    code = 0
    with warnings.catch_warnings(record=not debug) as caught:
        if not debug:
            warnings.simplefilter("always")
        try:
            code = args.run(args)
        except KeyboardInterrupt:
            sys.stderr.write(f"{PROG}: interrupted\n")
            code = 130
        except (KautzTwinError, ValueError, OSError) as exc:
            error = (exc, 2)
        except Exception as exc:  # the last resort of a command line
            error = (exc, 1)
    for w in caught or []:
        sys.stderr.write(f"{PROG}: warning: {' '.join(str(w.message).split())}\n")
    if error is not None:
        code = _fail(*error, debug)
    return code
