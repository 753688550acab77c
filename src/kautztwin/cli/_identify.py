"""``kautztwin identify``: estimate a continuous-time transfer function from measured records."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ._common import CLIError, _jsonable, check_output, format_pole, print_json

__all__ = ["register", "run"]

DESCRIPTION = """\
Estimate a continuous-time transfer function

    G(s) = exp(-tau s) (b_m s^m + ... + b_0) / (s^n + a_{n-1} s^{n-1} + ... + a_0)

from one or many measured records (MATLAB tfest's job): step tests (each with its
own step height, step time and initial offset), impulse tests, or general
input/output data.  Several DATA files are several records, fitted together;
--record COLUMN splits one long file into records instead.

The model is initialised from a Kautz (orthonormal-basis) regression with
optimised poles, reduced to the requested order, and refined by output-error
least squares on the exactly simulated output (zero- or first-order hold
between samples); poles stay stable.  Repeated time stamps (a step logged
twice at t = 0), jittered or missing samples and offsets are handled.

Linear or nonlinear: without --model, one input/output record and no linear
structure given (--order auto, no --zeros, --delay, --fixed-delay or --report),
the transfer function is then compared with nonlinear Kautz models on held-out
blocks of the estimation samples; a nonlinear model is kept only if it fits
them better by more than one standard error (a brief screen costs seconds; the
full nonlinear fit, minutes, runs only when the screen finds the data
nonlinear).  The output says which class was chosen and why.  --model linear
fits the transfer function only.
"""

EPILOG = """\
examples:
  kautztwin identify data/tclab_step_tests/step-test-data.csv --time Time \\
      --input Q1 --output T1 --kind step --order 2
  kautztwin identify data/tclab_step_tests/*.csv --time Time --input Q1 --output T1 \\
      --kind step --order auto --plot tclab.png --json
  kautztwin identify data/daisy_hair_dryer/dryer.dat --dt 0.08 --input 1 --output 2 \\
      --order 3 --delay --validate-from 40
  kautztwin identify data/hydraulic_actuator/actuator.csv --dt 1 --input u --output p \\
      --order 3 --zeros 1 --validate-from 512
  kautztwin identify data/daisy_hair_dryer/dryer.dat --dt 0.08 --input 1 --output 2 \\
      --order 3 --delay --validate-from 40 --report dryer-report

Files without a header row (DaISy .dat) take 1-based column numbers; for one
with two columns, --input and --output default to columns 1 and 2.
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``identify`` command to the command-line parser.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``kautztwin`` command's subparsers.
    common : argparse.ArgumentParser
        Parent parser with the flags every command shares (``--debug``).
    """
    p = subparsers.add_parser(
        "identify", parents=[common], allow_abbrev=False,
        help="estimate a transfer function from step, impulse or input/output records",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    data = p.add_argument_group("data")
    data.add_argument("data", nargs="+", metavar="DATA",
                      help="CSV or whitespace-separated files, one record each (or see --record)")
    data.add_argument("--time", metavar="COLUMN",
                      help="time column in seconds (non-uniform and repeated stamps are fine)")
    data.add_argument("--dt", type=float, metavar="SECONDS",
                      help="sampling period for files without a time column (t = k * dt)")
    data.add_argument("--input", metavar="COLUMN",
                      help="input column (several, comma-separated, fit a MIMO Kautz model); "
                      "required unless the file has no header row and two columns (then 1)")
    data.add_argument("--output", metavar="COLUMN",
                      help="output column (several, comma-separated, fit a MIMO Kautz model); "
                      "required unless the file has no header row and two columns (then 2)")
    data.add_argument("--record", metavar="COLUMN",
                      help="column whose (numeric) value names the record of each row")
    data.add_argument(
        "--kind", choices=("io", "step", "impulse"), default="io",
        help="step: the input is one step (its time, level before and height are read from "
        "the input; a constant input means a step from 0 at the first sample); impulse: a "
        "pulse (area and time read from the input); io: any input (default: %(default)s)",
    )
    model = p.add_argument_group("model")
    model.add_argument("--order", default="auto", metavar="N|auto",
                       help="number of poles, or 'auto' to search orders up to --max-order, "
                       "zeros and delay, choosing by the validation fit (with --validate-from) "
                       "or by the fit on held-out parts of the records (default: %(default)s)")
    model.add_argument("--zeros", type=int, metavar="M",
                       help="number of zeros (default: order - 1, as tfest)")
    model.add_argument("--max-order", type=int, default=None, metavar="N",
                       help="largest order tried by --order auto (default: what the data "
                       "support: 10, more with records over 1000 samples, at most 20)")
    model.add_argument(
        "--model", default=None,
        choices=("linear", "wiener", "hammerstein", "wiener-hammerstein", "volterra", "auto"),
        help="not given (default): the transfer function, or a nonlinear Kautz model where "
        "it fits held-out blocks of the estimation samples clearly better (one io record, no "
        "linear structure given; see above); linear: the transfer function only; the others "
        "fit that nonlinear Kautz model to one io record (auto: the structure and, with "
        "--order auto, 2 or 4 poles chosen by block cross-validation)",
    )
    model.add_argument("--save-model", metavar="FILE",
                       help="write the chosen model as JSON: a nonlinear Kautz model "
                       "(load_nonlinear_model reads it) or the transfer function (the --json "
                       "object, which kautztwin export reads)")
    model.add_argument("--delay", action="store_true", help="estimate an input delay")
    model.add_argument("--fixed-delay", type=float, metavar="SECONDS",
                       help="use this input delay instead of estimating it")
    model.add_argument("--intersample", choices=("zoh", "foh"), default="zoh",
                       help="input between samples of io records: held (zoh) or linear (foh) "
                       "(default: %(default)s)")
    model.add_argument(
        "--initial-state", choices=("auto", "zero", "estimate"), default="auto",
        help="estimate each record's initial state (auto: for io records only; step and "
        "impulse records then start at rest) (default: %(default)s)",
    )
    model.add_argument("--validate-from", type=float, metavar="T",
                       help="estimate on samples with t < T, report the fit on t >= T")
    out = p.add_argument_group("output")
    out.add_argument("--plot", metavar="FILE",
                     help="write a figure of measured and simulated output for every record")
    out.add_argument(
        "--report", metavar="DIR",
        help="write a validation report to DIR (made if missing): report.md and report.json "
        "(the verdict: residuals white, residuals independent of input, with p-values; fits; "
        "parameters with standard deviations; poles), compare.png, residuals.png (residual "
        "autocorrelation and input cross-correlation with confidence bounds), bode.png and "
        "step.png (with confidence bands from the parameter covariance)",
    )
    out.add_argument(
        "--json", action="store_true",
        help="print one JSON object: num, den, poles, zeros ([re, im] pairs), gain, delay, "
        "fit_percent, fit_percent_per_record, validation_fit_percent (with --validate-from), "
        "aic, and the uncertainties, records and order selection",
    )
    p.set_defaults(run=run)


def _order(text: str) -> int | str:
    if text == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        raise CLIError(f"--order must be a positive integer or 'auto'; got {text!r}") from None
    if n < 1:
        raise CLIError(f"--order must be a positive integer or 'auto'; got {text!r}")
    return n


def _check_flags(args: argparse.Namespace) -> int | str:
    """Reject contradicting flags before any data is read; return the order."""
    order = _order(args.order)
    if (args.time is None) == (args.dt is None):
        raise CLIError("give the time column with --time COLUMN, or --dt SECONDS for files "
                       "without one (exactly one of the two)")
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise CLIError(f"--dt must be a positive sampling period; got {args.dt}")
    if args.zeros is not None:
        if args.zeros < 0:
            raise CLIError(f"--zeros must be >= 0; got {args.zeros}")
        if order != "auto" and args.zeros > order:
            raise CLIError(f"--zeros {args.zeros} exceeds --order {order}: the model would be "
                           "improper")
    if args.max_order is not None and args.max_order < 1:
        raise CLIError(f"--max-order must be >= 1; got {args.max_order}")
    if args.delay and args.fixed_delay is not None:
        raise CLIError("give only one of --delay (estimate) and --fixed-delay SECONDS")
    if args.fixed_delay is not None and not (math.isfinite(args.fixed_delay)
                                             and args.fixed_delay >= 0):
        raise CLIError(f"--fixed-delay must be a number >= 0; got {args.fixed_delay}")
    if args.validate_from is not None and not math.isfinite(args.validate_from):
        raise CLIError(f"--validate-from must be a finite time; got {args.validate_from}")
    return order


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin identify``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags.

    Returns
    -------
    int
        Exit status (0; errors are raised and reported by the caller).
    """
    from ..ident import TransferFunctionEstimator, load_records

    order = _check_flags(args)
    _default_columns(args)
    if "," in args.input or "," in args.output:
        if args.model not in (None, "linear"):
            raise CLIError(f"--model {args.model} fits one input and one output; several "
                           "--input/--output columns fit a linear MIMO model (drop --model)")
        from ._identify_mimo import run_mimo

        args.model = "linear"  # the default is the linear MIMO model
        return run_mimo(args, order)
    if args.model not in (None, "linear"):
        from ._identify_nonlinear import run_nonlinear

        return run_nonlinear(args, order)
    plot = check_output(args.plot, "--plot") if args.plot else None
    save = None
    if args.save_model:
        from ._identify_nonlinear import check_model_file

        save = check_model_file(args.save_model)
    report = _check_report_dir(args.report) if args.report else None
    records = load_records(args.data, input=args.input, output=args.output, time=args.time,
                           dt=args.dt, record=args.record, kind=args.kind)
    if args.validate_from is not None and not any(
        np.sum(r.t >= args.validate_from) >= 2 for r in records
    ):
        raise CLIError(f"--validate-from {args.validate_from:g} leaves no validation samples "
                       "(no record has two samples at or after it)")
    delay: bool | float = True if args.delay else (args.fixed_delay or False)
    est = TransferFunctionEstimator(
        n_poles=order, n_zeros=args.zeros, delay=delay, intersample=args.intersample,
        initial_state=args.initial_state, validate_from=args.validate_from,
        max_order=args.max_order,
    )
    est.fit(records)
    model = est.model_
    choice = None
    if args.model is None and _class_choice_applies(args, order, records):
        from ._identify_nonlinear import choose_class

        choice = choose_class(args, est, records[0])
        if choice is not None and choice["model_class"] == "nonlinear":
            return choice["emit"](plot, save)
    summary = model.to_dict()
    summary["kind"] = args.kind
    summary["record_info"] = [
        {"name": r.name, "n_samples": r.n_samples, "t_start": float(r.t[0]),
         "t_end": float(r.t[-1]), "jitter": r.jitter,
         **({"step_time": r.start, "amplitude": r.amplitude, "u_before": r.u_before}
            if r.kind != "io" else {})}
        for r in records
    ]
    if plot is not None:
        _plot(est, records, plot, args)
        summary["plot"] = str(plot)
    if report is not None:
        summary["report"] = _report(est, records, report, args)
    if choice is not None:
        summary["model_class"] = choice["summary"]
    if save is not None:
        summary["model_file"] = str(save)
        save.write_text(json.dumps(_jsonable(summary), indent=1, allow_nan=False) + "\n")
    if args.json:
        print_json(summary)
        return 0
    _print_table(summary, model, records)
    return 0


def _class_choice_applies(args: argparse.Namespace, order: int | str,
                          records: list[Any]) -> bool:
    """Whether the default compares the transfer function with nonlinear models.

    Only for one input/output record with no linear structure given: a single step or
    impulse excites no nonlinearity, and ``--order N``, ``--zeros``, ``--delay``,
    ``--fixed-delay`` and ``--report`` ask for a linear model.
    """
    return (order == "auto" and args.kind == "io" and len(records) == 1
            and args.zeros is None and not args.delay and args.fixed_delay is None
            and not args.report)


def _default_columns(args: argparse.Namespace) -> None:
    """``--input 1 --output 2`` for a header-less two-column file; else a clear error."""
    if args.input is not None and args.output is not None:
        return
    missing = " and ".join(f for f, v in (("--input", args.input), ("--output", args.output))
                           if v is None)
    path = Path(args.data[0])
    line = ""
    try:
        with path.open(encoding="utf-8-sig") as fh:
            line = next((ln.strip() for ln in fh
                         if ln.strip() and not ln.lstrip().startswith("#")), "")
    except (OSError, UnicodeDecodeError):
        pass  # load_records reports an unreadable file
    fields = line.replace(",", " ").replace(";", " ").split()
    try:
        numeric = bool([float(f) for f in fields])
    except ValueError:
        numeric = False
    if numeric and len(fields) == 2 and args.time is None and {args.input, args.output} <= {
            None, "1", "2"}:
        args.input = args.input or ("2" if args.output == "1" else "1")
        args.output = args.output or ("2" if args.input == "1" else "1")
        print(f"note: {path.name} has no header row and two columns: --input {args.input} "
              f"--output {args.output}", file=sys.stderr)
        return
    if not fields:
        what = "could not be read, or is empty"
    elif not numeric:
        what = "has a header row: give column names"
    else:
        what = f"has {len(fields)} columns: give 1-based column numbers"
    raise CLIError(f"give {missing} ({path.name} {what}; only a header-less two-column file "
                   "defaults to --input 1 --output 2)")


def _check_report_dir(text: str) -> Path:
    """Fail early (before the fit) if the report folder cannot be made or written."""
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--report {text}: exists and is not a directory")
    parent = out
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise CLIError(f"--report {text}: {str(parent)!r} is not a directory")
    if not os.access(parent if parent.exists() else Path("."), os.W_OK):
        raise CLIError(f"--report {text}: {str(parent)!r} is not writable")
    return out


def _report(est: Any, records: list[Any], directory: Path,
            args: argparse.Namespace) -> dict[str, Any]:
    """Residual tests, confidence bands and the verdict, written to ``directory``."""
    from ..ident.diagnostics import diagnose
    from ..ident.diagnostics_plots import write_report

    diag = diagnose(est, records)
    paths = write_report(diag, directory, output_name=args.output)
    v = diag.verdict()
    return {"directory": str(directory), "files": sorted(paths),
            "tested_on": v["tested_on"], "residuals_white": v["residuals_white"],
            "whiteness_p_value": v["whiteness_p_value"],
            "residuals_independent_of_input": v["residuals_independent_of_input"],
            "input_p_value": v["input_p_value"]}


def _plot(est: Any, records: list[Any], path: Any, args: argparse.Namespace) -> None:
    """Measured vs simulated output, one panel per record."""
    from .. import plotting

    yhat = est.predict(records)
    fig, axes = plotting._new_figure(len(records), ncols=1, panel_size=(9.0, 3.2))
    model = est.model_
    val = est.validate_from
    for k, (ax, r, yh) in enumerate(zip(axes, records, yhat, strict=True)):
        ax.plot(r.t, r.y, ".", ms=2.5, color="0.35", label="measured")
        ax.plot(r.t, yh, "-", lw=1.5, color="C0", label="simulated model")
        if val is not None and r.t[-1] >= val:
            ax.axvspan(max(val, r.t[0]), r.t[-1], color="C1", alpha=0.08, label="validation")
        title = f"record {k + 1}: {r.name}"
        if k < len(model.fit_percent_per_record) and val is None:
            title += f"  (fit {model.fit_percent_per_record[k]:.2f} %)"
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("t [s]")
        ax.set_ylabel(args.output)
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.legend(fontsize=8, loc="best")
    head = (f"{model.n_poles} poles, {model.n_zeros} zeros, gain {model.gain:.4g}, "
            f"delay {model.delay:.4g} s: fit {model.fit_percent:.2f} %")
    if model.validation_fit_percent is not None:
        head += f", validation {model.validation_fit_percent:.2f} %"
    fig.suptitle(head, fontsize=10)
    plotting.save_figure(fig, path)


def _fmt_poly(c: list[float]) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in c) + "]"


def _print_table(summary: dict[str, Any], model: Any, records: list[Any]) -> None:
    lines = [f"records: {len(records)} ({summary['kind']})"]
    for i, (r, info) in enumerate(zip(records, summary["record_info"], strict=True), start=1):
        extra = ""
        if r.kind != "io":
            extra = f", {r.kind} {r.amplitude:g} at t = {r.start:g} from {r.u_before:g}"
        lines.append(f"  {i}. {r.name}: {r.n_samples} samples on [{r.t[0]:g}, {r.t[-1]:g}] s"
                     f"{extra}, jitter {info['jitter']:.3g} periods")
    std = dict(zip(summary["parameter_names"], summary["parameter_std"], strict=True))
    lines += [
        "",
        f"model:   {model.n_poles} poles, {model.n_zeros} zeros"
        + (f", delay {model.delay:.6g} s" if model.delay else ""),
        f"num      {_fmt_poly(summary['num'])}",
        f"den      {_fmt_poly(summary['den'])}",
        "poles    " + ", ".join(format_pole(p) for p in model.poles),
        "zeros    " + (", ".join(format_pole(z) for z in model.zeros) or "none"),
        f"gain     {model.gain:.6g} +- {model.gain_std:.2g}",
    ]
    if "delay" in std:
        lines.append(f"delay    {model.delay:.6g} +- {std['delay']:.2g} s")
    lines += [
        "",
        f"fit percent  {summary['fit_percent']:.4f} % (simulation, all records)",
    ]
    for i, f in enumerate(summary["fit_percent_per_record"], start=1):
        lines.append(f"  record {i}  {f:.4f} %")
    if "validation_fit_percent" in summary:
        lines.append(f"validation   {summary['validation_fit_percent']:.4f} %")
    lines.append(f"AIC          {summary['aic']:.6g}")
    if "order_selection" in summary:
        lines += ["", "order  zeros        AIC    fit %   validation %"]
        for row in summary["order_selection"]:
            v = row["validation_fit_percent"]
            lines.append(f"{row['n_poles']:>5}  {row['n_zeros']:>5}  {row['aic']:>9.2f}  "
                         f"{row['fit_percent']:>7.3f}  {'-' if v is None else f'{v:.3f}':>12}")
    if "report" in summary:
        rep = summary["report"]
        yn = {True: "yes", False: "no", None: "n/a (no input variation to test against)"}
        p_in = rep["input_p_value"]
        lines += [
            "",
            f"residuals white ({rep['tested_on']} data): {yn[rep['residuals_white']]} "
            f"(p = {rep['whiteness_p_value']:.3g})",
            f"residuals independent of input: {yn[rep['residuals_independent_of_input']]}"
            + ("" if p_in is None else f" (p = {p_in:.3g})"),
            f"wrote the report to {rep['directory']}",
        ]
    if "model_class" in summary:
        from ._identify_nonlinear import class_lines

        lines += ["", *class_lines(summary["model_class"])]
    for key in ("model_file", "plot"):
        if key in summary:
            lines.append(f"wrote {summary[key]}")
    sys.stdout.write("\n".join(lines) + "\n")
