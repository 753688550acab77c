"""KautzModel: the approximant G_N(s) = sum_i c_i K_i(s) (kautz-math.md 4.5 and 9.2).

Oracles: the reference system 6/((s+1)(s+3)(s^2+s+4)) simulated by scipy.signal,
the rows of the 9.2 table, python-control and scipy.signal conversions, and
the basis' own product-formula transfer functions.
"""

from __future__ import annotations

import dataclasses
import json

import control
import numpy as np
import pytest
import scipy.signal

import kautztwin as kt
from kautztwin.data import reference_system
from kautztwin.exceptions import DataError, DimensionError

SQ2, SQ6 = np.sqrt(2.0), np.sqrt(6.0)
W = np.sqrt(15.0) / 2.0
MAIN_POLES = [-1.0, -3.0, -0.5 + 1j * W, -0.5 - 1j * W]
MAIN_POLES_PAIR_FIRST = [-0.5 + 1j * W, -0.5 - 1j * W, -1.0, -3.0]
C_MAIN = [SQ2 / 8, -3 * SQ6 / 32, 5 * SQ2 / 32, SQ2 / 16]
C_MAIN_PAIR_FIRST = [-5 * SQ2 / 32, SQ2 / 16, 13 * SQ2 / 64, -SQ6 / 64]
MAIN_DEN = [1.0, 5.0, 11.0, 19.0, 12.0]


def main_model(pair_first=False):
    if pair_first:
        return kt.KautzModel(kt.KautzBasis(MAIN_POLES_PAIR_FIRST), C_MAIN_PAIR_FIRST)
    return kt.KautzModel(kt.KautzBasis(MAIN_POLES), C_MAIN)


ORDERINGS = [pytest.param(False, id="real-first"), pytest.param(True, id="pair-first")]


def discrete_model(delayed=False):
    basis = kt.KautzBasis([0.6, 0.3 + 0.4j, 0.3 - 0.4j, -0.2], dt=0.5, delayed=delayed)
    return kt.KautzModel(basis, [0.4, -0.3, 0.25, 0.1])


DELAYS = [pytest.param(False, id="undelayed"), pytest.param(True, id="delayed")]


# ======================================================================== matched reference system
@pytest.mark.parametrize("pair_first", ORDERINGS)
def test_transfer_function_of_matched_model(pair_first):
    num, den = main_model(pair_first).transfer_function()
    # Polynomial products of O(10) coefficients: rounding ~1e-14.  The cancelled
    # higher powers of the numerator (rounding noise) must have been dropped.
    np.testing.assert_allclose(num, [6.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(den, MAIN_DEN, rtol=0, atol=1e-12)


@pytest.mark.parametrize("pair_first", ORDERINGS)
def test_dc_gain_of_matched_model(pair_first):
    # G(0) = 6/12; a 4x4 solve, rounding only.
    assert main_model(pair_first).dc_gain == pytest.approx(0.5, abs=1e-13)


@pytest.mark.parametrize("pair_first", ORDERINGS)
def test_impulse_equals_scipy_impulse(pair_first):
    t = np.linspace(0.0, 20.0, 2001)
    _, h = scipy.signal.impulse(reference_system(), T=t)
    # Both exact up to rounding (9.2: <= 2.2e-15 observed); values O(0.1).
    np.testing.assert_allclose(main_model(pair_first).impulse(t), h, rtol=0, atol=1e-12)


@pytest.mark.parametrize("pair_first", ORDERINGS)
def test_step_equals_scipy_step(pair_first):
    t = np.linspace(0.0, 20.0, 2001)
    _, y = scipy.signal.step(reference_system(), T=t)
    # As above (9.2: step error <= 2.2e-15 on [0, 20]).
    np.testing.assert_allclose(main_model(pair_first).step(t), y, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("poles", "system", "gain"),
    [
        pytest.param(
            [-1.1, -0.8, -2.1], ([1.0], np.poly([-1.1, -0.8, -2.1])), 0.5411255411, id="a"
        ),
        pytest.param(
            [-1.1, -0.8, -1.5, -0.8 + 2j, -0.8 - 2j],
            ([1.0, 1.0], np.polymul(np.poly([-1.1, -0.8, -1.5]), [1.0, 1.6, 4.64])),
            0.1632706374,
            id="b",
        ),
    ],
)
def test_dc_gain_of_exact_table_rows(poles, system, gain):
    basis = kt.KautzBasis(poles)
    model = kt.KautzModel(basis, kt.coefficients_from_system(basis, system))
    # y_N(inf) = G(0), printed with 10 decimals (last-digit rounding 5e-11).
    assert abs(model.dc_gain - gain) <= 0.5e-10 + 1e-14
    # ... and G(0) itself exactly: num(0)/den(0).
    assert model.dc_gain == pytest.approx(system[0][-1] / system[1][-1], rel=1e-12)


def test_exact_model_is_independent_of_block_order():
    a, b = main_model(False), main_model(True)
    t = np.linspace(0.0, 10.0, 101)
    # Same G_N (kautz-math.md 8.3): responses agree to rounding.
    np.testing.assert_allclose(a.impulse(t), b.impulse(t), rtol=0, atol=1e-14)


# ============================================================================ Laguerre rows of 9.2
# basis, impulse fit %, impulse MSE, step fit %, step MSE, G_N(0): printed digits.
LAGUERRE_ROWS = {
    "a1_N8": (-1.0, 8, "80.659037", "2.385643e-4", "81.018361", "5.137643e-4", "0.5485387731"),
    "a2_N8": (-2.0, 8, "85.334798", "1.371593e-4", "86.454059", "2.616464e-4", "0.5193259442"),
    "a2_N16": (-2.0, 16, "98.097903", "2.307357e-6", "98.842639", "1.910004e-6", "0.5025194066"),
}
ROW_IDS = list(LAGUERRE_ROWS)


def printed_tolerance(printed):
    """Half a unit in the last printed digit of a number written like '2.385643e-4'."""
    mantissa, _, exponent = printed.partition("e")
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    return 0.5 * 10.0 ** (int(exponent or 0) - decimals)


def assert_rounds_to(value, printed):
    """value must round to the printed digits (plus 1e-12 relative for float noise)."""
    tol = printed_tolerance(printed) + 1e-12 * abs(float(printed))
    assert abs(value - float(printed)) <= tol, f"{value!r} does not round to {printed}"


@pytest.fixture(scope="module")
def table_grid():
    """t = 0, 0.1, ..., 20 (201 points) with the reference responses from scipy."""
    t = np.linspace(0.0, 20.0, 201)
    _, h = scipy.signal.impulse(reference_system(), T=t)
    _, y = scipy.signal.step(reference_system(), T=t)
    return t, h, y


def laguerre_row_model(row):
    pole, n = LAGUERRE_ROWS[row][:2]
    basis = kt.LaguerreBasis(pole=pole, n=n)
    return kt.KautzModel(basis, kt.coefficients_from_system(basis, reference_system()))


@pytest.mark.parametrize("row", ROW_IDS)
def test_laguerre_row_impulse_fit(row, table_grid):
    t, h, _ = table_grid
    assert_rounds_to(kt.fit_percent(h, laguerre_row_model(row).impulse(t)), LAGUERRE_ROWS[row][2])


@pytest.mark.parametrize("row", ROW_IDS)
def test_laguerre_row_impulse_mse(row, table_grid):
    t, h, _ = table_grid
    assert_rounds_to(kt.mse(h, laguerre_row_model(row).impulse(t)), LAGUERRE_ROWS[row][3])


@pytest.mark.parametrize("row", ROW_IDS)
def test_laguerre_row_step_fit(row, table_grid):
    t, _, y = table_grid
    assert_rounds_to(kt.fit_percent(y, laguerre_row_model(row).step(t)), LAGUERRE_ROWS[row][4])


@pytest.mark.parametrize("row", ROW_IDS)
def test_laguerre_row_step_mse(row, table_grid):
    t, _, y = table_grid
    assert_rounds_to(kt.mse(y, laguerre_row_model(row).step(t)), LAGUERRE_ROWS[row][5])


@pytest.mark.parametrize("row", ROW_IDS)
def test_laguerre_row_dc_gain(row):
    assert_rounds_to(laguerre_row_model(row).dc_gain, LAGUERRE_ROWS[row][6])


def test_truncated_model_does_not_preserve_dc_gain():
    # kautz-math.md 8.9: a static-gain error is normal for a non-exact expansion.
    assert laguerre_row_model("a1_N8").dc_gain > 0.54


# ============================================================================ responses
@pytest.mark.parametrize("pair_first", ORDERINGS)
def test_frequency_response_equals_transfer_function(pair_first):
    model = main_model(pair_first)
    w = np.logspace(-2, 2, 50)
    num, den = model.transfer_function()
    expected = np.polyval(num, 1j * w) / np.polyval(den, 1j * w)
    # Rounding only, but at w = 100 |G| = 6/w^4 ~ 6e-8 is the cancellation of
    # terms c_i K_i(jw) ~ 1e-2, so the state-space value is good to ~1e-18
    # absolute there (2e-11 relative): rtol 1e-12 plus atol 1e-16.
    np.testing.assert_allclose(model.frequency_response(w), expected, rtol=1e-12, atol=1e-16)


def test_frequency_response_equals_system():
    w = np.logspace(-2, 2, 50)
    _, expected = scipy.signal.freqresp(reference_system(), w=w)
    # As above: relative rounding, plus the high-frequency cancellation allowance.
    np.testing.assert_allclose(main_model().frequency_response(w), expected, rtol=1e-12, atol=1e-16)


def test_frequency_response_equals_sum_of_basis_transfer_functions():
    model = laguerre_row_model("a2_N8")
    w = np.linspace(0.0, 10.0, 31)
    tfs = model.basis.transfer_functions()
    expected = sum(
        c * np.polyval(num, 1j * w) / np.polyval(den, 1j * w)
        for c, (num, den) in zip(model.coefficients, tfs, strict=True)
    )
    # Degree <= 8 polynomials at |s| <= 10: rounding ~1e-14 on values O(1).
    np.testing.assert_allclose(model.frequency_response(w), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("delayed", DELAYS)
def test_discrete_frequency_response_equals_transfer_function(delayed):
    model = discrete_model(delayed)
    w = np.linspace(0.0, np.pi / model.dt, 40)
    num, den = model.transfer_function()
    z = np.exp(1j * w * model.dt)
    # Rounding only; |poles| <= 0.6 keeps everything well conditioned.
    np.testing.assert_allclose(
        model.frequency_response(w), np.polyval(num, z) / np.polyval(den, z), rtol=1e-12, atol=0
    )


def test_impulse_vanishes_before_zero():
    t = np.linspace(-1.0, 1.0, 21)
    h = main_model().impulse(t)
    np.testing.assert_array_equal(h[t < 0], 0.0)


def test_state_space_of_continuous_model():
    model = main_model()
    A, B, C, D = model.state_space()
    np.testing.assert_array_equal(A, model.basis.A)
    np.testing.assert_array_equal(B[:, 0], model.basis.B)
    np.testing.assert_array_equal(C[0], model.coefficients)
    np.testing.assert_array_equal(D, [[0.0]])


@pytest.mark.parametrize("delayed", DELAYS)
def test_discrete_impulse_is_weighted_sum_of_sequences(delayed):
    model = discrete_model(delayed)
    t = model.dt * np.arange(50)
    np.testing.assert_allclose(
        model.impulse(t), model.coefficients @ model.basis.evaluate(t), rtol=0, atol=1e-15
    )


@pytest.mark.parametrize("delayed", DELAYS)
def test_discrete_state_space_pulse_response_equals_impulse(delayed):
    model = discrete_model(delayed)
    A, B, C, D = model.state_space()
    n = 50
    x = B[:, 0].copy()
    pulse = [D[0, 0]]
    for _ in range(n - 1):
        pulse.append((C @ x)[0])
        x = A @ x
    # Hand-iterated realisation vs the model: rounding over 50 steps, values <= 1.
    np.testing.assert_allclose(model.impulse(model.dt * np.arange(n)), pulse, rtol=0, atol=1e-14)


@pytest.mark.parametrize("delayed", DELAYS)
def test_discrete_step_is_running_sum_of_impulse(delayed):
    model = discrete_model(delayed)
    t = model.dt * np.arange(60)
    # Closed-form running sums vs cumsum: rounding of O(1) values.
    np.testing.assert_allclose(model.step(t), np.cumsum(model.impulse(t)), rtol=0, atol=1e-13)


@pytest.mark.parametrize("delayed", DELAYS)
def test_discrete_dc_gain_is_sum_of_impulse(delayed):
    model = discrete_model(delayed)
    t = model.dt * np.arange(400)  # |poles| <= 0.6: 0.6^400 ~ 1e-89
    assert model.dc_gain == pytest.approx(model.impulse(t).sum(), abs=1e-13)


@pytest.mark.parametrize("delayed", DELAYS)
def test_discrete_transfer_function_pulse_response_equals_impulse(delayed):
    model = discrete_model(delayed)
    num, den = model.transfer_function()
    _, (h,) = scipy.signal.dimpulse((num, den, model.dt), n=40)
    # scipy iterates a canonical realisation of (num, den): ~40 steps of rounding.
    np.testing.assert_allclose(h[:, 0], model.impulse(model.dt * np.arange(40)), rtol=0, atol=1e-12)


def test_zero_coefficients_give_zero_numerator():
    model = kt.KautzModel(kt.LaguerreBasis(pole=-1.0, n=3), np.zeros(3))
    num, den = model.transfer_function()
    np.testing.assert_array_equal(num, [0.0])
    np.testing.assert_allclose(den, [1.0, 3.0, 3.0, 1.0], rtol=1e-15)


# ============================================================================ conversions
def test_to_scipy_impulse_equals_model():
    model = laguerre_row_model("a2_N8")
    t = np.linspace(0.0, 15.0, 301)
    sys = model.to_scipy()
    assert isinstance(sys, scipy.signal.lti)
    _, h = scipy.signal.impulse(sys, T=t)
    # Same (A, B, C), simulated by scipy's expm stepping: rounding only.
    np.testing.assert_allclose(h, model.impulse(t), rtol=0, atol=1e-12)


# scipy.signal.freqresp converts the state space to num/den; ss2tf leaves a
# rounding-size leading numerator coefficient (D = 0) that scipy trims with this
# warning.  That is scipy's conversion, not the model.
@pytest.mark.filterwarnings("ignore::scipy.signal.BadCoefficients")
def test_to_scipy_frequency_response_equals_model():
    model = laguerre_row_model("a2_N8")
    w = np.logspace(-2, 2, 40)
    _, H = scipy.signal.freqresp(model.to_scipy(), w=w)
    # scipy converts to a polynomial form first: degree-8 polynomials with
    # coefficients up to ~1e4 (2^8 binomials) lose ~4 digits.
    np.testing.assert_allclose(H, model.frequency_response(w), rtol=1e-10, atol=0)


@pytest.mark.parametrize("delayed", DELAYS)
def test_to_scipy_discrete_pulse_response_equals_model(delayed):
    model = discrete_model(delayed)
    sys = model.to_scipy()
    assert isinstance(sys, scipy.signal.dlti)
    assert sys.dt == model.dt
    _, (h,) = scipy.signal.dimpulse(sys, n=40)
    # Same realisation iterated by scipy: rounding only.
    np.testing.assert_allclose(h[:, 0], model.impulse(model.dt * np.arange(40)), rtol=0, atol=1e-14)


def test_to_control_impulse_equals_model():
    model = laguerre_row_model("a1_N8")
    t = np.linspace(0.0, 15.0, 301)
    sys = model.to_control()
    assert isinstance(sys, control.TransferFunction)
    response = control.impulse_response(sys, T=t)
    # control simulates a realisation of num/den (degree 8, coefficients ~1e2):
    # agreement to ~1e-12 on O(0.1) values.
    np.testing.assert_allclose(np.squeeze(response.outputs), model.impulse(t), rtol=0, atol=1e-10)


def test_to_control_frequency_response_equals_model():
    model = main_model()
    w = np.logspace(-2, 2, 40)
    values = np.array([complex(model.to_control()(1j * wk)) for wk in w])
    # Low-degree transfer function: rounding only (plus the high-frequency
    # cancellation allowance of the state-space side, see above).
    np.testing.assert_allclose(values, model.frequency_response(w), rtol=1e-12, atol=1e-16)


@pytest.mark.parametrize("delayed", DELAYS)
def test_to_control_discrete_equals_model(delayed):
    model = discrete_model(delayed)
    sys = model.to_control()
    assert sys.dt == model.dt
    w = np.linspace(0.1, 6.0, 20)
    values = np.array([complex(sys(np.exp(1j * wk * model.dt))) for wk in w])
    np.testing.assert_allclose(values, model.frequency_response(w), rtol=1e-12, atol=0)


# ============================================================================ value object
@pytest.mark.parametrize(
    "model",
    [
        pytest.param(main_model(), id="continuous-kautz"),
        pytest.param(laguerre_row_model("a1_N8"), id="continuous-laguerre"),
        pytest.param(discrete_model(False), id="discrete"),
        pytest.param(discrete_model(True), id="discrete-delayed"),
    ],
)
def test_dict_round_trip(model):
    data = json.loads(json.dumps(model.to_dict()))  # must be JSON-ready
    back = kt.KautzModel.from_dict(data)
    assert back.allclose(model, rtol=1e-15, atol=0)
    assert back.basis.delayed == model.basis.delayed
    t = model.dt * np.arange(30) if model.dt else np.linspace(0.0, 5.0, 30)
    np.testing.assert_allclose(back.impulse(t), model.impulse(t), rtol=0, atol=1e-15)


def test_to_dict_contents():
    d = main_model().to_dict()
    assert set(d) == {"poles", "dt", "delayed", "coefficients"}
    assert d["coefficients"] == list(C_MAIN)
    assert d["poles"][0] == [-1.0, 0.0]


def test_coefficients_are_read_only():
    model = main_model()
    with pytest.raises(ValueError, match="read-only"):
        model.coefficients[0] = 1.0


def test_setattr_raises():
    model = main_model()
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.coefficients = np.zeros(4)


def test_coefficients_are_copied():
    c = np.array(C_MAIN)
    model = kt.KautzModel(kt.KautzBasis(MAIN_POLES), c)
    c[0] = 99.0
    assert model.coefficients[0] == C_MAIN[0]


def test_with_coefficients_gives_new_model():
    model = main_model()
    other = model.with_coefficients(np.zeros(4))
    assert other.basis is model.basis
    np.testing.assert_array_equal(model.coefficients, C_MAIN)
    assert not model.allclose(other)


def test_allclose_compares_basis_and_coefficients():
    model = main_model()
    assert model.allclose(kt.KautzModel(kt.KautzBasis(MAIN_POLES), np.array(C_MAIN) * (1 + 1e-13)))
    assert not model.allclose(kt.KautzModel(kt.KautzBasis(MAIN_POLES_PAIR_FIRST), C_MAIN))
    assert not model.allclose("not a model")


def test_model_properties():
    model = discrete_model(True)
    assert model.n_functions == 4
    assert model.dt == 0.5
    np.testing.assert_array_equal(model.poles, model.basis.poles)


def test_coefficient_count_mismatch_raises():
    with pytest.raises(DimensionError, match=r"coefficients has shape \(3,\) but the basis has 4"):
        kt.KautzModel(kt.KautzBasis(MAIN_POLES), [1.0, 2.0, 3.0])


def test_two_dimensional_coefficients_raise():
    with pytest.raises(DimensionError, match=r"coefficients has shape \(1, 4\)"):
        kt.KautzModel(kt.KautzBasis(MAIN_POLES), [C_MAIN])


@pytest.mark.parametrize("bad", [np.nan, np.inf], ids=["nan", "inf"])
def test_non_finite_coefficients_raise(bad):
    with pytest.raises(DataError, match="coefficients contain NaN or inf"):
        kt.KautzModel(kt.KautzBasis(MAIN_POLES), [0.1, bad, 0.2, 0.3])


def test_basis_must_be_a_kautz_basis():
    with pytest.raises(DataError, match="basis must be a KautzBasis, got list"):
        kt.KautzModel([-1.0, -2.0], [0.1, 0.2])
