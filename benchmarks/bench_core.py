"""Benchmark of the kautztwin core: basis evaluation and projection of many records.

For each basis (the reference Kautz basis with N = 4, a Laguerre basis and a
mixed Kautz basis with N = 16) it measures, in the same run:

* ``basis.evaluate(t)`` on 900 samples over [0, 20] s, against evaluating the
  same functions one at a time with ``scipy.signal.impulse`` from
  ``basis.transfer_functions()``; the largest difference between the two is
  recorded as the accuracy check;
* ``kautztwin.project(basis, t, H)`` for 10,000 records of 900 samples, against
  the naive projection (a Python loop over records and functions, each
  coefficient by ``scipy.integrate.simpson``), timed on a subset of the records
  and scaled per record.

Times are medians of repeated ``time.perf_counter`` measurements after one
warm-up call.  Nothing is asserted about them: they depend on the machine.

Usage::

    python benchmarks/bench_core.py [--quick] [--out benchmarks/results/core.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import scipy.integrate
import scipy.signal

import kautztwin as kt
from kautztwin.data import reference_poles, reference_response

sys.path.insert(0, str(Path(__file__).resolve().parent))
# machine_info stays importable from here: bench_mpc.py takes it from bench_core
from _common import benchmark_result, machine_info, write_json  # noqa: E402

N_SAMPLES = 900
T_END = 20.0
N_RECORDS = 10_000
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "core.json"


def _bases() -> dict[str, kt.KautzBasis]:
    """The benchmarked bases, by name."""
    mixed = [-0.5, -1.0, -2.0, -4.0]
    for re, im in [(-0.3, 1.0), (-0.5, 2.0), (-0.8, 3.0), (-1.0, 0.5), (-1.5, 1.5), (-2.0, 4.0)]:
        mixed += [complex(re, im), complex(re, -im)]
    return {
        "kautz4_reference": kt.KautzBasis(reference_poles()),
        "laguerre16": kt.LaguerreBasis(pole=-1.0, n=16),
        "kautz16_mixed": kt.KautzBasis(mixed),
    }


def _timeit(
    fns: dict[str, Callable[[], Any]], repeats: int, min_time: float
) -> dict[str, list[float]]:
    """Seconds per call of each function: ``repeats`` samples each, interleaved.

    Every function is called once to warm up and to calibrate how many calls
    make one sample last about ``min_time`` (so short calls are not dominated by
    the timer's resolution).  The samples of the functions alternate, so that a
    burst of load on a shared machine hits the compared functions alike.
    """
    numbers = {}
    for name, fn in fns.items():
        start = time.perf_counter()
        fn()
        numbers[name] = max(1, int(min_time / max(time.perf_counter() - start, 1e-9)))
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            for _ in range(numbers[name]):
                fn()
            times[name].append((time.perf_counter() - start) / numbers[name])
    return times


def _scipy_functions(basis: kt.KautzBasis, t: np.ndarray) -> np.ndarray:
    """The basis functions evaluated one at a time by ``scipy.signal.impulse``."""
    tfs = basis.transfer_functions()
    return np.array([scipy.signal.impulse((num, den), T=t)[1] for num, den in tfs])


def _naive_projection(K: np.ndarray, t: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Coefficients record by record and function by function with ``scipy.integrate.simpson``."""
    c = np.empty((H.shape[0], K.shape[0]))
    for r in range(H.shape[0]):
        for i in range(K.shape[0]):
            c[r, i] = scipy.integrate.simpson(H[r] * K[i], x=t)
    return c


def bench_case(
    name: str,
    basis: kt.KautzBasis,
    t: np.ndarray,
    H: np.ndarray,
    *,
    repeats: int,
    min_time: float,
    naive_records: int,
) -> dict[str, Any]:
    """Time evaluation and projection for one basis; return the JSON-ready record."""
    n = basis.n_functions

    # basis evaluation: kautztwin (matrix-exponential recursion) vs scipy.signal.impulse
    timed = _timeit(
        {"kt": lambda: basis.evaluate(t), "scipy": lambda: _scipy_functions(basis, t)},
        repeats,
        min_time,
    )
    t_eval, t_scipy = timed["kt"], timed["scipy"]
    K = basis.evaluate(t)
    K_ref = _scipy_functions(basis, t)
    max_diff = float(np.max(np.abs(K - K_ref)))
    eval_kt, eval_sp = statistics.median(t_eval), statistics.median(t_scipy)

    # projection of all records at once vs the naive loop on a subset of them
    sub = H[:naive_records]
    timed = _timeit(
        {"kt": lambda: kt.project(basis, t, H), "naive": lambda: _naive_projection(K, t, sub)},
        repeats,
        min_time,
    )
    t_proj, t_naive = timed["kt"], timed["naive"]
    coef_diff = float(np.max(np.abs(_naive_projection(K, t, sub) - kt.project(basis, t, sub))))
    proj = statistics.median(t_proj)
    naive_per_record = statistics.median(t_naive) / naive_records
    naive_full = naive_per_record * H.shape[0]

    return {
        "name": name,
        "basis": repr(basis),
        "n_functions": n,
        "poles": [[float(p.real), float(p.imag)] for p in basis.poles],
        "evaluate": {
            "kautztwin_s": eval_kt,
            "kautztwin_s_min": min(t_eval),
            "scipy_impulse_s": eval_sp,
            "scipy_impulse_s_min": min(t_scipy),
            "speedup": eval_sp / eval_kt,
            "speedup_min": min(t_scipy) / min(t_eval),
            "max_abs_diff_vs_scipy": max_diff,
            "max_abs_value": float(np.max(np.abs(K))),
            "kautztwin_s_all": t_eval,
            "scipy_impulse_s_all": t_scipy,
        },
        "projection": {
            "n_records": int(H.shape[0]),
            "kautztwin_s": proj,
            "kautztwin_s_min": min(t_proj),
            "records_per_s": H.shape[0] / proj,
            "naive_records_timed": naive_records,
            "naive_s_per_record": naive_per_record,
            "naive_s_estimated": naive_full,
            "speedup": naive_full / proj,
            "speedup_min": min(t_naive) / naive_records * H.shape[0] / min(t_proj),
            "max_abs_coef_diff_vs_naive": coef_diff,
            "kautztwin_s_all": t_proj,
            "naive_s_all": t_naive,
        },
    }


def _records(t: np.ndarray, n_records: int, rng: np.random.Generator) -> np.ndarray:
    """Noisy copies of the reference impulse response (the paper's training-data shape)."""
    _, h = reference_response(kind="impulse", n_samples=t.size, t_end=float(t[-1]))
    return h[None, :] + 0.1 * np.max(np.abs(h)) * rng.standard_normal((n_records, t.size))


def _print_table(cases: list[dict[str, Any]]) -> None:
    print("\nBasis evaluation, 900 samples on [0, 20] s (median)")
    print(
        f"{'case':<18}{'N':>4}{'kautztwin':>14}{'scipy impulse':>16}"
        f"{'speed-up':>10}{'max |diff|':>13}"
    )
    for c in cases:
        e = c["evaluate"]
        print(
            f"{c['name']:<18}{c['n_functions']:>4}{e['kautztwin_s'] * 1e3:>11.3f} ms"
            f"{e['scipy_impulse_s'] * 1e3:>13.3f} ms{e['speedup']:>9.1f}x"
            f"{e['max_abs_diff_vs_scipy']:>13.1e}"
        )
    n_rec = cases[0]["projection"]["n_records"]
    print(f"\nProjection of {n_rec:,} records x 900 samples (median)")
    print(
        f"{'case':<18}{'N':>4}{'kautztwin':>13}{'records/s':>13}"
        f"{'naive (est.)':>15}{'speed-up':>11}{'max |dc|':>11}"
    )
    for c in cases:
        p = c["projection"]
        print(
            f"{c['name']:<18}{c['n_functions']:>4}{p['kautztwin_s'] * 1e3:>10.1f} ms"
            f"{p['records_per_s']:>13,.0f}{p['naive_s_estimated']:>13.2f} s"
            f"{p['speedup']:>10.0f}x{p['max_abs_coef_diff_vs_naive']:>11.1e}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats (smoke test, < 1 min)")
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="JSON file (default: results/core.json here)"
    )
    args = parser.parse_args(argv)

    repeats, min_time, naive_records = (5, 0.02, 50) if args.quick else (15, 0.1, 200)
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, T_END, N_SAMPLES)
    H = _records(t, N_RECORDS, rng)

    machine = machine_info()
    started = time.perf_counter()
    cases = [
        bench_case(
            name, basis, t, H, repeats=repeats, min_time=min_time, naive_records=naive_records
        )
        for name, basis in _bases().items()
    ]
    result = benchmark_result(
        "core",
        argv,
        quick=args.quick,
        settings={
            "n_samples": N_SAMPLES,
            "t_end": T_END,
            "n_records": N_RECORDS,
            "repeats": repeats,
            "min_time_per_repeat_s": min_time,
            "naive_records": naive_records,
            "timer": "time.perf_counter; median per call over interleaved repeats, after a warm-up",
        },
        machine=machine,
        cases=cases,
        elapsed_s=time.perf_counter() - started,
    )
    _print_table(cases)
    write_json(args.out, result)
    print(f"\n{result['elapsed_s']:.1f} s; results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
