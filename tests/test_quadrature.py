"""Quadrature weights on uniform and non-uniform grids (kautztwin._quadrature).

Oracles: scipy.integrate.simpson/trapezoid, polynomials the rules integrate
exactly, the classical uniform Simpson pattern, convergence orders, and the
Gram-matrix quadrature errors of kautz-math.md 9.4.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate

import kautztwin as kt
from kautztwin._quadrature import quadrature_weights
from kautztwin.exceptions import DataError


def random_grid(n, seed):
    """Strictly increasing non-uniform grid on about [0.5, 2.5] (spacings vary by 3x)."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform(0.5, 1.5, n - 1)
    return 0.5 + np.concatenate([[0.0], np.cumsum(steps)]) * 2.0 / (n - 1)


SIZES = [3, 4, 5, 6, 11, 12, 101, 102]
GRID_CASES = [
    pytest.param(n, seed, id=f"n={n}-{'odd' if n % 2 else 'even'}-seed={seed}")
    for n in SIZES
    for seed in (1, 2)
]


@pytest.mark.parametrize(("n", "seed"), GRID_CASES)
def test_simpson_weights_equal_scipy_simpson(n, seed):
    t = random_grid(n, seed)
    f = np.random.default_rng(seed + 100).standard_normal((5, n))
    # Same rule (for an even count scipy >= 1.11 also integrates the last interval
    # with the parabola through the last three points); only the summation order
    # differs: rounding ~1e-16 relative to sum |w f|.
    scale = np.abs(f) @ np.abs(quadrature_weights(t))
    np.testing.assert_allclose(
        f @ quadrature_weights(t, "simpson"),
        scipy.integrate.simpson(f, x=t),
        rtol=0,
        atol=1e-13 * scale.max(),
    )


@pytest.mark.parametrize(("n", "seed"), GRID_CASES)
def test_trapezoid_weights_equal_scipy_trapezoid(n, seed):
    t = random_grid(n, seed)
    f = np.random.default_rng(seed + 200).standard_normal((5, n))
    np.testing.assert_allclose(
        f @ quadrature_weights(t, "trapezoid"),
        scipy.integrate.trapezoid(f, x=t),
        rtol=1e-13,
        atol=1e-15,
    )


@pytest.mark.parametrize(("n", "seed"), GRID_CASES)
def test_simpson_is_exact_for_quadratics(n, seed):
    t = random_grid(n, seed)
    a, b = t[0], t[-1]
    f = 2.0 - 3.0 * t + 1.5 * t**2
    exact = (2.0 * b - 1.5 * b**2 + 0.5 * b**3) - (2.0 * a - 1.5 * a**2 + 0.5 * a**3)
    # Every panel (pairs and the odd last interval) uses an interpolating parabola.
    assert quadrature_weights(t) @ f == pytest.approx(exact, rel=1e-13)


@pytest.mark.parametrize("n", [3, 5, 21, 101])
def test_uniform_simpson_is_exact_for_cubics(n):
    t = np.linspace(-1.0, 2.0, n)
    f = t**3 - 2 * t
    exact = (2.0**4 / 4 - 2.0**2) - (1 / 4 - 1)
    # Symmetric pairs cancel the cubic error term: exact up to rounding.
    assert quadrature_weights(t) @ f == pytest.approx(exact, rel=1e-13)


@pytest.mark.parametrize(("n", "seed"), GRID_CASES)
def test_trapezoid_is_exact_for_lines(n, seed):
    t = random_grid(n, seed)
    f = 4.0 - 2.0 * t
    exact = (4.0 * t[-1] - t[-1] ** 2) - (4.0 * t[0] - t[0] ** 2)
    assert quadrature_weights(t, "trapezoid") @ f == pytest.approx(exact, rel=1e-13)


@pytest.mark.parametrize("rule", ["simpson", "trapezoid"])
@pytest.mark.parametrize(("n", "seed"), GRID_CASES[:6])
def test_weights_sum_to_interval_length(rule, n, seed):
    t = random_grid(n, seed)
    assert quadrature_weights(t, rule).sum() == pytest.approx(t[-1] - t[0], rel=1e-14)


def test_uniform_simpson_weights_pattern():
    dt = 0.25
    t = dt * np.arange(9)
    expected = dt / 3 * np.array([1, 4, 2, 4, 2, 4, 2, 4, 1])
    np.testing.assert_allclose(quadrature_weights(t), expected, rtol=1e-15, atol=0)


def test_uniform_trapezoid_weights_pattern():
    t = 0.5 * np.arange(5)
    np.testing.assert_allclose(
        quadrature_weights(t, "trapezoid"), [0.25, 0.5, 0.5, 0.5, 0.25], rtol=1e-15, atol=0
    )


def test_two_samples_fall_back_to_trapezoid():
    t = np.array([1.0, 3.0])
    np.testing.assert_array_equal(quadrature_weights(t), [1.0, 1.0])


@pytest.mark.parametrize(("rule", "order"), [("simpson", 4), ("trapezoid", 2)])
def test_convergence_order(rule, order):
    # f = e^{-t} sin 3t on [0, 2], antiderivative -e^{-t}(sin 3t + 3 cos 3t)/10.
    def integral(b):
        return (-np.exp(-b) * (np.sin(3 * b) + 3 * np.cos(3 * b)) / 10) - (-3 / 10)

    errors = []
    for n in (41, 81, 161):
        t = np.linspace(0.0, 2.0, n)
        errors.append(
            abs(quadrature_weights(t, rule) @ (np.exp(-t) * np.sin(3 * t)) - integral(2.0))
        )
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    # Halving the step divides the error by 2^order (asymptotically): allow 10%.
    np.testing.assert_allclose(ratios, 2.0**order, rtol=0.1)


def test_unknown_rule_raises():
    with pytest.raises(DataError, match="rule must be 'simpson' or 'trapezoid', got 'boole'"):
        quadrature_weights(np.linspace(0.0, 1.0, 5), "boole")


# ---------------------------------------------------------------------------- 9.4 regression
# max |Gram - I| on a uniform grid over [0, 80], from kautz-math.md 9.4 (3 digits).
TABLE_94 = {
    "a": (
        [-1.1, -0.8, -2.1],
        {
            ("trapezoid", 1e-2): 4.13e-4,
            ("trapezoid", 1e-3): 4.13e-6,
            ("simpson", 1e-2): 1.86e-7,
            ("simpson", 1e-3): 1.85e-11,
        },
    ),
    "b": (
        [-1.1, -0.8, -1.5, -0.8 + 2j, -0.8 - 2j],
        {
            ("trapezoid", 1e-2): 4.48e-4,
            ("trapezoid", 1e-3): 4.48e-6,
            ("simpson", 1e-2): 3.10e-7,
            ("simpson", 1e-3): 3.09e-11,
        },
    ),
    "laguerre_a1_N4": (
        [-1.0] * 4,
        {
            ("trapezoid", 1e-2): 2.33e-4,
            ("trapezoid", 1e-3): 2.33e-6,
            ("simpson", 1e-2): 1.31e-7,
            ("simpson", 1e-3): 1.33e-11,
        },
    ),
}
TABLE_CASES = [
    pytest.param(name, rule, dt, id=f"{name}-{rule}-dt={dt:g}")
    for name in TABLE_94
    for rule in ("trapezoid", "simpson")
    for dt in (1e-2, 1e-3)
]


@pytest.mark.parametrize(("name", "rule", "dt"), TABLE_CASES)
def test_gram_quadrature_error_matches_table(name, rule, dt):
    poles, table = TABLE_94[name]
    basis = kt.KautzBasis(poles)
    t = np.linspace(0.0, 80.0, int(round(80.0 / dt)) + 1)
    K = basis.evaluate(t)
    error = np.abs((K * quadrature_weights(t, rule)) @ K.T - np.eye(basis.n_functions)).max()
    expected = table[(rule, dt)]
    # Three printed digits: 0.6 % covers their rounding.  The Simpson dt = 1e-3
    # entries (~1e-11) sit near the summation rounding of 80,001 terms (~1e-13
    # absolute), which moves their third digit: 5 % there.
    rtol = 0.05 if (rule, dt) == ("simpson", 1e-3) else 0.006
    assert error == pytest.approx(expected, rel=rtol)
