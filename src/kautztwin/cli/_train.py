"""``kautztwin train`` and ``kautztwin estimate``: the DNN estimator from the command line."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from ._common import print_json

__all__ = ["register", "run_estimate", "run_train"]

TRAIN_DESCRIPTION = """\
Train an estimator for a plant family (--family FAMILY.toml: the nominal model,
its tolerances, the noise and the records; everything but the nominal model has
a default) or from a training spec (--config SPEC.toml).

--family trains the adaptive-pole estimator, calibrates its uncertainty on fresh
records and validates it against the oracle on other fresh records.  Writes
OUT/model/ (weights and metadata with the family, the calibration and the
validation report), OUT/report.json and OUT/curves.png.  See docs/nn.md,
"Train for your plant family", and examples/family_5th_order.toml.

--config trains a coefficient estimator from a TOML spec: the nominal model and its
uncertainty, the noise, the time grid, the basis (fixed poles, or 'adaptive' to
predict the poles too), the preset and the budget.  Writes OUT/model/ (weights
and metadata with checksums), OUT/curves.png (training and validation loss)
and OUT/summary.json (training time, final losses, fit on fresh test records
against the noise-free truth).  See docs/nn.md for the spec format.
"""

ESTIMATE_DESCRIPTION = """\
Apply a trained estimator to measured records: prints the Kautz coefficients,
poles and the fit of the estimated model to each record.  The records must be
sampled on the model's training grid; another grid or length is an error.
Several response columns (--response a,b,c) are several records.
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``train`` and ``estimate`` commands to the parser."""
    p = subparsers.add_parser(
        "train",
        parents=[common],
        allow_abbrev=False,
        help="train a DNN estimator for a plant family (--family) or from a spec (--config)",
        description=TRAIN_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--family", metavar="FAMILY.toml", help="a plant family file")
    src.add_argument("--config", metavar="SPEC.toml", help="a training spec")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(run=run_train)

    e = subparsers.add_parser(
        "estimate",
        parents=[common],
        allow_abbrev=False,
        help="estimate Kautz coefficients of records with a trained model",
        description=ESTIMATE_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    e.add_argument("data", metavar="DATA.csv", help="CSV file with a header row")
    e.add_argument("--model", required=True, metavar="DIR", help="model folder from 'train'")
    e.add_argument("--time", default="t", metavar="COLUMN", help="time column (default: t)")
    e.add_argument(
        "--response",
        default="h",
        metavar="COLUMNS",
        help="response column(s), comma-separated; each is one record (default: h)",
    )
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(run=run_estimate)


def run_train(args: argparse.Namespace) -> int:
    """Run ``kautztwin train``."""
    if args.family is not None:
        return _run_family(args)
    from ..experiments import TrainSpec
    from ..experiments.training import train_from_spec

    spec = TrainSpec.from_toml(args.config)
    summary = train_from_spec(spec, args.out, progress=not args.quiet and sys.stderr.isatty())
    if args.json:
        print_json(summary)
        return 0
    _print_summary(summary, args.out)
    return 0


def _run_family(args: argparse.Namespace) -> int:
    """``kautztwin train --family``: train, calibrate, validate, write."""
    from ..nn.family import PlantFamily, train_family, write_family_model

    family = PlantFamily.from_toml(args.family)
    progress = not args.quiet and sys.stderr.isatty()
    estimator, report = train_family(family, progress=progress)
    paths = write_family_model(estimator, report, args.out)
    if args.json:
        print_json({**report, **{k: str(v) for k, v in paths.items()}})
        return 0
    v = report["validation"]
    lines = [
        f"trained the adaptive estimator for {family.system.name!r} "
        f"({family.system.order} poles, {len(family.system.parameter_names)} parameters) on "
        f"{family.n_records} records in {report['train_seconds']:.1f} s (simulation included)",
        f"validation ({v['n_records']} fresh records, fit vs noise-free truth): mean "
        f"{v['fit']['mean']:.2f} %, p10 {v['fit']['p10']:.2f} %, min {v['fit']['min']:.2f} %",
    ]
    if "oracle_fit" in v:
        lines.append(
            f"oracle (true structure, least squares from the true parameters): mean "
            f"{v['oracle_fit']['mean']:.2f} %; estimator - oracle = "
            f"{v['gap_to_oracle']:+.2f} points"
        )
    lines += [
        f"90 % bands cover {100 * v['coverage']['0.9']:.1f} % of the true samples "
        f"(calibration scale {report['calibration']['scale']:.3f}); median relative width "
        f"{v['relative_width']['median']:.3f}",
        f"estimation time {1e6 * v['seconds_per_record']:.0f} us per record (with uncertainty)",
        f"wrote {paths['model']}, {paths['report']}, {paths['curves']}",
    ]
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def _print_summary(s: dict[str, Any], out: str) -> None:
    lines = [
        f"trained {s['estimator']} estimator ({s['preset']} preset) on {s['n_records']} records "
        f"in {s['train_seconds']:.1f} s",
        f"test fit vs noise-free truth ({s['n_test']} fresh records): "
        f"mean {s['test_fit_mean']:.3f} %, median {s['test_fit_median']:.3f} %, "
        f"min {s['test_fit_min']:.3f} %",
        f"estimation time {1e6 * s['seconds_per_record']:.1f} us per record",
        f"wrote {out}/model, {out}/curves.png, {out}/summary.json",
    ]
    sys.stdout.write("\n".join(lines) + "\n")


def run_estimate(args: argparse.Namespace) -> int:
    """Run ``kautztwin estimate``."""
    from ..data.csv import read_columns
    from ..experiments.training import estimate_records, load_estimator

    estimator = load_estimator(args.model)
    names = [c.strip() for c in args.response.split(",") if c.strip()]
    cols = read_columns(args.data, [args.time, *names])
    records = np.array([cols[n] for n in names])
    result = estimate_records(estimator, cols[args.time], records)
    width = None
    unc: dict[str, Any] = {}
    if hasattr(estimator, "estimate"):  # the adaptive estimator carries an uncertainty
        est = estimator.estimate(records, t=cols[args.time])
        unc = est.summary()
        width = est.relative_width
    if args.json:
        print_json({"model": args.model, **result.to_dict(),
                    **({"uncertainty": unc} if unc else {})})
        return 0
    for i, (name, c, poles, fit) in enumerate(zip(
        names, result.coefficients, result.poles, result.fit_percent, strict=True
    )):
        pole_text = ", ".join(
            f"{p.real:.6g}{p.imag:+.6g}j" if p.imag else f"{p.real:.6g}" for p in poles
        )
        sys.stdout.write(
            f"{name}: fit {fit:.3f} %\n  poles        {pole_text}\n"
            f"  coefficients {', '.join(f'{v:.6g}' for v in c)}\n"
        )
        if width is not None:
            state = "calibrated" if unc["calibrated"] else "uncalibrated"
            sys.stdout.write(
                f"  uncertainty  relative width of the {100 * unc['level']:g} % band "
                f"{width[i]:.4f} ({state})\n"
            )
    return 0
