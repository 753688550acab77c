"""Tests of the electro-hydraulic servo drive simulator (kautztwin.simulators.hydraulic)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal

from kautztwin.exceptions import DataError, DimensionError
from kautztwin.metrics import fit_percent
from kautztwin.simulators import (
    HydraulicParameters,
    HydraulicServoDrive,
    simulate_step_tests,
    walther_viscosity,
)

T_GRID = np.linspace(0.0, 3.0, 900)  # the paper's 900 samples on the default record length
TEMPERATURES = [20.0, 40.0, 60.0]
T_IDS = [f"{T:g}degC" for T in TEMPERATURES]


@pytest.fixture(scope="module")
def drive() -> HydraulicServoDrive:
    return HydraulicServoDrive()


# --------------------------------------------------------------------------- oil and parameters
def test_walther_viscosity_passes_through_datasheet_points():
    np.testing.assert_allclose(walther_viscosity([40.0, 100.0]), [46.0, 6.8], rtol=1e-12)
    nu = walther_viscosity(np.arange(-20.0, 121.0, 10.0))
    assert np.all(np.diff(nu) < 0)
    assert isinstance(walther_viscosity(40.0), float)


def test_temperature_scaling_of_leakage_friction_and_bulk_modulus():
    p = HydraulicParameters()
    cold, hot = p.at_temperature(20.0), p.at_temperature(60.0)
    ratio = walther_viscosity(60.0) / walther_viscosity(20.0)
    np.testing.assert_allclose(hot["leakage"] / cold["leakage"], 1 / ratio, rtol=1e-12)
    np.testing.assert_allclose(hot["viscous_friction"] / cold["viscous_friction"], ratio,
                               rtol=1e-12)
    np.testing.assert_allclose(hot["bulk_modulus"], p.bulk_modulus * (1 - 20 * 0.004), rtol=1e-12)
    np.testing.assert_allclose(p.at_temperature(40.0)["leakage"], p.leakage, rtol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"supply_pressure": -1.0}, "supply_pressure must be > 0"),
        ({"discharge_coefficient": 1.5}, r"discharge_coefficient must lie in \(0, 1\]"),
        ({"inertia": float("nan")}, "inertia must be finite"),
        ({"coulomb_friction": -0.1}, "coulomb_friction must be >= 0"),
        ({"viscosity_100": 50.0}, "viscosity_100 .* must be below viscosity_40"),
        ({"bulk_modulus_slope": 0.02}, "bulk modulus non-positive"),
        ({"viscous_friction": 0.0, "load_damping": 0.0}, "would not settle"),
    ],
    ids=["negative-pressure", "cd-above-one", "nan", "negative-coulomb", "viscosity-order",
         "bulk-slope", "no-damping"],
)
def test_parameter_errors(kwargs, match):
    with pytest.raises(DataError, match=match):
        HydraulicParameters(**kwargs)


def test_temperature_out_of_range_is_rejected():
    with pytest.raises(DataError, match=r"temperature must lie in \[-20, 120\]"):
        HydraulicParameters().at_temperature(150.0)


# --------------------------------------------------------------------------- linearisation
def test_nominal_linearization_has_three_distinct_real_poles(drive):
    lin = drive.linearize(0.5, temperature=40.0)
    assert lin.is_real
    poles = lin.poles.real
    assert np.all(poles < 0) and np.all(np.diff(poles) < -1.0)  # distinct, slowest first
    # documented in docs/hydraulic.md
    np.testing.assert_allclose(poles, [-2.936, -10.0, -41.31], rtol=2e-3)
    np.testing.assert_allclose(np.sort(np.roots(lin.den).real)[::-1], poles, rtol=1e-9)


@pytest.mark.parametrize("temperature", TEMPERATURES, ids=T_IDS)
def test_small_step_matches_linearization(drive, temperature):
    lin = drive.linearize(0.5, temperature)
    du = 0.001
    r = drive.simulate(T_GRID, 0.5 + du, temperature, x0=lin.x0)
    assert fit_percent(r.y - lin.y0, lin.step(T_GRID, du)) > 99.5


def test_linearization_is_exact_to_first_order(drive):
    """The odd part of +-du responses cancels the quadratic term: only O(du^3) remains."""
    lin = drive.linearize(0.5, 40.0)
    du = 0.002
    up = drive.simulate(T_GRID, 0.5 + du, 40.0, x0=lin.x0).y
    down = drive.simulate(T_GRID, 0.5 - du, 40.0, x0=lin.x0).y
    assert fit_percent((up - down) / 2, lin.step(T_GRID, du)) > 99.99


def test_equilibrium_is_a_steady_state(drive):
    x0 = drive.equilibrium(0.5, 40.0)
    r = drive.simulate(T_GRID, 0.5, 40.0, x0=x0)
    np.testing.assert_allclose(r.x, np.tile(x0, (T_GRID.size, 1)), rtol=1e-7, atol=1e-9)


def test_dc_gain_matches_equilibrium_slope(drive):
    h = 1e-5
    slope = (drive.equilibrium(0.5 + h)[2] - drive.equilibrium(0.5 - h)[2]) / (2 * h)
    np.testing.assert_allclose(drive.linearize(0.5).dc_gain, slope, rtol=1e-6)


def test_state_space_and_transfer_function_agree(drive):
    lin = drive.linearize(0.3, 50.0)
    num, den = scipy.signal.ss2tf(lin.A, lin.B, lin.C, lin.D)
    np.testing.assert_allclose(den, lin.den, rtol=1e-9)
    np.testing.assert_allclose(num[0][-1], lin.num[-1], rtol=1e-6)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(lin.A).real), np.sort(lin.poles.real),
                               rtol=1e-9)


def test_poles_drift_monotonically_with_temperature(drive):
    """20 -> 60 degC: the slow pole moves from -3.87 to -2.13, the fast one from -33.8 to -56.9."""
    temps = np.arange(20.0, 60.1, 5.0)
    poles = np.array([drive.linearize(0.5, T).poles.real for T in temps])
    assert np.all(np.diff(poles[:, 0]) > 0)  # slow hydro-mechanical pole: towards 0
    assert np.all(np.diff(poles[:, 2]) < 0)  # fast hydraulic pole: away from 0
    np.testing.assert_allclose(poles[:, 1], -10.0, rtol=1e-12)  # valve lag, temperature-free
    np.testing.assert_allclose(poles[[0, -1]][:, [0, 2]], [[-3.872, -33.78], [-2.129, -56.93]],
                               rtol=2e-3)


def test_linearization_at_the_stroke_limit_has_zero_gain(drive):
    lin = drive.linearize(1.2)
    assert lin.dc_gain == 0.0 and np.all(lin.poles.real < 0)


# --------------------------------------------------------------------------- nonlinearity
def test_spool_saturation_limits_the_flow(drive):
    full = drive.step_response(T_GRID, 1.0).y
    beyond = drive.step_response(T_GRID, 2.0).y
    np.testing.assert_allclose(beyond, full, rtol=0, atol=1e-9)


def test_large_step_differs_from_scaled_small_step(drive):
    small = drive.step_response(T_GRID, 0.05)
    large = drive.step_response(T_GRID, 0.9)
    scaled = 18.0 * small.y
    assert fit_percent(large.y, scaled) < 50.0
    assert large.y[-1] < 0.85 * scaled[-1]  # the orifice passes less flow at high load pressure
    # during the run-up the load pressure approaches the supply pressure
    assert large.x[:, 1].max() > 0.8 * drive.parameters.supply_pressure


def test_coulomb_friction_lowers_the_steady_speed():
    plain = HydraulicServoDrive()
    dry = HydraulicServoDrive(HydraulicParameters(coulomb_friction=0.5))
    x_dry = dry.equilibrium(0.5)
    assert x_dry[2] < plain.equilibrium(0.5)[2]
    r = dry.step_response(np.linspace(0.0, 6.0, 600), 0.5)
    np.testing.assert_allclose(r.y[-1], x_dry[2], rtol=1e-4)
    assert dry.linearize(0.5).is_real


# --------------------------------------------------------------------------- simulation API
def test_simulation_continues_from_the_last_state(drive):
    rng = np.random.default_rng(3)
    u = np.repeat(rng.uniform(-1, 1, 30), 30)
    whole = drive.simulate(T_GRID, u, 40.0)
    k = 450
    first = drive.simulate(T_GRID[: k + 1], u[: k + 1], 40.0)
    second = drive.simulate(T_GRID[k:], u[k:], 40.0, x0=first.x[-1])
    joined = np.concatenate([first.y, second.y[1:]])
    np.testing.assert_allclose(joined, whole.y, rtol=0, atol=1e-5)


def test_input_is_held_between_samples(drive):
    u = np.where(T_GRID < 1.0, 0.3, 0.6)
    r = drive.simulate(T_GRID, u, 40.0)
    k = int(np.argmax(T_GRID >= 1.0))
    ref = drive.step_response(T_GRID, 0.3, 40.0)
    np.testing.assert_allclose(r.y[: k + 1], ref.y[: k + 1], rtol=0, atol=1e-6)
    assert r.y[-1] > ref.y[-1] + 10.0  # the second step takes effect


def test_drifting_temperature_as_function_and_as_samples_agree(drive):
    ramp = 20.0 + 40.0 * T_GRID / T_GRID[-1]
    by_fn = drive.simulate(T_GRID, 0.5, lambda t: 20.0 + 40.0 * t / 3.0)
    by_samples = drive.simulate(T_GRID, 0.5, ramp)
    np.testing.assert_allclose(by_fn.y, by_samples.y, rtol=0, atol=1e-5)
    np.testing.assert_allclose(by_fn.temperature, ramp, atol=1e-12)
    # the warming oil ends between the constant-temperature responses
    cold, hot = drive.simulate(T_GRID, 0.5, 20.0), drive.simulate(T_GRID, 0.5, 60.0)
    assert not np.allclose(by_fn.y, cold.y) and not np.allclose(by_fn.y, hot.y)


@pytest.mark.parametrize("noise", [0.02, 0.1], ids=["2%", "10%"])
def test_noise_level_is_a_fraction_of_the_peak(drive, noise):
    r = drive.step_response(T_GRID, 0.5, noise=noise, random_state=7)
    sigma = np.std(r.y - r.y_true)
    np.testing.assert_allclose(sigma, noise * np.max(np.abs(r.y_true)), rtol=0.1)


def test_absolute_noise_and_quantisation_of_simulate():
    drive = HydraulicServoDrive(sensor_resolution=0.5)
    r = drive.simulate(T_GRID, 0.5, noise=2.0, random_state=0)
    np.testing.assert_allclose(r.y / 0.5, np.round(r.y / 0.5), atol=1e-9)
    np.testing.assert_allclose(np.std(r.y - r.y_true), math.sqrt(2.0**2 + 0.5**2 / 12), rtol=0.1)


def test_seeded_runs_are_reproducible(drive):
    a = drive.step_response(T_GRID, 0.5, noise=0.05, random_state=11)
    b = drive.step_response(T_GRID, 0.5, noise=0.05, random_state=11)
    c = drive.step_response(T_GRID, 0.5, noise=0.05, random_state=12)
    np.testing.assert_array_equal(a.y, b.y)
    assert not np.array_equal(a.y, c.y)
    s1 = simulate_step_tests(4, 100, random_state=5)
    s2 = simulate_step_tests(4, 100, random_state=5)
    np.testing.assert_array_equal(s1.y, s2.y)


def test_results_are_read_only(drive):
    r = drive.step_response(T_GRID[:50], 0.5)
    with pytest.raises(ValueError, match="read-only"):
        r.y[0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        drive.linearize().poles[0] = 0.0


# --------------------------------------------------------------------------- step-test sessions
def test_step_test_session_shapes_and_temperatures():
    rec = simulate_step_tests(30, 900, (20.0, 60.0), amplitude=0.5, noise=0.01, random_state=0)
    assert (rec.n_records, rec.n_samples) == (30, 900)
    assert rec.u.shape == rec.y.shape == rec.y_true.shape == (30, 900)
    np.testing.assert_allclose(rec.t[[0, -1]], [0.0, 3.0])
    np.testing.assert_allclose(rec.temperature, np.linspace(20.0, 60.0, 30))
    np.testing.assert_array_equal(rec.u, 0.5)
    np.testing.assert_array_equal(rec.y_true[:, 0], 0.0)  # from rest
    # every record has settled by the end (2 % band over the last 10 %)
    tail = rec.y_true[:, -90:]
    assert np.all(np.ptp(tail, axis=1) < 0.02 * tail[:, -1])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_records": 0}, "n_records must be >= 1"),
        ({"n_samples": 1}, "n_samples must be >= 2"),
        ({"n_records": 2.5}, "n_records must be an integer"),
        ({"temperatures": (60.0, 20.0)}, "lo <= hi"),
        ({"temperatures": (20.0, 200.0)}, r"temperatures\[1\] must lie in"),
        ({"t_end": 0.0}, "t_end must be > 0"),
        ({"amplitude": 0.0}, "amplitude must be nonzero"),
        ({"noise": -0.1}, "noise must be >= 0"),
    ],
    ids=["no-records", "one-sample", "float-count", "reversed", "too-hot", "zero-length",
         "zero-step", "negative-noise"],
)
def test_step_test_errors(kwargs, match):
    args = {"n_records": 2, "n_samples": 20, **kwargs}
    with pytest.raises(DataError, match=match):
        simulate_step_tests(**args)


def test_simulate_input_errors(drive):
    with pytest.raises(DimensionError, match=r"u must have shape \(900,\)"):
        drive.simulate(T_GRID, np.zeros(10))
    with pytest.raises(DimensionError, match="x0 must have shape"):
        drive.simulate(T_GRID, 0.5, x0=[0.0, 0.0])
    with pytest.raises(DataError, match="beyond the spool stroke"):
        drive.simulate(T_GRID, 0.5, x0=[1e-2, 0.0, 0.0])
    with pytest.raises(DataError, match=r"temperature\[0\] must lie in"):
        drive.simulate(T_GRID, 0.5, np.full(900, -40.0))
    with pytest.raises(DataError, match=r"temperature\(t\[0\]\) must lie in"):
        drive.simulate(T_GRID, 0.5, lambda t: 500.0)
    with pytest.raises(DataError, match="method must be one of"):
        HydraulicServoDrive(method="Euler")
