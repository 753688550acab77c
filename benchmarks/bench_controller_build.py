"""Benchmark: building the twin's controller for a new model version, against the history length.

Each model version's controller needs its filter states after the whole command
history (:func:`kautztwin.twin.prediction.controller._prepare_controller`; a live
twin runs it in its optimisation worker thread, beside the sample loop).  The
states are built in blocks of ``MAX_DELAY`` inputs (one product per block, at
most ``MAX_DELAY`` single steps); the baseline is the plain recursion, one Python
step ``x = A x + B w`` per input, which the controller used before.  Both are
timed in the same run, calls alternating, for histories of 1 000 to 100 000
samples, on a hydraulic-like third-order model (a real pole and a complex pair).
Also timed: the whole build (MPC problem and predictor maps included), and the largest difference of
the states from the recursion, relative to the largest state.

Usage::

    python benchmarks/bench_controller_build.py [--quick] [--out JSON]

(default ``benchmarks/results/controller_build.json``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 - the thread variables must be set before numpy loads
import statistics  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from _common import HERE, benchmark_result, machine_info, timed, write_json  # noqa: E402

import kautztwin as kt  # noqa: E402
from kautztwin.twin.prediction import MPCSettings  # noqa: E402
from kautztwin.twin.prediction.controller import (  # noqa: E402
    MAX_DELAY,
    _delay_maps,
    _FilterState,
    _prepare_controller,
)

U0 = 0.5


def _model() -> kt.KautzModel:
    p = 0.97 * np.exp(0.2j)
    basis = kt.KautzBasis([0.995, p, np.conj(p)], dt=0.01, delayed=True)
    return kt.KautzModel(basis, [2.0, -0.8, 0.3])


def _recursion(A: np.ndarray, B: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The baseline: one Python step per input (the controller's former build)."""
    x = prev = np.zeros(A.shape[0])
    for wk in w.tolist():
        prev, x = x, A @ x + B * wk
    return x, prev


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmark, print a table and write the JSON result.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    dict
        The result written to the JSON file.
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short histories, few repeats")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "controller_build.json")
    args = ap.parse_args(argv)
    machine = machine_info()
    lengths = [1_000, 6_000] if args.quick else [1_000, 6_000, 30_000, 100_000]
    repeats = 3 if args.quick else 7
    model = _model()
    settings = MPCSettings(50, 0.8, 8, 1e4, u_min=0.0, u_max=1.0, du_max=0.05)
    A, B = np.array(model.basis.A), np.array(model.basis.B)
    powers, AB = _delay_maps(A, B)
    PL, M = powers[MAX_DELAY], np.ascontiguousarray(AB[::-1].T)
    rng = np.random.default_rng(0)
    rows = []
    print(f"{'samples':>8} {'blocks ms':>10} {'recursion ms':>13} {'speed-up':>9} "
          f"{'build ms':>9} {'max rel diff':>13}")
    for n in lengths:
        v = U0 + 0.05 * rng.standard_normal(n)
        d = 0.01 * np.sign(rng.standard_normal(n))
        wv = v - U0

        def states(wv=wv, d=d):
            return _FilterState.from_history(A, B, PL, M, wv, d)

        def recursion(wv=wv, d=d):
            return _recursion(A, B, wv), _recursion(A, B, d)

        def build(v=v, d=d):
            return _prepare_controller(model, settings, v, d, U0)

        states(), recursion(), build()  # warm-up
        t_states, t_rec, t_build = [], [], []
        for _ in range(repeats):  # alternate, so that a burst of load hits all alike
            t_states.append(timed(states)[1])
            t_rec.append(timed(recursion)[1])
            t_build.append(timed(build)[1])
        f = states()
        (xv, xv_prev), (xd, _) = recursion()
        scale = np.abs(np.concatenate([xv, xd])).max()
        diff = max(np.abs(f.xv - xv).max(), np.abs(f.xv_prev - xv_prev).max(),
                   np.abs(f.xd - xd).max()) / scale
        row = {"samples": n, "states_s": statistics.median(t_states),
               "recursion_s": statistics.median(t_rec), "build_s": statistics.median(t_build),
               "max_rel_diff": float(diff), "repeats_states_s": t_states,
               "repeats_recursion_s": t_rec, "repeats_build_s": t_build}
        row["speedup_states"] = row["recursion_s"] / row["states_s"]
        rows.append(row)
        print(f"{n:>8} {1e3 * row['states_s']:>10.2f} {1e3 * row['recursion_s']:>13.2f} "
              f"{row['speedup_states']:>8.1f}x {1e3 * row['build_s']:>9.2f} {diff:>13.2e}")
    result = benchmark_result(
        "controller_build", argv, quick=args.quick,
        settings={"lengths": lengths, "repeats": repeats, "block": MAX_DELAY,
                  "model": "poles 0.995, 0.97 exp(+-0.2j), dt 0.01", "mpc": repr(settings)},
        machine=machine, rows=rows)
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
