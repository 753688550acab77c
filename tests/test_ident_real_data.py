"""Transfer-function estimation on measured data (the data sets under data/, with READMEs).

* TCLab heater step test (data/tclab_step_tests): the published least-squares
  second-order model K / ((tau_a s + 1)(tau_b s + 1)) fits T1 by 97.76 %
  (README); our second-order fits must match or beat it on the same rows.
* DaISy hair dryer (data/daisy_hair_dryer, Ts = 0.08 s): first 500 samples
  estimate, the rest validate; MATLAB's order-3 model fits over 90 %.
* Hydraulic actuator (data/hydraulic_actuator): first 512 samples estimate,
  last 512 validate; compared with ARX(3, 2, 1) by least squares on the same split.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kautztwin.ident import (
    ARXEstimator,
    Record,
    TransferFunctionEstimator,
    load_records,
    simulate_lti,
)
from kautztwin.metrics import fit_percent

DATA = Path(__file__).resolve().parent.parent / "data"
TCLAB = DATA / "tclab_step_tests"
TCLAB_FILES = [TCLAB / f for f in ("step-test-data.csv", "tclab-data.csv",
                                   "tclab-data-example.csv")]
# published model (README): K = 0.69537 degC/%, tau_a = 19.689 s, tau_b = 141.41 s, T1(0) = 20.911
PUBLISHED = (0.69537, 19.689, 141.41, 20.911)
PUBLISHED_FIT = 97.76  # README, T1 over the whole record


def tclab(paths):
    return load_records(paths, time="Time", input="Q1", output="T1", kind="step")


def published_fit_on_rows() -> float:
    """Fit of the published model on the 801 logged rows (the first row is before the step)."""
    K, ta, tb, T0 = PUBLISHED
    raw = np.genfromtxt(TCLAB_FILES[0], delimiter=",", names=True)
    yhat = T0 + simulate_lti(([K / (ta * tb)], np.polymul([1, 1 / ta], [1, 1 / tb])),
                             raw["Time"][1:], raw["Q1"][1:])
    return float(fit_percent(raw["T1"], np.concatenate([[T0], yhat])))


@pytest.fixture(scope="module")
def tclab_second_order():
    return TransferFunctionEstimator(n_poles=2, n_zeros=0).fit(tclab(TCLAB_FILES[0])).model_


def test_tclab_record_is_normalised():
    (rec,) = tclab(TCLAB_FILES[0])
    assert rec.n_samples == 800  # the two t = 0 rows are one sample of weight 2
    assert (rec.start, rec.u_before, rec.amplitude) == (0.0, 0.0, 50.0)
    assert rec.weights[0] == 2.0 and rec.jitter < 0.02


def test_tclab_second_order_matches_the_published_least_squares_fit(tclab_second_order):
    # the same model class and criterion as the published fit: at least its fit on the same rows
    published = published_fit_on_rows()
    assert published == pytest.approx(PUBLISHED_FIT, abs=0.005)
    assert tclab_second_order.fit_percent >= published - 1e-6


def test_tclab_second_order_reproduces_the_published_parameters(tclab_second_order):
    K, ta, tb, T0 = PUBLISHED
    taus = np.sort(-1.0 / tclab_second_order.poles.real)
    np.testing.assert_allclose(taus, [ta, tb], rtol=2e-3)
    assert tclab_second_order.gain == pytest.approx(K, rel=1e-3)
    assert tclab_second_order.offsets[0] == pytest.approx(T0, abs=0.01)


def test_tclab_second_order_with_default_zero_reaches_the_published_fit():
    model = TransferFunctionEstimator(n_poles=2).fit(tclab(TCLAB_FILES[0])).model_
    assert model.n_zeros == 1
    assert model.fit_percent >= PUBLISHED_FIT


def test_tclab_three_files_jointly():
    # three runs (different days and ambient temperatures), one model, own offsets
    model = TransferFunctionEstimator(n_poles=2, n_zeros=0).fit(tclab(TCLAB_FILES)).model_
    assert model.fit_percent_per_record.shape == (3,)
    assert 80.0 < model.fit_percent < 90.0  # 84.9 %: the runs differ (see docs)
    assert np.all(model.fit_percent_per_record > 75.0)
    assert 0.6 < model.gain < 0.75
    assert np.all(model.poles.real < 0)


@pytest.fixture(scope="module")
def dryer():
    raw = np.loadtxt(DATA / "daisy_hair_dryer" / "dryer.dat")
    t = np.arange(raw.shape[0]) * 0.08
    return Record.from_data(t, raw[:, 0], raw[:, 1], name="dryer")


def test_hair_dryer_order_three_validates_above_ninety_percent(dryer):
    est = TransferFunctionEstimator(n_poles=3, delay=True, validate_from=500 * 0.08)
    model = est.fit(dryer).model_
    assert model.n_samples == 500
    assert model.validation_fit_percent >= 90.0
    assert 0.1 < model.delay < 0.3  # MATLAB's example: 3 samples (0.24 s) of dead time


def test_hair_dryer_two_poles_one_zero_is_on_a_par_with_arx_223(dryer):
    # the models MATLAB's dryer example compares: tfest(2 poles, 1 zero, delay), arx([2 2 3])
    u, y = np.asarray(dryer.u), np.asarray(dryer.y)
    arx = ARXEstimator(2, 2, 3).fit(u[:500], y[:500], dt=0.08)
    arx_fit = fit_percent(y[500:], arx.simulate(u, y0=y[:2])[500:])
    model = TransferFunctionEstimator(n_poles=2, n_zeros=1, delay=True,
                                      validate_from=40.0).fit(dryer).model_
    assert model.validation_fit_percent >= arx_fit - 0.5  # 85.45 vs 85.56: on a par
    assert arx_fit > 80.0


def actuator_split():
    (rec,) = load_records(DATA / "hydraulic_actuator" / "actuator.csv", input="u", output="p",
                          dt=1.0)
    return rec


def test_hydraulic_actuator_validates_at_least_as_well_as_arx_321():
    rec = actuator_split()
    u, y = np.asarray(rec.u), np.asarray(rec.y)
    arx = ARXEstimator(3, 2, 1).fit(u[:512], y[:512])
    arx_fit = float(fit_percent(y[512:], arx.simulate(u, y0=y[:3])[512:]))
    # the same number of parameters as ARX(3, 2, 1): three poles and two numerator coefficients
    model = TransferFunctionEstimator(n_poles=3, n_zeros=1, validate_from=512).fit(rec).model_
    assert model.n_samples == 512
    assert model.validation_fit_percent >= arx_fit
    assert model.fit_percent > float(fit_percent(y[:512], arx.simulate(u, y0=y[:3])[:512]))
