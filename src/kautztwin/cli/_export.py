"""``kautztwin export``: a trained estimator as ONNX, a linear or Kautz model as an FMU."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ._common import CLIError, print_json

__all__ = ["register", "run"]

DESCRIPTION = """\
Export a model for deployment outside Python.

--onnx OUT.onnx   MODEL is a trained estimator's folder (kautztwin train writes
                  OUT/model): the coefficient networks or the adaptive-pole
                  estimator become one ONNX graph from raw records (float64,
                  any batch size) to coefficients (and poles), run by
                  onnxruntime without torch.
--fmu OUT.fmu     MODEL is a linear model's JSON (kautztwin identify --json, or
                  kautztwin approx --json): an FMI 2.0 co-simulation FMU with
                  input u and output y, the exact zero-order-hold recursion at the
                  step --step (a discrete model's own period), compiled from
                  generated C with the local C compiler.

An estimator, after 'kautztwin train --config SPEC.toml --out run1':
  kautztwin export run1/model --onnx estimator.onnx
A linear model, after 'kautztwin identify ... --json > model.json':
  kautztwin export model.json --fmu model.fmu --step 0.5

See docs/export.md.
"""

EPILOG = """\
examples:
  kautztwin export examples/tclab_model.json --fmu tclab.fmu --step 1
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``export`` command to the command-line parser.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``kautztwin`` command's subparsers.
    common : argparse.ArgumentParser
        Parent parser with the flags every command shares (``--debug``).
    """
    p = subparsers.add_parser(
        "export", parents=[common], allow_abbrev=False,
        help="write a trained estimator as ONNX, or a linear/Kautz model as an FMI 2.0 FMU",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", metavar="MODEL",
                   help="estimator folder (--onnx) or linear model JSON (--fmu)")
    target = p.add_mutually_exclusive_group(required=True)
    target.add_argument("--onnx", metavar="OUT.onnx", help="write an ONNX model")
    target.add_argument("--fmu", metavar="OUT.fmu", help="write an FMI 2.0 co-simulation FMU")
    p.add_argument("--dtype", choices=("auto", "float32", "float64"), default=None,
                   help="--onnx: arithmetic of the graph (default auto: float32 for the "
                   "coefficient networks, float64 for the adaptive estimator; docs/export.md)")
    p.add_argument("--step", type=float, metavar="SECONDS",
                   help="--fmu: the FMU's fixed step (required for continuous-time models)")
    p.add_argument("--name", metavar="IDENTIFIER",
                   help="--fmu: model identifier (default: the file name's stem)")
    p.add_argument("--cc", metavar="COMPILER",
                   help="--fmu: C compiler (default: $CC, else cc, gcc or clang)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(run=run)


def _size(path: Path) -> str:
    n = path.stat().st_size
    return f"{n / 2**20:.2f} MiB" if n >= 2**20 else f"{n / 2**10:.1f} KiB"


def _run_onnx(args: argparse.Namespace) -> dict[str, Any]:
    from ..export import export_onnx, load_estimator_file

    model = Path(args.model)
    if model.is_file():
        raise CLIError(f"{args.model} is a file; --onnx takes a trained estimator's folder "
                       "(a linear model's JSON goes to --fmu)")
    for flag in ("step", "name", "cc"):
        if getattr(args, flag) is not None:
            raise CLIError(f"--{flag} applies to --fmu only")
    est = load_estimator_file(model)
    out = export_onnx(est, args.onnx, dtype=args.dtype or "auto")
    return {"target": "onnx", "model": args.model, "out": str(out),
            "estimator": type(est).__name__, "kind": est.kind_, "dtype": _graph_dtype(out),
            "n_samples": int(est.n_samples_), "n_functions": int(est.n_functions_),
            "bytes": out.stat().st_size}


def _graph_dtype(path: Path) -> str:
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    return meta.get("dtype", "")


def _run_fmu(args: argparse.Namespace) -> dict[str, Any]:
    from ..export import discretize, export_fmu, read_model_file

    if args.dtype is not None:
        raise CLIError("--dtype applies to --onnx only")
    model_path = Path(args.model)
    if model_path.is_dir():
        raise CLIError(f"{args.model} is a folder (a trained estimator?); --fmu takes a linear "
                       "model's JSON from 'kautztwin identify --json' or 'approx --json' "
                       "(estimators go to --onnx)")
    model = read_model_file(model_path)
    r = discretize(model, args.step)
    out = export_fmu(model, args.fmu, step=args.step, model_identifier=args.name,
                     compiler=args.cc)
    return {"target": "fmu", "model": args.model, "out": str(out),
            "model_kind": type(model).__name__, "n_states": r.n_states, "step": r.h,
            "delay": float(getattr(model, "delay", 0.0)), "bytes": out.stat().st_size}


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin export``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags.

    Returns
    -------
    int
        Exit status (0; errors are raised and reported by the caller).
    """
    summary = _run_onnx(args) if args.onnx else _run_fmu(args)
    if args.json:
        print_json(summary)
        return 0
    out = Path(summary["out"])
    if summary["target"] == "onnx":
        text = (f"wrote {out} ({_size(out)}): {summary['estimator']}, {summary['n_samples']}-"
                f"sample {summary['kind']} records -> {summary['n_functions']} coefficients "
                f"({summary['dtype']} graph)")
    else:
        delay = f", input delay {summary['delay']:g} s" if summary["delay"] else ""
        text = (f"wrote {out} ({_size(out)}): FMI 2.0 co-simulation, {summary['model_kind']} "
                f"with {summary['n_states']} states, step {summary['step']:g} s{delay}")
    sys.stdout.write(text + "\n")
    return 0
