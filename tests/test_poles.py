"""Pole studies: sensitivity maps and variable-projection pole optimisation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

import kautztwin as kt
from kautztwin.data import reference_poles, reference_response, reference_system
from kautztwin.exceptions import DataError, PoleError

TRUE = reference_poles()
START_30 = TRUE * 1.3  # every pole 30 % away (rates and imaginary parts)


def _sorted(p):
    return np.sort_complex(np.asarray(p, dtype=complex))


# --------------------------------------------------------------------------- sensitivity
@pytest.mark.parametrize("index", [0, 1, 2, 3], ids=["real-1", "real-3", "pair-up", "pair-down"])
def test_sensitivity_system_matches_ise_from_system(index):
    p0 = TRUE[index]
    cands = (
        np.array([0.6, 0.9, 1.4]) * p0.real + 1j * abs(p0.imag) * np.array([1.3, 0.8, 1.1])
        if p0.imag
        else np.array([0.6, 0.9, 1.4]) * p0.real
    )
    got = kt.pole_sensitivity(TRUE, index, cands, system=reference_system())
    for value, g in zip(cands, got, strict=True):
        p = TRUE.copy()
        if p0.imag:
            mate = index + 1 if p0.imag > 0 else index - 1
            upper, lower = (index, mate) if p0.imag > 0 else (mate, index)
            p[upper], p[lower] = value, np.conj(value)
        else:
            p[index] = value
        # batched Kronecker solve vs scipy's Bartels-Stewart: both at the rounding level of
        # ||h||^2 = 0.14
        np.testing.assert_allclose(
            g, kt.ise_from_system(kt.KautzBasis(p), reference_system()), rtol=1e-9, atol=1e-15
        )


def test_sensitivity_is_zero_at_true_poles_and_positive_elsewhere():
    values = np.array([-0.5, -1.0, -2.0])
    out = kt.pole_sensitivity(TRUE, 0, values, system=reference_system())
    assert out[1] < 1e-12  # matched basis reproduces the system (ISE exact 0 up to rounding)
    assert out[0] > 1e-4 and out[2] > 1e-4


def test_sensitivity_2d_shape_and_minimum():
    re = np.linspace(-0.2, -1.0, 9)  # contains -0.5
    im = np.linspace(np.sqrt(15) / 2 - 0.4, np.sqrt(15) / 2 + 0.4, 5)  # contains the true value
    grid = re[None, :] + 1j * im[:, None]
    out = kt.pole_sensitivity(TRUE, 2, grid, system=reference_system())
    assert out.shape == (5, 9)
    i, j = np.unravel_index(np.argmin(out), out.shape)
    assert (i, j) == (2, 3)
    assert out[i, j] < 1e-12


def test_sensitivity_data_route_agrees_with_exact():
    # a long, fine record makes the least-squares ISE on the grid converge to the exact ISE;
    # the remaining gap is the trapezoid rule's O(dt^2) error (dt = 0.005) and the tail after 40 s
    t = np.linspace(0, 40, 8001)
    _, h = scipy.signal.impulse(reference_system(), T=t)
    values = np.array([-0.6, -1.5, -2.5])
    exact = kt.pole_sensitivity(TRUE, 0, values, system=reference_system())
    data = kt.pole_sensitivity(TRUE, 0, values, t=t, h=h)
    np.testing.assert_allclose(data, exact, rtol=1e-4)


def test_sensitivity_data_sums_records():
    t, h = reference_response()
    values = np.array([-0.7, -1.3])
    one = kt.pole_sensitivity(TRUE, 1, values, t=t, h=h)
    two = kt.pole_sensitivity(TRUE, 1, values, t=t, h=np.vstack([h, 2 * h]))
    np.testing.assert_allclose(two, 5 * one, rtol=1e-10)  # ||h||^2 + ||2h||^2 = 5 ||h||^2


@pytest.mark.parametrize(
    ("index", "values", "match"),
    [
        (0, [0.5], "Re < 0"),
        (0, [-1 + 1j], "real"),
        (2, [-1.0], "Im != 0"),
        (7, [-1.0], "out of range"),
        (0, [np.nan], "NaN"),
    ],
    ids=["unstable", "complex-for-real", "real-for-pair", "bad-index", "nan"],
)
def test_sensitivity_rejects_bad_candidates(index, values, match):
    with pytest.raises(PoleError, match=match):
        kt.pole_sensitivity(TRUE, index, values, system=reference_system())


def test_sensitivity_needs_exactly_one_target():
    t, h = reference_response()
    with pytest.raises(DataError, match="either system"):
        kt.pole_sensitivity(TRUE, 0, [-1.0])
    with pytest.raises(DataError, match="either system"):
        kt.pole_sensitivity(TRUE, 0, [-1.0], system=reference_system(), t=t, h=h)


# --------------------------------------------------------------------------- optimisation
def test_optimize_from_30_percent_off_recovers_reference():
    t, h = reference_response()
    res = kt.optimize_poles(t, h, START_30)
    assert res.success
    assert res.fit_percent > 99.99  # acceptance criterion
    # the noise-free optimum is the true pole set; 1e-6 relative leaves room for the solver's tol
    np.testing.assert_allclose(_sorted(res.basis.poles), _sorted(TRUE), rtol=1e-6)
    np.testing.assert_allclose(res.model.transfer_function()[1], reference_system().den, rtol=1e-6)


def test_optimize_automatic_start_recovers_reference():
    t, h = reference_response()
    res = kt.optimize_poles(t, h, 4)
    assert res.fit_percent > 99.99
    np.testing.assert_allclose(_sorted(res.basis.poles), _sorted(TRUE), rtol=1e-6)


def test_optimize_from_step_data():
    t, y = reference_response(kind="step")
    res = kt.optimize_poles(t, y, START_30, kind="step")
    assert res.fit_percent > 99.99
    np.testing.assert_allclose(_sorted(res.basis.poles), _sorted(TRUE), rtol=1e-6)
    np.testing.assert_allclose(res.model.dc_gain, 0.5, rtol=1e-6)


def test_optimize_noisy_beats_true_poles_on_data_and_start_on_truth():
    t, h_true = reference_response()
    _, h = reference_response(noise=0.10, random_state=3)
    res = kt.optimize_poles(t, h, START_30)
    # the optimum minimises the (Simpson-weighted) data misfit over the same structure, so its
    # ISE on the grid cannot exceed that of the true poles (1e-9 relative: the solver's ftol)
    truth_ise = kt.approximate(kt.KautzBasis(TRUE), t, h, method="lstsq").ise
    assert res.ise <= truth_ise * (1 + 1e-9)
    start_model = kt.approximate(kt.KautzBasis(START_30), t, h, method="lstsq").model
    fit_vs_truth = kt.fit_percent(h_true, res.model.impulse(t))
    assert fit_vs_truth > kt.fit_percent(h_true, start_model.impulse(t))
    assert fit_vs_truth > 90.0  # 10 % noise on 900 samples: the reported figure is about 97 %
    assert np.all(res.basis.poles.real < 0)


def test_optimize_many_records_share_poles():
    t = np.linspace(0, 20, 900)
    den = reference_system().den
    rng = np.random.default_rng(7)
    H = []
    for _ in range(5):
        num = rng.normal(size=3)
        _, hk = scipy.signal.impulse((num, den), T=t)
        H.append(hk)
    H = np.array(H)
    res = kt.optimize_poles(t, H, START_30)
    assert res.coefficients.shape == (5, 4)
    assert np.all(res.fit_percent > 99.99)
    np.testing.assert_allclose(_sorted(res.basis.poles), _sorted(TRUE), rtol=1e-6)
    assert len(res.models()) == 5
    with pytest.raises(DataError, match="one-record"):
        _ = res.model


def test_optimize_accepts_a_basis_and_reports_dict():
    t, h = reference_response()
    res = kt.optimize_poles(t, h, kt.KautzBasis(START_30))
    d = res.to_dict()
    assert {"coefficients", "poles", "ise", "fit_percent", "success", "initial_poles"} <= set(d)
    np.testing.assert_allclose(np.array(d["initial_poles"])[:, 0], np.real(START_30), rtol=1e-12)


@pytest.mark.parametrize(
    ("init", "error", "match"),
    [(0, PoleError, ">= 1"), ([-1, 1], PoleError, "Re >= 0"), (500, DataError, "too few")],
    ids=["zero", "unstable", "too-many"],
)
def test_optimize_rejects_bad_init(init, error, match):
    t, h = reference_response()
    with pytest.raises(error, match=match):
        kt.optimize_poles(t, h, init)


def test_optimize_rejects_bad_data():
    t, h = reference_response()
    h = h.copy()
    h[5] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        kt.optimize_poles(t, h, 4)
    with pytest.raises(DataError, match="kind"):
        kt.optimize_poles(t, np.nan_to_num(h), 4, kind="ramp")


def test_optimize_warns_when_a_pole_sticks_at_the_slowest_rate():
    # a first-order decay plus a constant offset cannot be separated from a pole at rate ~0:
    # the optimiser parks the second pole at the lower bound, and must say so
    t = np.linspace(0, 10, 500)
    h = np.exp(-t) + 0.2
    with pytest.warns(kt.exceptions.ConvergenceWarning, match="slowest allowed rate"):
        kt.optimize_poles(t, h, [-1.0, -0.5])


def test_restart_from_real_poles_converges_where_a_pair_collapses():
    """A double real optimum: the pair's imaginary part creeps to zero and the budget runs out.

    One simulated hydraulic step test (the drive's three real poles, two of them
    close) with three poles: the search from the automatic starts ends unconverged
    on a pair with ``|Im p| / |Re p|`` of a few thousandths; restarted from two real
    poles it converges to a lower error.
    """
    from kautztwin.approx.poles import COLLAPSING_PAIR, real_restart_poles
    from kautztwin.simulators import simulate_step_tests

    rec = simulate_step_tests(1, random_state=0)
    t, y = rec.t, rec.y[0] / rec.amplitude
    plain = kt.optimize_poles(t, y, 3, kind="step")
    pair = [p for p in plain.basis.poles if p.imag > 0]
    assert not plain.success and pair and abs(pair[0].imag) <= COLLAPSING_PAIR * abs(pair[0].real)
    assert real_restart_poles(plain.basis.poles) is not None
    again = kt.optimize_poles(t, y, 3, kind="step", restart_collapsed=True)
    assert again.success
    assert again.ise < plain.ise
    assert np.all(again.basis.poles.imag == 0)
    assert again.n_evaluations > plain.n_evaluations
    # an already converged search is returned as it is
    ok = kt.optimize_poles(t, y, again.basis, kind="step", restart_collapsed=True)
    assert ok.success and ok.ise <= again.ise * (1 + 1e-9)
