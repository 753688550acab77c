"""``kautztwin approx``: approximate a sampled impulse or step response in a Kautz basis."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from ._common import (
    CLIError,
    add_data_arguments,
    check_output,
    format_pole,
    load_record,
    parse_poles,
    print_json,
)

__all__ = ["register", "run"]

DESCRIPTION = """\
Approximate a sampled impulse or step response by a Kautz model
G_N(s) = sum_i c_i K_i(s) and report the coefficients c_i, the poles, the
integral of squared error (ISE) and the fit percent.

The poles are either given (--poles; the coefficients are then the orthogonal
projection of the record onto the basis, or a least-squares fit) or chosen
automatically (--optimize-poles N: N poles minimising the error, by variable
projection).  Give exactly one of the two.

The model is per unit input: a step of height A (or an impulse of area A)
is divided by A first, given by --amplitude A or, for a step, read from the
record's input column with --input COLUMN.  Without either, DATA is taken to be
a unit response, and a record of a step of 0.5 gives half the gain.

A search that stops at its iteration budget with a pair of complex poles
collapsing onto the real axis (the best model wants two equal real poles) is
restarted once from those real poles; if it still does not converge, the
warning says so and a larger --max-iter or another N may help.

Without DATA the built-in reference system 6/((s+1)(s+3)(s^2+s+4)) is used
(900 samples on [0, 20] s), optionally with --noise, so the command runs with
no data at all.
"""

EPILOG = """\
examples:
  kautztwin approx --poles "-1,-3,-0.5+1.9365j,-0.5-1.9365j"
  kautztwin approx --poles "-1,-3,-0.5+-1.9365j" --kind step --noise 0.05 --plot fit.png
  kautztwin approx --optimize-poles 4 --json
  kautztwin simulate hydraulic --records 1 --out data
  kautztwin approx data/record_01.csv --time t --response y --input u --kind step \\
      --optimize-poles 3                       (a step of 0.5: the gain is per unit command)
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``approx`` command to the command-line parser."""
    p = subparsers.add_parser(
        "approx", parents=[common], allow_abbrev=False,
        help="approximate an impulse or step response in a Kautz basis",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    data = p.add_argument_group("data")
    add_data_arguments(data, noise=True)
    poles = p.add_argument_group("poles (give exactly one of --poles and --optimize-poles)")
    poles.add_argument(
        "--poles", metavar="LIST",
        help="comma-separated basis poles, e.g. \"-1,-3,-0.5+1.9365j,-0.5-1.9365j\"; each "
        "complex pole with its conjugate (or a+-bj for both); 'i' may replace 'j'",
    )
    poles.add_argument("--optimize-poles", type=int, metavar="N",
                       help="choose N poles automatically (minimum approximation error)")
    poles.add_argument(
        "--method", choices=("quadrature", "lstsq"), default=None,
        help="with --poles: 'quadrature' projects the record onto the orthonormal basis "
        "(Simpson's rule; needs a record long enough to decay), 'lstsq' fits the record by "
        "least squares on its grid (better for short records) (default: quadrature)",
    )
    poles.add_argument("--max-iter", type=int, default=None, metavar="N",
                       help="with --optimize-poles: iteration budget per start (default: 100)")
    out = p.add_argument_group("output")
    out.add_argument("--plot", metavar="FILE",
                     help="also write a figure of the record and the approximant (.png, .pdf, ...)")
    out.add_argument(
        "--json", action="store_true",
        help="print one JSON object instead of the table: coefficients, poles ([re, im] "
        "pairs), ise, fit_percent, kind, dc_gain (per unit input), amplitude, source, "
        "n_samples; with --poles also mse "
        "and dt, with --optimize-poles also initial_poles, success, message, n_evaluations",
    )
    p.set_defaults(run=run)


def _optimize(args: argparse.Namespace, t: np.ndarray, y: np.ndarray) -> Any:
    """optimize_poles, restarted once from real poles when a pair collapsed unconverged."""
    import kautztwin

    kwargs = {} if args.max_iter is None else {"max_iter": args.max_iter}
    return kautztwin.optimize_poles(t, y, args.optimize_poles, kind=args.kind,
                                    restart_collapsed=True, **kwargs)


def _fit(args: argparse.Namespace, t: np.ndarray, y: np.ndarray) -> tuple[Any, dict[str, Any], str]:
    """Call the library; return (model, JSON-ready summary, short method name)."""
    import kautztwin

    if args.poles is not None:
        basis = kautztwin.KautzBasis(parse_poles(args.poles))
        method = args.method or "quadrature"
        res = kautztwin.approximate(basis, t, y, kind=args.kind, method=method)
        return res.model, res.to_dict(), method
    res = _optimize(args, t, y)
    summary = res.to_dict()
    summary.setdefault("kind", args.kind)
    summary.setdefault("dc_gain", res.model.dc_gain)
    if not res.success:
        sys.stderr.write(
            f"kautztwin: warning: the pole search did not converge: {res.message} (the poles "
            "are the best found; try a larger --max-iter, or another --optimize-poles N)\n"
        )
    return res.model, summary, "optimized poles (variable projection)"


def _check_flags(args: argparse.Namespace) -> None:
    """Reject contradicting flags before any data is read."""
    if args.poles is None and args.optimize_poles is None:
        raise CLIError(
            "give the basis poles with --poles LIST, or --optimize-poles N to choose them"
        )
    if args.poles is not None and args.optimize_poles is not None:
        raise CLIError("give only one of --poles and --optimize-poles")
    if args.poles is not None and args.max_iter is not None:
        raise CLIError("--max-iter applies to --optimize-poles only")
    if args.optimize_poles is not None:
        if args.method is not None:
            raise CLIError(
                "--method applies to --poles only; --optimize-poles fits by least squares"
            )
        if args.optimize_poles < 1:
            raise CLIError(f"--optimize-poles needs N >= 1 poles, got {args.optimize_poles}")
        if args.max_iter is not None and args.max_iter < 1:
            raise CLIError(f"--max-iter must be >= 1, got {args.max_iter}")


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin approx``; return the exit status."""
    _check_flags(args)
    plot = check_output(args.plot, "--plot") if args.plot else None
    record = load_record(args)
    model, summary, method = _fit(args, record.t, record.y)
    summary.update(source=record.source, n_samples=int(record.t.size),
                   amplitude=record.amplitude)
    if args.data is None and args.noise:
        # built-in reference with noise: also say how close the model is to the noise-free truth
        from ..data import reference_response
        from ..metrics import fit_percent

        _, clean = reference_response(kind=args.kind)
        yhat = model.impulse(record.t) if args.kind == "impulse" else model.step(record.t)
        summary["fit_percent_truth"] = float(fit_percent(clean, yhat))
    if plot is not None:
        from .. import plotting

        yhat = model.impulse(record.t) if args.kind == "impulse" else model.step(record.t)
        fig, (ax,) = plotting._new_figure(1, panel_size=(7.5, 4.5))
        plotting.plot_approximation(
            record.t, record.y, yhat, ax=ax,
            ylabel=f"{args.kind} response" + (" per unit input" if record.amplitude != 1 else ""),
            approx_label=f"Kautz approximant, N = {model.n_functions}",
            title=f"fit {summary['fit_percent']:.3f} %, ISE {summary['ise']:.3g}",
        )
        plotting.save_figure(fig, plot)
        summary["plot"] = str(plot)
    if args.json:
        print_json(summary)
        return 0
    _print_table(summary, model, method, record)
    return 0


def _kind_phrase(kind: str) -> str:
    """``'a step of'`` or ``'an impulse of area'``: the input's size in words.

    Parameters
    ----------
    kind : {'impulse', 'step'}

    Returns
    -------
    str
    """
    return "a step of" if kind == "step" else "an impulse of area"


def _print_table(summary: dict[str, Any], model: Any, method: str, record: Any) -> None:
    t = record.t
    lines = [
        f"data:    {summary['source']}, {t.size} samples on [{t[0]:g}, {t[-1]:g}] s",
    ]
    if record.amplitude != 1:
        lines.append(
            f"input:   {_kind_phrase(summary['kind'])} {record.amplitude:g} "
            f"({record.amplitude_source}); the response is divided by it, so the model, its "
            "coefficients and DC gain are per unit input"
        )
    lines += [
        f"method:  {method}",
        "",
        f"{'i':>3}  {'pole':<24}{'coefficient':>18}",
    ]
    for i, (p, c) in enumerate(zip(model.poles, model.coefficients, strict=True), start=1):
        lines.append(f"{i:>3}  {format_pole(p):<24}{c:>18.12g}")
    lines += [
        "",
        f"ISE          {summary['ise']:.6g}",
        f"fit percent  {summary['fit_percent']:.6f} %",
    ]
    if "fit_percent_truth" in summary:
        lines.append(f"  vs truth   {summary['fit_percent_truth']:.6f} % (the noise-free response)")
    lines += [
        f"DC gain      {summary['dc_gain']:.6g}",
    ]
    if "initial_poles" in summary:
        initial = ", ".join(format_pole(complex(*p)) for p in summary["initial_poles"])
        lines.append(f"start poles  {initial}")
        lines.append(f"converged    {summary.get('success')} ({summary.get('message')})")
    if "plot" in summary:
        lines.append(f"wrote {summary['plot']}")
    sys.stdout.write("\n".join(lines) + "\n")
