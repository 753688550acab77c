"""Uncertainty of the adaptive estimator: Laplace covariance, calibration, bands, files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kautztwin.approx import KautzModel
from kautztwin.basis import KautzBasis
from kautztwin.exceptions import DataError
from kautztwin.nn.adaptive import AdaptivePoleEstimator
from kautztwin.nn.family import PlantFamily, family_dataset, train_family
from kautztwin.nn.uncertainty import (
    ResponseEstimate,
    band_coverage,
    calibration_scale,
    laplace_response_covariance,
    normal_quantile,
)

FAMILY = {
    "plant": {"zeros": [-3.0], "poles": [-1.0, "-0.5+1.5j", "-0.5-1.5j"], "gain": 2.0},
    "tolerance": {"default": 0.2},
    "noise": {"level": 0.05, "color": "ar1", "ar1_pole": 0.8},
    "record": {"n_samples": 120},
    "training": {"n_records": 400, "n_calibration": 200, "n_validation": 20, "max_epochs": 4},
}


@pytest.fixture(scope="module")
def trained():
    torch.set_num_threads(1)
    fam = PlantFamily.from_dict(FAMILY)
    est, report = train_family(fam, oracle=False,
                               estimator_params={"hidden": (32,), "n_features": 12})
    return fam, est, report


# ----------------------------------------------------------------------------- Laplace
def test_laplace_matches_the_dense_sandwich_formula():
    rng = np.random.default_rng(0)
    n, p = 60, 3
    J = rng.standard_normal((2, n, p))
    r = rng.standard_normal((2, n)).cumsum(axis=1) * 0.1  # correlated residuals
    std, cov, s, rho = laplace_response_covariance(J, r)
    for i in range(2):
        lag = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
        R = rho[i] ** lag
        s2 = r[i] @ r[i] / (n - p)
        A = np.linalg.inv(J[i].T @ J[i])
        C = s2 * A @ J[i].T @ R @ J[i] @ A  # (J'J)^-1 J' Sigma J (J'J)^-1
        np.testing.assert_allclose(cov[i], C, rtol=1e-9, atol=0)
        np.testing.assert_allclose(std[i], np.sqrt(np.diag(J[i] @ C @ J[i].T)), rtol=1e-9)
        assert s[i] == pytest.approx(np.sqrt(s2), rel=1e-12)
        assert rho[i] == pytest.approx(r[i, 1:] @ r[i, :-1] / (r[i] @ r[i]), rel=1e-12)


def test_zero_residual_gives_a_zero_width_band():
    J = np.random.default_rng(1).standard_normal((1, 30, 2))
    std, cov, s, _ = laplace_response_covariance(J, np.zeros((1, 30)))
    assert np.all(std == 0) and np.all(cov == 0) and s[0] == 0
    est = ResponseEstimate(
        t=np.arange(30.0), kind="impulse", kinds=("real",), params=[[1.0]],
        coefficients=[[1.0]], response=np.ones((1, 30)), std=std, covariance=np.zeros((1, 2, 2)),
        noise_std=s, noise_correlation=np.zeros(1), scale=1.0, calibrated=False)
    np.testing.assert_array_equal(est.lower, est.upper)
    assert est.relative_width[0] == 0.0


def test_zero_jacobian_rows_give_zero_width_there():
    # a step-response basis is 0 at t = 0: the fit, and its band, are exactly 0 there
    J = np.random.default_rng(2).standard_normal((1, 40, 2))
    J[0, 0] = 0.0
    std, *_ = laplace_response_covariance(J, np.random.default_rng(3).standard_normal((1, 40)))
    assert std[0, 0] == 0.0 and np.all(std[0, 1:] > 0)


def test_laplace_rejects_bad_shapes():
    with pytest.raises(DataError, match="J must have shape"):
        laplace_response_covariance(np.ones((4, 2)), np.ones((1, 4)))
    with pytest.raises(DataError, match="cannot carry"):
        laplace_response_covariance(np.ones((1, 2, 3)), np.ones((1, 2)))


# ----------------------------------------------------------------------------- calibration
def test_calibration_scale_is_the_conformal_quantile():
    rng = np.random.default_rng(4)
    err = 3.0 * rng.standard_normal((300, 40))  # true sd 3, claimed sd 1
    kappa = calibration_scale(err, np.zeros_like(err), np.ones_like(err), 0.9)
    # the 90 % quantile of |N(0, 9)| / 1.645 is 3 (12 000 samples: within 3 %)
    assert kappa == pytest.approx(3.0, rel=0.03)
    z = normal_quantile(0.9)
    assert band_coverage(err, -kappa * z * np.ones_like(err), kappa * z * np.ones_like(err)) \
        >= 0.9


def test_calibration_rejects_zero_width_bands_that_miss():
    with pytest.raises(DataError, match="zero width"):
        calibration_scale(np.ones((2, 5)), np.zeros((2, 5)), np.zeros((2, 5)))
    with pytest.raises(DataError, match="level must lie in"):
        normal_quantile(1.0)


# ----------------------------------------------------------------------------- estimator
def test_estimate_is_the_prediction(trained):
    fam, est, _ = trained
    data = family_dataset(fam, 10, seed=50)
    e = est.estimate(data)
    np.testing.assert_allclose(e.response, est.predict_responses(data), rtol=0, atol=1e-12)
    assert e.calibrated and e.scale == est.uncertainty_scale_
    z = normal_quantile(0.9)
    np.testing.assert_allclose(
        e.relative_width, z * np.linalg.norm(e.std, axis=1) / np.linalg.norm(e.response, axis=1))


def test_fresh_coverage_of_the_90_percent_band(trained):
    """Per-sample coverage of the true impulse responses on fresh records.

    The records are the independent units (samples within a record are correlated), so the
    tolerance is four standard errors of the difference between two means of per-record
    coverages: the calibration set's (which is 0.9 by construction) and the fresh set's.
    """
    fam, est, report = trained
    cal = family_dataset(fam, fam.n_calibration, seed=fam.random_state + 1)  # as train_family
    fresh = family_dataset(fam, 200, seed=99)
    per_record = {}
    for name, data in (("cal", cal), ("fresh", fresh)):
        e = est.estimate(data)
        per_record[name] = np.mean((data.clean >= e.lower) & (data.clean <= e.upper), axis=1)
    assert per_record["cal"].mean() == pytest.approx(report["calibration"]["coverage"], abs=1e-12)
    se = np.sqrt(sum(v.var(ddof=1) / v.size for v in per_record.values()))
    assert se < 0.02  # the test can fail: the tolerance is a few points at most
    assert abs(per_record["fresh"].mean() - 0.9) <= 4 * se + 0.002  # + the quantile's grain


def test_bands_from_the_covariance_agree_with_the_projector(trained):
    fam, est, _ = trained
    e = est.estimate(family_dataset(fam, 2, seed=51))
    band = e.impulse_band(1, t=fam.t)  # the covariance route, re-evaluated on the grid
    np.testing.assert_allclose(band.y, e.response[1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(band.std, e.std[1], rtol=1e-5, atol=1e-9 * e.std[1].max())
    assert e.impulse_band(1).std is not None and e.step_band(1).t.size == fam.t.size
    f = e.frequency_band(1)
    assert np.all(f.magnitude_std > 0) and f.confidence == 0.9


def test_step_and_frequency_bands_match_monte_carlo():
    """Delta-method bands against a Monte Carlo over a small parameter covariance."""
    kinds, params, coef = ("real", "pair"), np.array([1.0, 0.5, 1.5]), np.array([0.8, -0.3, 0.6])
    rng = np.random.default_rng(5)
    L = 1e-3 * rng.standard_normal((6, 6))
    cov = L @ L.T
    t = np.linspace(0.0, 10.0, 60)
    e = ResponseEstimate(
        t=t, kind="impulse", kinds=kinds, params=params[None], coefficients=coef[None],
        response=np.zeros((1, 60)), std=np.zeros((1, 60)), covariance=cov[None],
        noise_std=np.zeros(1), noise_correlation=np.zeros(1), scale=1.0, calibrated=False)
    draws = rng.multivariate_normal(np.r_[params, coef], cov, size=2000)
    models = [KautzModel(KautzBasis._from_blocks(kinds, d[:3]), d[3:]) for d in draws]
    w = np.array([0.3, 1.0, 3.0])
    step_mc = np.array([m.step(t) for m in models]).std(axis=0)
    mag_mc = np.abs(np.array([m.frequency_response(w) for m in models])).std(axis=0)
    # 2000 draws: the sd of a sample standard deviation is 1.6 %; tolerance 6 %
    np.testing.assert_allclose(e.step_band(0, t=t).std[1:], step_mc[1:], rtol=0.06)
    np.testing.assert_allclose(e.frequency_band(0, w).magnitude_std, mag_mc, rtol=0.06)
    assert e.step_band(0, t=t).std[0] == 0.0  # a step response starts at 0, exactly


def test_calibration_survives_save_and_load(trained, tmp_path):
    fam, est, _ = trained
    loaded = AdaptivePoleEstimator.load(est.save(tmp_path / "m"))
    assert loaded.uncertainty_scale_ == est.uncertainty_scale_
    assert loaded.calibration_ == est.calibration_
    assert loaded.training_data_["family"]["noise"]["color"] == "ar1"
    data = family_dataset(fam, 3, seed=52)
    # the network runs in float32: the reloaded module (identical weights, another memory
    # layout) may differ in the last bit of its poles, ~1e-7, which moves the std ~1e-5
    np.testing.assert_allclose(loaded.estimate(data).std, est.estimate(data).std, rtol=1e-4)


def test_uncalibrated_files_load_uncalibrated(trained, tmp_path):
    fam, est, _ = trained
    data = family_dataset(fam, 30, seed=53)
    plain = AdaptivePoleEstimator(hidden=(8,), n_features=4, config={"max_epochs": 1}).fit(data)
    loaded = AdaptivePoleEstimator.load(plain.save(tmp_path / "old"))
    assert loaded.calibration_ is None and loaded.uncertainty_scale_ == 1.0
    assert not loaded.estimate(data).calibrated


def test_coefficient_estimator_carries_a_fixed_basis_uncertainty(tmp_path):
    from kautztwin.datasets import draw_parameters, make_dataset, paper_system
    from kautztwin.nn import CoefficientEstimator

    system = paper_system()
    basis = KautzBasis(system.poles())
    t = np.linspace(0.0, 20.0, 100)
    train, cal = (make_dataset(system, draw_parameters(system, 0.1, n, random_state=s), basis, t,
                               noise=0.05, random_state=s + 1) for n, s in ((80, 0), (60, 10)))
    est = CoefficientEstimator(per_coefficient=False, config={"max_epochs": 2}).fit(train)
    raw = est.estimate(cal)
    assert not raw.calibrated and raw.scale == 1.0
    np.testing.assert_allclose(raw.response, est.predict(cal) @ basis.evaluate(t), atol=1e-12)
    # the poles are fixed: only the coefficient block of the covariance is nonzero
    assert np.all(raw.covariance[:, :4, :] == 0) and np.all(raw.covariance[:, :, :4] == 0)
    est.calibrate(cal)
    e = est.estimate(cal)
    assert e.calibrated and band_coverage(cal.clean, e.lower, e.upper) >= 0.9
    loaded = CoefficientEstimator.load(est.save(tmp_path / "c"))
    assert loaded.calibration_ == est.calibration_
