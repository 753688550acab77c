"""Tests of kautztwin.ident.diagnostics: residual tests, confidence bands, the verdict.

Oracles: the Ljung-Box formula written out with ``scipy.stats.chi2``; ``numpy.correlate``;
Monte Carlo rejection rates against the binomial distribution of the nominal level; a
Monte Carlo over the parameter covariance with responses from ``scipy.signal`` (``freqs``,
``residue``); known systems identified from noisy data.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal
import scipy.stats

from kautztwin.exceptions import DataError, DimensionError, NotFittedError
from kautztwin.ident import Record, TransferFunctionEstimator, TransferFunctionModel, simulate_lti
from kautztwin.ident.diagnostics import (
    autocorrelation,
    cross_correlation,
    cross_correlation_test,
    diagnose,
    frequency_response_band,
    frequency_response_jacobian,
    pole_uncertainty,
    step_response_band,
    step_response_jacobian,
    whiteness_test,
)

N_SEQ = 400  # sequences in each rejection-rate experiment


def binomial_range(n: int, p: float = 0.05, level: float = 0.999) -> tuple[int, int]:
    """Central ``level`` range of the number of rejections of ``n`` tests at nominal ``p``.

    A fixed seed makes each experiment deterministic; the range says how far a correct
    test may stray from ``n p`` by chance (two-sided 99.9 %), so a miss means a wrong size.
    """
    lo, hi = scipy.stats.binom.ppf([(1 - level) / 2, (1 + level) / 2], n, p)
    return int(lo), int(hi)


def ar1(rng, phi: float, n: int) -> np.ndarray:
    return scipy.signal.lfilter([1.0], [1.0, -phi], rng.standard_normal(n + 200))[200:]


# =============================================================================== correlations
def test_autocorrelation_matches_numpy_correlate():
    e = np.random.default_rng(0).standard_normal(300) + 2.0
    c = e - e.mean()
    full = np.correlate(c, c, "full")[c.size - 1:]
    np.testing.assert_allclose(autocorrelation(e, 10), full[:11] / full[0], rtol=1e-12)


def test_autocorrelation_of_records_does_not_bridge_the_gap():
    rng = np.random.default_rng(1)
    a, b = rng.standard_normal(50) + 5.0, rng.standard_normal(80) - 3.0
    ca, cb = a - a.mean(), b - b.mean()
    num = [ca[k:] @ ca[: ca.size - k] + cb[k:] @ cb[: cb.size - k] for k in range(6)]
    np.testing.assert_allclose(autocorrelation([a, b], 5), np.array(num) / num[0], rtol=1e-12)
    assert not np.allclose(autocorrelation([a, b], 5), autocorrelation(np.r_[a, b], 5))


def test_cross_correlation_matches_numpy_correlate():
    rng = np.random.default_rng(2)
    e, u = rng.standard_normal(200), rng.standard_normal(200)
    lags, r = cross_correlation(e, u, 7)
    ce, cu = e - e.mean(), u - u.mean()
    full = np.correlate(ce, cu, "full") / np.sqrt((ce @ ce) * (cu @ cu))  # lag k at n-1+k
    np.testing.assert_array_equal(lags, np.arange(-7, 8))
    np.testing.assert_allclose(r, full[e.size - 1 - 7: e.size + 7], rtol=1e-12, atol=1e-15)


# =============================================================================== whiteness
@pytest.mark.parametrize("n_fitted", [0, 3], ids=["plain", "arma-dof"])
def test_ljung_box_matches_the_formula_and_chi2(n_fitted):
    e = np.random.default_rng(3).standard_normal(400)
    h, n = 20, e.size
    c = e - e.mean()
    r = np.array([c[k:] @ c[: n - k] for k in range(1, h + 1)]) / (c @ c)
    q = n * (n + 2) * np.sum(r**2 / (n - np.arange(1, h + 1)))
    res = whiteness_test(e, max_lag=h, n_fitted=n_fitted)
    assert res.statistic == pytest.approx(q, rel=1e-12)
    assert res.dof == h - n_fitted
    assert res.p_value == pytest.approx(scipy.stats.chi2.sf(q, h - n_fitted), rel=1e-10)
    assert res.bound == pytest.approx(scipy.stats.norm.ppf(0.975) / np.sqrt(n), rel=1e-12)


def test_ljung_box_of_records_counts_pairs_within_records():
    rng = np.random.default_rng(4)
    a, b = rng.standard_normal(60), rng.standard_normal(90)
    h, n = 6, 150
    r = autocorrelation([a, b], h)[1:]
    pairs = (60 - np.arange(1, h + 1)) + (90 - np.arange(1, h + 1))
    q = n * (n + 2) * np.sum(r**2 / pairs)
    assert whiteness_test([a, b], max_lag=h).statistic == pytest.approx(q, rel=1e-12)


def test_whiteness_test_rejects_white_noise_at_its_nominal_rate():
    rng = np.random.default_rng(5)
    n_rej = sum(not whiteness_test(rng.standard_normal(500)).white for _ in range(N_SEQ))
    lo, hi = binomial_range(N_SEQ)
    assert lo <= n_rej <= hi, (n_rej, lo, hi)


def test_whiteness_test_rejects_coloured_noise():
    rng = np.random.default_rng(6)
    tests = [whiteness_test(ar1(rng, 0.5, 500)) for _ in range(50)]
    assert not any(t.white for t in tests)
    assert min(t.n_outside for t in tests) >= 1


# =============================================================================== cross test
@pytest.mark.parametrize(
    "kind", ["white-white", "coloured-coloured", "white-blocks", "coloured-step"])
def test_cross_correlation_test_has_its_nominal_size(kind):
    """Independent residual and input: rejections at about alpha, whatever their colour."""
    rng = np.random.default_rng(7)
    n = 500

    def pair():
        if kind == "white-white":
            return rng.standard_normal(n), rng.standard_normal(n)
        if kind == "coloured-coloured":
            return ar1(rng, 0.8, n), ar1(rng, 0.9, n)
        if kind == "white-blocks":
            return rng.standard_normal(n), np.repeat(rng.standard_normal(n // 10), 10)
        return ar1(rng, 0.9, n), np.r_[np.zeros(100), np.ones(n - 100)]

    n_rej = sum(not cross_correlation_test(*pair()).independent for _ in range(N_SEQ))
    lo, hi = binomial_range(N_SEQ)
    assert lo <= n_rej <= hi, (n_rej, lo, hi)


def test_cross_correlation_test_detects_filtered_input():
    rng = np.random.default_rng(8)
    for _ in range(20):
        u = rng.standard_normal(500)
        missed = scipy.signal.lfilter([0.0, 0.4], [1.0, -0.7], u)  # dynamics the model lacks
        res = cross_correlation_test(rng.standard_normal(500) + missed, u)
        assert not res.independent and res.n_outside >= 1


def test_two_sided_test_sees_feedback_that_the_causal_test_ignores():
    rng = np.random.default_rng(9)
    e = rng.standard_normal(600)
    u = rng.standard_normal(600) + 0.5 * np.r_[np.zeros(3), e[:-3]]  # u reacts to e
    assert cross_correlation_test(e, u).independent
    assert not cross_correlation_test(e, u, two_sided=True).independent


def test_bound_is_the_bartlett_bound_for_white_sequences():
    rng = np.random.default_rng(10)
    res = cross_correlation_test(rng.standard_normal(4000), rng.standard_normal(4000))
    assert res.bound == pytest.approx(1.96 / np.sqrt(4000), rel=0.05)


# =============================================================================== bands
@pytest.fixture(scope="module")
def fitted():
    """A second-order model with a zero and a delay, fitted to noisy data (realistic cov)."""
    rng = np.random.default_rng(11)
    t = 0.05 * np.arange(800)
    u = np.repeat(rng.choice([-1.0, 1.0], 80), 10)
    true = ([1.0, 4.0], np.poly([-1 + 2j, -1 - 2j]))
    y = simulate_lti(true, t, u, delay=0.12) + 0.05 * rng.standard_normal(t.size)
    est = TransferFunctionEstimator(n_poles=2, n_zeros=1, delay=True)
    return est.fit(Record.from_data(t, u, y)).model_


def draws(model, n, seed=12):
    theta = np.concatenate([model.num, model.den[1:], [model.delay]])
    return np.random.default_rng(seed).multivariate_normal(theta, model.covariance, size=n)


def test_jacobians_match_finite_differences_of_scipy(fitted):
    w, t = np.logspace(-1, 1.5, 25), np.linspace(0.0, 6.0, 31)
    g, jac = frequency_response_jacobian(fitted, w)
    y, jac_y = step_response_jacobian(fitted, t)
    theta = np.concatenate([fitted.num, fitted.den[1:], [fitted.delay]])

    def freq(th):
        return scipy.signal.freqs(th[:2], np.r_[1.0, th[2:4]], w)[1] * np.exp(-1j * w * th[4])

    def step(th):
        r, p, _ = scipy.signal.residue(th[:2], np.r_[1.0, th[2:4]])
        tk = np.maximum(t - th[4], 0.0)
        return np.real((r / p) * (np.exp(np.outer(tk, p)) - 1)).sum(axis=1)

    np.testing.assert_allclose(g, freq(theta), rtol=1e-10)
    np.testing.assert_allclose(y, step(theta), atol=1e-10)
    for j in range(theta.size):
        h = 1e-6 * max(abs(theta[j]), 1e-3)
        d = np.zeros_like(theta)
        d[j] = h
        np.testing.assert_allclose(jac[:, j], (freq(theta + d) - freq(theta - d)) / (2 * h),
                                   rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(jac_y[:, j], (step(theta + d) - step(theta - d)) / (2 * h),
                                   rtol=1e-5, atol=1e-7)


def test_bode_band_agrees_with_monte_carlo(fitted):
    """Delta-method std within 6 % of the Monte Carlo std (its own error is ~1.6 % at 2000
    draws); coverage of the 95 % band 95 +- 1 % on average, no point below 93 %."""
    w = np.logspace(-1, np.log10(np.pi / 0.05), 60)
    band = frequency_response_band(fitted, w)
    S = draws(fitted, 2000)
    G = np.array([scipy.signal.freqs(s[:2], np.r_[1.0, s[2:4]], w)[1] * np.exp(-1j * w * s[4])
                  for s in S])
    mag, ph = np.abs(G), np.angle(G / band.response) + band.phase
    np.testing.assert_allclose(mag.std(axis=0), band.magnitude_std, rtol=0.06)
    np.testing.assert_allclose(ph.std(axis=0), band.phase_std, rtol=0.06)
    for x, lo, hi in [(mag, band.magnitude_lower, band.magnitude_upper),
                      (ph, band.phase_lower, band.phase_upper)]:
        cover = np.mean((x >= lo) & (x <= hi), axis=0)
        assert abs(cover.mean() - 0.95) < 0.01 and cover.min() > 0.93, cover


def test_step_band_agrees_with_monte_carlo(fitted):
    t = np.linspace(0.0, 6.0, 61)
    band = step_response_band(fitted, t)
    Y = []
    for s in draws(fitted, 1000):
        r, p, _ = scipy.signal.residue(s[:2], np.r_[1.0, s[2:4]])
        tk = np.maximum(t - s[4], 0.0)
        Y.append(np.real((r / p) * (np.exp(np.outer(tk, p)) - 1)).sum(axis=1))
    Y = np.array(Y)
    after = t > 0.3  # before the delay both are zero
    np.testing.assert_allclose(Y.std(axis=0)[after], band.std[after], rtol=0.08)
    cover = np.mean((Y >= band.lower) & (Y <= band.upper), axis=0)[after]
    assert abs(cover.mean() - 0.95) < 0.015, cover


def test_pole_std_agrees_with_monte_carlo(fitted):
    pu = pole_uncertainty(fitted)
    P = np.array([np.sort_complex(np.roots(np.r_[1.0, s[2:4]])) for s in draws(fitted, 2000)])
    order = np.argsort(pu.poles.imag)  # sort_complex: same real part, by imaginary part
    np.testing.assert_allclose(P.real.std(axis=0), pu.std_real[order], rtol=0.06)
    np.testing.assert_allclose(P.imag.std(axis=0), pu.std_imag[order], rtol=0.06)


def test_zero_covariance_gives_zero_width_bands(fitted):
    import dataclasses

    m = dataclasses.replace(fitted, covariance=np.zeros_like(fitted.covariance))
    bode, step = frequency_response_band(m), step_response_band(m)
    np.testing.assert_array_equal(bode.magnitude_upper, bode.magnitude)
    np.testing.assert_array_equal(bode.phase_lower, bode.phase)
    np.testing.assert_array_equal(step.upper, step.y)
    assert not np.any(pole_uncertainty(m).std_real)


def test_model_without_covariance_is_an_error():
    m = TransferFunctionModel(num=[1.0], den=[1.0, 1.0])
    with pytest.raises(DataError, match="no parameter covariance"):
        frequency_response_band(m)


# =============================================================================== verdict
def second_order_record(rng, noise=0.02, n=1200):
    t = 0.05 * np.arange(n)
    u = np.repeat(rng.choice([0.0, 1.0], n // 10), 10)
    y = simulate_lti(([2.0], [1.0, 1.2, 1.0]), t, u) + noise * rng.standard_normal(n)
    return Record.from_data(t, u, y)


@pytest.mark.parametrize("order", [2, 1], ids=["right-order", "under-modelled"])
def test_verdict_sees_an_under_modelled_system(order):
    rec = second_order_record(np.random.default_rng(13))
    est = TransferFunctionEstimator(n_poles=order, n_zeros=0, validate_from=30.0).fit(rec)
    diag = diagnose(est)
    v = diag.verdict()
    assert v["tested_on"] == "validation"
    assert v["residuals_white"] is (order == 2)
    assert v["residuals_independent_of_input"] is (order == 2)
    assert diag.estimation.whiteness.white is (order == 2)
    text = diag.to_markdown()
    assert f"residuals white: {'yes' if order == 2 else 'no'}" in text


def test_diagnose_needs_a_fitted_estimator():
    with pytest.raises(NotFittedError):
        diagnose(TransferFunctionEstimator())


# =============================================================================== bad input
@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (lambda: whiteness_test(np.ones(50)), DataError, "constant"),
        (lambda: whiteness_test(np.r_[1.0, np.nan, np.zeros(40)]), DataError, "non-finite"),
        (lambda: whiteness_test(np.arange(10.0), max_lag=9), DataError, "max_lag"),
        (lambda: whiteness_test([np.arange(5.0), np.arange(6.0)], max_lag=6), DataError,
         "not shorter than any record"),
        (lambda: whiteness_test(np.arange(50.0), alpha=1.5), DataError, "alpha"),
        (lambda: whiteness_test(np.arange(50.0), max_lag=5, n_fitted=5), DataError, "n_fitted"),
        (lambda: whiteness_test(np.ones((5, 5, 2))), DimensionError, "1-D"),
        (lambda: cross_correlation_test(np.arange(50.0), np.arange(40.0)), DimensionError,
         "same lengths"),
        (lambda: cross_correlation_test(np.sin(np.arange(50.0)), np.ones(50)), DataError,
         "u is constant"),
    ],
    ids=["constant", "nan", "lag-too-long", "lag-beyond-records", "alpha", "no-dof", "3-d",
         "lengths", "constant-input"],
)
def test_bad_input_is_a_one_line_error(call, error, match):
    with pytest.raises(error, match=match) as info:
        call()
    assert "\n" not in str(info.value)


def test_step_jacobian_of_a_biproper_model_with_a_delay():
    """Direct feedthrough: the delay column is minus the impulse response of the strictly
    proper part (away from the jump at t = tau)."""
    names = ("num[0]", "num[1]", "num[2]", "den[1]", "den[2]", "delay")
    theta = np.array([0.5, 1.0, 2.0, 3.0, 2.0, 0.3])
    m = TransferFunctionModel(num=theta[:3], den=np.r_[1.0, theta[3:5]], delay=theta[5],
                              covariance=1e-4 * np.eye(6), parameter_names=names)
    t = np.linspace(0.0, 5.0, 26)

    def step(th):
        r, p, k = scipy.signal.residue(th[:3], np.r_[1.0, th[3:5]])
        tk = np.maximum(t - th[5], 0.0)
        return (np.real((r / p) * (np.exp(np.outer(tk, p)) - 1)).sum(axis=1)
                + k[0] * (t >= th[5]))

    y, jac = step_response_jacobian(m, t)
    np.testing.assert_allclose(y, step(theta), atol=1e-12)
    away = np.abs(t - theta[5]) > 1e-3
    for j in range(theta.size):
        d = np.zeros(6)
        d[j] = 1e-6
        fd = (step(theta + d) - step(theta - d)) / 2e-6
        np.testing.assert_allclose(jac[away, j], fd[away], atol=1e-8)
