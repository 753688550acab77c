"""Tests of kautztwin.ident: records, TransferFunctionEstimator and the ARX baseline.

Acceptance oracle: a known third-order system 2/((s+0.5)(s+1.5)(s+4)), simulated
exactly, is recovered from several step records (different heights, offsets,
step times and grids) to 1e-6; with 10 % noise the fit to the noisy data is
within one point of the true model's fit on the same data.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from kautztwin.exceptions import ConvergenceWarning, DataError, DimensionError, NotFittedError
from kautztwin.ident import (
    ARXEstimator,
    ARXModel,
    Record,
    TransferFunctionEstimator,
    TransferFunctionModel,
    impulse_response,
    simulate_lti,
    step_response,
)
from kautztwin.ident.tfest.problem import _pooled_fit

TRUE_POLES = np.array([-4.0, -1.5, -0.5])
TRUE_NUM = [2.0]
TRUE_DEN = np.poly(TRUE_POLES).real
TRUE_GAIN = 2.0 / 3.0
# (step height, offset, step time, sampling period, samples, jitter as a fraction of dt)
STEP_SETUPS = [(1.0, 0.0, 0.0, 0.05, 300, 0.0), (2.5, 3.0, 1.0, 0.1, 200, 0.0),
               (-1.5, -2.0, 0.7, 0.07, 250, 0.15)]


def step_records(noise: float = 0.0, seed: int = 0, delay: float = 0.0):
    """Step records of the true system; returns (records, noise-free outputs)."""
    rng = np.random.default_rng(seed)
    recs, clean = [], []
    for height, offset, start, dt, n, jitter in STEP_SETUPS:
        t = np.arange(n) * dt + jitter * dt * rng.uniform(-1, 1, n)
        t[0] = 0.0
        t[np.argmin(np.abs(t - start))] = start  # the step happens at a sample
        yc = offset + height * step_response((TRUE_NUM, TRUE_DEN), t, delay=start + delay)
        y = yc + noise * np.ptp(yc) * rng.standard_normal(n)
        u = np.where(t >= start, height, 0.0)
        recs.append(Record.from_data(t, u, y, kind="step"))
        clean.append(yc)
    return recs, clean


@pytest.fixture(scope="module")
def noise_free_fit():
    recs, _ = step_records()
    return TransferFunctionEstimator(n_poles=3, n_zeros=0).fit(recs)


# --------------------------------------------------------------------------- acceptance
def test_noise_free_steps_recover_poles(noise_free_fit):
    poles = np.sort(noise_free_fit.model_.poles.real)
    np.testing.assert_allclose(poles, np.sort(TRUE_POLES), rtol=1e-6)
    assert np.all(noise_free_fit.model_.poles.imag == 0)


def test_noise_free_steps_recover_gain(noise_free_fit):
    np.testing.assert_allclose(noise_free_fit.model_.gain, TRUE_GAIN, rtol=1e-6)


def test_noise_free_steps_recover_offsets(noise_free_fit):
    np.testing.assert_allclose(noise_free_fit.model_.offsets, [0.0, 3.0, -2.0], atol=1e-6)
    assert noise_free_fit.model_.fit_percent > 99.9999


def test_noisy_steps_fit_within_one_point_of_the_true_model():
    recs, clean = step_records(noise=0.10, seed=1)
    true_fit = _pooled_fit([r.y for r in recs], clean, [r.weights for r in recs])
    model = TransferFunctionEstimator(n_poles=3, n_zeros=0).fit(recs).model_
    assert abs(model.fit_percent - true_fit) <= 1.0
    assert np.all(model.poles.real < 0)


def test_noise_free_fractional_delay_is_recovered():
    recs, _ = step_records(delay=0.37)
    model = TransferFunctionEstimator(n_poles=3, n_zeros=0, delay=True).fit(recs[:2]).model_
    np.testing.assert_allclose(model.delay, 0.37, rtol=1e-6)
    np.testing.assert_allclose(np.sort(model.poles.real), np.sort(TRUE_POLES), rtol=1e-6)


@pytest.mark.parametrize("intersample", ["zoh", "foh"])
def test_io_record_with_offset_and_initial_state_is_recovered(intersample):
    rng = np.random.default_rng(3)
    t = np.arange(400) * 0.05
    u = np.repeat(rng.standard_normal(40), 10)
    num, den = [1.0, 2.0], [1.0, 1.2, 4.0]
    A, B, C, D = (np.array([[0.0, 1.0], [-4.0, -1.2]]), np.array([[0.0], [1.0]]),
                  np.array([[2.0, 1.0]]), np.array([[0.0]]))
    y = 5.0 + simulate_lti((A, B, C, D), t, u, intersample=intersample, x0=[0.3, -0.2],
                           u_before=u[0])
    rec = Record.from_data(t, u + 0.0, y, kind="io", u_before=0.0)
    model = TransferFunctionEstimator(n_poles=2, intersample=intersample,
                                      initial_state="estimate").fit(rec).model_
    np.testing.assert_allclose(model.num, num, rtol=1e-6)
    np.testing.assert_allclose(model.den, den, rtol=1e-6)
    assert model.fit_percent > 99.9999


def test_impulse_records_are_recovered():
    t = np.linspace(0.0, 8.0, 161)
    recs = [Record.impulse_response(t, a * impulse_response(([2.0], [1.0, 3.0, 2.0]), t,
                                                            delay=s) + o,
                                    amplitude=a, start=s)
            for a, s, o in [(1.0, 0.0, 0.0), (0.5, 1.0, 2.0)]]
    model = TransferFunctionEstimator(n_poles=2, n_zeros=0).fit(recs).model_
    np.testing.assert_allclose(np.sort(model.poles.real), [-2.0, -1.0], rtol=1e-6)
    np.testing.assert_allclose(model.gain, 1.0, rtol=1e-6)


def test_automatic_order_prefers_the_true_order():
    # two step records: each is held out in turn (issue #13: not AIC alone)
    recs, _ = step_records(noise=0.01, seed=4)
    est = TransferFunctionEstimator(n_poles="auto", n_zeros=0, max_order=5).fit(recs[:2])
    rows = est.model_.order_selection
    assert [r["n_poles"] for r in rows] == [1, 2, 3, 4, 5]
    assert est.n_poles_ == 3
    chosen = next(r for r in rows if r["n_poles"] == 3)
    assert all(r["criterion"] < chosen["criterion"] for r in rows if r["n_poles"] < 3)


def test_automatic_order_uses_validation_fit_when_held_out():
    recs, _ = step_records(noise=0.01, seed=5)
    est = TransferFunctionEstimator(n_poles="auto", n_zeros=0, max_order=5,
                                    validate_from=8.0).fit(recs[:1])
    rows = est.model_.order_selection
    best = max(rows, key=lambda r: r["validation_fit_percent"])
    assert est.n_poles_ == best["n_poles"]
    assert est.model_.validation_fit_percent is not None


def test_covariance_matches_monte_carlo_scatter():
    # first-order step data: the predicted gain std agrees with the scatter over noise draws
    t = np.linspace(0.0, 6.0, 121)
    clean = 1.5 * step_response(([2.0], [1.0, 2.0]), t)
    rng = np.random.default_rng(6)
    gains, stds = [], []
    for _ in range(12):
        rec = Record.step_response(t, clean + 0.05 * rng.standard_normal(t.size))
        m = TransferFunctionEstimator(n_poles=1, n_zeros=0).fit(rec).model_
        gains.append(m.gain)
        stds.append(m.gain_std)
    ratio = np.std(gains, ddof=1) / np.mean(stds)
    assert 0.5 < ratio < 2.0
    assert m.parameter_names == ("num[0]", "den[1]")
    assert m.std.shape == (2,)


def test_validation_fit_is_reported_for_the_held_out_part():
    rng = np.random.default_rng(7)
    t = np.arange(600) * 0.05
    u = np.repeat(rng.choice([0.0, 1.0], 60), 10)
    y = 2.0 + simulate_lti(([2.0], [1.0, 3.0, 2.0]), t, u) + 0.01 * rng.standard_normal(t.size)
    est = TransferFunctionEstimator(n_poles=2, n_zeros=0, validate_from=15.0)
    model = est.fit(Record.from_data(t, u, y)).model_
    assert model.n_samples == 300
    assert 95.0 < model.validation_fit_percent < 100.0
    assert model.validation_fit_percent_per_record.shape == (1,)


def test_predict_and_score_reproduce_the_fit(noise_free_fit):
    recs, _ = step_records()
    preds = noise_free_fit.predict(recs)
    assert [p.shape for p in preds] == [r.y.shape for r in recs]
    assert noise_free_fit.score(recs) == pytest.approx(noise_free_fit.model_.fit_percent)


def test_estimator_simulate_matches_the_model(noise_free_fit):
    t = np.linspace(0.0, 5.0, 51)
    np.testing.assert_allclose(noise_free_fit.simulate(t, np.ones(t.size)),
                               noise_free_fit.model_.step(t), atol=1e-12)


def test_fit_accepts_tuples():
    t = np.linspace(0.0, 10.0, 201)
    y = 1.0 + 2.0 * step_response(([2.0], [1.0, 3.0, 2.0]), t)
    u = np.full(t.size, 2.0)
    model = TransferFunctionEstimator(n_poles=2, n_zeros=0, kind="step").fit((t, u, y)).model_
    np.testing.assert_allclose(model.den, [1.0, 3.0, 2.0], rtol=1e-8)


def test_fitted_poles_are_stable_even_for_drifting_data():
    t = np.linspace(0.0, 10.0, 200)
    u = np.sign(np.sin(t))
    y = 0.3 * t + np.random.default_rng(8).normal(0, 0.01, t.size)  # a pure drift
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = TransferFunctionEstimator(n_poles=2).fit(Record.from_data(t, u, y)).model_
    assert np.all(model.poles.real < 0)


def test_get_and_set_params_round_trip():
    est = TransferFunctionEstimator(n_poles=3, delay=True)
    assert est.get_params()["n_poles"] == 3
    assert est.set_params(n_zeros=1).n_zeros == 1
    with pytest.raises(ValueError, match="unknown parameter"):
        est.set_params(poles=2)


# --------------------------------------------------------------------------- estimator errors
def test_predict_before_fit_raises():
    with pytest.raises(NotFittedError, match="not fitted"):
        TransferFunctionEstimator().predict(Record.step_response([0, 1, 2, 3], [0, 1, 2, 2]))


@pytest.mark.parametrize(
    ("params", "match"),
    [({"n_poles": 0}, "n_poles must be"), ({"n_poles": "many"}, "n_poles must be"),
     ({"n_poles": 2, "n_zeros": 3}, "improper"), ({"delay": -1.0}, "delay must be"),
     ({"intersample": "cubic"}, "intersample"), ({"initial_state": "guess"}, "initial_state")],
    ids=["zero-poles", "text-poles", "improper", "negative-delay", "intersample", "init-state"],
)
def test_rejects_bad_parameters(params, match):
    rec = Record.step_response(np.linspace(0, 1, 20), np.linspace(0, 1, 20))
    with pytest.raises(DataError, match=match):
        TransferFunctionEstimator(**params).fit(rec)


def test_rejects_too_few_samples_for_the_order():
    rec = Record.step_response(np.arange(6.0), [0, 1, 2, 2.5, 2.7, 2.8])
    with pytest.raises(DataError, match="too short"):
        TransferFunctionEstimator(n_poles=4).fit(rec)


def test_rejects_validation_split_without_estimation_data():
    rec = Record.step_response(np.linspace(0, 1, 20), np.linspace(0, 1, 20))
    with pytest.raises(DataError, match="validate_from"):
        TransferFunctionEstimator(validate_from=0.05).fit(rec)


def test_rejects_initial_state_estimation_for_a_record_that_starts_at_its_step():
    rec = Record.step_response(np.linspace(0, 1, 20), np.linspace(0, 1, 20))
    with pytest.raises(DataError, match="cannot be told apart"):
        TransferFunctionEstimator(initial_state="estimate").fit(rec)


def test_rejects_impulse_records_with_as_many_zeros_as_poles():
    rec = Record.impulse_response(np.linspace(0, 5, 50), np.exp(-np.linspace(0, 5, 50)))
    with pytest.raises(DataError, match="fewer zeros than poles"):
        TransferFunctionEstimator(n_poles=1, n_zeros=1).fit(rec)


def test_rejects_records_of_another_kind():
    rec = Record.step_response(np.linspace(0, 1, 20), np.linspace(0, 1, 20))
    with pytest.raises(DataError, match="kind='io'"):
        TransferFunctionEstimator(kind="io").fit(rec)


def test_rejects_non_records():
    with pytest.raises(DataError, match="Record"):
        TransferFunctionEstimator().fit([np.arange(5)])


# --------------------------------------------------------------------------- records
def test_repeated_stamps_merge_with_weights():
    rec = Record.from_data([0, 0, 1, 2, 3], [0, 50, 50, 50, 50], [20, 22, 21, 22, 23], kind="step")
    np.testing.assert_allclose(rec.t, [0, 1, 2, 3])
    np.testing.assert_allclose(rec.y, [21, 21, 22, 23])
    np.testing.assert_allclose(rec.weights, [2, 1, 1, 1])
    assert (rec.start, rec.u_before, rec.amplitude) == (0.0, 0.0, 50.0)


def test_step_is_detected_inside_the_record():
    t = np.arange(10.0)
    rec = Record.from_data(t, np.where(t >= 4, 3.0, 1.0), np.zeros(10), kind="step")
    assert (rec.start, rec.u_before, rec.amplitude) == (4.0, 1.0, 2.0)


def test_constant_step_input_means_a_step_from_zero_at_the_start():
    rec = Record.from_data(np.arange(5.0), np.full(5, 50.0), np.arange(5.0), kind="step")
    assert (rec.start, rec.u_before, rec.amplitude) == (0.0, 0.0, 50.0)


def test_pulse_area_is_detected():
    t = np.arange(8.0) * 0.5
    u = np.zeros(8)
    u[2] = 4.0  # held for 0.5 s: area 2
    rec = Record.from_data(t, u, np.zeros(8), kind="impulse")
    assert (rec.start, rec.amplitude) == (1.0, 2.0)


def test_jitter_ignores_missing_samples():
    t = np.array([0.0, 1.0, 2.01, 4.0, 5.0, 6.0, 7.0])  # one stamp 0.01 late, one sample missing
    rec = Record.from_data(t, [0, 1, 0, 1, 0, 1, 0], np.zeros(7))
    assert rec.jitter == pytest.approx(0.01)


def test_select_keeps_the_step():
    rec = Record.step_response(np.arange(10.0), np.arange(10.0), amplitude=2.0, start=3.0)
    part = rec.select(rec.t < 6)
    assert (part.n_samples, part.start, part.amplitude) == (6, 3.0, 2.0)


def test_record_is_immutable():
    rec = Record.step_response(np.arange(5.0), np.arange(5.0))
    with pytest.raises(ValueError, match="read-only"):
        rec.y[0] = 1.0


@pytest.mark.parametrize(
    ("args", "kind", "error", "match"),
    [(([0, 1, 2, 3], [0, 1, 2, 3], [0, 1, np.nan, 3]), "io", DataError, "non-finite"),
     (([0, 2, 1, 3], [0, 1, 2, 3], [0, 1, 2, 3]), "io", DataError, "must not decrease"),
     (([0, 1, 2], [0, 1, 2], [0, 1, 2]), "io", DimensionError, "too short"),
     (([0, 1, 2, 3], [1, 1, 1, 1], [0, 1, 2, 3]), "io", DataError, "input is constant"),
     (([0, 1, 2, 3], [0, 0, 0, 0], [0, 1, 2, 3]), "step", DataError, "no step"),
     (([0, 1, 2, 3, 4], [0, 1, 1, 2, 2], [0, 1, 2, 3, 4]), "step", DataError, "single step"),
     (([0, 1, 2, 3], [0, 0, 0, 0], [0, 1, 2, 3]), "impulse", DataError, "pulse"),
     (([0, 1, 2, 3], [0, 1, 2], [0, 1, 2, 3]), "io", DimensionError, "same length"),
     (([0, 1, 2, 3], [0, 1, 2, 3], [0, 1, 2, 3]), "ramp", DataError, "kind must be")],
    ids=["nan", "decreasing", "short", "constant-io", "zero-step", "two-steps", "no-pulse",
         "lengths", "kind"],
)
def test_record_errors(args, kind, error, match):
    with pytest.raises(error, match=match):
        Record.from_data(*args, kind=kind)


# --------------------------------------------------------------------------- result object
def test_model_reports_poles_zeros_gain():
    m = TransferFunctionModel(num=[2.0, 2.0], den=[2.0, 6.0, 4.0])  # normalised to monic
    np.testing.assert_allclose(m.den, [1.0, 3.0, 2.0])
    np.testing.assert_allclose(m.zeros, [-1.0])
    assert m.gain == pytest.approx(0.5)
    assert m.allclose(TransferFunctionModel(num=[1.0, 1.0], den=[1.0, 3.0, 2.0]))


def test_model_to_dict_has_the_reported_keys(noise_free_fit):
    d = noise_free_fit.model_.to_dict()
    for key in ("num", "den", "poles", "zeros", "gain", "delay", "fit_percent",
                "fit_percent_per_record", "aic", "covariance", "parameter_std"):
        assert key in d
    assert "validation_fit_percent" not in d


def test_model_rejects_improper_transfer_functions():
    with pytest.raises(DataError, match="improper"):
        TransferFunctionModel(num=[1.0, 0.0, 0.0], den=[1.0, 1.0])


# --------------------------------------------------------------------------- ARX
def test_arx_recovers_a_noise_free_model():
    rng = np.random.default_rng(9)
    u = rng.standard_normal(300)
    true = ARXModel(a=[-1.2, 0.5, -0.1], b=[0.8, 0.3], nk=2)
    y = true.simulate(u)
    est = ARXEstimator(na=3, nb=2, nk=2, detrend=False).fit(u, y)
    np.testing.assert_allclose(est.model_.a, true.a, atol=1e-10)
    np.testing.assert_allclose(est.model_.b, true.b, atol=1e-10)
    assert est.fit_percent_ == pytest.approx(100.0)


def test_arx_one_step_prediction_is_exact_without_noise():
    u = np.random.default_rng(10).standard_normal(100)
    m = ARXModel(a=[-0.5], b=[1.0])
    y = m.simulate(u)
    np.testing.assert_allclose(m.predict(u, y)[1:], y[1:], atol=1e-12)


def test_arx_rejects_constant_input():
    with pytest.raises(DataError, match="constant"):
        ARXEstimator().fit(np.ones(50), np.arange(50.0))
