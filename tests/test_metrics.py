"""Fit metrics (kautz-math.md section 7).

Oracles: small examples computed by hand from the MATLAB ``compare`` definition
fit = 100 (1 - ||y - yhat|| / ||y - mean(y)||), and scipy.integrate for the ISE.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate

import kautztwin as kt
from kautztwin.exceptions import DataError, DimensionError

Y = np.array([0.0, 1.0, 2.0, 3.0])  # mean 1.5, ||y - mean|| = sqrt(5)

# yhat, fit %, nrmse, R^2, MSE: all by hand.
HAND = {
    "perfect": ([0.0, 1.0, 2.0, 3.0], 100.0, 0.0, 1.0, 0.0),
    "mean": ([1.5, 1.5, 1.5, 1.5], 0.0, 1.0, 0.0, 1.25),
    # ||y - yhat|| = 1: nrmse = 1/sqrt(5), R^2 = 1 - 1/5
    "one-off": ([1.0, 1.0, 2.0, 3.0], 100 * (1 - 1 / np.sqrt(5)), 1 / np.sqrt(5), 0.8, 0.25),
    # ||y - yhat|| = sqrt(20) = 2 sqrt(5): worse than the mean
    "reversed": ([3.0, 2.0, 1.0, 0.0], -100.0, 2.0, -3.0, 5.0),
}
HAND_IDS = list(HAND)
# Every hand value is a few float operations away from exact: 1e-12 is rounding.
TOL = 1e-12


@pytest.mark.parametrize("case", HAND_IDS)
def test_fit_percent_hand_examples(case):
    yhat, fit, *_ = HAND[case]
    assert kt.fit_percent(Y, yhat) == pytest.approx(fit, abs=TOL)


@pytest.mark.parametrize("case", HAND_IDS)
def test_nrmse_hand_examples(case):
    yhat, _, nrmse, *_ = HAND[case]
    assert kt.nrmse(Y, yhat) == pytest.approx(nrmse, abs=TOL)


@pytest.mark.parametrize("case", HAND_IDS)
def test_r_squared_hand_examples(case):
    yhat, _, _, r2, _ = HAND[case]
    assert kt.r_squared(Y, yhat) == pytest.approx(r2, abs=TOL)


@pytest.mark.parametrize("case", HAND_IDS)
def test_mse_hand_examples(case):
    yhat, *_, mse = HAND[case]
    assert kt.mse(Y, yhat) == pytest.approx(mse, abs=TOL)


def test_fit_percent_of_a_scaled_model():
    # y = sin, yhat = 0.9 y: ||y - yhat|| = 0.1 ||y||, and mean(y) = 0 on whole periods.
    t = np.linspace(0.0, 2 * np.pi, 1001)[:-1]
    y = np.sin(t)
    assert kt.fit_percent(y, 0.9 * y) == pytest.approx(90.0, abs=1e-9)


def test_fit_percent_is_invariant_to_offset_and_scale():
    rng = np.random.default_rng(31)
    y = rng.standard_normal(50)
    yhat = y + 0.3 * rng.standard_normal(50)
    # The normalisation removes a common affine change: rounding only.
    assert kt.fit_percent(3 * y + 7, 3 * yhat + 7) == pytest.approx(
        kt.fit_percent(y, yhat), abs=1e-10
    )


def test_metrics_relations():
    rng = np.random.default_rng(32)
    y = rng.standard_normal(100)
    yhat = y + 0.5 * rng.standard_normal(100)
    nrmse = kt.nrmse(y, yhat)
    # section 7: NRMSE = 1 - fit/100, R^2 = 1 - NRMSE^2 (identities; rounding only)
    assert kt.fit_percent(y, yhat) == pytest.approx(100 * (1 - nrmse), abs=1e-12)
    assert kt.r_squared(y, yhat) == pytest.approx(1 - nrmse**2, abs=1e-12)


@pytest.mark.parametrize("metric", ["fit_percent", "nrmse", "r_squared", "mse"])
def test_records_give_one_value_per_row(metric):
    rng = np.random.default_rng(33)
    y = rng.standard_normal((4, 30))
    yhat = y + 0.2 * rng.standard_normal((4, 30))
    func = getattr(kt, metric)
    out = func(y, yhat)
    assert out.shape == (4,)
    np.testing.assert_allclose(
        out, [func(a, b) for a, b in zip(y, yhat, strict=True)], rtol=1e-14, atol=1e-14
    )


@pytest.mark.parametrize("metric", ["fit_percent", "nrmse", "r_squared", "mse"])
def test_single_record_gives_python_float(metric):
    assert isinstance(getattr(kt, metric)(Y, HAND["one-off"][0]), float)


# ---------------------------------------------------------------------------- ISE
def make_grid(kind, n, rng):
    if kind == "uniform":
        return np.linspace(0.0, 3.0, n)
    return np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 1.5, n - 1))]) * 3.0 / n


GRIDS = [
    pytest.param(kind, n, id=f"{kind}-{n}")
    for kind in ("uniform", "non-uniform")
    for n in (3, 4, 51, 52, 400, 401)
]


@pytest.mark.parametrize(("kind", "n"), GRIDS)
def test_ise_equals_scipy_simpson(kind, n):
    rng = np.random.default_rng(34 + n)
    t = make_grid(kind, n, rng)
    y = np.exp(-t) * np.sin(3 * t)
    yhat = y + 0.1 * np.cos(t)
    expected = scipy.integrate.simpson((y - yhat) ** 2, x=t)
    # Same rule (scipy >= 1.11 treats an even sample count the same way): the weights
    # differ only in summation order, rounding ~1e-16 relative.
    assert kt.ise(t, y, yhat) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(("kind", "n"), GRIDS)
def test_ise_trapezoid_equals_scipy_trapezoid(kind, n):
    rng = np.random.default_rng(35 + n)
    t = make_grid(kind, n, rng)
    err = rng.standard_normal(n)
    expected = scipy.integrate.trapezoid(err**2, x=t)
    assert kt.ise(t, err, np.zeros(n), rule="trapezoid") == pytest.approx(expected, rel=1e-12)


def test_ise_of_analytic_error():
    t = np.linspace(0.0, 30.0, 3001)
    # error e^{-t}: integral of e^{-2t} over [0, 30] = (1 - e^{-60})/2; Simpson at
    # dt = 0.01 errs by ~dt^4/180 * 16 * 1/2 ~ 4e-10.
    assert kt.ise(t, np.exp(-t), np.zeros(t.size)) == pytest.approx(0.5, abs=1e-9)


def test_ise_records():
    rng = np.random.default_rng(36)
    t = np.linspace(0.0, 1.0, 21)
    y = rng.standard_normal((3, 21))
    out = kt.ise(t, y, np.zeros_like(y))
    assert out.shape == (3,)
    np.testing.assert_allclose(out, [kt.ise(t, r, np.zeros(21)) for r in y], rtol=1e-14)


def test_ise_is_clamped_at_zero():
    # Simpson weights of a strongly non-uniform pair (h0 = 1, h1 = 1e-3) are
    # negative at the last point: w = (s/6)(2 - h0/h1) < 0.  An error there only
    # would give a negative "integral of a square"; it is clamped to 0.
    t = np.array([0.0, 1.0, 1.001])
    assert kt.ise(t, np.array([0.0, 0.0, 1.0]), np.zeros(3)) == 0.0


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize("metric", ["fit_percent", "nrmse", "r_squared"])
def test_constant_signal_raises(metric):
    with pytest.raises(DataError, match="undefined for a constant measured signal"):
        getattr(kt, metric)([2.0, 2.0, 2.0], [1.0, 2.0, 3.0])


def test_constant_record_among_many_raises():
    y = np.array([[0.0, 1.0, 2.0], [5.0, 5.0, 5.0]])
    with pytest.raises(DataError, match="constant measured signal"):
        kt.fit_percent(y, y + 0.1)


def test_constant_signal_is_fine_for_mse():
    # MSE needs no normalisation.
    assert kt.mse([2.0, 2.0], [1.0, 3.0]) == 1.0


@pytest.mark.parametrize("metric", ["fit_percent", "nrmse", "r_squared", "mse"])
def test_shape_mismatch_raises(metric):
    with pytest.raises(DimensionError, match=r"y has shape \(4,\) but yhat has shape \(3,\)"):
        getattr(kt, metric)(Y, [1.0, 2.0, 3.0])


@pytest.mark.parametrize("metric", ["fit_percent", "nrmse", "r_squared", "mse"])
def test_empty_signal_raises(metric):
    with pytest.raises(DimensionError, match="at least one sample"):
        getattr(kt, metric)([], [])


@pytest.mark.parametrize(
    ("y", "yhat", "name"),
    [
        ([0.0, np.nan, 1.0], [0.0, 1.0, 1.0], "y"),
        ([0.0, 2.0, 1.0], [0.0, np.inf, 1.0], "yhat"),
    ],
    ids=["nan-in-y", "inf-in-yhat"],
)
def test_non_finite_values_raise(y, yhat, name):
    with pytest.raises(DataError, match=f"^{name} contains a non-finite value .* at index 1"):
        kt.fit_percent(y, yhat)


def test_ise_length_mismatch_raises():
    with pytest.raises(DimensionError, match="y has 4 samples but t has 5"):
        kt.ise(np.arange(5.0), Y, Y)


def test_ise_non_increasing_time_raises():
    with pytest.raises(DataError, match="t must be strictly increasing"):
        kt.ise([0.0, 2.0, 1.0, 3.0], Y, Y)


def test_ise_unknown_rule_raises():
    with pytest.raises(DataError, match="rule must be 'simpson' or 'trapezoid', got 'midpoint'"):
        kt.ise(np.arange(4.0), Y, Y, rule="midpoint")
