"""Benchmark of the amortised estimator on a held-out family it was never trained on.

The family is ``examples/family_5th_order.toml`` (5th order with a zero, +-30 % on every
parameter, 5 % AR(1) noise, impulse records), the one of ``bench_family.py``; the records
are the same (``family_dataset(family, n_test, 12345)``) and so is the metric: the fit
percent of each estimate's noise-free response against the noise-free truth, averaged.

* **amortised** -- the shipped model (``src/kautztwin/nn/amortised/pretrained``, trained on
  random stable systems only by ``examples/amortised_estimator.py --train``), or one
  trained here (``--train``): network poles, least-squares coefficients;
* **amortised + VARPRO** -- the same, refined by variable projection from the network's
  poles (:meth:`AmortisedEstimator.estimate` with ``refine=True``);
* **oracle** -- least squares in the true structure started at the true parameters
  (:func:`kautztwin.nn.oracle_fit`, as ``bench_family.py``), on the first ``--n-oracle``
  records, with the amortised figures on the same records for a paired comparison;
* **VARPRO from Prony** -- :func:`kautztwin.optimize_poles` with ``init=5`` (its own
  starts: Prony, spread real poles, pairs) on the same subset: what the network's start
  is worth;
* **prior-scale sweep** -- the MAP refinement's ``prior_scale`` on ``--n-sweep`` fresh
  random stable systems (the training distribution, where the default was chosen) and,
  for information only, on the family's first ``--n-oracle`` records; plain
  variable projection (``refine_method='varpro'``) beside it;
* **per-family estimator** -- quoted from ``benchmarks/results/family.json`` (the adaptive
  estimator trained on this very family, same records); ``--family-json`` names another.

Times are per record, single-threaded, with the machine's load recorded.

Usage::

    python benchmarks/bench_amortised.py [--quick] [--train] [--n-test 500] [--n-oracle 100]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 - the thread variables must be set before numpy loads
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from kautztwin.approx import optimize_poles  # noqa: E402
from kautztwin.exceptions import ConvergenceWarning  # noqa: E402
from kautztwin.metrics import fit_percent  # noqa: E402
from kautztwin.nn.amortised import AmortisedEstimator, random_systems  # noqa: E402
from kautztwin.nn.family import PlantFamily, family_dataset, train_family  # noqa: E402
from kautztwin.nn.oracle import oracle_fit  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import benchmark_result, machine_info, write_json  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
FAMILY = ROOT / "examples" / "family_5th_order.toml"
MODEL = ROOT / "src" / "kautztwin" / "nn" / "amortised" / "pretrained"  # the shipped model
TEST_SEED = 12345  # bench_family.py's test records


def _summary(values: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(values)), "median": float(np.median(values)),
            "p10": float(np.percentile(values, 10)), "min": float(np.min(values))}


def _quoted_family(path: Path, n_test: int, family_file: Path) -> dict[str, Any] | None:
    """The per-family estimator's and the oracle's figures from a bench_family run."""
    if not path.is_file():
        return None
    d = json.loads(path.read_text())
    if d.get("settings", {}).get("family_file") != str(family_file.relative_to(ROOT)):
        return None
    test = d["test"]
    return {
        "source": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path),
        "created_utc": d.get("created_utc"),
        "quick": d.get("quick"),
        "same_records": bool(test.get("seed") == TEST_SEED and test.get("n_records") == n_test),
        "n_records": test.get("n_records"),
        "per_family_fit": test["fit"],
        "oracle_fit": test.get("oracle_fit"),
        "per_family_seconds_per_record": test.get("seconds_per_record"),
        "train_seconds": d.get("training", {}).get("train_seconds"),
    }


SWEEP_SEED = 2024  # fresh random systems: neither the training draws nor the family
SWEEP_SCALES = (0.1, 0.2, 0.3, 0.5, 1.0, float("inf"))


def _sweep(est: AmortisedEstimator, n: int, t: np.ndarray, Y: np.ndarray, clean: np.ndarray,
           raw: Any, ofit: np.ndarray) -> dict[str, Any]:
    """Mean fit after refinement per prior scale (and plain VARPRO): random systems, family."""
    draws = random_systems(n, 500, np.random.default_rng(SWEEP_SEED),
                           max_order=est.network_.max_order)
    tr = 20.0 * draws.tau  # any record length: time is normalised inside the estimator
    base = est.get_params()
    settings = [("map", s) for s in SWEEP_SCALES] + [("varpro", base["prior_scale"])]
    r_raw = est.estimate(tr, draws.responses)
    f_raw = est.estimate(t, Y)
    rows = []
    ref_r = None
    for method, scale in settings:
        est.set_params(refine_method=method, prior_scale=scale)
        fr = fit_percent(draws.clean, est.refine(tr, draws.responses, r_raw).response)
        ff = fit_percent(clean, est.refine(t, Y, f_raw).response)
        if method == base["refine_method"] and scale == base["prior_scale"]:
            ref_r = fr
        rows.append({"method": method, "prior_scale": None if method == "varpro" else scale,
                     "random_fit": fr, "family_fit": ff})
        print(f"sweep {method} prior_scale={scale:g}: random systems {fr.mean():.2f} % "
              f"(median {np.median(fr):.2f}), family {ff.mean():.2f} %", flush=True)
    est.set_params(**base)
    out = []
    for r in rows:
        dr = r["random_fit"] - ref_r if ref_r is not None else None
        out.append({
            "method": r["method"], "prior_scale": r["prior_scale"],
            "random_systems_fit_mean": float(r["random_fit"].mean()),
            "random_systems_fit_median": float(np.median(r["random_fit"])),
            "random_systems_minus_default_mean": None if dr is None else float(dr.mean()),
            "random_systems_minus_default_stderr":
                None if dr is None else float(dr.std(ddof=1) / np.sqrt(dr.size)),
            "family_fit_mean": float(r["family_fit"].mean()),
            "family_minus_oracle": float(r["family_fit"].mean() - ofit.mean()),
        })
    return {"n_random_systems": n, "seed": SWEEP_SEED, "random_record_length": 20.0,
            "random_raw_fit_mean": float(fit_percent(draws.clean, r_raw.response).mean()),
            "n_family_records": int(Y.shape[0]), "default": {
                "refine_method": base["refine_method"], "prior_scale": base["prior_scale"]},
            "rows": out}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run (few records)")
    ap.add_argument("--train", action="store_true",
                    help="train the amortised model here (defaults) instead of loading it")
    ap.add_argument("--model", type=Path, default=MODEL, help="amortised model folder")
    ap.add_argument("--n-test", type=int, default=500, help="test records (bench_family's)")
    ap.add_argument("--n-oracle", type=int, default=100, help="records of the oracle fits")
    ap.add_argument("--family", type=Path, default=FAMILY, help="the held-out family file")
    ap.add_argument("--train-family", action="store_true",
                    help="train the per-family adaptive estimator here (train_family, its "
                         "defaults) instead of quoting --family-json")
    ap.add_argument("--n-sweep", type=int, default=300,
                    help="random systems of the prior-scale sweep (0: no sweep)")
    ap.add_argument("--family-json", type=Path, default=HERE / "results" / "family.json")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "amortised.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    machine = machine_info()
    start = time.perf_counter()
    n_test, n_oracle = args.n_test, args.n_oracle
    if args.quick:
        n_test, n_oracle = min(n_test, 20), min(n_oracle, 5)
        args.n_sweep = min(args.n_sweep, 10)
    n_oracle = min(n_oracle, n_test)

    if args.train:
        est = AmortisedEstimator(progress=sys.stderr.isatty()).fit()
        source = {"trained_here": True, "training_seconds": est.training_seconds_}
    else:
        est = AmortisedEstimator.load(args.model)
        source = {"trained_here": False, "model": str(args.model.relative_to(ROOT))
                  if args.model.is_relative_to(ROOT) else str(args.model),
                  "training_seconds": est.training_seconds_}
    source["params"] = {k: (list(v) if isinstance(v, tuple) else v)
                        for k, v in est.get_params().items()}

    family_file = args.family.resolve()
    family = PlantFamily.from_toml(family_file)
    data = family_dataset(family, n_test, TEST_SEED)
    t, Y, clean = data.t, data.responses, data.clean

    raw = est.estimate(t, Y)  # warm-up is part of it: the first call is timed as well
    fit_raw = fit_percent(clean, raw.response)
    ref = est.refine(t, Y, raw)
    fit_ref = fit_percent(clean, ref.response)
    print(f"amortised on {n_test} records: raw {fit_raw.mean():.2f} % "
          f"({1e6 * raw.seconds_per_record:.0f} us/record), + VARPRO "
          f"({est.refine_method}) {fit_ref.mean():.2f} % "
          f"({1e3 * ref.seconds_per_record:.0f} ms/record)")

    # the oracle and VARPRO from its own starts, on the first n_oracle records
    ofit = np.empty(n_oracle)
    pfit = np.empty(n_oracle)
    o_sec = p_sec = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        warnings.simplefilter("ignore", ConvergenceWarning)
        for i in range(n_oracle):
            t0 = time.perf_counter()
            res = oracle_fit(t, Y[i], family.system, data.parameters[i], kind=family.kind)
            o_sec += time.perf_counter() - t0
            ofit[i] = fit_percent(clean[i], res.response)
            t0 = time.perf_counter()
            pv = optimize_poles(t, Y[i], est.network_.max_order, max_iter=est.refine_max_iter,
                                tol=est.refine_tol, restart_collapsed=True)
            p_sec += time.perf_counter() - t0
            pfit[i] = fit_percent(clean[i], pv.coefficients @ pv.basis.evaluate(t))
    sub = slice(0, n_oracle)
    paired = {
        "n_records": n_oracle,
        "oracle_fit": _summary(ofit),
        "oracle_seconds_per_record": o_sec / n_oracle,
        "amortised_fit": _summary(fit_raw[sub]),
        "amortised_varpro_fit": _summary(fit_ref[sub]),
        "varpro_from_prony_fit": _summary(pfit),
        "varpro_from_prony_seconds_per_record": p_sec / n_oracle,
        "gap_amortised_to_oracle": float(fit_raw[sub].mean() - ofit.mean()),
        "gap_amortised_varpro_to_oracle": float(fit_ref[sub].mean() - ofit.mean()),
        "gap_varpro_from_prony_to_oracle": float(pfit.mean() - ofit.mean()),
        "records_varpro_from_prony_below_oracle_by_5_points": int(np.sum(pfit < ofit - 5)),
        "records_amortised_varpro_below_oracle_by_5_points": int(np.sum(fit_ref[sub] < ofit - 5)),
    }
    print(f"first {n_oracle} records: oracle {ofit.mean():.2f} %, amortised "
          f"{fit_raw[sub].mean():.2f} %, amortised + VARPRO {fit_ref[sub].mean():.2f} %, "
          f"VARPRO from Prony {pfit.mean():.2f} %")

    sweep = _sweep(est, args.n_sweep, t[:], Y[sub], clean[sub], raw, ofit) if args.n_sweep else None

    per_family = None
    if args.train_family:
        budget = family
        if args.quick:
            budget = dataclasses.replace(family, n_records=1000, n_calibration=200,
                                         n_validation=5, max_epochs=5)
        fam_est, report = train_family(budget, oracle=False, progress=sys.stderr.isatty())
        t0 = time.perf_counter()
        fam_fit = fit_percent(clean, fam_est.estimate(data).response)
        per_family = {"train_seconds": report["train_seconds"],
                      "fit": _summary(fam_fit),
                      "seconds_per_record": (time.perf_counter() - t0) / n_test,
                      "fit_first_n_oracle_mean": float(fam_fit[sub].mean())}
        print(f"per-family adaptive estimator (trained here in {report['train_seconds']:.0f} s):"
              f" {fam_fit.mean():.2f} % on all {n_test}, {fam_fit[sub].mean():.2f} % on the "
              f"first {n_oracle}")
    quoted = None if args.train_family else _quoted_family(args.family_json, n_test,
                                                           family_file)
    full = {
        "n_records": n_test,
        "seed": TEST_SEED,
        "amortised_fit": _summary(fit_raw),
        "amortised_seconds_per_record": raw.seconds_per_record,
        "amortised_varpro_fit": _summary(fit_ref),
        "amortised_varpro_method": est.refine_method,
        "amortised_varpro_prior_scale": est.prior_scale,
        "amortised_varpro_seconds_per_record": ref.seconds_per_record,
    }
    acceptance: dict[str, Any] = {}
    if quoted is not None and quoted["same_records"] and quoted["oracle_fit"]:
        oracle_mean = quoted["oracle_fit"]["mean"]
        full["oracle_fit_quoted"] = quoted["oracle_fit"]
        full["per_family_fit_quoted"] = quoted["per_family_fit"]
        full["gap_amortised_to_oracle"] = float(fit_raw.mean() - oracle_mean)
        full["gap_amortised_varpro_to_oracle"] = float(fit_ref.mean() - oracle_mean)
        full["gap_amortised_to_per_family"] = float(fit_raw.mean()
                                                    - quoted["per_family_fit"]["mean"])
        acceptance = {
            "amortised_within_3_points_of_oracle": bool(fit_raw.mean() >= oracle_mean - 3.0),
            "amortised_varpro_within_0.5_points_of_oracle": bool(
                fit_ref.mean() >= oracle_mean - 0.5),
            "oracle_reference": f"{oracle_mean:.4f} % ({quoted['source']}, same records)",
        }
        print(f"all {n_test} records: oracle {oracle_mean:.2f} % and per-family "
              f"{quoted['per_family_fit']['mean']:.2f} % (quoted); gaps to the oracle: "
              f"amortised {full['gap_amortised_to_oracle']:+.2f}, + VARPRO "
              f"{full['gap_amortised_varpro_to_oracle']:+.2f} points")
    else:
        acceptance = {
            "amortised_within_3_points_of_oracle": bool(
                paired["gap_amortised_to_oracle"] >= -3.0),
            "amortised_varpro_within_0.5_points_of_oracle": bool(
                paired["gap_amortised_varpro_to_oracle"] >= -0.5),
            "oracle_reference": f"paired, first {n_oracle} records",
        }
    result = benchmark_result(
        "amortised",
        argv,
        quick=args.quick,
        settings={"family_file": str(family_file.relative_to(ROOT)), "n_test": n_test,
                  "n_oracle": n_oracle, "test_seed": TEST_SEED},
        machine=machine,
        amortised_model=source,
        test=full,
        paired_with_oracle=paired,
        per_family_trained_here=per_family,
        prior_scale_sweep=sweep,
        per_family_quoted=quoted,
        acceptance=acceptance,
        elapsed_s=time.perf_counter() - start,
    )
    write_json(args.out, result)
    print(f"{result['elapsed_s']:.1f} s; results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
