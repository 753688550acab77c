"""Benchmark of the exports: ONNX parity and latency against torch, and the FMU's step cost.

ONNX (``kautztwin.export.export_onnx``): two estimators on the paper's system
(``kautztwin.datasets.paper_system``, +-50 % uncertainty, impulse records of 900 samples on
[0, 20] s, 10 % white noise), trained briefly (the latency does not depend on how well they
are trained; the parity is measured on the trained weights):

* ``coefficient``: the paper's estimator, one :class:`~kautztwin.nn.PaperNetwork` per
  coefficient (four networks of 488 171 weights);
* ``adaptive``: :class:`~kautztwin.nn.adaptive.AdaptivePoleEstimator` with its default
  network (two stages of 256-256-256, 32 features; the correction stage builds a Kautz basis
  and solves a least-squares problem per record inside the graph).

For each: the largest difference between onnxruntime's outputs and the torch estimator's
``predict`` (``refine=False``) on 1 000 fresh records, relative to the output's largest
magnitude, against the acceptance limit of 1e-5 (``parity_met``, and ``parity_margin``: the
limit divided by the largest difference).  The adaptive estimator predicts in ``float64``
(its ``float32``-trained weights cast exactly), as its default graph does; beside that, its
graph is also compared with the same network evaluated by torch in ``float32``
(``torch_network_float32``: what ``predict`` returned before the network was kept in
``float64``), and the ``float32`` graph (``adaptive_float32``) with that evaluation.  Then the
latency of both, for a batch of 1 000 records (seconds per record) and for
a single record (seconds per call), medians over repeats that alternate between torch and
onnxruntime.  Both run single-threaded (``torch.set_num_threads(1)``,
``intra_op_num_threads = 1``): the machine is shared.

FMU (``kautztwin.export.export_fmu``): the paper's Kautz model (4 states) and an identified
transfer function with a fractional input delay, at a step of 0.02 s.  Timed: one
``fmi2DoStep`` over 100 000 steps (the C recursion alone, per step), and a
co-simulation loop through FMPy (``setReal``, ``doStep``, ``getReal`` per step, as a
Python master pays it), beside ``kautztwin.ident.simulate_lti`` on the same input (per
sample; a batch computation, for scale).  The largest difference between the FMU's output
and ``simulate_lti`` over the loop is recorded too.

Usage::

    python benchmarks/bench_export.py [--quick] [--out benchmarks/results/export.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 - the thread variables must be set before numpy loads
import copy  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import fmpy  # noqa: E402
import numpy as np  # noqa: E402
import onnx  # noqa: E402
import onnxruntime as ort  # noqa: E402
import scipy  # noqa: E402
import torch  # noqa: E402

import kautztwin as kt  # noqa: E402
from kautztwin.datasets import draw_parameters, make_dataset, paper_system  # noqa: E402
from kautztwin.export import export_fmu, export_onnx  # noqa: E402
from kautztwin.ident import TransferFunctionModel, simulate_lti  # noqa: E402
from kautztwin.nn import AdaptivePoleEstimator, CoefficientEstimator  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import benchmark_result, machine_info, write_json  # noqa: E402

N_SAMPLES = 900
T_END = 20.0
UNCERTAINTY = 0.5
NOISE = 0.1
N_PARITY = 1000
#: acceptance (issue #14): every output within this much of torch, relative to its magnitude
PARITY_LIMIT = 1e-5
FMU_STEP = 0.02
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "export.json"
FULL = {"n_train": 2000, "epochs": 5, "pretrain": 20, "repeats": 15, "fmu_loop": 20000}
QUICK = {"n_train": 300, "epochs": 1, "pretrain": 2, "repeats": 3, "fmu_loop": 2000}


def _records(n: int, seed: int) -> Any:
    system = paper_system()
    t = np.linspace(0.0, T_END, N_SAMPLES)
    P = draw_parameters(system, UNCERTAINTY, n, random_state=seed)
    return make_dataset(system, P, kt.KautzBasis(system.poles()), t, noise=NOISE,
                        random_state=seed + 1)


def _session(path: Path) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def _alternate(fns: dict[str, Any], repeats: int) -> dict[str, dict[str, float]]:
    """Median and minimum seconds of each function; repeats alternate between them."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    for fn in fns.values():
        fn()  # warm-up
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return {k: {"median_s": statistics.median(v), "min_s": min(v)} for k, v in times.items()}


def _parity(got: np.ndarray, ref: np.ndarray) -> float:
    return float(np.max(np.abs(got - ref)) / np.max(np.abs(ref)))


def _predict(est: Any, x: np.ndarray) -> dict[str, np.ndarray]:
    """The torch estimator's outputs, named as the ONNX graph's."""
    if isinstance(est, AdaptivePoleEstimator):
        poles, coef = est.predict(x, refine=False)
        return {"poles_real": poles.real, "poles_imag": poles.imag, "coefficients": coef}
    return {"coefficients": est.predict(x)}


def _network_float32(est: Any) -> Any:
    """A copy of an adaptive estimator whose network computes in float32 (as trained)."""
    est32 = copy.deepcopy(est)
    est32.network_.cast(torch.float32)
    return est32


def onnx_case(name: str, est: Any, folder: Path, X: np.ndarray, repeats: int,
              dtype: str = "auto") -> dict[str, Any]:
    if dtype == "float32" and isinstance(est, AdaptivePoleEstimator):
        est = _network_float32(est)  # the float32 graph against the float32 network
    path = export_onnx(est, folder / f"{name}.onnx", dtype=dtype)
    sess = _session(path)
    model = onnx.load(str(path))
    names = [o.name for o in sess.get_outputs()]
    got = dict(zip(names, sess.run(None, {"responses": X}), strict=True))
    parity = {"torch_predict": {k: _parity(got[k], v) for k, v in _predict(est, X).items()}}
    if isinstance(est, AdaptivePoleEstimator) and dtype != "float32":
        # the same trained network evaluated by torch in float32 (the predict of before)
        ref = _predict(_network_float32(est), X)
        parity["torch_network_float32"] = {k: _parity(got[k], v) for k, v in ref.items()}
    worst = max(parity["torch_predict"].values())
    one = X[:1]
    batch = _alternate({"torch": lambda: _predict(est, X),
                        "onnxruntime": lambda: sess.run(None, {"responses": X})}, repeats)
    single = _alternate({"torch": lambda: _predict(est, one),
                         "onnxruntime": lambda: sess.run(None, {"responses": one})},
                        repeats * 20)
    out = {
        "estimator": type(est).__name__,
        "graph_dtype": next(p.value for p in model.metadata_props if p.key == "dtype"),
        "n_parameters": int(est.n_parameters_),
        "onnx_bytes": path.stat().st_size,
        "onnx_nodes": len(model.graph.node),
        "parity_max_rel_diff": parity,
        "parity_limit": PARITY_LIMIT,
        "parity_met": bool(worst <= PARITY_LIMIT),
        "parity_margin": PARITY_LIMIT / worst if worst > 0 else float("inf"),
        "batch_records": int(X.shape[0]),
        "batch_s_per_record": {k: v["median_s"] / X.shape[0] for k, v in batch.items()},
        "single_record_s": {k: v["median_s"] for k, v in single.items()},
        "batch_raw": batch,
        "single_raw": single,
    }
    out["speedup_batch"] = batch["torch"]["median_s"] / batch["onnxruntime"]["median_s"]
    out["speedup_single"] = single["torch"]["median_s"] / single["onnxruntime"]["median_s"]
    return out


def torch_float_gap(est: Any, X: np.ndarray) -> dict[str, float]:
    """How far torch's own float32 and float64 evaluations of the adaptive network differ."""
    a, b = _predict(_network_float32(est), X), _predict(est, X)
    return {k: _parity(a[k], b[k]) for k in a}


def _slave(path: Path, folder: Path) -> tuple[Any, dict[str, int]]:
    from fmpy.fmi2 import FMU2Slave

    md = fmpy.read_model_description(str(path))
    unzip = fmpy.extract(str(path), unzipdir=str(folder / path.stem))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzip,
                    modelIdentifier=md.coSimulation.modelIdentifier, instanceName="bench")
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    return fmu, {v.name: v.valueReference for v in md.modelVariables}


def fmu_case(name: str, model: Any, folder: Path, n_loop: int) -> dict[str, Any]:
    path = folder / f"{name}.fmu"
    start = time.perf_counter()
    export_fmu(model, path, step=FMU_STEP)
    build_s = time.perf_counter() - start
    rng = np.random.default_rng(0)
    u = np.repeat(rng.uniform(-1, 1, n_loop // 10 + 1), 10)[:n_loop]
    t = FMU_STEP * np.arange(n_loop)
    fmu, vr = _slave(path, folder)
    y = np.empty(n_loop)
    start = time.perf_counter()
    for k in range(n_loop):
        fmu.setReal([vr["u"]], [u[k]])
        y[k] = fmu.getReal([vr["y"]])[0]
        fmu.doStep(currentCommunicationPoint=t[k], communicationStepSize=FMU_STEP)
    loop_s = (time.perf_counter() - start) / n_loop
    n_inner = 100_000
    inner = []
    for _ in range(5):
        start = time.perf_counter()
        fmu.doStep(currentCommunicationPoint=0.0, communicationStepSize=n_inner * FMU_STEP)
        inner.append((time.perf_counter() - start) / n_inner)
    fmu.terminate()
    fmu.freeInstance()
    system = (model.num, model.den) if isinstance(model, TransferFunctionModel) \
        else model.state_space()
    delay = float(getattr(model, "delay", 0.0))
    start = time.perf_counter()
    ref = simulate_lti(system, t, u, delay=delay)
    sim_s = (time.perf_counter() - start) / n_loop
    return {
        "model": type(model).__name__,
        "n_states": int(len(model.poles)),
        "delay": delay,
        "step": FMU_STEP,
        "build_s": build_s,
        "fmu_bytes": path.stat().st_size,
        "c_doStep_s_per_step": statistics.median(inner),
        "fmpy_loop_s_per_step": loop_s,
        "simulate_lti_s_per_sample": sim_s,
        "n_steps": n_loop,
        "max_abs_diff_vs_simulate_lti": float(np.max(np.abs(y - ref))),
    }


def _print(cases: dict[str, Any], fmus: dict[str, Any]) -> None:
    for name, c in cases.items():
        b, s = c["batch_s_per_record"], c["single_record_s"]
        label = name
        for ref, par in c["parity_max_rel_diff"].items():
            text = ", ".join(f"{k} {v:.2g}" for k, v in par.items())
            print(f"{label:16s} parity vs {ref}: {text}")
            label = ""
        print(f"{'':16s} limit {c['parity_limit']:g}: "
              f"{'met' if c['parity_met'] else 'NOT met'} (margin {c['parity_margin']:.3g}x)")
        print(f"{'':16s} batch  torch {1e6 * b['torch']:8.1f} us/rec  onnxruntime "
              f"{1e6 * b['onnxruntime']:8.1f} us/rec  ({c['speedup_batch']:.2f}x)")
        print(f"{'':16s} single torch {1e6 * s['torch']:8.1f} us      onnxruntime "
              f"{1e6 * s['onnxruntime']:8.1f} us      ({c['speedup_single']:.2f}x)")
    for name, f in fmus.items():
        print(f"fmu {name:8s} C {1e9 * f['c_doStep_s_per_step']:6.1f} ns/step, FMPy loop "
              f"{1e6 * f['fmpy_loop_s_per_step']:6.1f} us/step, simulate_lti "
              f"{1e6 * f['simulate_lti_s_per_sample']:6.2f} us/sample, max diff "
              f"{f['max_abs_diff_vs_simulate_lti']:.2g}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny training, few repeats")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help="JSON file (default: results/export.json)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    s = QUICK if args.quick else FULL
    machine = machine_info({
        "numpy": np.__version__, "scipy": scipy.__version__, "torch": torch.__version__,
        "onnx": onnx.__version__, "onnxruntime": ort.__version__, "fmpy": fmpy.__version__,
        "kautztwin": kt.__version__,
    })
    started = time.perf_counter()
    X = _records(N_PARITY, seed=100).responses
    coef = CoefficientEstimator(per_coefficient=True,
                                config={"max_epochs": s["epochs"]}).fit(_records(400, seed=0))
    adaptive = AdaptivePoleEstimator(config={"max_epochs": s["epochs"]},
                                     pretrain_epochs=s["pretrain"])
    adaptive.fit_distribution(paper_system(), UNCERTAINTY, np.linspace(0.0, T_END, N_SAMPLES),
                              noise=NOISE, n_train=s["n_train"])
    w = 15**0.5 / 2
    models = {
        "kautz": kt.KautzModel(kt.KautzBasis([-1, -3, -0.5 + 1j * w, -0.5 - 1j * w]),
                               [2**0.5 / 8, -3 * 6**0.5 / 32, 5 * 2**0.5 / 32, 2**0.5 / 16]),
        "tf_delay": TransferFunctionModel(num=[0.5, 4.0], den=np.poly([-0.3 + 2j, -0.3 - 2j,
                                                                       -1.5]).real,
                                          delay=0.137),
    }
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cases = {
            "coefficient": onnx_case("coefficient", coef, folder, X, s["repeats"]),
            "adaptive": onnx_case("adaptive", adaptive, folder, X, s["repeats"]),
            "adaptive_float32": onnx_case("adaptive_float32", adaptive, folder, X,
                                          s["repeats"], dtype="float32"),
        }
        gap = torch_float_gap(adaptive, X)
        print(f"torch's own float32 vs float64 evaluation of the adaptive network: {gap}")
        fmus = {k: fmu_case(k, m, folder, s["fmu_loop"]) for k, m in models.items()}
    _print(cases, fmus)
    result = benchmark_result(
        "export", argv, quick=args.quick,
        settings={
            "system": "paper_system, +-50 % uncertainty, impulse records, 10 % white noise",
            "n_samples": N_SAMPLES, "t_end": T_END, "n_parity_records": N_PARITY,
            "training": s,
            "threads": "torch.set_num_threads(1); onnxruntime intra/inter op threads 1",
            "timer": "time.perf_counter medians; torch and onnxruntime repeats alternate",
            "fmu_step": FMU_STEP,
        },
        machine=machine, onnx=cases, adaptive_torch_float32_vs_float64=gap, fmu=fmus,
        elapsed_s=time.perf_counter() - started,
    )
    write_json(args.out, result)
    print(f"\n{result['elapsed_s']:.1f} s; results written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
