"""``kautztwin train`` and ``kautztwin estimate``: the DNN estimator from the command line."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from ._common import CLIError, print_json

__all__ = ["register", "run_estimate", "run_train"]

TRAIN_DESCRIPTION = """\
Train an estimator for a plant family (--family FAMILY.toml: the nominal model,
its tolerances, the noise and the records; everything but the nominal model has
a default), from a training spec (--config SPEC.toml), or for no plant in
particular (--amortised: one network over random stable systems up to an order).

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

--amortised trains the amortised estimator on random stable systems of orders
1..--max-order (real and complex poles, zeros, delays, white and coloured noise),
time measured in record lengths, so that it applies to any plant's impulse
record; 'kautztwin estimate --model OUT/model [--refine]' then estimates any
record (--refine: variable projection from the network's poles).  Writes
OUT/model/ and OUT/report.json.  kautztwin ships one such model, trained with
the defaults: 'kautztwin estimate' uses it when --model is left out.  See
docs/nn.md, "One network for any plant".
"""

ESTIMATE_DESCRIPTION = """\
Apply a trained estimator to measured records: prints the Kautz coefficients,
poles and the fit of the estimated model to each record.  Several response
columns (--response a,b,c) are several records.

Without --model, the amortised model shipped with kautztwin is used (5 poles,
trained on random stable systems of orders 1..5; AmortisedEstimator.load_default
in Python).  An amortised model (the shipped one, or one from train --amortised)
takes impulse records on any grid starting at the impulse (t >= 0); --refine
polishes its poles by variable projection.  A model from train --config or
--family needs records sampled on its training grid; another grid or length is
an error.
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
    src.add_argument("--amortised", action="store_true",
                     help="one network over random stable systems (no plant file)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    a = p.add_argument_group("--amortised options")
    a.add_argument("--max-order", type=int, metavar="N", help="largest system order (default 5)")
    a.add_argument("--n-records", type=int, metavar="N",
                   help="random training systems (default 40000)")
    a.add_argument("--epochs", type=int, metavar="N", help="training epochs (default 40)")
    a.add_argument("--seed", type=int, metavar="N", help="random state (default 0)")
    p.set_defaults(run=run_train)

    e = subparsers.add_parser(
        "estimate",
        parents=[common],
        allow_abbrev=False,
        help="estimate Kautz coefficients of records (default: the shipped amortised model)",
        description=ESTIMATE_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    e.add_argument("data", metavar="DATA.csv", help="CSV file with a header row")
    e.add_argument("--model", metavar="DIR",
                   help="model folder from 'train' (default: the amortised model shipped "
                        "with kautztwin)")
    e.add_argument("--time", default="t", metavar="COLUMN", help="time column (default: t)")
    e.add_argument(
        "--response",
        default="h",
        metavar="COLUMNS",
        help="response column(s), comma-separated; each is one record (default: h)",
    )
    e.add_argument("--refine", action="store_true",
                   help="amortised models (the default one included): refine the poles by "
                        "variable projection")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(run=run_estimate)


def run_train(args: argparse.Namespace) -> int:
    """Run ``kautztwin train``."""
    amortised_only = [f"--{k.replace('_', '-')}" for k in _AMORTISED_OPTIONS
                      if getattr(args, k) is not None]
    if args.amortised:
        return _run_amortised(args)
    if amortised_only:
        raise CLIError(f"{', '.join(amortised_only)} applies to --amortised only")
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


_AMORTISED_OPTIONS = {"max_order": "max_order", "n_records": "n_records",
                      "epochs": "max_epochs", "seed": "random_state"}


def _run_amortised(args: argparse.Namespace) -> int:
    """``kautztwin train --amortised``: train on random stable systems, write the model."""
    import json
    from pathlib import Path

    from ..nn.amortised import AmortisedEstimator

    params = {v: getattr(args, k) for k, v in _AMORTISED_OPTIONS.items()
              if getattr(args, k) is not None}
    est = AmortisedEstimator(progress=not args.quiet and sys.stderr.isatty(), **params).fit()
    out = Path(args.out)
    model = est.save(out / "model")
    h = est.history_
    report = {
        "estimator": "amortised",
        "params": {k: (list(v) if isinstance(v, tuple) else v)
                   for k, v in est.get_params().items()},
        "train_seconds": est.training_seconds_,
        "best_epoch": h.best_epoch,
        "validation_fit_percent": 100.0 * (1.0 - min(h.val_loss)),
        "model": str(model),
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    if args.json:
        print_json(report)
        return 0
    sys.stdout.write(
        f"trained the amortised estimator (orders 1..{est.max_order}) on {est.n_records} "
        f"random stable systems in {est.training_seconds_:.1f} s\n"
        f"validation (held-out random systems, fit vs noise-free truth): mean "
        f"{report['validation_fit_percent']:.2f} % at epoch {h.best_epoch + 1}\n"
        f"wrote {model}, {out / 'report.json'}\n")
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

    names = [c.strip() for c in args.response.split(",") if c.strip()]
    if args.model is None or _is_amortised(args.model):
        return _estimate_amortised(args, names)
    if args.refine:
        raise CLIError("--refine applies to amortised models (train --amortised) only")
    estimator = load_estimator(args.model)
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


_SHIPPED = "shipped"  # the "model" of the JSON output without --model


def _is_amortised(model: str) -> bool:
    """Whether the model folder holds an amortised estimator (its ``estimator.json``)."""
    import json
    from pathlib import Path

    kind_file = Path(model) / "estimator.json"
    try:
        return json.loads(kind_file.read_text()).get("estimator") == "amortised"
    except (OSError, ValueError, AttributeError):
        return False  # the other estimators' loader reports a missing or malformed folder


def _estimate_amortised(args: argparse.Namespace, names: list[str]) -> int:
    """``kautztwin estimate`` with an amortised model: poles, coefficients, fit per record.

    Without ``--model`` the shipped model (:meth:`AmortisedEstimator.load_default`); the
    JSON names it ``"shipped"`` and the text output says so in its first line.
    """
    from ..data.csv import read_columns
    from ..nn.amortised import AmortisedEstimator

    cols = read_columns(args.data, [args.time, *names])
    records = np.array([cols[n] for n in names])
    shipped = args.model is None
    estimator = AmortisedEstimator.load_default() if shipped else AmortisedEstimator.load(
        args.model)
    est = estimator.estimate(cols[args.time], records, refine=args.refine)
    if args.json:
        body = est.to_dict()
        print_json({"model": _SHIPPED if shipped else args.model, "estimator": "amortised",
                    "refined": est.refined,
                    "records": [
                        {"name": n, "poles": p, "coefficients": c, "fit_percent": f}
                        for n, p, c, f in zip(names, body["poles"], body["coefficients"],
                                              body["fit_percent"], strict=True)]})
        return 0
    if shipped:
        sys.stdout.write(f"model: the amortised model shipped with kautztwin (orders "
                         f"1..{estimator.max_order}, random stable systems; --model DIR "
                         f"for another)\n")
    for name, c, poles, fit in zip(names, est.coefficients, est.poles, est.fit_percent,
                                   strict=True):
        pole_text = ", ".join(
            f"{p.real:.6g}{p.imag:+.6g}j" if p.imag else f"{p.real:.6g}" for p in poles
        )
        sys.stdout.write(
            f"{name}: fit {fit:.3f} %{' (refined)' if est.refined else ''}\n"
            f"  poles        {pole_text}\n"
            f"  coefficients {', '.join(f'{v:.6g}' for v in c)}\n"
        )
    return 0
