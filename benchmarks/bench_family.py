"""Benchmark of ``kautztwin train --family`` on a held-out family, with its uncertainty.

The family is ``examples/family_5th_order.toml``: a 5th-order plant with a zero
(``3 (s + 2) / ((s + 0.8)(s^2 + 0.9 s + 2.25)(s^2 + 3 s + 9))``, approximately),
every parameter (gain, zero and pole rates, natural frequencies, damping ratios)
uniform within +-30 %, 5 % AR(1) noise (lag-1 correlation 0.9), impulse records;
everything else at the family file's defaults (20 000 training records, 1 000
calibration records, 500 samples over ten slowest time constants, the adaptive
estimator's default network and budget).  It trains with
:func:`kautztwin.nn.family.train_family` exactly as the command does, then measures on
``--n-test`` fresh records (a seed no training or calibration record used):

* the fit percent of the estimator's noise-free estimate against the truth, and the
  oracle's (least squares in the true structure, started at the true parameters);
* on the first ``--n-gls`` of those records, the *whitened* oracle as well: least squares
  on the residual whitened with the true AR(1) pole (generalised least squares, the
  maximum-likelihood estimate under the family's noise), because under coloured noise
  ordinary least squares is not the statistical limit and a network that has learned the
  noise colour and the parameter prior can beat it;
* the per-sample coverage of the true impulse response by the estimator's bands at
  50/80/90/95 % (the acceptance: 88-92 % at 90 %), with the standard error of the
  90 % coverage across records (records are the independent units);
* the same coverage before calibration (the Laplace covariance alone).

Usage::

    python benchmarks/bench_family.py [--quick] [--out benchmarks/results/family.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 - the thread variables must be set before numpy loads
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402
import torch  # noqa: E402

from kautztwin.metrics import fit_percent  # noqa: E402
from kautztwin.nn.family import (  # noqa: E402
    PlantFamily,
    family_dataset,
    train_family,
    validation_report,
)
from kautztwin.nn.oracle import simulate_parametric  # noqa: E402
from kautztwin.nn.uncertainty import band_coverage  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import benchmark_result, machine_info, write_json  # noqa: E402

HERE = Path(__file__).resolve().parent
FAMILY = HERE.parent / "examples" / "family_5th_order.toml"
TEST_SEED = 12345


def _whiten(r: np.ndarray, a: float) -> np.ndarray:
    """Innovations of stationary AR(1) noise with pole ``a`` (unit-variance scaling)."""
    w = np.empty_like(r)
    w[0] = r[0]
    w[1:] = (r[1:] - a * r[:-1]) / np.sqrt(1.0 - a * a)
    return w


def _gls_oracle(family: PlantFamily, n: int) -> dict[str, Any]:
    """Whitened least squares in the true structure from the true parameters (first n)."""
    data = family_dataset(family, n, TEST_SEED)
    a = family.ar1_pole
    fits = np.empty(n)
    for i in range(n):
        y, p0 = data.responses[i], data.parameters[i]
        big = 1e6 * (1.0 + np.abs(y).max())

        def res(p: np.ndarray, y: np.ndarray = y, big: float = big) -> np.ndarray:
            with np.errstate(all="ignore"):
                r = simulate_parametric(family.system, p, family.t, kind=family.kind) - y
            return _whiten(r, a) if np.all(np.isfinite(r)) else np.full(y.size, big)

        sol = scipy.optimize.least_squares(res, p0, method="lm", x_scale="jac", ftol=1e-10,
                                           xtol=1e-10, gtol=1e-10, max_nfev=100 * (p0.size + 1))
        fits[i] = fit_percent(data.clean[i],
                              simulate_parametric(family.system, sol.x, family.t,
                                                  kind=family.kind))
    return {"n_records": n, "fit_mean": float(fits.mean()), "fit_median": float(np.median(fits)),
            "fit_per_record": fits.tolist()}


def _coverage_detail(est: Any, family: PlantFamily, n: int) -> dict[str, Any]:
    """90 % coverage per record (its spread), and before calibration."""
    data = family_dataset(family, n, TEST_SEED)
    e = est.estimate(data)
    inside = (data.clean >= e.lower) & (data.clean <= e.upper)
    per_record = inside.mean(axis=1)
    raw_scale = 1.0 / est.uncertainty_scale_
    lo = e.response - raw_scale * e.z * e.std
    hi = e.response + raw_scale * e.z * e.std
    return {
        "coverage_90": float(inside.mean()),
        "coverage_90_stderr_across_records": float(per_record.std(ddof=1) / np.sqrt(n)),
        "coverage_90_per_record_p10": float(np.percentile(per_record, 10)),
        "coverage_90_uncalibrated": band_coverage(data.clean, lo, hi),
    }


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small budget (a smoke run)")
    ap.add_argument("--n-test", type=int, default=500, help="fresh test records")
    ap.add_argument("--n-gls", type=int, default=200, help="records of the whitened oracle")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "family.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    machine = machine_info()
    start = time.perf_counter()
    family = PlantFamily.from_toml(FAMILY)
    n_test = args.n_test
    if args.quick:
        family = dataclasses.replace(family, n_records=1000, n_calibration=200, max_epochs=5)
        n_test = min(n_test, 40)
        args.n_gls = min(args.n_gls, 10)
    est, report = train_family(family, oracle=False, progress=sys.stderr.isatty())
    print(f"trained in {report['train_seconds']:.1f} s")
    test = validation_report(est, family, n=n_test, seed=TEST_SEED, oracle=True,
                             progress=sys.stderr.isatty())
    detail = _coverage_detail(est, family, n_test)
    fit, oracle = test["fit"]["mean"], test["oracle_fit"]["mean"]
    n_gls = min(args.n_gls, n_test) if family.color == "ar1" else 0
    gls = _gls_oracle(family, n_gls) if n_gls else None
    if gls is not None:
        same = slice(0, n_gls)
        gls["estimator_fit_mean_same_records"] = float(np.mean(test["fit_per_record"][same]))
        gls["ls_oracle_fit_mean_same_records"] = float(
            np.mean(test["oracle_fit_per_record"][same]))
        print(f"on the first {n_gls} records: estimator "
              f"{gls['estimator_fit_mean_same_records']:.2f} %, least-squares oracle "
              f"{gls['ls_oracle_fit_mean_same_records']:.2f} %, whitened oracle "
              f"{gls['fit_mean']:.2f} %")
    verdict = {
        "fit_within_1_point_of_oracle": bool(fit >= oracle - 1.0),
        "coverage_90_in_88_92": bool(0.88 <= detail["coverage_90"] <= 0.92),
    }
    print(f"estimator mean fit {fit:.2f} %, oracle {oracle:.2f} % "
          f"(gap {fit - oracle:+.2f} points)")
    print(f"90 % band coverage {100 * detail['coverage_90']:.2f} % "
          f"(+-{100 * detail['coverage_90_stderr_across_records']:.2f}), uncalibrated "
          f"{100 * detail['coverage_90_uncalibrated']:.2f} %; levels "
          + ", ".join(f"{k}: {100 * v:.1f} %" for k, v in test["coverage"].items()))
    print(f"estimator {1e6 * test['seconds_per_record']:.0f} us per record with uncertainty, "
          f"oracle {1e3 * test['oracle_seconds_per_record']:.1f} ms per record")
    test_summary = {k: v for k, v in test.items() if not k.endswith("_per_record")
                    or k.startswith(("seconds", "oracle_seconds"))}
    result = benchmark_result(
        "family",
        argv,
        quick=args.quick,
        settings={
            "family_file": str(FAMILY.relative_to(HERE.parent)),
            "family": family.to_dict(),
            "n_test": n_test,
            "test_seed": TEST_SEED,
        },
        machine=machine,
        training={k: report[k] for k in ("n_records", "simulate_seconds", "train_seconds",
                                          "calibration")},
        training_validation={k: v for k, v in report["validation"].items()
                             if not k.endswith("per_record") or k == "seconds_per_record"},
        test=test_summary,
        whitened_oracle=gls,
        coverage=detail,
        acceptance=verdict,
        elapsed_s=time.perf_counter() - start,
    )
    write_json(args.out, result)
    print(f"{result['elapsed_s']:.1f} s; results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
