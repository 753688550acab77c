"""``kautztwin basis``: plot the functions of a Kautz or Laguerre basis (Figure 2)."""

from __future__ import annotations

import argparse
import math
import sys
import warnings

import numpy as np

from ._common import CLIError, check_output, format_pole, parse_number, parse_poles, print_json

__all__ = ["register", "run"]

_MAX_SAMPLES = 1_000_000

#: largest max|Gram - I| accepted: beyond it the computed functions are not orthonormal
GRAM_TOLERANCE = 1e-6

#: float64 n x n matrices the command holds at once (the network matrix, the Lyapunov
#: solution for the Gram matrix and its Schur-form workspace)
_MATRICES = 6

DESCRIPTION = """\
Plot every function of an orthonormal basis against time (the paper's Figure 2)
and write the figure to --out.  The basis is a Kautz basis with the poles given
by --poles, or a Laguerre basis of --n functions with one repeated real pole
(--laguerre).  Without --dt the basis is continuous (poles with Re p < 0);
with --dt it is the discrete basis with that sampling period (poles |z| < 1).
"""

EPILOG = """\
examples:
  kautztwin basis --poles "-1.1,-0.8,-2.1" --out fig2.png
  kautztwin basis --poles "-1,-3,-0.5+1.9365j,-0.5-1.9365j" --out kautz.png --json
  kautztwin basis --poles "-1,-0.5+-1.9365j" --out pair.png      (a+-bj: both members)
  kautztwin basis --laguerre -1 --n 4 --t-end 12 --out laguerre.png
  kautztwin basis --poles "0.8,0.5+0.3j,0.5-0.3j" --dt 0.1 --out discrete.png
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``basis`` command to the command-line parser."""
    p = subparsers.add_parser(
        "basis", parents=[common], allow_abbrev=False,
        help="plot the functions of a Kautz or Laguerre basis (Figure 2)",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    which = p.add_argument_group("basis (give --poles, or --laguerre with --n)")
    which.add_argument(
        "--poles", metavar="LIST",
        help="comma-separated pole locations, e.g. \"-1.1,-0.8,-2.1\" or "
        "\"-1,-0.5+1.9365j,-0.5-1.9365j\"; list each complex pole with its conjugate "
        "(or write the pair as -0.5+-1.9365j); 'i' may replace 'j'",
    )
    which.add_argument("--laguerre", metavar="POLE",
                       help="a Laguerre basis with this repeated real pole instead of --poles")
    which.add_argument("--n", type=int, metavar="N",
                       help="number of Laguerre functions (with --laguerre)")
    grid = p.add_argument_group("time grid")
    grid.add_argument(
        "--t-end", type=float, metavar="T",
        help="end of the plotted time range in seconds (default: 8 time constants of the "
        "slowest pole, so every function has decayed)",
    )
    grid.add_argument("--samples", type=int, metavar="N",
                      help="continuous bases: number of points on [0, T] (default: 900)")
    grid.add_argument(
        "--dt", type=float, metavar="DT",
        help="make a discrete-time basis with this sampling period (poles inside the unit "
        "circle); it is plotted at t = k*DT, k = 0 ... T/DT",
    )
    out = p.add_argument_group("output")
    out.add_argument("--out", required=True, metavar="FILE",
                     help="figure file to write (.png, .pdf, .svg, ...)")
    out.add_argument(
        "--json", action="store_true",
        help="print one JSON object to stdout: poles ([re, im] pairs), dt, n_functions, the "
        "network matrices A and B, gram_deviation = max|Gram - I|, and the output file",
    )
    p.set_defaults(run=run)


def _n_functions(args: argparse.Namespace) -> int:
    """The number of basis functions the flags ask for (before anything is built)."""
    if args.laguerre is not None:
        if args.n < 1:
            raise CLIError(f"--n must be a positive number of functions, got {args.n}")
        return args.n
    return len(parse_poles(args.poles))


def _check_size(args: argparse.Namespace) -> None:
    """Refuse, before any work, a basis whose matrices would not fit in memory."""
    from .._validation import check_memory

    n = _n_functions(args)
    samples = 900 if args.samples is None else max(args.samples, 0)
    flag = f"--n {n}" if args.laguerre is not None else f"--poles with {n} poles"
    check_memory(
        8.0 * (_MATRICES * float(n) ** 2 + 2.0 * n * min(samples, _MAX_SAMPLES)),
        f"{flag} (a {n} x {n} Gram matrix and {n} curves)",
    )


def _check_orthonormal(basis) -> float:
    """Return max|Gram - I|; refuse a basis that is not orthonormal in floating point."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy's "eigenvalue pair ... perturbing" notice
        gram = basis.gram()
    deviation = float(np.max(np.abs(gram - np.eye(basis.n_functions))))
    if deviation <= GRAM_TOLERANCE:  # also False for NaN
        return deviation
    poles = np.asarray(basis.poles)
    if basis.dt == 0:
        rates = -poles.real
        slow, fast = float(np.min(rates)), float(np.max(np.abs(poles)))
        if fast / slow > 1e9:
            hint = (
                f"the largest pole magnitude ({fast:.3g}) is {fast / slow:.3g} times the "
                f"slowest decay rate ({slow:.3g} 1/s); keep that ratio below about 1e9 "
                "(no pole much nearer the imaginary axis, or much faster, than the rest)"
            )
        else:
            hint = (
                f"the poles ({slow:.3g} to {fast:.3g} 1/s) are too extreme for floating "
                "point; rescale time so that they are moderate numbers (about 1e-6 to 1e6)"
            )
    else:
        hint = "move the poles away from the unit circle"
    raise CLIError(
        f"the basis is not orthonormal in floating point (max |Gram - I| = {deviation:.2e} "
        f"> {GRAM_TOLERANCE:g}): {hint}"
    )


def _basis(args: argparse.Namespace):
    from ..basis import KautzBasis, LaguerreBasis

    dt = 0.0 if args.dt is None else args.dt
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise CLIError(f"--dt must be a positive sampling period, got {args.dt}")
    if (args.poles is None) == (args.laguerre is None):
        raise CLIError("give exactly one of --poles LIST and --laguerre POLE")
    if args.laguerre is not None:
        if args.n is None:
            raise CLIError("--laguerre needs --n, the number of functions")
        pole = parse_number(args.laguerre, "--laguerre")
        return LaguerreBasis(pole if pole.imag else pole.real, args.n, dt=dt)
    if args.n is not None:
        raise CLIError("--n applies to --laguerre only; --poles gives one function per pole")
    return KautzBasis(parse_poles(args.poles), dt=dt)


def _grid(args: argparse.Namespace, basis) -> np.ndarray:
    if args.t_end is not None and not (math.isfinite(args.t_end) and args.t_end > 0):
        raise CLIError(f"--t-end must be a positive time in seconds, got {args.t_end}")
    poles = np.asarray(basis.poles)
    if basis.dt == 0:
        rate = float(np.min(-poles.real))
        t_end = args.t_end if args.t_end is not None else 8.0 / rate
        n = 900 if args.samples is None else args.samples
        if not 2 <= n <= _MAX_SAMPLES:
            raise CLIError(f"--samples must be between 2 and {_MAX_SAMPLES}, got {n}")
        return np.linspace(0.0, t_end, n)
    if args.samples is not None:
        raise CLIError("--samples applies to continuous bases; a discrete basis is plotted at "
                       "t = k*DT up to --t-end")
    if args.t_end is None:
        slowest = float(np.max(np.abs(poles)))
        steps = 10 if slowest == 0 else max(10, math.ceil(8.0 / -math.log(slowest)))
    else:
        steps = math.floor(args.t_end / basis.dt + 1e-9)
    if steps + 1 > _MAX_SAMPLES:
        raise CLIError(f"the plot would need {steps + 1} samples; give a shorter --t-end")
    return basis.dt * np.arange(max(steps, 1) + 1)


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin basis``; return the exit status."""
    from .. import plotting

    out = check_output(args.out, "--out")
    if (args.poles is None) == (args.laguerre is None):
        raise CLIError("give exactly one of --poles LIST and --laguerre POLE")
    if args.laguerre is not None and args.n is None:
        raise CLIError("--laguerre needs --n, the number of functions")
    _check_size(args)
    basis = _basis(args)
    deviation = _check_orthonormal(basis)
    t = _grid(args, basis)
    fig, (ax,) = plotting._new_figure(1, panel_size=(7.5, 4.5))
    plotting.plot_basis(basis, t, ax=ax)
    plotting.save_figure(fig, out)
    if args.json:
        A, B = basis.state_space()
        print_json({
            "poles": [[p.real, p.imag] for p in basis.poles],
            "dt": basis.dt,
            "n_functions": basis.n_functions,
            "A": A,
            "B": B,
            "gram_deviation": deviation,
            "t_end": float(t[-1]),
            "n_samples": int(t.size),
            "out": str(out),
        })
        return 0
    poles = ", ".join(format_pole(p) for p in basis.poles)
    domain = "continuous" if basis.dt == 0 else f"discrete, dt = {basis.dt:g} s"
    sys.stdout.write(
        f"{type(basis).__name__} ({domain}), {basis.n_functions} functions, poles: {poles}\n"
        f"max |Gram - I| = {deviation:.2e}\n"
        f"wrote {out} ({t.size} samples on [0, {t[-1]:g}] s)\n"
    )
    return 0
