"""Coefficients of responses in a basis (kautz-math.md sections 4, 5 and 9.2).

Oracles: the closed-form coefficients of section 9.2, Sylvester coefficients
(themselves checked against the closed forms), scipy.signal impulse/step
simulations, partial-fraction impulse responses, direct summation in discrete
time, and polynomials for which the integration/differentiation rules are exact.
"""

from __future__ import annotations

import warnings

import control
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.signal

import kautztwin as kt
from kautztwin.data import reference_system
from kautztwin.exceptions import DataError, DimensionError

SQ2, SQ6 = np.sqrt(2.0), np.sqrt(6.0)
W = np.sqrt(15.0) / 2.0
MAIN_POLES = [-1.0, -3.0, -0.5 + 1j * W, -0.5 - 1j * W]
MAIN_POLES_PAIR_FIRST = [-0.5 + 1j * W, -0.5 - 1j * W, -1.0, -3.0]
# kautz-math.md 9.2, exact values
C_MAIN = np.array([SQ2 / 8, -3 * SQ6 / 32, 5 * SQ2 / 32, SQ2 / 16])
C_MAIN_PAIR_FIRST = np.array([-5 * SQ2 / 32, SQ2 / 16, 13 * SQ2 / 64, -SQ6 / 64])
H_NORM2_MAIN = 9 / 64

B_POLES = [-1.1, -0.8, -1.5, -0.8 + 2j, -0.8 - 2j]
B_PRIME_POLES = [-0.8 + 2j, -0.8 - 2j, -1.1, -0.8, -1.5]
SYSTEM_A = ([1.0], np.poly([-1.1, -0.8, -2.1]))
SYSTEM_B = ([1.0, 1.0], np.polymul(np.poly([-1.1, -0.8, -1.5]), [1.0, 1.6, 4.64]))


def main_system():
    return reference_system()


def impulse_response(system, t):
    """h(t) by partial fractions (any grid, uniform or not): independent of scipy's simulator."""
    num, den = system
    r, p, _ = scipy.signal.residue(num, den)
    return np.real(np.sum(r[:, None] * np.exp(np.outer(p, t)), axis=0))


def sampled_main(t_end=20.0, n=2001, kind="impulse"):
    t = np.linspace(0.0, t_end, n)
    simulate = scipy.signal.impulse if kind == "impulse" else scipy.signal.step
    _, y = simulate(main_system(), T=t)
    return t, y


BASES = {
    "matched": lambda: kt.KautzBasis(MAIN_POLES),
    "matched_pair_first": lambda: kt.KautzBasis(MAIN_POLES_PAIR_FIRST),
    "laguerre_a1_N8": lambda: kt.LaguerreBasis(pole=-1.0, n=8),
    "laguerre_a2_N16": lambda: kt.LaguerreBasis(pole=-2.0, n=16),
    "basis_b": lambda: kt.KautzBasis(B_POLES),
}
BASIS_IDS = list(BASES)


# ========================================================================== Sylvester coefficients
def test_matched_coefficients_equal_closed_form():
    c = kt.coefficients_from_system(kt.KautzBasis(MAIN_POLES), main_system())
    # 4x4 Sylvester solve with O(1) data: rounding ~1e-15 (criterion: 1e-10).
    np.testing.assert_allclose(c, C_MAIN, rtol=0, atol=1e-13)


def test_matched_coefficients_pair_first_equal_closed_form():
    c = kt.coefficients_from_system(kt.KautzBasis(MAIN_POLES_PAIR_FIRST), main_system())
    # As above.
    np.testing.assert_allclose(c, C_MAIN_PAIR_FIRST, rtol=0, atol=1e-13)


def test_matched_coefficients_equal_printed_values():
    # The digits printed in 9.2 (12 decimals), in both orderings, to the 1e-10 criterion.
    c1 = kt.coefficients_from_system(kt.KautzBasis(MAIN_POLES), main_system())
    c2 = kt.coefficients_from_system(kt.KautzBasis(MAIN_POLES_PAIR_FIRST), main_system())
    np.testing.assert_allclose(
        c1, [0.176776695297, -0.229639663386, 0.220970869121, 0.088388347648], rtol=0, atol=1e-10
    )
    np.testing.assert_allclose(
        c2, [-0.220970869121, 0.088388347648, 0.287262129857, -0.038273277231], rtol=0, atol=1e-10
    )


@pytest.mark.parametrize(
    "form",
    [
        "TransferFunction",
        "ZerosPolesGain",
        "StateSpace",
        "num-den",
        "ABCD",
        "control.tf",
        "control.ss",
    ],
)
def test_every_system_description_gives_same_coefficients(form):
    sys = main_system()
    system = {
        "TransferFunction": sys,
        "ZerosPolesGain": sys.to_zpk(),
        "StateSpace": sys.to_ss(),
        "num-den": (sys.num, sys.den),
        "ABCD": scipy.signal.tf2ss(sys.num, sys.den),
        "control.tf": control.tf(sys.num, sys.den),
        "control.ss": control.ss(control.tf(sys.num, sys.den)),
    }[form]
    c = kt.coefficients_from_system(kt.KautzBasis(MAIN_POLES), system)
    # Different realisations change the Sylvester problem's conditioning a little:
    # observed <= 2e-15, allow 1e-13.
    np.testing.assert_allclose(c, C_MAIN, rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    ("system", "poles", "expected"),
    [
        pytest.param(
            SYSTEM_A,
            [-1.1, -0.8, -2.1],
            [0.110888135274, -0.215218534040, 0.052580822896],
            id="system_a",
        ),
        pytest.param(
            SYSTEM_B,
            B_POLES,
            [0.037661390328, -0.078853278523, 0.006922904151, 0.017827439640, 0.024304552985],
            id="system_b",
        ),
        pytest.param(
            ([1.0], np.poly([-1.0] * 3)),
            [-1.0] * 3,
            [SQ2 / 8, -SQ2 / 4, SQ2 / 8],
            id="laguerre_cube",
        ),
    ],
)
def test_table_coefficients(system, poles, expected):
    c = kt.coefficients_from_system(kt.KautzBasis(poles), system)
    # Printed with 12 decimals (last-digit rounding 5e-13); Sylvester is exact to ~1e-16.
    np.testing.assert_allclose(c, expected, rtol=0, atol=0.5e-12 + 1e-15)


@pytest.mark.parametrize(
    ("system", "poles", "h_norm2"),
    [
        pytest.param(main_system(), MAIN_POLES, H_NORM2_MAIN, id="main"),
        pytest.param(SYSTEM_A, [-1.1, -0.8, -2.1], 0.0613799388754016, id="system_a"),
        pytest.param(SYSTEM_B, B_POLES, 0.00859267535702602, id="system_b"),
        pytest.param(([1.0], np.poly([-1.0] * 3)), [-1.0] * 3, 3 / 16, id="laguerre_cube"),
    ],
)
def test_matched_basis_has_zero_ise_and_full_energy(system, poles, h_norm2):
    basis = kt.KautzBasis(poles)
    c = kt.coefficients_from_system(basis, system)
    # ISE = ||h||^2 - ||c||^2 cancels to rounding (~1e-17) and is clamped at 0.
    assert kt.ise_from_system(basis, system) < 1e-12
    # Parseval: ||c||^2 = ||h||^2 (printed with >= 15 significant digits).
    np.testing.assert_allclose(c @ c, h_norm2, rtol=1e-13, atol=0)


# kautz-math.md 9.2, Laguerre approximations of the main system: coefficients
# (12 decimals) and ISE (7 significant digits).
LAGUERRE_ROWS = {
    "a1_N8": (
        -1.0,
        8,
        [
            0.176776695297,
            -0.265165042945,
            -0.073656956374,
            0.081022652011,
            0.119078746137,
            0.059539373069,
            -0.022608593554,
            -0.063682576865,
        ],
        "4.781179e-3",
    ),
    "a2_N8": (
        -2.0,
        8,
        [
            0.08,
            -0.250666666667,
            0.230755555556,
            0.016521481481,
            -0.102019160494,
            -0.023696013169,
            0.065478191056,
            0.012729840315,
        ],
        "2.451284e-3",
    ),
    "a2_N16": (
        -2.0,
        16,
        [
            0.08,
            -0.250666666667,
            0.230755555556,
            0.016521481481,
            -0.102019160494,
            -0.023696013169,
            0.065478191056,
            0.012729840315,
            -0.038804099305,
            -0.007801464072,
            0.023336455256,
            0.004662775028,
            -0.013995859653,
            -0.002799673711,
            0.008398184518,
            0.001679581150,
        ],
        "4.125863e-5",
    ),
}


def printed_tolerance(printed):
    """Half a unit in the last printed digit of a number written like '4.781179e-3'."""
    mantissa, _, exponent = printed.partition("e")
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    return 0.5 * 10.0 ** (int(exponent or 0) - decimals)


@pytest.mark.parametrize("row", list(LAGUERRE_ROWS))
def test_laguerre_row_coefficients(row):
    pole, n, expected, _ = LAGUERRE_ROWS[row]
    c = kt.coefficients_from_system(kt.LaguerreBasis(pole=pole, n=n), main_system())
    # Printed with 12 decimals; Sylvester with a Jordan-block A (N <= 16) is accurate to ~1e-15.
    np.testing.assert_allclose(c, expected, rtol=0, atol=0.5e-12 + 1e-15)


@pytest.mark.parametrize("row", list(LAGUERRE_ROWS))
def test_laguerre_row_ise(row):
    pole, n, _, printed = LAGUERRE_ROWS[row]
    value = kt.ise_from_system(kt.LaguerreBasis(pole=pole, n=n), main_system())
    # Must round to the printed digits.
    assert abs(value - float(printed)) <= printed_tolerance(printed)


def test_ise_from_system_equals_quadrature_of_error():
    basis = kt.LaguerreBasis(pole=-1.0, n=8)
    t = np.linspace(0.0, 60.0, 60_001)
    h = impulse_response((main_system().num, main_system().den), t)
    c = kt.coefficients_from_system(basis, main_system())
    error2 = (h - c @ basis.evaluate(t)) ** 2
    quad = scipy.integrate.simpson(error2, x=t)
    # Simpson at dt = 1e-3 on a smooth integrand (error ~1e-13), tail after t = 60
    # below e^{-0.5 * 120} ~ 1e-26.
    np.testing.assert_allclose(kt.ise_from_system(basis, main_system()), quad, rtol=1e-9, atol=0)


def test_coefficient_error_adds_to_ise():
    # ||h - c_hat^T K||^2 = ||c - c_hat||^2 + ISE (kautz-math.md 4.1).
    rng = np.random.default_rng(7)
    basis = kt.LaguerreBasis(pole=-2.0, n=8)
    c = kt.coefficients_from_system(basis, main_system())
    c_hat = c + 0.05 * rng.standard_normal(c.size)
    t = np.linspace(0.0, 60.0, 60_001)
    h = impulse_response((main_system().num, main_system().den), t)
    lhs = scipy.integrate.simpson((h - c_hat @ basis.evaluate(t)) ** 2, x=t)
    rhs = (c - c_hat) @ (c - c_hat) + kt.ise_from_system(basis, main_system())
    # Simpson error at dt = 1e-3 on O(1) integrands: ~1e-12 relative.
    np.testing.assert_allclose(lhs, rhs, rtol=1e-9, atol=0)


def test_block_order_does_not_change_ise():
    # (b) and (b') span the same space (kautz-math.md 0).
    a = kt.ise_from_system(kt.KautzBasis(B_POLES), main_system())
    b = kt.ise_from_system(kt.KautzBasis(B_PRIME_POLES), main_system())
    # Both are ||h||^2 - ||c||^2 with ||h||^2 = 0.14; rounding of the difference ~1e-16.
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)
    assert a > 1e-4  # a non-trivial approximation, not two zeros


def test_block_order_does_not_change_approximant():
    t = np.linspace(0.0, 20.0, 201)
    responses = []
    for poles in (B_POLES, B_PRIME_POLES):
        basis = kt.KautzBasis(poles)
        responses.append(kt.coefficients_from_system(basis, main_system()) @ basis.evaluate(t))
    # Same orthogonal projection; values O(0.1), rounding ~1e-16.
    np.testing.assert_allclose(responses[0], responses[1], rtol=0, atol=1e-14)


def test_feedthrough_is_left_out_with_warning():
    # G = (s + 4)/(s + 3) = 1 + 1/(s + 3): only 1/(s + 3) is in L2.
    basis = kt.KautzBasis([-3.0, -1.0])
    with pytest.warns(UserWarning, match="direct feedthrough D = 1"):
        c = kt.coefficients_from_system(basis, ([1.0, 4.0], [1.0, 3.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c_proper = kt.coefficients_from_system(basis, ([1.0], [1.0, 3.0]))
    np.testing.assert_allclose(c, c_proper, rtol=0, atol=1e-15)
    # 1/(s+3) = K_1/sqrt(6): exact (rounding only).
    np.testing.assert_allclose(c, [1 / np.sqrt(6), 0.0], rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------- discrete time
# Pulse response h(0) = D = 0.5, h(k) = sum_i r_i xi_i^k: the numerator vanishes at
# z = 0, so h lies in the span of the matched undelayed basis (z-transform z Q(z)/d(z)).
DISCRETE_SYSTEM = ([0.5, -0.2, 0.1, 0.0], np.poly([0.6, 0.3 + 0.4j, 0.3 - 0.4j]).real, 1.0)


def discrete_pulse(system, n):
    _, (h,) = scipy.signal.dimpulse(system, n=n)
    return h[:, 0]


@pytest.mark.parametrize("delayed", [False, True], ids=["undelayed", "delayed"])
@pytest.mark.parametrize(
    "poles",
    [[0.6, 0.3 + 0.4j, 0.3 - 0.4j], [0.5] * 4, [0.2, -0.7, 0.5j, -0.5j]],
    ids=["matched", "laguerre", "mixed"],
)
def test_discrete_coefficients_equal_direct_summation(poles, delayed):
    basis = kt.KautzBasis(poles, dt=1.0, delayed=delayed)
    k = np.arange(400.0)  # |poles| <= 0.7: 0.7^400 ~ 1e-62
    direct = basis.evaluate(k) @ discrete_pulse(DISCRETE_SYSTEM, k.size)
    # Stein solve (Kronecker form) vs a plain sum of 400 O(1) products (9.3: 3e-16).
    np.testing.assert_allclose(
        kt.coefficients_from_system(basis, DISCRETE_SYSTEM), direct, rtol=0, atol=1e-14
    )


@pytest.mark.parametrize("delayed", [False, True], ids=["undelayed", "delayed"])
def test_discrete_ise_equals_direct_summation(delayed):
    basis = kt.LaguerreBasis(pole=0.5, n=3, dt=1.0, delayed=delayed)
    k = np.arange(400.0)
    h = discrete_pulse(DISCRETE_SYSTEM, k.size)
    c = kt.coefficients_from_system(basis, DISCRETE_SYSTEM)
    residual = h - c @ basis.evaluate(k)
    # ||h||^2 - ||c||^2 vs a direct sum of squares: both ~1e-16 accurate, values O(0.1).
    np.testing.assert_allclose(
        kt.ise_from_system(basis, DISCRETE_SYSTEM), residual @ residual, rtol=1e-12, atol=0
    )


def test_matched_discrete_basis_represents_system_exactly():
    basis = kt.KautzBasis([0.6, 0.3 + 0.4j, 0.3 - 0.4j], dt=1.0)
    # The undelayed basis covers the feedthrough sample h(0) too: ISE is rounding
    # of ||h||^2 - ||c||^2 with ||h||^2 ~ 0.5.
    assert kt.ise_from_system(basis, DISCRETE_SYSTEM) < 1e-14


def test_matched_delayed_basis_misses_only_the_feedthrough():
    basis = kt.KautzBasis([0.6, 0.3 + 0.4j, 0.3 - 0.4j], dt=1.0, delayed=True)
    # Delayed sequences vanish at k = 0; the strictly proper part G - D is in their
    # span, so the ISE is exactly h(0)^2 = D^2 = 0.25 (rounding ~1e-16).
    np.testing.assert_allclose(kt.ise_from_system(basis, DISCRETE_SYSTEM), 0.25, rtol=1e-13)


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    ("basis", "system"),
    [
        pytest.param(
            kt.KautzBasis([-1.0]), ([1.0], [1.0, -0.5], 0.1), id="continuous-basis-discrete-system"
        ),
        pytest.param(
            kt.KautzBasis([0.5], dt=0.1), ([1.0], [1.0, 1.0]), id="discrete-basis-continuous-system"
        ),
        pytest.param(
            kt.KautzBasis([0.5], dt=0.1), ([1.0], [1.0, -0.5], 0.2), id="other-sampling-period"
        ),
    ],
)
def test_system_with_other_dt_raises(basis, system):
    with pytest.raises(DataError, match="the system has dt = .* but the basis has dt"):
        kt.coefficients_from_system(basis, system)


@pytest.mark.parametrize(
    ("basis", "system"),
    [
        pytest.param(kt.KautzBasis([-1.0]), ([1.0], [1.0, -1.0]), id="continuous-unstable"),
        pytest.param(kt.KautzBasis([-1.0]), ([1.0], [1.0, 0.0, 1.0]), id="continuous-oscillator"),
        pytest.param(
            kt.KautzBasis([0.5], dt=1.0), ([1.0], [1.0, -1.5], 1.0), id="discrete-unstable"
        ),
        pytest.param(
            kt.KautzBasis([0.5], dt=1.0), ([1.0], [1.0, -1.0], 1.0), id="discrete-integrator"
        ),
    ],
)
def test_unstable_system_raises(basis, system):
    with pytest.raises(DataError, match="the system is not stable"):
        kt.coefficients_from_system(basis, system)


def test_unstable_system_raises_in_ise():
    with pytest.raises(DataError, match="the system is not stable"):
        kt.ise_from_system(kt.KautzBasis([-1.0]), ([1.0], [1.0, -1.0]))


def test_improper_system_raises():
    with pytest.raises(DataError, match="improper"):
        kt.coefficients_from_system(kt.KautzBasis([-1.0]), ([1.0, 0.0, 1.0], [1.0, 1.0]))


def test_mimo_system_raises():
    A, B, C, D = -np.eye(2), np.eye(2), np.eye(2), np.zeros((2, 2))
    with pytest.raises(DimensionError, match="only SISO systems"):
        kt.coefficients_from_system(kt.KautzBasis([-1.0]), (A, B, C, D))


def test_unknown_system_type_raises():
    with pytest.raises(DataError, match="system must be a scipy.signal lti"):
        kt.coefficients_from_system(kt.KautzBasis([-1.0]), "1/(s+1)")


def test_non_finite_system_raises():
    system = (np.array([[-1.0]]), np.array([[1.0]]), np.array([[np.nan]]), np.array([[0.0]]))
    with pytest.raises(DataError, match="system matrix C contains NaN"):
        kt.coefficients_from_system(kt.KautzBasis([-1.0]), system)


# ============================================================================ projection of samples
@pytest.mark.parametrize("name", BASIS_IDS)
def test_simpson_projection_equals_sylvester(name):
    basis = BASES[name]()
    t, h = sampled_main(t_end=40.0, n=4001)
    # Simpson at dt = 0.01: the end-point error term dt^4/180 |(hK)'''(0)| =
    # dt^4/180 * 6 |K(0)| <= 1e-9 dominates (h ~ t^3 near 0); the record covers
    # the decay (e^{-0.5 * 40} * e^{-0.5 * 40}).  Criterion: ~1e-8.
    c = kt.project(basis, t, h)
    np.testing.assert_allclose(
        c, kt.coefficients_from_system(basis, main_system()), rtol=0, atol=1e-8
    )


@pytest.mark.parametrize("name", ["matched", "laguerre_a1_N8"])
def test_simpson_projection_on_non_uniform_grid(name):
    rng = np.random.default_rng(4)
    basis = BASES[name]()
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.005, 0.015, 4000))])  # ends near t = 40
    h = impulse_response((main_system().num, main_system().den), t)
    # Non-uniform Simpson keeps an odd error term ~(h1 - h0) h^3 f''' per pair of
    # intervals that no longer cancels; with random spacings it sums to ~3e-8 here.
    c = kt.project(basis, t, h)
    np.testing.assert_allclose(
        c, kt.coefficients_from_system(basis, main_system()), rtol=0, atol=3e-7
    )


@pytest.mark.parametrize("name", ["matched", "matched_pair_first"])
def test_lstsq_is_exact_for_system_in_span_on_short_record(name):
    basis = BASES[name]()
    t, h = sampled_main(t_end=5.0, n=501)  # far from decayed: quadrature would be wrong
    c = kt.project(basis, t, h, method="lstsq")
    # h lies in the span; least squares on 501 samples recovers c to rounding of a
    # well-conditioned 501x4 problem (~1e-14).
    np.testing.assert_allclose(
        c, kt.coefficients_from_system(basis, main_system()), rtol=0, atol=1e-12
    )


def test_lstsq_recovers_any_combination_on_short_record():
    rng = np.random.default_rng(8)
    basis = kt.KautzBasis(B_POLES)
    c_true = rng.standard_normal(basis.n_functions)
    t = np.linspace(0.0, 3.0, 301)
    h = c_true @ basis.evaluate(t)
    # Exact data in the span: least-squares rounding only.
    np.testing.assert_allclose(kt.project(basis, t, h, method="lstsq"), c_true, rtol=0, atol=1e-11)


def test_quadrature_on_short_record_is_truncated_projection():
    # The counterpart of the lstsq test: on [0, 3] the functions have not decayed,
    # so the quadrature coefficients are the finite-horizon inner products, which
    # differ from c by the non-identity finite Gram matrix I - e^{AT}e^{A^T T}.
    rng = np.random.default_rng(8)
    basis = kt.KautzBasis(B_POLES)
    c_true = rng.standard_normal(basis.n_functions)
    t = np.linspace(0.0, 3.0, 3001)
    c = kt.project(basis, t, c_true @ basis.evaluate(t))
    expm = scipy.linalg.expm(basis.A * 3.0)
    gram_T = np.eye(basis.n_functions) - expm @ expm.T  # kautz-math.md 2.3
    # Simpson at dt = 1e-3 on O(1) smooth functions: ~1e-12.
    np.testing.assert_allclose(c, gram_T @ c_true, rtol=0, atol=1e-10)


def test_lstsq_step_kind_recovers_combination_of_step_functions():
    rng = np.random.default_rng(9)
    basis = kt.LaguerreBasis(pole=-1.5, n=5)
    c_true = rng.standard_normal(basis.n_functions)
    t = np.linspace(0.0, 4.0, 401)
    y = c_true @ basis.step_functions(t)
    # Exact data in the span of the step functions: rounding only.
    np.testing.assert_allclose(
        kt.project(basis, t, y, kind="step", method="lstsq"), c_true, rtol=0, atol=1e-10
    )


@pytest.mark.parametrize("name", BASIS_IDS)
def test_step_route_equals_impulse_route(name):
    basis = BASES[name]()
    t, h = sampled_main(n=2001)
    _, y = sampled_main(n=2001, kind="step")
    c_impulse = kt.project(basis, t, h)
    c_step = kt.project(basis, t, y, kind="step")
    # Acceptance criterion < 1e-8 (noise-free).  At dt = 0.01 each route is within
    # ~1e-9 of the Sylvester coefficients (Simpson end-point term, see above).
    np.testing.assert_allclose(c_step, c_impulse, rtol=0, atol=1e-8)


@pytest.mark.parametrize("name", BASIS_IDS)
def test_step_route_equals_sylvester(name):
    basis = BASES[name]()
    t, y = sampled_main(t_end=40.0, n=4001, kind="step")
    # Integration by parts: boundary terms are exact, the remaining integral is
    # Simpson on y K (smooth, y(0) = 0): same ~1e-9 error budget as the impulse route.
    c = kt.project(basis, t, y, kind="step")
    np.testing.assert_allclose(
        c, kt.coefficients_from_system(basis, main_system()), rtol=0, atol=1e-8
    )


def test_step_route_with_nonzero_start():
    # A step record that starts after t = 0 uses the y(t0) K(t0) boundary term.
    basis = kt.KautzBasis(MAIN_POLES)
    t, y = sampled_main(t_end=40.0, n=4001, kind="step")
    _, h = sampled_main(t_end=40.0, n=4001)
    c_step = kt.project(basis, t[500:], y[500:], kind="step")
    c_impulse = kt.project(basis, t[500:], h[500:])
    # Both estimate int_{5}^{40} h K dt; Simpson error ~1e-10 each.
    np.testing.assert_allclose(c_step, c_impulse, rtol=0, atol=1e-8)


@pytest.mark.parametrize("method", ["quadrature", "lstsq"])
@pytest.mark.parametrize("kind", ["impulse", "step"])
def test_many_records_equal_row_by_row(kind, method):
    rng = np.random.default_rng(12)
    basis = kt.LaguerreBasis(pole=-1.0, n=6)
    t, y = sampled_main(n=901, kind=kind)
    records = y + 0.01 * rng.standard_normal((7, t.size))
    batch = kt.project(basis, t, records, kind=kind, method=method)
    assert batch.shape == (7, 6)
    rows = np.array([kt.project(basis, t, r, kind=kind, method=method) for r in records])
    # Same arithmetic, different BLAS blocking: rounding only.
    np.testing.assert_allclose(batch, rows, rtol=0, atol=1e-13)


@pytest.mark.parametrize("kind", ["impulse", "step"])
def test_many_records_equal_row_by_row_discrete(kind):
    rng = np.random.default_rng(13)
    basis = kt.LaguerreBasis(pole=0.5, n=4, dt=0.1)
    t = 0.1 * np.arange(200)
    records = rng.standard_normal((5, t.size))
    batch = kt.project(basis, t, records, kind=kind)
    rows = np.array([kt.project(basis, t, r, kind=kind) for r in records])
    np.testing.assert_allclose(batch, rows, rtol=0, atol=1e-13)


def test_discrete_projection_is_plain_sum():
    basis = kt.KautzBasis([0.6, 0.3 + 0.4j, 0.3 - 0.4j], dt=0.5)
    t = 0.5 * np.arange(300)
    h = discrete_pulse((*DISCRETE_SYSTEM[:2], 0.5), t.size)
    # Exact in l2 (matched poles): plain sums of exact samples, rounding ~1e-16.
    np.testing.assert_allclose(
        kt.project(basis, t, h),
        kt.coefficients_from_system(basis, (*DISCRETE_SYSTEM[:2], 0.5)),
        rtol=0,
        atol=1e-14,
    )


@pytest.mark.parametrize("delayed", [False, True], ids=["undelayed", "delayed"])
def test_discrete_step_route_equals_impulse_route(delayed):
    basis = kt.LaguerreBasis(pole=0.4, n=5, dt=1.0, delayed=delayed)
    k = np.arange(300.0)
    h = discrete_pulse(DISCRETE_SYSTEM, k.size)
    y = np.cumsum(h)
    # The step route differences the record exactly: rounding of a cumulative sum.
    np.testing.assert_allclose(
        kt.project(basis, k, y, kind="step"), kt.project(basis, k, h), rtol=0, atol=1e-13
    )


def test_discrete_lstsq_equals_projection_on_long_record():
    basis = kt.LaguerreBasis(pole=0.4, n=5, dt=1.0)
    k = np.arange(300.0)
    h = discrete_pulse(DISCRETE_SYSTEM, k.size)
    # 0.4^600: the finite Gram is I to rounding, so least squares = projection.
    np.testing.assert_allclose(
        kt.project(basis, k, h, method="lstsq"), kt.project(basis, k, h), rtol=0, atol=1e-13
    )


@pytest.mark.parametrize("kind", ["impulse", "step"])
@pytest.mark.parametrize(
    "k",
    [np.arange(0.0, 40.0, 2.0), np.arange(3.0, 40.0), np.array([0.0, 1.0, 2.0, 4.0, 5.0])],
    ids=["every-other-sample", "starts-at-k=3", "one-gap"],
)
def test_discrete_record_that_is_not_the_whole_sequence_raises(k, kind):
    # Regression: plain sums over a record that skips samples or starts after
    # k = 0 used to return wrong coefficients silently for kind='impulse'.
    basis = kt.LaguerreBasis(pole=0.4, n=3, dt=1.0)
    with pytest.raises(DataError, match=f"a discrete {kind} record must hold consecutive samples"):
        kt.project(basis, k, np.ones(k.size), kind=kind)


def test_discrete_lstsq_accepts_a_sparse_grid():
    basis = kt.KautzBasis([0.6, 0.3 + 0.4j, 0.3 - 0.4j], dt=1.0)
    k = np.arange(0.0, 60.0, 2.0)
    h = discrete_pulse(DISCRETE_SYSTEM, 60)[::2]
    # h is in the span (matched undelayed basis): least squares on any 30 samples
    # recovers the exact coefficients, to rounding.
    np.testing.assert_allclose(
        kt.project(basis, k, h, method="lstsq"),
        kt.coefficients_from_system(basis, DISCRETE_SYSTEM),
        rtol=0,
        atol=1e-12,
    )


# ---------------------------------------------------------------------------- approximate
def test_approximate_fields():
    basis = kt.LaguerreBasis(pole=-1.0, n=8)
    t, h = sampled_main(n=2001)
    res = kt.approximate(basis, t, h)
    assert isinstance(res, kt.Approximation)
    assert isinstance(res.model, kt.KautzModel)
    assert res.kind == "impulse"
    np.testing.assert_array_equal(res.model.coefficients, kt.project(basis, t, h))
    yhat = res.model.impulse(t)
    # The reported errors are the metrics of the model on the data grid.
    assert res.ise == pytest.approx(kt.ise(t, h, yhat), rel=1e-12)
    assert res.mse == pytest.approx(kt.mse(h, yhat), rel=1e-12)
    assert res.fit_percent == pytest.approx(kt.fit_percent(h, yhat), rel=1e-12)


def test_approximate_step_kind_reports_step_errors():
    basis = kt.LaguerreBasis(pole=-2.0, n=8)
    t, y = sampled_main(n=2001, kind="step")
    res = kt.approximate(basis, t, y, kind="step")
    assert res.kind == "step"
    assert res.fit_percent == pytest.approx(kt.fit_percent(y, res.model.step(t)), rel=1e-12)


def test_approximate_matched_basis_is_perfect():
    t, h = sampled_main(n=2001)
    res = kt.approximate(kt.KautzBasis(MAIN_POLES), t, h, method="lstsq")
    # Exact representation: errors are rounding of O(0.1) values.
    assert res.fit_percent == pytest.approx(100.0, abs=1e-9)
    assert res.ise < 1e-25
    assert res.mse < 1e-25


def test_approximation_to_dict():
    t, h = sampled_main(n=2001)
    res = kt.approximate(kt.KautzBasis(MAIN_POLES), t, h)
    d = res.to_dict()
    assert set(d) == {"coefficients", "poles", "dt", "kind", "ise", "mse", "fit_percent", "dc_gain"}
    assert d["kind"] == "impulse"
    assert d["dt"] == 0.0
    assert d["coefficients"] == res.model.coefficients.tolist()
    assert d["poles"][2] == [-0.5, W]
    assert d["dc_gain"] == res.model.dc_gain


def test_approximation_is_frozen():
    t, h = sampled_main(n=201)
    res = kt.approximate(kt.LaguerreBasis(pole=-1.0, n=2), t, h)
    with pytest.raises(AttributeError):
        res.ise = 0.0


def test_approximate_rejects_many_records():
    t, h = sampled_main(n=201)
    with pytest.raises(DimensionError, match="approximate\\(\\) takes one record"):
        kt.approximate(kt.LaguerreBasis(pole=-1.0, n=2), t, np.vstack([h, h]))


# ---------------------------------------------------------------------------- projection errors
BASIS_ERR = kt.LaguerreBasis(pole=-1.0, n=3)
T_ERR = np.linspace(0.0, 5.0, 51)


def test_nan_in_record_raises():
    h = np.ones(T_ERR.size)
    h[7] = np.nan
    with pytest.raises(DataError, match="h contains a non-finite value .* at index 7"):
        kt.project(BASIS_ERR, T_ERR, h)


def test_inf_in_record_raises():
    h = np.ones((2, T_ERR.size))
    h[1, 3] = np.inf
    with pytest.raises(DataError, match=r"h contains a non-finite value .* at index \(1, 3\)"):
        kt.project(BASIS_ERR, T_ERR, h)


def test_nan_in_time_raises():
    t = T_ERR.copy()
    t[4] = np.nan
    with pytest.raises(DataError, match="t contains a non-finite value"):
        kt.project(BASIS_ERR, t, np.ones(t.size))


def test_unequal_lengths_raise():
    with pytest.raises(DimensionError, match="h has 50 samples per record but t has 51"):
        kt.project(BASIS_ERR, T_ERR, np.ones(50))


@pytest.mark.parametrize(
    "t",
    [np.array([0.0, 1.0, 1.0, 2.0]), np.array([0.0, 2.0, 1.0, 3.0])],
    ids=["repeated", "decreasing"],
)
def test_non_increasing_time_raises(t):
    with pytest.raises(DataError, match="t must be strictly increasing"):
        kt.project(BASIS_ERR, t, np.ones(t.size))


def test_unknown_kind_raises():
    with pytest.raises(DataError, match="kind must be one of 'impulse', 'step'; got 'ramp'"):
        kt.project(BASIS_ERR, T_ERR, np.ones(T_ERR.size), kind="ramp")


def test_unknown_method_raises():
    with pytest.raises(DataError, match="method must be one of 'quadrature', 'lstsq'; got 'ridge'"):
        kt.project(BASIS_ERR, T_ERR, np.ones(T_ERR.size), method="ridge")


def test_unknown_rule_raises():
    with pytest.raises(DataError, match="rule must be 'simpson' or 'trapezoid', got 'gauss'"):
        kt.project(BASIS_ERR, T_ERR, np.ones(T_ERR.size), rule="gauss")


def test_three_dimensional_records_raise():
    with pytest.raises(DimensionError, match="h must be 1-D .* or 2-D"):
        kt.project(BASIS_ERR, T_ERR, np.ones((2, 2, T_ERR.size)))


def test_single_sample_raises():
    with pytest.raises(DimensionError, match="t needs at least 2 samples, got 1"):
        kt.project(BASIS_ERR, [0.0], [1.0])


def test_discrete_record_off_grid_raises():
    basis = kt.LaguerreBasis(pole=0.5, n=2, dt=0.1)
    with pytest.raises(DataError, match="not a multiple of the sampling period"):
        kt.project(basis, [0.0, 0.1, 0.15], [1.0, 0.5, 0.2])


# ============================================================================ impulse_to_step
def test_impulse_to_step_matches_analytic_step():
    t, h = sampled_main(n=2001)
    _, y = sampled_main(n=2001, kind="step")
    # Cumulative Simpson at dt = 0.01: O(dt^4) per interval, observed 2.4e-9.
    np.testing.assert_allclose(kt.impulse_to_step(t, h), y, rtol=0, atol=1e-8)


def test_impulse_to_step_is_exact_for_quadratics_on_non_uniform_grid():
    rng = np.random.default_rng(21)
    t = 1.0 + np.concatenate([[0.0], np.cumsum(rng.uniform(0.01, 0.05, 200))])
    h = 1.0 + 2.0 * t - 3.0 * t**2
    expected = (t + t**2 - t**3) - (t[0] + t[0] ** 2 - t[0] ** 3)  # integral from t[0]
    # The parabola through three samples is exact for quadratics: rounding only.
    np.testing.assert_allclose(kt.impulse_to_step(t, h), expected, rtol=0, atol=1e-11)


def test_impulse_to_step_with_noise():
    rng = np.random.default_rng(22)
    t, h = sampled_main(n=2001)
    _, y = sampled_main(n=2001, kind="step")
    sigma = 1e-3
    error = kt.impulse_to_step(t, h + sigma * rng.standard_normal(t.size)) - y
    # Integrated white noise is a random walk: its std at t = 20 is
    # sigma * sqrt(dt * t) ~ 4.5e-4 (x1.05 for Simpson's weights).  Allow 4 std
    # for the maximum over the path.
    assert np.max(np.abs(error)) < 4 * 1.05 * sigma * np.sqrt(0.01 * 20.0)


def test_impulse_to_step_many_records():
    rng = np.random.default_rng(23)
    t = np.linspace(0.0, 2.0, 41)
    h = rng.standard_normal((3, t.size))
    rows = np.array([kt.impulse_to_step(t, r) for r in h])
    np.testing.assert_allclose(kt.impulse_to_step(t, h), rows, rtol=0, atol=1e-15)


def test_impulse_to_step_needs_three_samples():
    with pytest.raises(DimensionError, match="t needs at least 3 samples"):
        kt.impulse_to_step([0.0, 1.0], [1.0, 1.0])


def test_impulse_to_step_rejects_nan():
    with pytest.raises(DataError, match="h contains a non-finite value"):
        kt.impulse_to_step([0.0, 1.0, 2.0], [1.0, np.nan, 1.0])


# ============================================================================ step_to_impulse
def test_step_to_impulse_is_exact_for_cubics():
    t = np.linspace(0.0, 2.0, 201)
    y = 0.3 - 1.2 * t + 0.7 * t**2 + 0.25 * t**3
    # A cubic Savitzky-Golay fit reproduces a cubic exactly, edges included
    # (mode='interp'); the derivative is then exact to rounding of O(1) values / dt.
    np.testing.assert_allclose(
        kt.step_to_impulse(t, y), -1.2 + 1.4 * t + 0.75 * t**2, rtol=0, atol=1e-10
    )


def test_step_to_impulse_matches_analytic_impulse():
    t, h = sampled_main(n=2001)
    _, y = sampled_main(n=2001, kind="step")
    est = kt.step_to_impulse(t, y)
    # Default window 41 samples (0.4 s): cubic-fit bias ~ y^(5) (0.2 s)^4 / 30 ~ 2e-5
    # in the interior (observed 1.7e-5); the edge fits extrapolate and are not tested.
    np.testing.assert_allclose(est[50:-50], h[50:-50], rtol=0, atol=1e-4)


def test_step_to_impulse_is_the_savitzky_golay_derivative():
    t = np.linspace(0.0, 10.0, 1001)
    spike = np.zeros(t.size)
    spike[500] = 1.0
    coeffs = scipy.signal.savgol_coeffs(21, 3, deriv=1, delta=0.01)  # convolution order
    # The response to a unit spike is the filter's impulse response, i.e. its
    # convolution coefficients: a linear filter applied exactly (values O(1) to O(10)).
    out = kt.step_to_impulse(t, spike, window=21)
    np.testing.assert_allclose(out[490:511], coeffs, rtol=1e-12, atol=1e-12)


def test_step_to_impulse_smooths_noise():
    rng = np.random.default_rng(24)
    t, h = sampled_main(n=2001)
    _, y = sampled_main(n=2001, kind="step")
    sigma = 1e-3
    noisy = y + sigma * rng.standard_normal(t.size)
    error = (kt.step_to_impulse(t, noisy) - h)[50:-50]
    gain = np.linalg.norm(scipy.signal.savgol_coeffs(41, 3, deriv=1, delta=0.01))
    # White noise passes the derivative filter with std sigma * ||coeffs|| (3.3e-3);
    # with the bias (< 1e-4) the RMS error is well inside twice that, while plain
    # finite differences give sigma / (sqrt(2) dt) ~ 0.07.
    rms = np.sqrt(np.mean(error**2))
    assert rms < 2 * sigma * gain + 1e-4
    naive = np.sqrt(np.mean((np.gradient(noisy, t) - h)[50:-50] ** 2))
    assert rms < naive / 10


def test_step_to_impulse_non_uniform_grid_uses_finite_differences():
    rng = np.random.default_rng(25)
    t = np.sort(rng.uniform(0.0, 5.0, 300))
    y = 2.0 - 0.5 * t
    # numpy.gradient is exact for linear functions on any grid.
    np.testing.assert_allclose(kt.step_to_impulse(t, y), -0.5, rtol=0, atol=1e-10)


def test_step_to_impulse_many_records():
    rng = np.random.default_rng(26)
    t = np.linspace(0.0, 5.0, 301)
    y = rng.standard_normal((3, t.size))
    rows = np.array([kt.step_to_impulse(t, r) for r in y])
    np.testing.assert_allclose(kt.step_to_impulse(t, y), rows, rtol=0, atol=1e-12)


def test_step_to_impulse_window_longer_than_record_raises():
    t = np.linspace(0.0, 1.0, 11)
    with pytest.raises(DataError, match="window = 13 is longer than the record"):
        kt.step_to_impulse(t, t, window=13)


def test_step_to_impulse_polyorder_too_large_raises():
    t = np.linspace(0.0, 1.0, 101)
    with pytest.raises(DataError, match="polyorder = 5 must be smaller than window = 5"):
        kt.step_to_impulse(t, t, window=5, polyorder=5)


def test_step_to_impulse_rejects_unequal_lengths():
    with pytest.raises(DimensionError, match="y has 4 samples per record but t has 5"):
        kt.step_to_impulse(np.arange(5.0), np.arange(4.0))
