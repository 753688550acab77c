"""``kautztwin identify --input U1,U2 --output Y1,Y2``: a MIMO Kautz model.

The multi-input multi-output branch of ``kautztwin identify`` (several comma-separated
``--input``/``--output`` columns): one uniformly sampled input/output record, a discrete
Kautz model with shared poles fitted by :class:`kautztwin.ident.mimo.MIMOKautzEstimator`
(``--order auto``: the number of poles chosen on the held-out end of the estimation
samples), scored by free-run simulation per output on the estimation samples and, with
``--validate-from``, on the validation samples.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ._common import CLIError, format_pole, print_json

__all__ = ["run_mimo"]


def _columns(text: str, flag: str) -> list[str]:
    cols = [c.strip() for c in text.split(",")]
    if any(not c for c in cols):
        raise CLIError(f"{flag} {text!r}: empty column name in the comma-separated list")
    return cols


def _model_file(text: str) -> Path:
    """Fail before the fit if the model file cannot be written."""
    out = Path(text)
    parent = out.parent if str(out.parent) else Path(".")
    if out.is_dir() or not parent.is_dir():
        raise CLIError(f"--save-model {text}: not a file in an existing directory")
    return out


def run_mimo(args: argparse.Namespace, order: int | str) -> int:
    """Fit and report a MIMO Kautz model for ``kautztwin identify`` with column lists.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags of ``identify``.
    order : int or 'auto'
        ``--order``: the number of shared poles, or ``'auto'`` (1 to ``--max-order``,
        default 6).

    Returns
    -------
    int
        Exit status 0 (errors are raised and reported by the caller).
    """
    from ..ident.mimo import MIMOKautzEstimator, load_mimo_record
    from ..metrics import fit_percent

    inputs = _columns(args.input, "--input")
    outputs = _columns(args.output, "--output")
    unsupported = (
        ("--kind", args.kind != "io"), ("--record", args.record), ("--delay", args.delay),
        ("--fixed-delay", args.fixed_delay is not None), ("--zeros", args.zeros is not None),
        ("--report", getattr(args, "report", None)), ("--plot", args.plot),
        ("--model", getattr(args, "model", "linear") != "linear"),
    )
    for flag, used in unsupported:
        if used:
            raise CLIError(f"{flag} is not supported for a MIMO model (several --input or "
                           "--output columns)")
    if len(args.data) != 1:
        raise CLIError(f"a MIMO model is fitted to one file; got {len(args.data)}")
    save = _model_file(args.save_model) if args.save_model else None
    rec = load_mimo_record(args.data[0], inputs=inputs, outputs=outputs, time=args.time,
                           dt=args.dt)
    n = rec.u.shape[0]
    n_est = n
    if args.validate_from is not None:
        n_est = int(np.sum(rec.t < args.validate_from))
        if n - n_est < 2:
            raise CLIError(f"--validate-from {args.validate_from:g} leaves no validation "
                           "samples (fewer than two at or after it)")
    est = MIMOKautzEstimator(
        n_poles=order, max_poles=args.max_order or 6,
        initial_state="estimate" if args.initial_state == "estimate" else "zero",
    )
    est.fit(rec.u[:n_est], rec.y[:n_est], dt=rec.dt)
    model = est.model_
    yh = np.atleast_2d(model.simulate(rec.u).T).T
    summary: dict[str, Any] = {
        "model": "mimo_kautz", "inputs": inputs, "outputs": outputs, "dt": rec.dt,
        "poles_structure": est.poles_, "n_poles": int(est.n_poles_[0]),
        "poles_z": [[p.real, p.imag] for p in model.poles],
        "n_states": model.n_states,
        "fit_percent": np.atleast_1d(fit_percent(rec.y[:n_est].T, yh[:n_est].T)).tolist(),
        "order_selection": est.selection_,
        "model_dict": model.to_dict(),
    }
    if n_est < n:
        summary["validation_fit_percent"] = np.atleast_1d(
            fit_percent(rec.y[n_est:].T, yh[n_est:].T)).tolist()
    if save is not None:
        model.save(save)
        summary["model_file"] = str(save)
    if args.json:
        print_json(summary)
        return 0
    lines = [
        f"model:   MIMO Kautz, {len(inputs)} inputs x {len(outputs)} outputs, "
        f"{summary['n_poles']} shared poles ({model.n_states} states), dt = {rec.dt:g} s",
        "poles    " + ", ".join(format_pole(p) for p in model.poles) + "  (z-plane)",
        "",
        "output          fit %   " + ("validation %" if n_est < n else ""),
    ]
    val = summary.get("validation_fit_percent", [None] * len(outputs))
    for name, f, v in zip(outputs, summary["fit_percent"], val, strict=True):
        lines.append(f"{name:<12} {f:>8.3f}   " + ("" if v is None else f"{v:>10.3f}"))
    if "model_file" in summary:
        lines += ["", f"wrote {summary['model_file']}"]
    sys.stdout.write("\n".join(lines) + "\n")
    return 0
