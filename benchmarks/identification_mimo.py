"""MIMO identification on the TCLab emulator (2 heaters -> 2 thermistors): kautztwin vs SIPPY.

The plant is ``tclab.TCLabModel`` (the ``tclab`` package's emulator of the board: a fourth-
order heat-transfer model, two heaters, two thermistors coupled through the heater
temperatures), driven on a simulated clock exactly as :class:`kautztwin.twin.physical.
TCLabPlant` drives it, but with both heaters: every second both heater powers are set,
the emulator is integrated to the next sample and both thermistors are read with tclab's
noise (standard deviation 0.043 degC, drawn from a seeded numpy generator) and its A/D
quantisation (0.3223 degC).  Two independent runs, each from ambient with the heaters off
for the first 30 s, then multi-level random steps of both heaters (levels uniform in
0-100 %, hold times uniform in 10-150 s, independent per heater; fixed seeds):

* estimation: 3600 s (seed 1); validation: 1800 s (seed 2).  Nothing is downloaded.

Methods (all judged by free-run simulation from rest at the reference levels, per output,
with MATLAB ``compare``'s fit ``100 (1 - ||y - yhat|| / ||y - mean y||)`` on the whole
validation run):

* ``kautztwin``: :class:`kautztwin.ident.mimo.MIMOKautzEstimator` with its defaults
  (shared poles, 1-6 poles chosen on the held-out last 25 % of the estimation run, refit on
  the whole run), ``input_offset=0`` (the heaters' rest level);
* ``kautztwin_per_output``, ``kautztwin_auto_structure``: per-output poles, and the
  structure chosen on the held-out data too;
* ``sippy_n4sid``: SIPPY's MIMO N4SID (``SS_fixed_order`` 1-8, ``SS_f = 20``), and
  ``sippy_arx``: SIPPY's MIMO ARX (least squares, ``na = nb`` in 1-20, one-sample delay),
  both with the order chosen by the *same* rule as kautztwin (fit on the first 75 % of the
  estimation run, best mean fit on the held-out 25 %, refit on the whole run); data measured
  from the rest levels (heaters 0 %, thermistors the mean of the 30 s at rest);
* ``sippy_n4sid_oracle``, ``sippy_arx_oracle``: SIPPY's best order of the same grids chosen
  *on the validation run itself*, an upper bound of what SIPPY can do here.

The acceptance figure is kautztwin's validation fit per output against the best SIPPY entry
per output (oracles included).  Times are wall-clock ``time.perf_counter`` of the
identification including its order search (for the oracles: every fit of the grid); the
headline pair (kautztwin's defaults, SIPPY N4SID with its order search) is timed again
``--repeat`` times, interleaved, and compared by the minima (the machine may be shared).

Usage::

    python benchmarks/identification_mimo.py [--repeat 3]
        [--out benchmarks/results/identification_mimo.json]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import io
import json
import os
import platform
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import scipy.signal

from kautztwin._json import to_jsonable
from kautztwin.ident.mimo import MIMOKautzEstimator
from kautztwin.metrics import fit_percent

ROOT = Path(__file__).resolve().parents[1]
DT = 1.0
LEAD_IN = 30
HOLDOUT = 0.25
TCLAB_NOISE = 0.043


def simulate_tclab(
    n_samples: int, seed: int, *, hold: tuple[int, int] = (10, 150)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One two-heater run of tclab's emulator: ``u, y, y_true`` of shape (n_samples, 2)."""
    import tclab

    rng = np.random.default_rng(seed)
    u = np.zeros((n_samples, 2))
    for j in range(2):
        k = LEAD_IN
        while k < n_samples:
            h = int(rng.integers(hold[0], hold[1] + 1))
            u[k : k + h, j] = rng.uniform(0.0, 100.0)
            k += h
    with contextlib.redirect_stdout(io.StringIO()):
        lab = tclab.TCLabModel(synced=False)
    origin = float(lab.tlast)
    y = np.empty((n_samples, 2))
    y_true = np.empty((n_samples, 2))
    for k in range(n_samples):
        if k:
            lab.update(origin + k * DT)
        y_true[k] = lab._T1, lab._T2
        y[k] = [lab.quantize(t + TCLAB_NOISE * rng.standard_normal()) for t in y_true[k]]
        lab.Q1(u[k, 0])
        lab.Q2(u[k, 1])
    with contextlib.redirect_stdout(io.StringIO()):
        lab.close()
    return u, y, y_true


def _fits(y: np.ndarray, yhat: np.ndarray) -> list[float]:
    return [float(v) for v in np.atleast_1d(fit_percent(y.T, yhat.T))]


# --------------------------------------------------------------------------- kautztwin
def m_kautztwin(data: dict[str, Any], poles: str) -> dict[str, Any]:
    (ue, ye), (uv, yv) = data["est"], data["val"]
    est = MIMOKautzEstimator(poles=poles, input_offset=[0.0, 0.0], holdout=HOLDOUT)
    t0 = time.perf_counter()
    est.fit(ue, ye, dt=DT)
    elapsed = time.perf_counter() - t0
    m = est.model_
    return {
        "config": {"n_poles": "auto (1-6)", "poles": poles, "holdout": HOLDOUT,
                   "initial": "rest at u = 0; output offsets fitted"},
        "chosen": {"poles": est.poles_, "n_poles": est.n_poles_.tolist()},
        "estimation_fit_percent": _fits(ye, m.simulate(ue)),
        "validation_fit_percent": _fits(yv, m.simulate(uv)),
        "time_s": elapsed,
        "model": {"poles_z": [[p.real, p.imag] for p in m.poles], "n_states": m.n_states,
                  "output_offset": m.output_offset.tolist()},
    }


# --------------------------------------------------------------------------- SIPPY
def _sippy() -> Any:
    try:
        import sippy_unipi
    except ImportError as exc:
        raise RuntimeError(
            f"sippy-unipi is not installed ({exc}); pip install sippy-unipi==1.0.1"
        ) from None
    return sippy_unipi


def _sippy_fit(u: np.ndarray, y: np.ndarray, method: str, order: int) -> Callable:
    """Fit SIPPY to centred data; return a simulator ``u -> yhat`` (centred, from rest)."""
    sippy = _sippy()
    kw: dict[str, Any]
    if method == "N4SID":
        kw = {"SS_fixed_order": order, "SS_f": 20}
    else:
        kw = {"ARX_orders": [order, order, 0], "ARX_mod": "LLS"}
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            model = sippy.system_identification(y.T, u.T, method, tsample=DT, **kw)
        except SystemExit as exc:  # SIPPY reports bad arguments by sys.exit
            raise RuntimeError(f"SIPPY exited: {exc}") from None

    if method == "N4SID":
        from sippy_unipi import functionsetSIM

        def simulate(v: np.ndarray) -> np.ndarray:
            with np.errstate(all="ignore"):
                _, ys = functionsetSIM.SS_lsim_process_form(model.A, model.B, model.C,
                                                            model.D, v.T)
            return np.asarray(ys, dtype=float).T
    else:

        def simulate(v: np.ndarray) -> np.ndarray:
            out = np.zeros((v.shape[0], y.shape[1]))
            with np.errstate(all="ignore"):
                for i in range(y.shape[1]):
                    for j in range(v.shape[1]):
                        num = np.asarray(model.NUMERATOR[i][j], dtype=float)
                        den = np.asarray(model.DENOMINATOR[i][j], dtype=float)
                        out[:, i] += scipy.signal.lfilter(np.concatenate([[0.0], num]), den,
                                                          v[:, j])
            return out

    return simulate


def _finite_fits(y: np.ndarray, yhat: np.ndarray) -> list[float]:
    if not np.all(np.isfinite(yhat)):
        return [-1e9] * y.shape[1]
    return _fits(y, yhat)


def m_sippy(data: dict[str, Any], method: str, orders: range, oracle: bool) -> dict[str, Any]:
    (ue, ye), (uv, yv) = data["est"], data["val"]
    y_ref = ye[:LEAD_IN].mean(axis=0)
    yv_ref = yv[:LEAD_IN].mean(axis=0)
    yc, yvc = ye - y_ref, yv - yv_ref
    n_est = ye.shape[0] - int(round(HOLDOUT * ye.shape[0]))
    table = []
    t0 = time.perf_counter()
    if oracle:
        for order in orders:
            sim = _sippy_fit(ue, yc, method, order)
            table.append({"order": order, "validation_fit_percent":
                          _finite_fits(yvc, sim(uv))})
        pick = max(table, key=lambda r: np.mean(r["validation_fit_percent"]))
        order = pick["order"]
        sim = _sippy_fit(ue, yc, method, order)
        rule = "best mean validation fit over the grid (oracle)"
    else:
        for order in orders:
            sim = _sippy_fit(ue[:n_est], yc[:n_est], method, order)
            yh = sim(ue)
            table.append({"order": order, "holdout_fit_percent":
                          _finite_fits(yc[n_est:], yh[n_est:])})
        pick = max(table, key=lambda r: np.mean(r["holdout_fit_percent"]))
        order = pick["order"]
        sim = _sippy_fit(ue, yc, method, order)
        rule = f"best mean fit on the held-out last {HOLDOUT:.0%} of the estimation run"
    elapsed = time.perf_counter() - t0
    return {
        "config": {"method": method, "orders": [orders.start, orders.stop - 1],
                   "selection": rule,
                   "initial": "rest; signals from the rest levels (u = 0, y = mean of the "
                              f"first {LEAD_IN} s)"},
        "chosen": {"order": order},
        "estimation_fit_percent": _finite_fits(yc, sim(ue)),
        "validation_fit_percent": _finite_fits(yvc, sim(uv)),
        "time_s": elapsed,
        "selection": table,
    }


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for pkg in ("kautztwin", "numpy", "scipy", "tclab", "sippy-unipi", "control"):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "benchmarks/results/identification_mimo.json"))
    parser.add_argument("--repeat", type=int, default=3,
                        help="timing repeats of kautztwin and SIPPY N4SID (default 3)")
    args = parser.parse_args(argv)
    ue, ye, _ = simulate_tclab(3600, seed=1)
    uv, yv, yv_true = simulate_tclab(1800, seed=2)
    data = {"est": (ue, ye), "val": (uv, yv)}
    methods: dict[str, Callable[[], dict[str, Any]]] = {
        "kautztwin": lambda: m_kautztwin(data, "shared"),
        "kautztwin_per_output": lambda: m_kautztwin(data, "per_output"),
        "kautztwin_auto_structure": lambda: m_kautztwin(data, "auto"),
        "sippy_n4sid": lambda: m_sippy(data, "N4SID", range(1, 9), oracle=False),
        "sippy_arx": lambda: m_sippy(data, "ARX", range(1, 21), oracle=False),
        "sippy_n4sid_oracle": lambda: m_sippy(data, "N4SID", range(1, 9), oracle=True),
        "sippy_arx_oracle": lambda: m_sippy(data, "ARX", range(1, 21), oracle=True),
    }
    rows: dict[str, Any] = {}
    for name, fn in methods.items():
        try:
            rows[name] = {"status": "ok", **fn()}
        except RuntimeError as exc:
            rows[name] = {"status": "unavailable", "reason": str(exc)}
        r = rows[name]
        if r["status"] == "ok":
            fits = ", ".join(f"{v:7.3f}" for v in r["validation_fit_percent"])
            print(f"{name:26s} validation fit [T1, T2] = [{fits}] %   "
                  f"{r['time_s']:7.2f} s   {r['chosen']}")
        else:
            print(f"{name:26s} {r['reason']}")
    # timing under a shared machine's load is noisy: the headline pair, interleaved, repeated
    timing: dict[str, Any] = {}
    if rows["sippy_n4sid"]["status"] == "ok":
        t_ours, t_sippy = [], []
        for _ in range(args.repeat):
            t_ours.append(m_kautztwin(data, "shared")["time_s"])
            t_sippy.append(m_sippy(data, "N4SID", range(1, 9), oracle=False)["time_s"])
        timing = {"repeats": args.repeat, "kautztwin_s": t_ours, "sippy_n4sid_s": t_sippy,
                  "ratio_of_minima": min(t_ours) / min(t_sippy)}
        print(f"timing (min of {args.repeat}, interleaved): kautztwin {min(t_ours):.2f} s, "
              f"SIPPY N4SID {min(t_sippy):.2f} s, ratio {timing['ratio_of_minima']:.2f}")
    # the noise floor: the noise-free emulator output (plus the mean quantisation bias) as
    # the "model"
    floor = _fits(yv, yv_true + (yv - yv_true).mean(axis=0))
    print(f"{'noise floor (true T)':26s} validation fit [T1, T2] = "
          f"[{', '.join(f'{v:7.3f}' for v in floor)}] %")
    sippy = [r for k, r in rows.items() if k.startswith("sippy") and r["status"] == "ok"]
    verdict: dict[str, Any] = {}
    if sippy:
        best = np.max([r["validation_fit_percent"] for r in sippy], axis=0)
        ours = np.asarray(rows["kautztwin"]["validation_fit_percent"])
        verdict = {
            "best_sippy_validation_fit_percent": best.tolist(),
            "kautztwin_validation_fit_percent": ours.tolist(),
            "margin_percent_points": (ours - best).tolist(),
            "kautztwin_at_least_best_sippy_per_output": bool(np.all(ours >= best)),
        }
        print("kautztwin >= best SIPPY per output:",
              verdict["kautztwin_at_least_best_sippy_per_output"],
              "margins", np.round(ours - best, 4).tolist())
    out = {
        "benchmark": "identification_mimo",
        "plant": "tclab.TCLabModel emulator, Q1, Q2 -> T1, T2, dt = 1 s, noise 0.043 degC "
                 "(seeded) + tclab's 0.3223 degC quantisation",
        "records": {"estimation": {"n_samples": 3600, "seed": 1},
                    "validation": {"n_samples": 1800, "seed": 2},
                    "excitation": f"heaters off for {LEAD_IN} s, then random levels "
                                  "U(0, 100) % held U{10..150} s, independent per heater"},
        "noise_floor_validation_fit_percent": floor,
        "methods": rows,
        "verdict": verdict,
        "timing": timing,
        "versions": _versions(),
        "threads": {k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")},
        "command": "python " + " ".join([Path(sys.argv[0]).name, *(argv or sys.argv[1:])]),
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(out), indent=1) + "\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
