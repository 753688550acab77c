"""``kautztwin.export``: ONNX parity with torch, FMUs validated and simulated by FMPy (#14 item 6).

ONNX: each estimator kind is exported and run in onnxruntime on 1 000 fresh records; every
output matches the torch estimator's ``predict`` to 1e-5 of that output's largest magnitude.
FMU: the generated C is compiled with the local compiler; FMPy validates the model
description, and its co-simulation of a step and of a random piecewise-constant input matches
the model's exact simulation (:func:`kautztwin.ident.simulate_lti`, scipy.signal) to 1e-6.
"""

from __future__ import annotations

import copy
import functools
import json
import shutil
import subprocess

import fmpy  # the [test] extra
import numpy as np
import onnxruntime as ort  # the [test] extra
import pytest
import scipy.signal
import torch

import kautztwin as kt
from kautztwin.cli.main import main
from kautztwin.datasets import draw_parameters, make_dataset, paper_system
from kautztwin.exceptions import DataError
from kautztwin.export import (
    ExportError,
    discretize,
    export_fmu,
    export_onnx,
    find_compiler,
    load_estimator_file,
    read_model_file,
)
from kautztwin.ident import TransferFunctionModel, simulate_lti
from kautztwin.nn import AdaptivePoleEstimator, CoefficientEstimator

#: ONNX parity: the largest difference, relative to the output's largest magnitude
ONNX_TOL = 1e-5
#: a float64 graph against torch in float64: both exact to rounding (measured about 1e-13;
#: a float32 rounding anywhere, such as onnxruntime fusing a scale into a float32
#: attribute, shows up as 1e-7 or more)
ONNX_TOL_FLOAT64 = 1e-10
#: FMU parity with the exact simulation (outputs of order one)
FMU_TOL = 1e-6
N_PARITY = 1000


# --------------------------------------------------------------------------- ONNX
def _records(t, n, kind="impulse", seed=5):
    """``n`` noisy records of the paper's system under +-50 % uncertainty on the grid ``t``."""
    t = np.asarray(t, dtype=float)
    return _cached_records(float(t[0]), float(t[-1]), t.size, n, kind, seed).responses


@functools.lru_cache(maxsize=8)
def _cached_records(t0, t_end, n_samples, n, kind, seed):
    system = paper_system()
    P = draw_parameters(system, 0.5, n, random_state=seed)
    basis = kt.KautzBasis(system.poles())
    t = np.linspace(t0, t_end, n_samples)
    return make_dataset(system, P, basis, t, noise=0.1, kind=kind, random_state=seed + 1)


def _session(path):
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def _assert_parity(got, ref, what, tol=ONNX_TOL):
    scale = float(np.max(np.abs(ref)))
    err = float(np.max(np.abs(got - ref)))
    assert err <= tol * scale, f"{what}: max difference {err:.3g} > {tol:g} x {scale:.3g}"


@pytest.fixture(scope="module")
def coefficient_estimator():
    # one network per coefficient, as in the paper (the single multi-output network is the
    # example of docs/export.md, run by tests/test_docs.py with the same tolerance)
    torch.set_num_threads(1)
    data = _cached_records(0.0, 20.0, 120, 80, "impulse", 0)
    est = CoefficientEstimator(per_coefficient=True, config={"max_epochs": 3})
    return est.fit(data)


ADAPTIVE_CASES = {
    # impulse records on [0, 20], ordinary least squares, two stages
    "impulse-2-stages": dict(kind="impulse", t=np.linspace(0.0, 20.0, 200), weights="uniform",
                             n_stages=2),
    # step records from t = 0.5 (the grid's first exponential), Simpson weights, three stages
    "step-3-stages": dict(kind="step", t=np.linspace(0.5, 20.0, 150), weights="simpson",
                          n_stages=3),
}


@pytest.fixture(scope="module", params=list(ADAPTIVE_CASES))
def adaptive_estimator(request):
    torch.set_num_threads(1)
    case = ADAPTIVE_CASES[request.param]
    est = AdaptivePoleEstimator(hidden=(32, 32), n_features=16, n_stages=case["n_stages"],
                                weights=case["weights"], config={"max_epochs": 3},
                                pretrain_epochs=3, relative_degree=4)
    est.fit_distribution(paper_system(), 0.5, case["t"], noise=0.1, n_train=400,
                         kind=case["kind"])
    return est


def test_onnx_coefficient_estimator_matches_torch_on_1000_records(coefficient_estimator,
                                                                   tmp_path):
    est = coefficient_estimator
    path = export_onnx(est, tmp_path / "coef.onnx")
    X = _records(est.t_, N_PARITY)
    (got,) = _session(path).run(None, {"responses": X})
    assert got.shape == (N_PARITY, est.n_functions_) and got.dtype == np.float64
    _assert_parity(got, est.predict(X), "coefficients")


def _adaptive_parity(path, est, X, tol):
    re, im, coef, params = _session(path).run(None, {"responses": X})
    poles, ref_coef = est.predict(X, refine=False)
    _assert_parity(re, poles.real, "poles_real", tol)
    _assert_parity(im, poles.imag, "poles_imag", tol)
    _assert_parity(coef, ref_coef, "coefficients", tol)
    assert np.all(params > 0) and np.all(re < 0)


def test_onnx_adaptive_estimator_matches_torch_on_1000_records(adaptive_estimator, tmp_path):
    est = adaptive_estimator
    X = _records(est.t_, N_PARITY, kind=est.kind_)
    # the estimator predicts in float64 (its float32-trained weights cast exactly) and so
    # does the default graph: the two agree to rounding, far inside the 1e-5 of the issue
    assert est.network_.dtype == torch.float64 and est.relative_degree_ == 4
    path = export_onnx(est, tmp_path / "adaptive.onnx")
    _adaptive_parity(path, est, X, ONNX_TOL_FLOAT64)
    # the float32 graph against the estimator's network evaluated in float32
    est32 = copy.deepcopy(est)
    est32.network_.cast(torch.float32)
    _adaptive_parity(export_onnx(est32, tmp_path / "a32.onnx", dtype="float32"), est32, X,
                     ONNX_TOL)


def test_onnx_graph_of_the_unconstrained_fit_matches_torch(tmp_path):
    # relative_degree=1: the plain least squares of the graph, without constraint columns
    torch.set_num_threads(1)
    t = np.linspace(0.0, 20.0, 120)
    est = AdaptivePoleEstimator(hidden=(16,), n_features=8, config={"max_epochs": 1},
                                pretrain_epochs=1, relative_degree=1)
    est.fit_distribution(paper_system(), 0.5, t, noise=0.1, n_train=200)
    assert est.relative_degree_ == 1
    path = export_onnx(est, tmp_path / "free.onnx")
    _adaptive_parity(path, est, _records(t, 200), ONNX_TOL_FLOAT64)
    # stages trained under the constraint, final fit without it (what 'auto' may choose)
    mixed = AdaptivePoleEstimator(hidden=(16,), n_features=8, config={"max_epochs": 1},
                                  pretrain_epochs=1, relative_degree=4)
    mixed.fit_distribution(paper_system(), 0.5, t, noise=0.1, n_train=200)
    mixed.relative_degree_ = 1
    assert mixed.network_.relative_degree == 4
    _adaptive_parity(export_onnx(mixed, tmp_path / "mixed.onnx"), mixed, _records(t, 200),
                     ONNX_TOL_FLOAT64)


def test_onnx_takes_any_batch_size_and_names_the_estimator(adaptive_estimator, tmp_path):
    import onnx

    est = adaptive_estimator
    path = export_onnx(est, tmp_path / "a.onnx")
    X = _records(est.t_, N_PARITY, kind=est.kind_)[:3]
    sess = _session(path)
    one = sess.run(["coefficients"], {"responses": X[:1]})[0]
    three = sess.run(["coefficients"], {"responses": X})[0]
    np.testing.assert_allclose(one[0], three[0], rtol=1e-12, atol=0)
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert meta["estimator"] == "AdaptivePoleEstimator" and meta["kind"] == est.kind_
    assert int(meta["n_samples"]) == est.n_samples_


def test_onnx_errors_are_one_line_data_errors(tmp_path):
    with pytest.raises(DataError, match="CoefficientEstimator or an AdaptivePoleEstimator"):
        export_onnx(object(), tmp_path / "x.onnx")
    with pytest.raises(DataError, match="not fitted"):
        export_onnx(CoefficientEstimator(), tmp_path / "x.onnx")
    with pytest.raises(DataError, match="dtype must be"):
        export_onnx(CoefficientEstimator(), tmp_path / "x.onnx", dtype="half")
    with pytest.raises(DataError, match="does not exist"):
        load_estimator_file(tmp_path / "missing")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "metadata.json").write_text("{not json")
    with pytest.raises(DataError, match="cannot read"):
        load_estimator_file(tmp_path / "bad")


def test_onnx_adaptive_needs_a_uniform_grid(tmp_path):
    torch.set_num_threads(1)
    t = np.r_[np.linspace(0.0, 5.0, 60), np.linspace(5.5, 20.0, 40)]
    est = AdaptivePoleEstimator(hidden=(8,), n_features=8, n_stages=1, config={"max_epochs": 1},
                                pretrain_epochs=1)
    est.fit_distribution(paper_system(), 0.2, t, noise=0.05, n_train=60)
    with pytest.raises(DataError, match="uniform time grid"):
        export_onnx(est, tmp_path / "x.onnx")


# --------------------------------------------------------------------------- FMU
W = 15**0.5 / 2
MODELS = {
    # real poles -1, -3 and a zero: 2 (s + 2) / ((s + 1)(s + 3))
    "real-poles": TransferFunctionModel(num=[2.0, 4.0], den=np.poly([-1.0, -3.0])),
    # a lightly damped pair and a real pole, one zero
    "complex-poles": TransferFunctionModel(
        num=[0.5, 4.0], den=np.real(np.poly([-0.3 + 2.0j, -0.3 - 2.0j, -1.5]))
    ),
    # the paper's Kautz model of 6 / ((s+1)(s+3)(s^2+s+4))
    "kautz": kt.KautzModel(
        kt.KautzBasis([-1, -3, -0.5 + 1j * W, -0.5 - 1j * W]),
        [2**0.5 / 8, -3 * 6**0.5 / 32, 5 * 2**0.5 / 32, 2**0.5 / 16],
    ),
}
STEP = 0.05


def _state_space(model):
    if isinstance(model, TransferFunctionModel):
        return (model.num, model.den)
    return model.state_space()


def _piecewise_constant(n, seed=3):
    rng = np.random.default_rng(seed)
    u = np.empty(n)
    k = 0
    while k < n:
        hold = int(rng.integers(1, 12))
        u[k : k + hold] = rng.uniform(-1.5, 1.5)
        k += hold
    return u


def _fmpy_run(path, t, u):
    signal = np.array(list(zip(t, u, strict=True)), dtype=[("time", float), ("u", float)])
    res = fmpy.simulate_fmu(str(path), start_time=t[0], stop_time=t[-1], output_interval=STEP,
                            input=signal, output=["y"])
    assert res["time"].shape == t.shape
    np.testing.assert_allclose(res["time"], t, rtol=0, atol=1e-9)
    return res["y"]


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    d = tmp_path_factory.mktemp("fmu")
    return {name: export_fmu(m, d / f"{name.replace('-', '_')}.fmu", step=STEP)
            for name, m in MODELS.items()}


@pytest.mark.parametrize("name", list(MODELS))
def test_fmu_passes_fmpy_validation(fmus, name):
    from fmpy.validation import validate_fmu

    assert validate_fmu(str(fmus[name])) == []
    md = fmpy.read_model_description(str(fmus[name]))
    assert md.fmiVersion == "2.0" and md.coSimulation is not None
    assert {v.name: v.causality for v in md.modelVariables} == {
        "u": "input", "y": "output", "u_offset": "parameter", "y_offset": "parameter"}
    assert float(md.defaultExperiment.stepSize) == STEP


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("signal", ["step", "random"])
def test_fmu_simulation_matches_the_model(fmus, name, signal):
    model = MODELS[name]
    t = STEP * np.arange(301)
    u = np.ones_like(t) if signal == "step" else _piecewise_constant(t.size)
    y = _fmpy_run(fmus[name], t, u)
    ref = simulate_lti(_state_space(model), t, u)
    assert np.max(np.abs(ref)) > 0.1  # the comparison is not of two zero signals
    np.testing.assert_allclose(y, ref, rtol=0, atol=FMU_TOL)
    if signal == "step":  # the exact step response of the model itself
        np.testing.assert_allclose(y, model.step(t), rtol=0, atol=FMU_TOL)


def test_fmu_matches_scipy_zoh_simulation(fmus):
    # an independent oracle: scipy's zero-order-hold lsim of the Kautz realisation
    t = STEP * np.arange(201)
    u = _piecewise_constant(t.size, seed=11)
    _, ref, _ = scipy.signal.lsim(MODELS["kautz"].to_scipy(), u, t, interp=False)
    np.testing.assert_allclose(_fmpy_run(fmus["kautz"], t, u), ref, rtol=0, atol=FMU_TOL)


class _Slave:
    """One FMU driven by hand through FMPy's FMI 2.0 wrapper (inputs set before reading y)."""

    def __init__(self, path, tmp_path):
        from fmpy.fmi2 import FMU2Slave

        md = fmpy.read_model_description(str(path))
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        folder = fmpy.extract(str(path), unzipdir=str(tmp_path / path.stem))
        self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=folder,
                             modelIdentifier=md.coSimulation.modelIdentifier,
                             instanceName="test")
        self.fmu.instantiate()
        self.fmu.setupExperiment(startTime=0.0)

    def start(self, **params):
        self.fmu.enterInitializationMode()
        for name, value in params.items():
            self.fmu.setReal([self.vr[name]], [value])
        self.fmu.exitInitializationMode()

    def run(self, u, h, every=1):
        out = []
        for k in range(0, len(u), every):
            self.fmu.setReal([self.vr["u"]], [u[k]])
            out.append(self.fmu.getReal([self.vr["y"]])[0])
            self.fmu.doStep(currentCommunicationPoint=k * h, communicationStepSize=every * h)
        return np.array(out)

    def close(self):
        self.fmu.terminate()
        self.fmu.freeInstance()


@pytest.mark.parametrize("delay", [0.0, 3 * STEP, 0.137], ids=["no-delay", "whole", "fraction"])
def test_fmu_with_delay_feedthrough_and_offsets(tmp_path, delay):
    # a biproper model (direct feedthrough D = 0.5) with an input delay: the output at t_k
    # reads the delayed input at t_k, so the input is set before the output is read
    model = TransferFunctionModel(num=[0.5, 1.0, 3.0], den=np.poly([-1.0, -2.0]), delay=delay)
    path = export_fmu(model, tmp_path / "delayed.fmu", step=STEP)
    t = STEP * np.arange(200)
    u = _piecewise_constant(t.size, seed=7)
    slave = _Slave(path, tmp_path)
    slave.start(u_offset=0.25, y_offset=-2.0)
    y = slave.run(u, STEP)
    slave.close()
    if delay == 3 * STEP:
        # a whole number of steps: the input shifted by three samples (simulate_lti would put
        # the delayed input's jumps at t_k + 0.15000000000000002, on either side of a sample)
        shifted = np.r_[np.full(3, 0.25), u[:-3]]
        ref = -2.0 + simulate_lti((model.num, model.den), t, shifted - 0.25)
    else:
        ref = -2.0 + simulate_lti((model.num, model.den), t, u - 0.25, delay=delay)
    np.testing.assert_allclose(y, ref, rtol=0, atol=FMU_TOL)


def test_fmu_steps_whole_multiples_and_rejects_other_steps(fmus, tmp_path):
    t = STEP * np.arange(120)
    u = np.repeat(_piecewise_constant(40, seed=2), 3)  # constant over every 3 steps
    slave = _Slave(fmus["complex-poles"], tmp_path)
    slave.start()
    y = slave.run(u, STEP, every=3)
    from fmpy.fmi1 import FMICallException

    with pytest.raises(FMICallException, match="fmi2DoStep"):
        slave.fmu.doStep(currentCommunicationPoint=t[-1], communicationStepSize=0.7 * STEP)
    slave.close()
    model = MODELS["complex-poles"]
    ref = simulate_lti((model.num, model.den), t, u)[::3]
    np.testing.assert_allclose(y, ref, rtol=0, atol=FMU_TOL)


def test_discrete_kautz_model_is_stepped_at_its_period(tmp_path):
    basis = kt.KautzBasis([0.8, 0.5 + 0.3j, 0.5 - 0.3j], dt=0.1)
    model = kt.KautzModel(basis, [0.4, -0.2, 0.3])
    path = export_fmu(model, tmp_path / "discrete.fmu")
    assert discretize(model).h == 0.1
    t = 0.1 * np.arange(150)
    u = _piecewise_constant(t.size, seed=4)
    slave = _Slave(path, tmp_path)
    slave.start()
    y = slave.run(u, 0.1)
    slave.close()
    _, ref, _ = scipy.signal.dlsim(model.to_scipy(), u)
    np.testing.assert_allclose(y, ref[:, 0], rtol=0, atol=FMU_TOL)
    with pytest.raises(DataError, match="sampling period"):
        discretize(model, 0.05)


def test_generated_c_compiles_without_warnings(fmus, tmp_path):
    import zipfile

    with zipfile.ZipFile(fmus["complex-poles"]) as zf:
        names = zf.namelist()
        source = zf.read("sources/complex_poles.c").decode()
    assert "binaries/linux64/complex_poles.so" in names and "modelDescription.xml" in names
    c_file = tmp_path / "model.c"
    c_file.write_text(source)
    done = subprocess.run([find_compiler(), "-std=c99", "-Wall", "-Wextra", "-Werror",
                           "-fsyntax-only", str(c_file)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_fmu_errors(tmp_path, monkeypatch):
    model = MODELS["real-poles"]
    with pytest.raises(DataError, match="needs the FMU's step"):
        export_fmu(model, tmp_path / "x.fmu")
    with pytest.raises(DataError, match="positive number"):
        export_fmu(model, tmp_path / "x.fmu", step=-1.0)
    with pytest.raises(DataError, match="TransferFunctionModel or a KautzModel"):
        export_fmu(object(), tmp_path / "x.fmu", step=0.1)
    with pytest.raises(DataError, match="does not exist"):
        export_fmu(model, tmp_path / "no" / "x.fmu", step=0.1)
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(ExportError, match="no C compiler found"):
        export_fmu(model, tmp_path / "x.fmu", step=0.1)


def test_read_model_file_reads_identify_and_approx_json(tmp_path):
    tf = TransferFunctionModel(num=[1.0, 2.0], den=[1.0, 4.0, 3.0], delay=0.2)
    (tmp_path / "tf.json").write_text(json.dumps(tf.to_dict()))
    assert read_model_file(tmp_path / "tf.json").allclose(tf)
    kz = MODELS["kautz"]
    (tmp_path / "kz.json").write_text(json.dumps(kz.to_dict()))
    assert read_model_file(tmp_path / "kz.json").allclose(kz)
    (tmp_path / "other.json").write_text(json.dumps({"a": 1}))
    with pytest.raises(DataError, match="not a linear model"):
        read_model_file(tmp_path / "other.json")
    (tmp_path / "unstable.json").write_text(json.dumps({"poles": [[1.0, 0.0]],
                                                       "coefficients": [1.0]}))
    with pytest.raises(DataError, match="invalid model"):
        read_model_file(tmp_path / "unstable.json")


# --------------------------------------------------------------------------- CLI
def test_cli_writes_an_onnx_model_from_a_model_folder(coefficient_estimator, tmp_path, capsys):
    est = coefficient_estimator
    est.save(tmp_path / "model")
    assert main(["export", str(tmp_path / "model"), "--onnx", str(tmp_path / "e.onnx")]) == 0
    assert "(float32 graph)" in capsys.readouterr().out
    assert main(["export", str(tmp_path / "model"), "--onnx", str(tmp_path / "e64.onnx"),
                 "--dtype", "float64", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["dtype"] == "float64"
    X = _records(est.t_, N_PARITY)[:20]
    for name in ("e.onnx", "e64.onnx"):
        (got,) = _session(tmp_path / name).run(None, {"responses": X})
        _assert_parity(got, est.predict(X), "coefficients")


def test_cli_writes_an_fmu_from_identify_and_approx_json(tmp_path, capsys):
    from fmpy.validation import validate_fmu

    (tmp_path / "tf.json").write_text(json.dumps(MODELS["complex-poles"].to_dict()))
    # what 'kautztwin approx --json' prints (the built-in reference system)
    assert main(["approx", "--poles", "-1,-3,-0.5+-1.9365j", "--json"]) == 0
    (tmp_path / "kz.json").write_text(capsys.readouterr().out)
    assert read_model_file(tmp_path / "kz.json").allclose(MODELS["kautz"], rtol=1e-4, atol=1e-5)
    for name in ("tf", "kz"):
        code = main(["export", str(tmp_path / f"{name}.json"), "--fmu",
                     str(tmp_path / f"{name}.fmu"), "--step", "0.1", "--name", f"plant_{name}",
                     "--json"])
        assert code == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["target"] == "fmu" and summary["step"] == 0.1
        assert validate_fmu(str(tmp_path / f"{name}.fmu")) == []
        md = fmpy.read_model_description(str(tmp_path / f"{name}.fmu"))
        assert md.coSimulation.modelIdentifier == f"plant_{name}"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.json", "--fmu", "x.fmu", "--step", "1"], "does not exist"),
        (["bad.json", "--fmu", "x.fmu", "--step", "1"], "cannot read model file"),
        (["tf.json", "--fmu", "x.fmu"], "needs the FMU's step"),
        (["tf.json", "--onnx", "x.onnx"], "--onnx takes a trained estimator's folder"),
        ([".", "--fmu", "x.fmu", "--step", "1"], "estimators go to --onnx"),
        ([".", "--onnx", "x.onnx"], "not a model folder"),
        (["tf.json", "--fmu", "x.fmu", "--step", "1", "--cc", "no-such-cc"], "not found"),
        (["tf.json", "--fmu", "x.fmu", "--step", "1", "--dtype", "float64"], "--onnx only"),
        ([".", "--onnx", "x.onnx", "--step", "1"], "--fmu only"),
        (["tf.json"], "one of the arguments --onnx --fmu is required"),
    ],
    ids=["missing", "corrupt", "no-step", "onnx-of-json", "fmu-of-folder", "no-metadata",
         "no-compiler", "dtype-for-fmu", "step-for-onnx", "no-target"],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "tf.json").write_text(json.dumps(MODELS["real-poles"].to_dict()))
    assert main(["export", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err


def test_cli_no_compiler_exits_2(tmp_path, monkeypatch, capsys):
    (tmp_path / "tf.json").write_text(json.dumps(MODELS["real-poles"].to_dict()))
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc is not None  # the FMU tests need one (CI has gcc)
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    code = main(["export", str(tmp_path / "tf.json"), "--fmu", str(tmp_path / "x.fmu"),
                 "--step", "0.1"])
    assert code == 2 and "no C compiler found" in capsys.readouterr().err


def test_export_error_lives_in_the_exceptions_module():
    import kautztwin.exceptions as exc
    import kautztwin.export.fmu as fmu

    assert fmu.ExportError is exc.ExportError is ExportError
    assert issubclass(ExportError, exc.KautzTwinError) and issubclass(ExportError, RuntimeError)
    assert "ExportError" in exc.__all__
