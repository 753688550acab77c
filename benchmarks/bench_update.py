"""Benchmark: the twin's update module, per sample (fast path) and per re-identification fit.

**Fast path.**  Every sample the update module runs one recursive least-squares update of
the Kautz coefficients (:class:`kautztwin.twin.update.RecursiveKautzEstimator`, four
functions and the offset) and, around it, the monitor and the bookkeeping
(:meth:`kautztwin.twin.update.Updater.step`, re-identification off).  The baseline, in the
same run, is what the recursion replaces: the weighted least-squares fit of the same
coefficients over the forgetting factor's memory (``3 / (1 - forgetting)`` samples, the
weights ``forgetting^age``) recomputed at every sample.  The recursion's coefficients are
compared with that fit's at the last sample.  The hydraulic profile's recursion (its
quadratic input channel and directional forgetting: nine parameters instead of five, and
the information matrix kept beside the covariance) is timed in the same loop, as a ratio
to the plain one.

**Re-identification fit.**  A live twin's re-identification runs in a worker while the
plant goes on: at 10x real time, every 100 ms of fit is 50 samples (1 s of plant time)
before the candidate can be judged, so the fit's wall time stretches the recovery after a
drift.  The fit is :func:`kautztwin.ident.identify_output_error` from three starts
(``kautztwin.twin.update.worker._fit_window``), a variable projection whose every
residual evaluation builds the regressors of one basis: the filter states (the basis
sequences convolved with the input) and, with the initial state estimated, the free
response.  Timed, calls alternating, on the windows of the offline acceptance run's
re-identifications (hydraulic drive, 40 % pole drift at 30 and 60 s, the twin's own
attempts captured as they were made):

- **current**: the three starts searched together, as one problem (one batched evaluation
  of all starts per step), the basis sequences ``A^k B`` by doubling
  (``kautztwin.basis._propagate._power_columns``);
- **baseline**: the previous arrangement: the starts searched one after another, the
  sequences by the one-step recursion in sqrt(n) blocks.

Both use Golub and Pereyra's variable-projection Jacobian (its gain over a difference
Jacobian was measured by this benchmark before, docs/service.md) and give the same model
to the fit's resolution (the cost is flat along some pole directions: the candidates'
held-out predictions are compared, not their poles).

Usage::

    python benchmarks/bench_update.py [--quick] [--out JSON]

(default ``benchmarks/results/update.json``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 - the thread variables must be set before numpy loads
import statistics  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from _common import HERE, benchmark_result, machine_info, timed, write_json  # noqa: E402

from kautztwin.basis import _propagate  # noqa: E402
from kautztwin.ident import kautz_oe  # noqa: E402
from kautztwin.ident.kautz_oe import filter_states  # noqa: E402
from kautztwin.twin import DigitalTwin, TwinConfig, make_plant  # noqa: E402
from kautztwin.twin.update import (  # noqa: E402
    RecursiveKautzEstimator,
    SyncMonitor,
    Updater,
    worker,
)

DRIFTS = (30.0, 60.0)


def _blocked_discrete_functions(A: np.ndarray, B: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The previous ``A^k B``: the one-step recursion arranged in sqrt(n) blocks."""
    n = int(k.max()) + 1
    m = max(1, int(np.ceil(np.sqrt(n))))
    return _propagate._blocked_recursion(A, np.linalg.matrix_power(A, m), B, n, m)[:, :, k]


@contextmanager
def _blocked_sequences():
    current = kautz_oe.discrete_functions
    kautz_oe.discrete_functions = _blocked_discrete_functions
    try:
        yield
    finally:
        kautz_oe.discrete_functions = current


def _sequential_fit(job: Any) -> Any:
    """The baseline: the three starts one after another, each its own search."""
    best = None
    with _blocked_sequences():
        for scale in worker._START_SCALES:
            fit = kautz_oe.identify_output_error(
                job.u[: job.n_est], job.y[: job.n_est], worker._scaled_poles(job.poles, scale),
                dt=job.dt, burn_in=job.w0, input_offset=job.input_offset,
                min_rate=job.min_rate, max_iter=job.max_iter,
                initial_state=worker._INITIAL_STATE)
            if best is None or fit.fit_percent > best.fit_percent:
                best = fit
    return best


def _jobs(duration: float) -> list[Any]:
    """The re-identification windows of an offline drift run, as the twin submitted them."""
    jobs: list[Any] = []
    fit_window = worker._fit_window

    def capture(job: Any, *args: Any, **kwargs: Any) -> Any:
        jobs.append(job)
        return fit_window(job, *args, **kwargs)

    plant = make_plant("hydraulic", drift=0.4, drift_events=DRIFTS, seed=0)
    cfg = TwinConfig.for_plant(plant, duration=duration, seed=0, drift_events=DRIFTS)
    worker._fit_window = capture
    try:
        with DigitalTwin(plant, cfg, history=":memory:", background=False) as tw:
            tw.run(progress=False)
    finally:
        worker._fit_window = fit_window
    return jobs


def _held_out(job: Any, fit: Any) -> np.ndarray:
    """The candidate's prediction of the window's held-out samples (what the judging uses)."""
    v = job.u - job.input_offset
    y = filter_states(fit.model.basis, v)[:-1] @ fit.model.coefficients + fit.offset
    return y[job.u.size - job.n_val:]


FAST_DT = 0.02
FORGETTING = 0.98


def _fast_path(n: int, repeats: int) -> dict[str, Any]:
    """Per-sample cost of the recursion and of ``Updater.step``, against the windowed refit."""
    poles = np.exp(np.array([-1.0, -2.0, -4.0, -8.0]) * FAST_DT)
    rng = np.random.default_rng(0)
    u = np.repeat(rng.choice([-1.0, 1.0], n // 10 + 1), 10)[:n]
    plant = RecursiveKautzEstimator(poles, dt=FAST_DT, coef_init=[1.0, -0.5, 0.3, 0.1],
                                    offset_init=2.0).reset()
    y = plant.simulate(u) + 0.01 * rng.standard_normal(n)
    memory = int(round(3 / (1 - FORGETTING)))

    def recursion(**options):
        est = RecursiveKautzEstimator(poles, dt=FAST_DT, forgetting=FORGETTING,
                                      **options).reset()
        for uk, yk in zip(u.tolist(), y.tolist(), strict=True):
            est.update(uk, yk)
        return est

    def hydraulic_options():  # the hydraulic profile's fast path: 9 parameters, not 5
        return recursion(quadratic_scale=1.0, directional=True)

    def updater():
        model = RecursiveKautzEstimator(poles, dt=FAST_DT).reset().model_
        upd = Updater(model, dt=FAST_DT, forgetting=FORGETTING, reidentify=False,
                      monitor=SyncMonitor(window=150, stride=25))
        for uk, yk in zip(u.tolist(), y.tolist(), strict=True):
            upd.step(uk, yk)
        return upd

    X = np.hstack([filter_states(plant.basis_, u)[:-1], np.ones((n, 1))])
    weights = FORGETTING ** (np.arange(memory)[::-1] / 2.0)  # square roots of the weights

    def refit():
        theta = None
        for k in range(memory, n + 1):
            w = weights[:, None]
            theta, *_ = np.linalg.lstsq(X[k - memory:k] * w, y[k - memory:k] * w[:, 0],
                                        rcond=None)
        return theta

    est, _, theta, _ = recursion(), updater(), refit(), hydraulic_options()  # warm-up
    t_rec, t_upd, t_fit, t_hyd = [], [], [], []
    for _ in range(repeats):  # alternate, so that a burst of load hits all alike
        t_rec.append(timed(recursion)[1] / n)
        t_upd.append(timed(updater)[1] / n)
        t_fit.append(timed(refit)[1] / (n - memory + 1))
        t_hyd.append(timed(hydraulic_options)[1] / n)
    row = {"samples": n, "memory": memory, "recursion_s": statistics.median(t_rec),
           "updater_step_s": statistics.median(t_upd), "refit_s": statistics.median(t_fit),
           "recursion_quadratic_directional_s": statistics.median(t_hyd),
           "repeats_recursion_quadratic_directional_s": t_hyd,
           "coef_rel_diff": float(np.max(np.abs(est.parameters_ - theta))
                                  / np.max(np.abs(theta))),
           "repeats_recursion_s": t_rec, "repeats_updater_step_s": t_upd,
           "repeats_refit_s": t_fit}
    row["speedup"] = row["refit_s"] / row["recursion_s"]
    row["quadratic_directional_cost"] = row["recursion_quadratic_directional_s"] / row[
        "recursion_s"]
    print(f"fast path, per sample: RLS update {1e6 * row['recursion_s']:.1f} us, Updater.step "
          f"{1e6 * row['updater_step_s']:.1f} us; windowed refit ({memory} samples) "
          f"{1e6 * row['refit_s']:.1f} us ({row['speedup']:.1f}x); coefficients differ by "
          f"{row['coef_rel_diff']:.1e} of the largest; with the quadratic channel and "
          f"directional forgetting {1e6 * row['recursion_quadratic_directional_s']:.1f} us "
          f"({row['quadratic_directional_cost']:.2f}x the plain update)")
    return row


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
    ap.add_argument("--quick", action="store_true", help="a shorter run, fewer repeats")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "update.json")
    args = ap.parse_args(argv)
    machine = machine_info()
    duration = 45.0 if args.quick else 90.0
    repeats = 2 if args.quick else 5
    fast = _fast_path(2_000 if args.quick else 20_000, repeats)
    jobs = _jobs(duration)
    if args.quick:
        jobs = jobs[:4]
    rows = []
    print(f"{'sample':>7} {'window':>7} {'current ms':>11} {'baseline ms':>12} {'speed-up':>9} "
          f"{'held-out diff':>14}")
    for job in jobs:
        def current(job=job):
            return worker._fit_window(job).fit

        def baseline(job=job):
            return _sequential_fit(job)

        fit_c, fit_b = current(), baseline()  # warm-up, and the models compared
        t_cur, t_base = [], []
        for _ in range(repeats):  # alternate, so that a burst of load hits both alike
            t_cur.append(timed(current)[1])
            t_base.append(timed(baseline)[1])
        yc, yb = _held_out(job, fit_c), _held_out(job, fit_b)
        spread = float(np.ptp(job.y[job.u.size - job.n_val:][np.isfinite(
            job.y[job.u.size - job.n_val:])]))
        diff = float(np.max(np.abs(yc - yb)) / spread)
        row = {"k": int(job.k), "window": int(job.u.size - job.w0), "n_val": int(job.n_val),
               "current_s": statistics.median(t_cur), "baseline_s": statistics.median(t_base),
               "held_out_rel_diff": diff, "fit_current": float(fit_c.fit_percent),
               "fit_baseline": float(fit_b.fit_percent), "repeats_current_s": t_cur,
               "repeats_baseline_s": t_base}
        row["speedup"] = row["baseline_s"] / row["current_s"]
        rows.append(row)
        print(f"{row['k']:>7} {row['window']:>7} {1e3 * row['current_s']:>11.1f} "
              f"{1e3 * row['baseline_s']:>12.1f} {row['speedup']:>8.2f}x {diff:>14.2e}")
    total_c = sum(r["current_s"] for r in rows)
    total_b = sum(r["baseline_s"] for r in rows)
    print(f"all {len(rows)} fits: current {1e3 * total_c:.0f} ms, baseline {1e3 * total_b:.0f} ms "
          f"({total_b / total_c:.2f}x)")
    result = benchmark_result(
        "update", argv, quick=args.quick,
        settings={"duration_s": duration, "drift_events_s": list(DRIFTS), "repeats": repeats,
                  "plant": "hydraulic, 40 % pole drift", "initial_state":
                  worker._INITIAL_STATE},
        machine=machine, fast_path=fast, rows=rows,
        summary={"fits": len(rows), "current_s": total_c, "baseline_s": total_b,
                 "speedup": total_b / total_c})
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
