"""``kautztwin identify --model wiener|...|auto``, and the default's linear/nonlinear choice.

The nonlinear branch of ``kautztwin identify``: one input/output record, a nonlinear Kautz
model chosen and fitted by :func:`kautztwin.ident.nonlinear.identify_nonlinear` (block
cross-validation on the estimation samples), its free-run simulation scored on the
estimation samples and, with ``--validate-from``, on the validation samples (the simulation
runs over the whole record from the estimated initial state; no validation output is used).

Without ``--model``, :func:`choose_class` asks
:func:`kautztwin.ident.nonlinear.choice.choose_model_class` whether a nonlinear model beats
the transfer function already fitted, on held-out blocks of the estimation samples.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ._common import CLIError, check_output, format_pole, print_json

__all__ = ["check_model_file", "choose_class", "run_nonlinear"]


def run_nonlinear(args: argparse.Namespace, order: int | str) -> int:
    """Fit and report a nonlinear model for ``kautztwin identify --model ...``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags of ``identify``.
    order : int or 'auto'
        ``--order``: the number of poles, or ``'auto'`` (2 and 4 tried).

    Returns
    -------
    int
        Exit status 0 (errors are raised and reported by the caller).
    """
    from ..ident import load_records
    from ..ident.nonlinear import identify_nonlinear

    if args.kind != "io":
        raise CLIError(f"--model {args.model} needs an input/output record (--kind io), "
                       f"not --kind {args.kind}")
    for flag, value in (("--delay", args.delay), ("--fixed-delay", args.fixed_delay),
                        ("--zeros", args.zeros), ("--report", getattr(args, "report", None))):
        if value:
            raise CLIError(f"{flag} applies to linear transfer functions, not to --model "
                           f"{args.model}")
    plot = check_output(args.plot, "--plot") if args.plot else None
    save = check_model_file(args.save_model) if args.save_model else None
    records = load_records(args.data, input=args.input, output=args.output, time=args.time,
                           dt=args.dt, record=args.record, kind="io")
    if len(records) != 1:
        raise CLIError(f"--model {args.model} fits one record; got {len(records)}")
    rec = records[0]
    n_est, dt = _split(rec, args)
    fit = identify_nonlinear(rec.u[:n_est], rec.y[:n_est], model=args.model,
                             n_poles="auto" if order == "auto" else order, dt=dt)
    return _emit(fit, rec, n_est, args, plot, save, args.model)


def _split(rec: Any, args: argparse.Namespace) -> tuple[int, float]:
    """Number of estimation samples (before ``--validate-from``) and the sampling period."""
    n_est = rec.n_samples
    if args.validate_from is not None:
        n_est = int(np.sum(rec.t < args.validate_from))
        if rec.n_samples - n_est < 2:
            raise CLIError(f"--validate-from {args.validate_from:g} leaves no validation "
                           "samples (fewer than two at or after it)")
    dt = float(np.median(np.diff(rec.t))) if rec.n_samples > 1 else 1.0
    return n_est, dt


def choose_class(args: argparse.Namespace, est: Any, rec: Any) -> dict[str, Any] | None:
    """The default's model class: the fitted transfer function or a nonlinear Kautz model.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags of ``identify``.
    est : TransferFunctionEstimator
        The fitted linear estimator (its poles and delay start the comparison).
    rec : Record
        The one input/output record.

    Returns
    -------
    dict or None
        ``model_class`` ('linear' or 'nonlinear'), ``summary`` (JSON-ready: the class, the
        reason, the held-out fit of every candidate) and ``emit(plot, save)``, which prints
        the nonlinear model's report; ``None`` when the estimation samples are too few to
        compare (fewer than 60), the transfer function is integrating (a pole at
        :math:`s = 0`, which the nonlinear Kautz models, stable by construction, cannot
        hold), or the comparison failed (a note on stderr says why).
    """
    from ..exceptions import KautzTwinError
    from ..ident.nonlinear.choice import choose_model_class

    n_est, dt = _split(rec, args)
    if n_est < 60 or float(np.std(rec.u[:n_est])) == 0.0:
        return None
    lin = est.model_
    if lin.integrating:
        print("note: kept the integrating transfer function without comparing nonlinear "
              "models (their poles are stable: they cannot integrate)", file=sys.stderr)
        return None
    try:
        choice = choose_model_class(rec.u[:n_est], rec.y[:n_est], lin.poles, dt=dt,
                                    delay=lin.delay)
    except (KautzTwinError, ImportError) as exc:  # the linear model stands; say why
        print(f"note: kept the transfer function without comparing nonlinear models: {exc}",
              file=sys.stderr)
        return None
    rows = [{k: r[k] for k in ("class", "structure", "map", "n_poles", "n_parameters",
                               "stage", "cv_fit_percent", "seconds", "chosen")}
            for r in choice.candidates]
    summary = {"chosen": choice.model_class, "reason": choice.reason,
               "held_out": "6 contiguous blocks of the estimation samples",
               "candidates": rows, "stages": choice.stages, "seconds": choice.seconds}
    out: dict[str, Any] = {"model_class": choice.model_class, "summary": summary}
    if choice.model_class == "nonlinear":
        linear = {"n_poles": lin.n_poles, "n_zeros": lin.n_zeros, "delay": lin.delay,
                  "fit_percent": lin.fit_percent}
        if lin.validation_fit_percent is not None:
            linear["validation_fit_percent"] = lin.validation_fit_percent
        summary["linear"] = linear
        fit = choice.nonlinear
        assert fit is not None

        def emit(plot: Path | None, save: Path | None) -> int:
            return _emit(fit, rec, n_est, args, plot, save, "default", summary)

        out["emit"] = emit
    return out


def _emit(fit: Any, rec: Any, n_est: int, args: argparse.Namespace, plot: Path | None,
          save: Path | None, asked: str, model_class: dict[str, Any] | None = None) -> int:
    """Score, save, plot and print a nonlinear fit."""
    from ..metrics import fit_percent

    yh = fit.simulate(rec.u)
    summary: dict[str, Any] = {
        "model": asked, "structure": fit.structure, "map": fit.map,
        "n_poles": fit.n_poles, "n_members": len(fit.model.members),
        "poles": [[p.real, p.imag] for p in fit.model.members[0].poles],
        "cv_fit_percent": fit.cv_fit_percent,
        "fit_percent": float(fit_percent(rec.y[:n_est], yh[:n_est])),
        "candidates": fit.candidates, "seconds": fit.seconds,
    }
    if n_est < rec.n_samples:
        summary["validation_fit_percent"] = float(fit_percent(rec.y[n_est:], yh[n_est:]))
    if model_class is not None:
        summary["model_class"] = model_class
    if save is not None:
        fit.model.save(save)
        summary["model_file"] = str(save)
    if plot is not None:
        _plot(rec, yh, n_est, plot, args, summary)
        summary["plot"] = str(plot)
    if args.json:
        print_json(summary)
        return 0
    _print(summary, fit)
    return 0


def check_model_file(text: str) -> Path:
    """Fail before the fit if the ``--save-model`` file cannot be written.

    Parameters
    ----------
    text : str
        The flag's value.

    Returns
    -------
    Path
    """
    out = Path(text)
    if out.is_dir():
        raise CLIError(f"--save-model {text}: is a directory; give a file name such as m.json")
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise CLIError(f"--save-model {text}: directory {str(parent)!r} does not exist")
    return out


def _plot(rec: Any, yh: Any, n_est: int, path: Any, args: argparse.Namespace,
          summary: dict[str, Any]) -> None:
    from .. import plotting

    fig, axes = plotting._new_figure(1, ncols=1, panel_size=(9.0, 3.4))
    ax = axes[0]
    ax.plot(rec.t, rec.y, ".", ms=2.5, color="0.35", label="measured")
    ax.plot(rec.t, yh, "-", lw=1.5, color="C0", label=f"{summary['structure']} (simulated)")
    if n_est < rec.n_samples:
        ax.axvspan(rec.t[n_est], rec.t[-1], color="C1", alpha=0.08, label="validation")
    ax.set_xlabel("t [s]")
    ax.set_ylabel(args.output)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    head = f"{summary['structure']}, {summary['n_poles']} poles: fit {summary['fit_percent']:.2f} %"
    if "validation_fit_percent" in summary:
        head += f", validation {summary['validation_fit_percent']:.2f} %"
    fig.suptitle(head, fontsize=10)
    plotting.save_figure(fig, path)


def _print(summary: dict[str, Any], fit: Any) -> None:
    poles = fit.model.members[0].poles
    lines = [
        f"model:   {summary['structure']} ({summary['map']} map), {summary['n_poles']} poles, "
        f"average of {summary['n_members']} fold/seed models",
        "poles    " + ", ".join(format_pole(p) for p in poles) + "  (first member)",
        "",
        f"cross-validated fit  {summary['cv_fit_percent']:.4f} % (out-of-fold simulation)",
        f"fit percent          {summary['fit_percent']:.4f} % (simulation, estimation samples)",
    ]
    if "validation_fit_percent" in summary:
        lines.append(f"validation           {summary['validation_fit_percent']:.4f} %")
    lines += ["", "structure            map   poles   cv fit %   seconds"]
    for c in summary["candidates"]:
        lines.append(f"{c['structure']:<20} {c['map']:<5} {c['n_poles']:>5}  "
                     f"{c['cv_fit_percent']:>9.3f}  {c['seconds']:>8.1f}")
    if "model_class" in summary:
        lines += ["", *class_lines(summary["model_class"])]
    for key in ("model_file", "plot"):
        if key in summary:
            lines.append(f"wrote {summary[key]}")
    sys.stdout.write("\n".join(lines) + "\n")


def class_lines(mc: dict[str, Any]) -> list[str]:
    """Text lines of the default's model-class choice (reason and held-out fits).

    Parameters
    ----------
    mc : dict
        ``choose_class(...)["summary"]``.

    Returns
    -------
    list of str
    """
    lines = [f"model class  {mc['reason']}",
             f"held-out fits ({mc['held_out']}, {mc['seconds']:.1f} s):",
             "  class      stage    structure            map     poles   held-out fit %"]
    for r in mc["candidates"]:
        mark = "  <- chosen" if r["chosen"] else ""
        lines.append(f"  {r['class']:<10} {r['stage']:<8} {r['structure']:<20} {r['map']:<7} "
                     f"{r['n_poles']:>5}  {r['cv_fit_percent']:>14.3f}{mark}")
    if "linear" in mc:
        lin = mc["linear"]
        v = lin.get("validation_fit_percent")
        lines.append(f"  (transfer function: {lin['n_poles']} poles, {lin['n_zeros']} zeros, "
                     f"fit {lin['fit_percent']:.2f} %"
                     + ("" if v is None else f", validation {v:.2f} %") + ")")
    return lines
