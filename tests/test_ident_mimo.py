"""MIMO Kautz models (kautztwin.ident.mimo): truth recovery, interop, estimator, bad input."""

from __future__ import annotations

import contextlib
import io

import control
import numpy as np
import pytest
import scipy.signal

from kautztwin import KautzBasis
from kautztwin.exceptions import DataError, DimensionError, NotFittedError
from kautztwin.ident.mimo import (
    MIMOKautzEstimator,
    MIMOKautzModel,
    check_mimo_data,
    identify_mimo,
    load_mimo_model,
)

DT = 0.5


def _steps(rng: np.random.Generator, n: int, m: int, hold: int = 8) -> np.ndarray:
    return np.repeat(rng.uniform(-1, 1, (n // hold + 1, m)), hold, axis=0)[:n]


def _truth_real() -> control.StateSpace:
    """A 2x2 discrete system whose four channels share the poles 0.95, 0.8, 0.5."""
    A = np.diag([0.95, 0.8, 0.5])
    B = np.array([[1.0, 0.3], [-0.5, 1.0], [0.8, 0.4]])
    C = np.array([[1.0, 0.5, -0.7], [0.2, -1.0, 0.6]])
    return control.ss(A, B, C, np.zeros((2, 2)), DT)


def _truth_pair() -> control.StateSpace:
    """A 2x2 discrete system with a real pole and a lightly damped complex pair."""
    r, th = 0.9, 0.4
    A = np.array([[0.7, 0, 0], [0, r * np.cos(th), -r * np.sin(th)],
                  [0, r * np.sin(th), r * np.cos(th)]])
    B = np.array([[1.0, 0.5], [0.4, -1.0], [0.0, 0.7]])
    C = np.array([[0.6, 1.0, 0.2], [-1.0, 0.3, 0.8]])
    return control.ss(A, B, C, np.zeros((2, 2)), DT)


def _response(sys: control.StateSpace, u: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """python-control's simulation (the independent oracle), shape (n_samples, n_outputs)."""
    t = np.arange(u.shape[0]) * sys.dt
    res = control.forced_response(sys, T=t, U=u.T, X0=0 if x0 is None else x0)
    return np.asarray(res.outputs).T


# ----------------------------------------------------------------------------- truth recovery
def test_shared_poles_and_coefficient_matrices_recovered_from_noise_free_data():
    rng = np.random.default_rng(0)
    truth = _truth_real()
    u = _steps(rng, 600, 2)
    y = _response(truth, u) + np.array([2.0, -1.0])  # output levels at rest
    fit = identify_mimo(u, y, 3, dt=DT, input_offset=[0.0, 0.0])
    np.testing.assert_allclose(np.sort(fit.model.poles.real), [0.5, 0.8, 0.95], atol=1e-8)
    assert fit.model.shared and fit.model.n_states == 6
    np.testing.assert_allclose(fit.model.output_offset, [2.0, -1.0], atol=1e-8)
    # coefficient matrices: the exact projection of the truth on the fitted basis (Stein eq.)
    exact = MIMOKautzModel.from_state_space(truth, poles=fit.model.poles)
    for c_fit, c_true in zip(fit.model.coefficients, exact.coefficients, strict=True):
        np.testing.assert_allclose(c_fit, c_true, atol=1e-7)
    # and the simulation of a fresh input matches python-control's of the truth
    u2 = _steps(rng, 300, 2, hold=5)
    np.testing.assert_allclose(fit.model.simulate(u2) - [2.0, -1.0], _response(truth, u2),
                               atol=1e-7)
    assert fit.fit_percent.min() > 99.9999


def test_complex_pair_recovered_from_nearby_starting_poles():
    rng = np.random.default_rng(1)
    truth = _truth_pair()
    u = _steps(rng, 800, 2, hold=6)
    y = _response(truth, u)
    z_true = np.linalg.eigvals(truth.A)
    s_true = np.log(z_true.astype(complex)) / DT
    start = 1.3 * s_true.real + 0.8j * s_true.imag  # 30 % off in rate, 20 % in frequency
    fit = identify_mimo(u, y, start, dt=DT, input_offset=[0.0, 0.0], fit_offset=False)
    np.testing.assert_allclose(np.sort_complex(fit.model.poles), np.sort_complex(z_true),
                               atol=1e-8)
    np.testing.assert_allclose(fit.model.simulate(u), y, atol=1e-7)


def test_per_output_poles_recovered():
    rng = np.random.default_rng(2)
    s1 = control.ss([[0.9]], [[1.0, 0.5]], [[1.0]], [[0.0, 0.0]], DT)
    s2 = control.ss(np.diag([0.6, 0.3]), [[1.0, -0.4], [0.5, 1.0]], [[1.0, 0.7]],
                    [[0.0, 0.0]], DT)
    u = _steps(rng, 500, 2)
    y = np.column_stack([_response(s1, u), _response(s2, u)])
    fit = identify_mimo(u, y, [1, 2], dt=DT, poles="per_output", input_offset=[0.0, 0.0])
    assert not fit.model.shared
    np.testing.assert_allclose(fit.model.bases[0].poles.real, [0.9], atol=1e-8)
    np.testing.assert_allclose(np.sort(fit.model.bases[1].poles.real), [0.3, 0.6], atol=1e-8)
    np.testing.assert_allclose(fit.model.simulate(u), y, atol=1e-7)
    assert fit.model.n_states == 2 * (1 + 2)


def test_initial_state_estimated_for_a_record_that_does_not_start_at_rest():
    rng = np.random.default_rng(3)
    truth = _truth_real()
    u = _steps(rng, 500, 2)
    y = _response(truth, u, x0=np.array([3.0, -2.0, 1.5]))
    est = identify_mimo(u, y, 3, dt=DT, input_offset=[0.0, 0.0], initial_state="estimate")
    np.testing.assert_allclose(np.sort(est.model.poles.real), [0.5, 0.8, 0.95], atol=1e-7)
    np.testing.assert_allclose(est.simulate(u), y, atol=1e-6)
    zero = identify_mimo(u, y, 3, dt=DT, input_offset=[0.0, 0.0])
    assert zero.fit_percent.min() < 99.9 < est.fit_percent.min()


def _tclab_run(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free two-heater run of tclab's emulator from ambient (heaters off for 20 s)."""
    import tclab  # a test dependency (the tclab extra)
    rng = np.random.default_rng(seed)
    u = np.zeros((n, 2))
    u[20:] = _steps(rng, n - 20, 2, hold=40) * 50 + 50
    with contextlib.redirect_stdout(io.StringIO()):
        lab = tclab.TCLabModel(synced=False)
    origin = float(lab.tlast)
    y = np.empty((n, 2))
    for k in range(n):
        if k:
            lab.update(origin + k)
        y[k] = lab._T1, lab._T2
        lab.Q1(u[k, 0])
        lab.Q2(u[k, 1])
    return u, y


def test_tclab_emulator_poles_recovered_from_its_equations():
    # the emulator integrates dH/dt, dT/dt (tclab 1.0) by Euler steps of 0.2 s: its exact
    # sampled model is M^5, with M = I + 0.2 F; three distinct poles
    F = np.array([[-0.06, 0.01, 0, 0], [0.01, -0.06, 0, 0],
                  [1 / 140, 0, -1 / 140, 0], [0, 1 / 140, 0, -1 / 140]])
    M = np.eye(4) + 0.2 * F
    Ad = np.linalg.matrix_power(M, 5)
    G = np.array([[200 / 5720, 0], [0, 100 / 5720], [0, 0], [0, 0]]) * 0.2
    Bd = sum(np.linalg.matrix_power(M, i) @ G for i in range(5))
    truth = control.ss(Ad, Bd, np.eye(4)[2:], np.zeros((2, 2)), 1.0)
    u, y = _tclab_run(1500, seed=4)
    fit = identify_mimo(u, y, 3, dt=1.0, input_offset=[0.0, 0.0])
    poles = np.unique(np.round(np.linalg.eigvals(Ad).real, 12))
    np.testing.assert_allclose(np.sort(fit.model.poles.real), poles, rtol=1e-6)
    np.testing.assert_allclose(fit.model.output_offset, [21.0, 21.0], atol=1e-5)
    u2, _ = _tclab_run(600, seed=5)
    np.testing.assert_allclose(fit.model.simulate(u2) - 21.0, _response(truth, u2 * 1.0),
                               atol=1e-4)


def test_batched_regressors_equal_the_siso_filter_states():
    from kautztwin.ident.kautz_oe import filter_states
    from kautztwin.ident.mimo.fit import _Regressors

    basis = KautzBasis([0.9, 0.5 + 0.2j, 0.5 - 0.2j], dt=DT, delayed=True)
    v = np.random.default_rng(10).normal(size=(70, 2))
    X = _Regressors(v, True, True).matrix(basis)
    ref = np.hstack([filter_states(basis, v[:, j])[:-1] for j in range(2)])
    np.testing.assert_allclose(X[:, :6], ref, atol=1e-12)
    np.testing.assert_array_equal(X[:, 6], 1.0)
    free = np.array([np.linalg.matrix_power(basis.A, k) @ basis.B for k in range(70)])
    np.testing.assert_allclose(X[:, 7:], free, atol=1e-12)


# ----------------------------------------------------------------------------- interop
@pytest.fixture
def model() -> MIMOKautzModel:
    rng = np.random.default_rng(5)
    basis = KautzBasis([0.9, 0.6 + 0.3j, 0.6 - 0.3j], dt=DT, delayed=True)
    return MIMOKautzModel(basis, rng.normal(size=(3, 2, 3)), input_offset=[0.5, -0.5],
                          output_offset=[1.0, 2.0, 3.0])


def test_frequency_response_matches_python_control(model):
    w = np.linspace(0.01, np.pi / DT * 0.99, 40)
    ours = model.frequency_response(w)
    resp = control.frequency_response(model.to_control(), w)
    ref = np.asarray(resp.complex)  # (n_outputs, n_inputs, n_freqs)
    np.testing.assert_allclose(ours, np.moveaxis(ref, -1, 0), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(model.dc_gain, np.real(control.dcgain(model.to_control())),
                               rtol=1e-10)


def test_round_trip_through_python_control_and_scipy(model):
    w = np.linspace(0.05, 5.0, 25)
    for sys in (model.to_control(), model.to_scipy(), control.ss2tf(model.to_control())):
        back = MIMOKautzModel.from_state_space(sys)
        np.testing.assert_allclose(back.frequency_response(w), model.frequency_response(w),
                                   rtol=1e-8, atol=1e-10)
    # scipy's simulation of the realisation equals the model's own (deviation variables)
    u = _steps(np.random.default_rng(6), 120, 2)
    _, y_sp, _ = scipy.signal.dlsim(model.to_scipy(), u - model.input_offset)
    np.testing.assert_allclose(model.simulate(u) - model.output_offset, y_sp, atol=1e-10)


def test_from_continuous_system_discretised_with_zero_order_hold():
    sys_c = control.ss([[-1.0, 2.0], [0.0, -3.0]], [[1.0, 0.0], [0.5, 1.0]],
                       [[1.0, 0.0], [0.3, 1.0]], [[0.0, 0.1], [0.0, 0.0]])
    model = MIMOKautzModel.from_state_space(sys_c, dt=0.1)
    ref = control.sample_system(sys_c, 0.1, method="zoh")
    w = np.linspace(0.1, 20.0, 30)
    np.testing.assert_allclose(model.frequency_response(w),
                               np.moveaxis(np.asarray(control.frequency_response(ref, w)
                                                      .complex), -1, 0), rtol=1e-8, atol=1e-12)
    with pytest.raises(DataError, match="continuous-time"):
        MIMOKautzModel.from_state_space(sys_c)
    with pytest.raises(DataError, match="not stable"):
        MIMOKautzModel.from_state_space(control.ss([[1.2]], [[1.0]], [[1.0]], [[0.0]], 1.0))


def test_save_load_and_dict_round_trip(model, tmp_path):
    path = tmp_path / "mimo.json"
    model.save(path)
    back = load_mimo_model(path)
    assert back.allclose(model, rtol=1e-14, atol=0)
    u = _steps(np.random.default_rng(7), 50, 2)
    np.testing.assert_array_equal(back.simulate(u), model.simulate(u))
    per = MIMOKautzModel([KautzBasis([0.5], dt=1.0, delayed=True),
                          KautzBasis([0.2, 0.7], dt=1.0, delayed=True)],
                         [np.ones((1, 1)), np.ones((1, 2))])
    assert MIMOKautzModel.from_dict(per.to_dict()).allclose(per) and not per.shared
    with pytest.raises(DataError, match="not a MIMO Kautz model"):
        MIMOKautzModel.from_dict({"type": "KautzModel"})


def test_simulate_from_a_state_matches_scipy(model):
    u = _steps(np.random.default_rng(8), 60, 2)
    x0 = np.linspace(-1, 1, model.n_states)
    _, y_sp, _ = scipy.signal.dlsim(model.to_scipy(), u - model.input_offset, x0=x0)
    np.testing.assert_allclose(model.simulate(u, x0) - model.output_offset, y_sp, atol=1e-10)


# ----------------------------------------------------------------------------- estimator
def test_estimator_chooses_the_true_order_on_held_out_data():
    rng = np.random.default_rng(9)
    truth = _truth_real()
    u = _steps(rng, 800, 2)
    y = _response(truth, u) + 0.01 * rng.normal(size=(800, 2))
    est = MIMOKautzEstimator(max_poles=5, input_offset=[0.0, 0.0]).fit(u, y, dt=DT)
    assert est.poles_ == "shared" and est.n_poles_.tolist() == [3, 3]
    assert [r["n_poles"] for r in est.selection_][:3] == [1, 2, 3]
    u2 = _steps(rng, 400, 2, hold=5)
    assert est.score(u2, _response(truth, u2)) > 99.0
    np.testing.assert_allclose(est.predict(u2), est.model_.simulate(u2))


@pytest.mark.parametrize("rest_at", ["zero", "first"])
def test_estimator_input_offset_auto_finds_the_operating_point(rest_at):
    """A record that starts at rest at u = 0 with u[0] != 0 (a heater switched on at the
    first sample), and one that starts at the equilibrium of u[0]: 'auto' picks the offset
    that is true in each, and the noise-free fit is then exact."""
    rng = np.random.default_rng(21)
    truth = _truth_real()
    u = _steps(rng, 600, 2) + 0.5
    assert np.all(u[0] != 0.0)
    u_true = np.zeros(2) if rest_at == "zero" else u[0]
    y = _response(truth, u - u_true)
    est = MIMOKautzEstimator(3).fit(u, y, dt=DT)
    np.testing.assert_array_equal(est.input_offset_, u_true)
    assert len(est.offset_selection_) == 2
    assert est.score(u, y) > 99.99
    # the other offset, forced, cannot fit this record exactly
    wrong = u[0] if rest_at == "zero" else np.zeros(2)
    forced = MIMOKautzEstimator(3, input_offset=wrong).fit(u, y, dt=DT)
    assert forced.score(u, y) < 99.0
    assert MIMOKautzEstimator(3, input_offset=None).fit(u, y, dt=DT).input_offset_.tolist() \
        == u[0].tolist()


def test_estimator_input_offset_bad_string():
    u = _steps(np.random.default_rng(2), 100, 2)
    with pytest.raises(DataError, match="input_offset must be"):
        MIMOKautzEstimator(1, input_offset="first").fit(u, u, dt=DT)


def test_estimator_not_fitted():
    with pytest.raises(NotFittedError, match="not fitted"):
        MIMOKautzEstimator().predict(np.zeros((5, 2)))


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("u", "y", "match"),
    [
        (np.ones((50, 2)).cumsum(0), np.ones((49, 2)).cumsum(0), "one length"),
        (np.where(np.arange(100)[:, None] == 7, np.nan, 1.0) * np.arange(100)[:, None],
         np.arange(100.0), r"u\[7, 0\] is nan"),
        (np.column_stack([np.arange(60.0), np.full(60, 3.0)]), np.arange(60.0) ** 0.5,
         r"u\[:, 1\] is constant"),
        (np.arange(12.0), np.arange(12.0) ** 2, "too few"),
    ],
    ids=["unequal-lengths", "nan", "constant-input", "too-short"],
)
def test_bad_input_raises_a_one_line_data_error(u, y, match):
    with pytest.raises(DataError, match=match) as info:
        identify_mimo(u, y, 3, dt=1.0)
    assert "\n" not in str(info.value)
    with pytest.raises(DataError, match=match):
        MIMOKautzEstimator(3).fit(u, y)


def test_bad_shapes_and_settings():
    with pytest.raises(DimensionError, match="1-D or 2-D"):
        check_mimo_data(np.zeros((4, 2, 2)), np.zeros(4))
    u = np.random.default_rng(0).normal(size=(100, 2))
    with pytest.raises(DataError, match="poles must be one of"):
        identify_mimo(u, u, 1, dt=1.0, poles="full")
    with pytest.raises(DimensionError, match="input_offset"):
        identify_mimo(u, u, 1, dt=1.0, input_offset=[0.0])
    m = MIMOKautzModel(KautzBasis([0.5], dt=1.0, delayed=True), np.ones((1, 2, 1)))
    with pytest.raises(DimensionError, match="3 column"):
        m.simulate(np.zeros((5, 3)))


# ----------------------------------------------------------------------------- command line
def _csv(tmp_path, n: int = 500):
    rng = np.random.default_rng(11)
    truth = _truth_real()
    u = _steps(rng, n, 2)
    u[:10] = 0.0  # the record starts at rest at its first input (the default operating point)
    y = _response(truth, u) + [20.0, 21.0]
    t = np.arange(n) * DT
    path = tmp_path / "mimo.csv"
    np.savetxt(path, np.column_stack([t, u, y]), delimiter=",", header="t,Q1,Q2,T1,T2",
               comments="")
    return path, u, y


def test_cli_identify_with_several_columns_fits_a_mimo_model(tmp_path, capsys):
    import json

    from kautztwin.cli.main import main

    path, u, y = _csv(tmp_path)
    model_file = tmp_path / "m.json"
    code = main(["identify", str(path), "--time", "t", "--input", "Q1,Q2", "--output",
                 "T1,T2", "--order", "3", "--validate-from", "200", "--json",
                 "--save-model", str(model_file)])
    out = capsys.readouterr()
    assert code == 0, out.err
    summary = json.loads(out.out)
    np.testing.assert_allclose(np.sort([p[0] for p in summary["poles_z"]]), [0.5, 0.8, 0.95],
                               atol=1e-6)
    assert min(summary["validation_fit_percent"]) > 99.99
    # the saved model is the library's fit of the estimation samples
    saved = load_mimo_model(model_file)
    lib = identify_mimo(u[:400], y[:400], 3, dt=DT)
    np.testing.assert_allclose(saved.simulate(u), lib.model.simulate(u), atol=1e-6)
    # a file without a header takes 1-based column numbers, and --dt instead of a time column
    bare = tmp_path / "mimo.dat"
    bare.write_text("\n".join(path.read_text().splitlines()[1:]) + "\n")
    code = main(["identify", str(bare), "--dt", str(DT), "--input", "2,3", "--output",
                 "4,5", "--order", "3", "--validate-from", "200", "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    np.testing.assert_allclose(json.loads(out.out)["validation_fit_percent"],
                               summary["validation_fit_percent"], rtol=1e-9)


@pytest.mark.parametrize(
    ("extra", "match"),
    [(["--delay"], "--delay is not supported for a MIMO model"),
     (["--kind", "step"], "--kind is not supported"),
     (["--input", "Q1,"], "empty column name"),
     (["--model", "wiener"], "--model wiener fits one input and one output")],
    ids=["delay", "kind", "empty-column", "nonlinear-model"],
)
def test_cli_mimo_usage_errors_are_one_line(tmp_path, capsys, extra, match):
    from kautztwin.cli.main import main

    path, _, _ = _csv(tmp_path, n=100)
    argv = ["identify", str(path), "--time", "t", "--input", "Q1,Q2", "--output", "T1,T2",
            "--order", "2", *extra]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and match in err and err.count("\n") == 1, err
