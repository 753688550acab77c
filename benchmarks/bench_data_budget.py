"""Data-budget sweep of the paper's network: where it meets the fixed-basis ceiling.

The paper trains its coefficient networks on 50 records; ``reproduce simulation`` does the
same and reaches about 51 % mean fit against a fixed-basis ceiling of about 69 %.  This
script trains the paper's architecture (:class:`~kautztwin.nn.PaperNetwork`, one
multi-output network, ``default`` preset: Adam 1e-3, weight decay, early stopping) on
50 ... 20 000 records of the paper's simulation case (``paper_system()``, +-50 %
uniform, impulse responses on 0..20 s with 900 samples, 10 % white noise, labels in the
nominal N = 4 Kautz basis) and measures on 1 000 fresh records:

* the mean / median fit of the network's model against the noise-free truth;
* the coefficient NMSE (mean over c1..c4 of the squared error over the label variance);
* the same for the two references that need no training: the fixed-basis ceiling (the
  exact coefficients of the truth: no estimator on this basis can do better) and the
  projection of the noisy record.

Why ``default`` and not ``paper``: the paper preset (learning rate 1e-5, 1000 epochs) is
far from converged even on 2 000 records (``docs/nn-presets.md``) and would take hours on
20 000; the paper's own 50-record setting with the paper preset is the first row (one
network per coefficient, as ``reproduce simulation``).

Usage::

    python benchmarks/bench_data_budget.py [--quick] [--out benchmarks/results/data_budget.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 - the thread variables must be set before numpy loads
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import kautztwin as kt  # noqa: E402
from kautztwin.datasets import draw_parameters, make_dataset, paper_system  # noqa: E402
from kautztwin.nn import CoefficientEstimator  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import benchmark_result, machine_info, write_json  # noqa: E402

HERE = Path(__file__).resolve().parent
T = np.linspace(0.0, 20.0, 900)
BUDGETS = (50, 200, 1000, 5000, 20000)
QUICK_BUDGETS = (50, 200, 1000)


def _data(n: int, seed: int, basis: kt.KautzBasis) -> Any:
    system = paper_system()
    P = draw_parameters(system, 0.5, n, random_state=seed)
    return make_dataset(system, P, basis, T, noise=0.1, random_state=seed + 1)


def _scores(coef: np.ndarray, test: Any, K: np.ndarray) -> dict[str, float]:
    fits = kt.fit_percent(test.clean, coef @ K)
    C = test.coefficients
    nmse = ((coef - C) ** 2).mean(axis=0) / C.var(axis=0)
    return {"fit_mean": float(np.mean(fits)), "fit_median": float(np.median(fits)),
            "fit_p10": float(np.percentile(fits, 10)), "coef_nmse": float(nmse.mean())}


def main(argv: list[str] | None = None) -> int:
    """Run the sweep; returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="budgets up to 1000, 30 epochs")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "data_budget.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    machine = machine_info()
    start = time.perf_counter()
    basis = kt.KautzBasis(paper_system().poles())
    K = basis.evaluate(T)
    test = _data(200 if args.quick else 1000, 100, basis)
    refs = {
        "fixed_basis_ceiling": _scores(test.coefficients, test, K),
        "projection": _scores(kt.project(basis, T, test.responses), test, K),
    }
    print(f"fixed-basis ceiling {refs['fixed_basis_ceiling']['fit_mean']:.2f} %, "
          f"projection {refs['projection']['fit_mean']:.2f} %")
    cap = {"max_epochs": 30} if args.quick else {}
    rows = []
    runs = [("paper", True, 50)] + [("default", False, n)
                                    for n in (QUICK_BUDGETS if args.quick else BUDGETS)]
    for preset, per_coef, n in runs:
        train = _data(n, 0, basis)
        est = CoefficientEstimator(preset=preset, per_coefficient=per_coef, random_state=0,
                                   config=cap or None)
        t0 = time.perf_counter()
        est.fit(train)
        seconds = time.perf_counter() - t0
        row = {"n_records": n, "preset": preset, "per_coefficient": per_coef,
               "epochs": [h.n_epochs for h in est.histories_], "train_seconds": seconds,
               **_scores(est.predict(test.responses), test, K)}
        rows.append(row)
        print(f"{preset:<8} {n:>6} records: fit mean {row['fit_mean']:7.2f} %, median "
              f"{row['fit_median']:6.2f} %, coef NMSE {row['coef_nmse']:.4f} "
              f"({seconds:.0f} s, epochs {row['epochs']})", flush=True)
    result = benchmark_result(
        "data_budget",
        argv,
        quick=args.quick,
        settings={"system": "paper_system", "uncertainty": 0.5, "noise": 0.1,
                  "n_samples": T.size, "t_end": float(T[-1]), "n_test": len(test),
                  "network": "PaperNetwork (multi-output unless per_coefficient)",
                  "epoch_cap": cap.get("max_epochs")},
        machine=machine,
        references=refs,
        runs=rows,
        elapsed_s=time.perf_counter() - start,
    )
    write_json(args.out, result)
    print(f"{result['elapsed_s']:.1f} s; results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
