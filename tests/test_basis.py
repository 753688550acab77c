"""Continuous-time Kautz and Laguerre bases (kautz-math.md sections 1, 2 and 9.1, 9.4).

Oracles: the closed forms of section 1.4, an independent implementation of the
product formulas of section 1.3 (written here from the note, not from the library),
scipy.signal.impulse/step of every function's transfer function, scipy.linalg.expm,
Simpson quadrature on a fine grid, and the reference values printed in section 9.1.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.signal
import scipy.special

import kautztwin as kt
from kautztwin._quadrature import quadrature_weights
from kautztwin.exceptions import (
    DataError,
    DimensionError,
    KautzTwinError,
    PoleError,
    UnstableModelError,
)

# ---------------------------------------------------------------------------- pole sets
# A basis is described here by its blocks in order: ("real", p) is the real pole
# s = -p, ("pair", sigma, omega) the pair s = -sigma +- j omega (kautz-math.md 0).


def poles_from_blocks(blocks):
    """Pole locations in the API's form: each pair as (p, conj p), block order kept."""
    poles = []
    for block in blocks:
        if block[0] == "real":
            poles.append(-block[1])
        else:
            _, sigma, omega = block
            poles += [complex(-sigma, omega), complex(-sigma, -omega)]
    return poles


REFERENCE_BLOCKS = {
    "a": [("real", 1.1), ("real", 0.8), ("real", 2.1)],
    "b": [("real", 1.1), ("real", 0.8), ("real", 1.5), ("pair", 0.8, 2.0)],
    "b_prime": [("pair", 0.8, 2.0), ("real", 1.1), ("real", 0.8), ("real", 1.5)],
    "c_laguerre_a1_N8": [("real", 1.0)] * 8,
    "d": [("pair", 0.8, 2.0), ("pair", 0.5, 1.0), ("real", 1.2)],
}
REFERENCE_IDS = list(REFERENCE_BLOCKS)


def random_blocks(seed):
    """A random mix of real poles and complex pairs (1 to 4 blocks, N <= 8).

    Rates lie in [0.3, 2] and frequencies in [0.2, 3]: slow enough that every
    function has decayed below 1e-20 by t = 80 (e^{-0.3 * 80} ~ 4e-11, squared
    in the Gram entries), and fast/oscillating enough to be a real test, while the
    Simpson error on a 1e-3 grid stays below ~4e-10 (checked on these 100 seeds).
    """
    rng = np.random.default_rng(seed)
    blocks = []
    for _ in range(int(rng.integers(1, 5))):
        if rng.random() < 0.5:
            blocks.append(("real", float(rng.uniform(0.3, 2.0))))
        else:
            blocks.append(("pair", float(rng.uniform(0.3, 1.5)), float(rng.uniform(0.2, 3.0))))
    return blocks


RANDOM_SEEDS = [pytest.param(seed, id=f"random{seed:03d}") for seed in range(100)]
LAGUERRE_NS = [1, 2, 3, 4, 5, 8, 10, 15, 20, 25, 30]


def product_formula(blocks, s):
    """K(s) from the Laplace-domain product formulas of kautz-math.md 1.3 (independent oracle)."""
    s = complex(s)
    prefix = 1.0 + 0.0j  # G_j(s), the product of the all-pass factors of earlier blocks
    out = []
    for block in blocks:
        if block[0] == "real":
            p = block[1]
            out.append(np.sqrt(2 * p) / (s + p) * prefix)
            prefix *= (s - p) / (s + p)
        else:
            _, sigma, omega = block
            b, c = 2 * sigma, sigma**2 + omega**2
            den = s**2 + b * s + c
            out.append(np.sqrt(2 * b) * s / den * prefix)
            out.append(np.sqrt(2 * b * c) / den * prefix)
            prefix *= (s**2 - b * s + c) / den
    return np.array(out)


@pytest.fixture(scope="module")
def grid80():
    """Uniform grid on [0, 80] with dt = 1e-3 and its composite Simpson weights.

    kautz-math.md 9.4: Simpson at dt = 1e-3 gives Gram errors of ~3e-11 for the
    reference sets, well below the 1e-9 acceptance level; t = 80 is long enough
    for the slowest reference rate (0.5): e^{-2 * 0.5 * 80} ~ 2e-35.
    """
    t = np.linspace(0.0, 80.0, 80_001)
    return t, quadrature_weights(t, "simpson")


@pytest.fixture(scope="module")
def grid150_fine():
    """Uniform grid on [0, 150] with dt = 4e-4 for Laguerre bases up to N = 30.

    The Laguerre polynomial factor L_29(2t) delays the decay: at t = 80 the 30th
    function is still ~3e-5, at t = 150 it is ~3e-26.  Its oscillations also need
    the finer step: the Simpson Gram error is 7.6e-9 at dt = 1e-3 but ~2e-10 at
    dt = 4e-4 (error ~ dt^4).
    """
    t = np.linspace(0.0, 150.0, 375_001)
    return t, quadrature_weights(t, "simpson")


def numerical_gram(basis, grid):
    t, w = grid
    K = basis.evaluate(t)
    return (K * w) @ K.T


# ---------------------------------------------------------------------------- orthonormality
@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_gram_analytic_is_identity_reference(name):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    # Lyapunov solution of a well-conditioned N <= 8 problem: rounding ~1e-15 (9.1: <= 3.3e-15).
    np.testing.assert_allclose(basis.gram(), np.eye(basis.n_functions), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_gram_numerical_is_identity_reference(name, grid80):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    # Simpson at dt = 1e-3 on [0, 80]: error ~3e-11 (9.4); the acceptance level is 1e-9.
    np.testing.assert_allclose(
        numerical_gram(basis, grid80), np.eye(basis.n_functions), rtol=0, atol=1e-9
    )


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_lossless_identity_reference(name):
    A, B = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name])).state_space()
    # Holds exactly in exact arithmetic (2.3); entries are O(10), so rounding is ~1e-15.
    np.testing.assert_allclose(A + A.T + np.outer(B, B), 0.0, rtol=0, atol=1e-13)


@pytest.mark.parametrize("seed", RANDOM_SEEDS)
def test_gram_analytic_is_identity_random(seed):
    basis = kt.KautzBasis(poles_from_blocks(random_blocks(seed)))
    # Same Lyapunov rounding argument as for the reference sets (observed <= 1e-14).
    np.testing.assert_allclose(basis.gram(), np.eye(basis.n_functions), rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", RANDOM_SEEDS)
def test_gram_numerical_is_identity_random(seed, grid80):
    basis = kt.KautzBasis(poles_from_blocks(random_blocks(seed)))
    # Simpson dt = 1e-3 on [0, 80]; the pole ranges of random_blocks keep the
    # quadrature error below ~4e-10 (see its docstring), under the 1e-9 criterion.
    np.testing.assert_allclose(
        numerical_gram(basis, grid80), np.eye(basis.n_functions), rtol=0, atol=1e-9
    )


@pytest.mark.parametrize("seed", RANDOM_SEEDS[:20])
def test_lossless_identity_random(seed):
    A, B = kt.KautzBasis(poles_from_blocks(random_blocks(seed))).state_space()
    # Exact identity; entries are at most ~10, rounding ~1e-15.
    np.testing.assert_allclose(A + A.T + np.outer(B, B), 0.0, rtol=0, atol=1e-13)


@pytest.mark.parametrize("n", LAGUERRE_NS, ids=[f"N={n}" for n in LAGUERRE_NS])
def test_gram_analytic_is_identity_laguerre(n):
    basis = kt.LaguerreBasis(pole=-1.0, n=n)
    # A is one Jordan block, but the Lyapunov solver is backward stable: observed 1.3e-14 at N=30.
    np.testing.assert_allclose(basis.gram(), np.eye(n), rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", LAGUERRE_NS, ids=[f"N={n}" for n in LAGUERRE_NS])
def test_gram_numerical_is_identity_laguerre(n, grid150_fine):
    basis = kt.LaguerreBasis(pole=-1.0, n=n)
    # Simpson dt = 4e-4 on [0, 150]: error <= 2e-10 up to N = 30 (see grid150_fine).
    np.testing.assert_allclose(numerical_gram(basis, grid150_fine), np.eye(n), rtol=0, atol=1e-9)


def test_reordered_bases_are_related_by_an_orthogonal_matrix():
    # (b) and (b') span the same space (section 0): the cross-Gram X = <K_b, K_b'^T>,
    # which solves A X + X A'^T + B B'^T = 0, must be orthogonal.
    b = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS["b"]))
    bp = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS["b_prime"]))
    X = scipy.linalg.solve_sylvester(b.A, bp.A.T, -np.outer(b.B, bp.B))
    # Sylvester solve of a 5x5 well-conditioned problem: rounding ~1e-15.
    np.testing.assert_allclose(X @ X.T, np.eye(5), rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------- A, B and K(t)
# Reference values printed with 10 (A, B) or 12 (K) decimals in kautz-math.md 2.1/9.1;
# the tolerance is the rounding of the last printed digit (plus nothing else: the
# computation itself is accurate to ~1e-15).
A_REF = {
    "a": [[-1.1, 0, 0], [-1.8761663039, -0.8, 0], [-3.0397368307, -2.5922962794, -2.1]],
    "b": [
        [-1.1, 0, 0, 0, 0],
        [-1.8761663039, -0.8, 0, 0, 0],
        [-2.5690465157, -2.1908902300, -1.5, 0, 0],
        [-2.6532998323, -2.2627416998, -3.0983866770, -1.6, -2.1540659229],
        [0, 0, 0, 2.1540659229, 0],
    ],
}
B_REF = {
    "a": [1.4832396974, 1.2649110641, 2.0493901532],
    "b": [1.4832396974, 1.2649110641, 1.7320508076, 1.7888543820, 0.0],
}
K_REF = {
    "a": {
        0.5: [0.855754862175, -0.018208414292, -0.647111420772],
        1.0: [0.493727605464, -0.511903805776, -0.535693358780],
        2.0: [0.164347643082, -0.589602182646, 0.280654722603],
    },
    "b": {
        0.5: [0.855754862175, -0.018208414292, -0.528283199328, -0.782213668743, -0.166033895287],
        1.0: [0.493727605464, -0.511903805776, -0.562942559777, 0.324921492708, -0.449457199734],
        2.0: [0.164347643082, -0.589602182646, 0.218859572192, 0.111797188242, 0.702730834666],
    },
    "laguerre_a1_N4": {
        0.5: [0.857763884961, 0.0, -0.428881942480, -0.571842589974],
        1.0: [0.520260095023, -0.520260095023, -0.520260095023, -0.173420031674],
        2.0: [0.191392993021, -0.574178979062, 0.191392993021, 0.446583650382],
    },
}
K_BLOCKS = {**REFERENCE_BLOCKS, "laguerre_a1_N4": [("real", 1.0)] * 4}


@pytest.mark.parametrize("name", ["a", "b"])
def test_state_matrix_matches_reference(name):
    A = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name])).A
    np.testing.assert_allclose(A, A_REF[name], rtol=0, atol=0.5e-10 + 1e-15)


@pytest.mark.parametrize("name", ["a", "b"])
def test_initial_state_matches_reference(name):
    B = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name])).B
    np.testing.assert_allclose(B, B_REF[name], rtol=0, atol=0.5e-10 + 1e-15)


@pytest.mark.parametrize(
    ("name", "t"),
    [(name, t) for name in K_REF for t in (0.5, 1.0, 2.0)],
    ids=[f"{name}-t={t}" for name in K_REF for t in (0.5, 1.0, 2.0)],
)
def test_function_values_match_reference(name, t):
    basis = kt.KautzBasis(poles_from_blocks(K_BLOCKS[name]))
    K = basis.evaluate(np.array([t]))[:, 0]
    np.testing.assert_allclose(K, K_REF[name][t], rtol=0, atol=0.5e-12 + 1e-15)


def test_laguerre_matrices_closed_form():
    a, n = 1.7, 6
    basis = kt.LaguerreBasis(pole=-a, n=n)
    A_expected = -a * np.eye(n) - 2 * a * np.tril(np.ones((n, n)), k=-1)
    # Entries are products of two square roots of 2a: one rounding each, ~1e-15.
    np.testing.assert_allclose(basis.A, A_expected, rtol=1e-14, atol=0)
    np.testing.assert_allclose(basis.B, np.sqrt(2 * a) * np.ones(n), rtol=1e-15, atol=0)


def test_all_real_matrices_element_form():
    p = np.array([1.1, 0.8, 2.1, 0.35])
    basis = kt.KautzBasis(-p)
    A_expected = np.diag(-p) + np.tril(-2 * np.sqrt(np.outer(p, p)), k=-1)
    # Element form of 2.1 (case A); a few roundings per entry.
    np.testing.assert_allclose(basis.A, A_expected, rtol=1e-14, atol=0)
    np.testing.assert_allclose(basis.B, np.sqrt(2 * p), rtol=1e-15, atol=0)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_functions_start_at_b(name):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    # K(0) = e^{0} B is exactly B.
    np.testing.assert_array_equal(basis.evaluate(np.array([0.0, 1.0]))[:, 0], basis.B)


# ---------------------------------------------------------------------------- transfer functions
S_POINTS = [0.0, 0.5, 1j, 2.5j, 1 + 1j, 3 - 4j, 20j, -0.2 + 5j]


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_resolvent_equals_product_formula(name):
    blocks = REFERENCE_BLOCKS[name]
    basis = kt.KautzBasis(poles_from_blocks(blocks))
    for s in S_POINTS:
        resolvent = np.linalg.solve(s * np.eye(basis.n_functions) - basis.A, basis.B)
        # |K_i(s)| <= ~2 at these points, which stay away from the poles; a 5x5 solve
        # loses a few digits at most (9.1: agreement <= 4e-15).
        np.testing.assert_allclose(resolvent, product_formula(blocks, s), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_transfer_functions_equal_product_formula(name):
    blocks = REFERENCE_BLOCKS[name]
    tfs = kt.KautzBasis(poles_from_blocks(blocks)).transfer_functions()
    for s in S_POINTS:
        values = np.array([np.polyval(num, s) / np.polyval(den, s) for num, den in tfs])
        # Polynomials of degree <= 8 with O(10) coefficients evaluated at |s| <= 20:
        # the quotient keeps ~13 digits.
        np.testing.assert_allclose(values, product_formula(blocks, s), rtol=0, atol=1e-12)


RESOLVENT_CASES = [pytest.param(REFERENCE_BLOCKS[name], id=name) for name in REFERENCE_IDS] + [
    pytest.param(random_blocks(seed), id=f"random{seed:03d}") for seed in range(20)
]


@pytest.mark.parametrize("blocks", RESOLVENT_CASES)
def test_transfer_functions_equal_resolvent(blocks):
    basis = kt.KautzBasis(poles_from_blocks(blocks))
    tfs = basis.transfer_functions()
    for s in S_POINTS:
        values = np.array([np.polyval(num, s) / np.polyval(den, s) for num, den in tfs])
        resolvent = np.linalg.solve(s * np.eye(basis.n_functions) - basis.A, basis.B)
        # As above: |K_i(s)| <= ~3, both sides accurate to ~1e-14.
        np.testing.assert_allclose(values, resolvent, rtol=0, atol=1e-12)


def test_laguerre_transfer_function_closed_form():
    a, n = 2.0, 5
    tfs = kt.LaguerreBasis(pole=-a, n=n).transfer_functions()
    for i, (num, den) in enumerate(tfs):
        # L_i(s) = sqrt(2a) (s - a)^{i} / (s + a)^{i+1}: integer-valued polynomial
        # coefficients times sqrt(2a), built with a few roundings.
        expected_num = np.sqrt(2 * a) * np.poly([a] * i)
        np.testing.assert_allclose(num, expected_num, rtol=1e-14, atol=0)
        np.testing.assert_allclose(den, np.poly([-a] * (i + 1)), rtol=1e-14, atol=0)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_denominator_is_product_of_pole_factors(name):
    blocks = REFERENCE_BLOCKS[name]
    basis = kt.KautzBasis(poles_from_blocks(blocks))
    expected = np.array([1.0])
    for block in blocks:
        factor = (
            [1.0, block[1]]
            if block[0] == "real"
            else [1.0, 2 * block[1], block[1] ** 2 + block[2] ** 2]
        )
        expected = np.polymul(expected, factor)
    # np.poly of complex roots then real part: rounding relative to the largest coefficient.
    np.testing.assert_allclose(basis.denominator(), expected, rtol=1e-13, atol=1e-13)


# ---------------------------------------------------------------------------- time domain
@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_functions_equal_scipy_impulse_of_transfer_functions(name):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    t = np.linspace(0.0, 20.0, 401)
    K = basis.evaluate(t)
    for i, (num, den) in enumerate(basis.transfer_functions()):
        _, h = scipy.signal.impulse((num, den), T=t)
        # scipy simulates a controllable-canonical realisation with expm; both
        # sides are exact up to rounding (9.1: <= 1.3e-13 with a different oracle).
        np.testing.assert_allclose(K[i], h, rtol=0, atol=1e-11, err_msg=f"function {i}")


@pytest.mark.parametrize("a", [0.5, 1.0, 2.5])
def test_laguerre_closed_form(a):
    n = 10
    t = np.linspace(0.0, 15.0, 301)
    K = kt.LaguerreBasis(pole=-a, n=n).evaluate(t)
    expected = np.array(
        [
            np.sqrt(2 * a) * np.exp(-a * t) * scipy.special.eval_laguerre(i, 2 * a * t)
            for i in range(n)
        ]
    )
    # Values are O(sqrt(2a)); Laguerre recurrences and the blocked exponential
    # recursion are both accurate to ~1e-13 (9.1: <= 1.2e-13).
    np.testing.assert_allclose(K, expected, rtol=0, atol=1e-11)


@pytest.mark.parametrize("name", ["b_prime", "d"])
def test_first_pair_closed_form(name):
    _, sigma, omega = REFERENCE_BLOCKS[name][0]
    b, c = 2 * sigma, sigma**2 + omega**2
    t = np.linspace(0.0, 15.0, 301)
    K = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name])).evaluate(t)
    decay = np.exp(-sigma * t)
    k1 = np.sqrt(2 * b) * decay * (np.cos(omega * t) - sigma / omega * np.sin(omega * t))
    k2 = np.sqrt(2 * b * c) * decay * np.sin(omega * t) / omega
    # Elementary functions, O(1) values: agreement to rounding (9.1: <= 1.2e-13).
    np.testing.assert_allclose(K[0], k1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(K[1], k2, rtol=0, atol=1e-12)


def distinct_real_closed_form(p, t):
    """K_i(t) = sqrt(2 p_i) sum_k r_ik e^{-p_k t} (kautz-math.md 1.4)."""
    out = []
    for i in range(len(p)):
        total = np.zeros_like(t)
        for k in range(i + 1):
            num = np.prod([-p[k] - p[m] for m in range(i)])
            den = np.prod([p[m] - p[k] for m in range(i + 1) if m != k])
            total += num / den * np.exp(-p[k] * t)
        out.append(np.sqrt(2 * p[i]) * total)
    return np.array(out)


def test_distinct_real_closed_form():
    p = [1.1, 0.8, 2.1, 0.45]
    t = np.linspace(0.0, 15.0, 301)
    K = kt.KautzBasis([-x for x in p]).evaluate(t)
    # Partial fractions with residues up to ~50 that cancel at t = 0: the closed form
    # itself loses ~2 digits, so 1e-11 absolute (the values are O(1)).
    np.testing.assert_allclose(K, distinct_real_closed_form(p, t), rtol=0, atol=1e-11)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_jittered_grid_equals_uniform_grid(name):
    rng = np.random.default_rng(11)
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    t_uniform = np.linspace(0.0, 10.0, 201)
    extra = rng.uniform(0.0, 10.0, 150)  # makes the merged grid non-uniform
    t_jittered = np.concatenate([t_uniform, extra])
    order = np.argsort(t_jittered, kind="stable")
    K_jittered = basis.evaluate(t_jittered[order])
    shared = np.argsort(order)[: t_uniform.size]  # where the uniform points ended up
    # One expm per sample vs the blocked recursion: both exact up to ~1e-14.
    np.testing.assert_allclose(K_jittered[:, shared], basis.evaluate(t_uniform), rtol=0, atol=1e-12)


def test_jittered_grid_equals_closed_form():
    rng = np.random.default_rng(3)
    p = [1.1, 0.8, 2.1]
    t = np.sort(rng.uniform(0.0, 12.0, 300))
    K = kt.KautzBasis([-x for x in p]).evaluate(t)
    # Same accuracy argument as test_distinct_real_closed_form.
    np.testing.assert_allclose(K, distinct_real_closed_form(p, t), rtol=0, atol=1e-11)


def test_jittered_grid_equals_matrix_exponential():
    rng = np.random.default_rng(5)
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS["d"]))
    t = np.sort(rng.uniform(0.0, 8.0, 50))
    expected = np.array([scipy.linalg.expm(basis.A * tk) @ basis.B for tk in t]).T
    # Same algorithm (expm) per sample; identical to rounding.
    np.testing.assert_allclose(basis.evaluate(t), expected, rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    "t",
    [np.linspace(-2.0, 2.0, 41), np.array([-3.0, -1e-9, 0.0, 0.7, 1.9])],
    ids=["uniform", "non-uniform"],
)
def test_functions_vanish_before_zero(t):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS["b"]))
    K = basis.evaluate(t)
    np.testing.assert_array_equal(K[:, t < 0], 0.0)
    # The non-negative part is unaffected by the negative samples.
    np.testing.assert_allclose(K[:, t >= 0], basis.evaluate(t[t >= 0]), rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    "t",
    [np.linspace(-2.0, 2.0, 41), np.array([-3.0, -0.5, 0.0, 0.7])],
    ids=["uniform", "non-uniform"],
)
def test_step_functions_vanish_before_zero(t):
    S = kt.LaguerreBasis(pole=-1.0, n=4).step_functions(t)
    np.testing.assert_array_equal(S[:, t < 0], 0.0)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_step_functions_equal_cumulative_integral(name):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    t = np.linspace(0.0, 20.0, 20_001)
    integral = scipy.integrate.cumulative_simpson(basis.evaluate(t), x=t, axis=-1, initial=0.0)
    # The oracle's error is dominated by the first intervals, where the high
    # Laguerre functions have large derivatives (|d^3 K/dt^3 (0)| ~ 1e3 for N = 8):
    # a local error ~ dt^4 |K'''| / 24 ~ 4e-11 at dt = 1e-3 (2e-8 seen at dt = 5e-3).
    np.testing.assert_allclose(basis.step_functions(t), integral, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_step_functions_equal_scipy_step(name):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    t = np.linspace(0.0, 20.0, 401)
    S = basis.step_functions(t)
    for i, (num, den) in enumerate(basis.transfer_functions()):
        _, y = scipy.signal.step((num, den), T=t)
        # Both exact up to rounding; A^{-1} of the network matrix is well conditioned.
        np.testing.assert_allclose(S[i], y, rtol=0, atol=1e-11, err_msg=f"function {i}")


@pytest.mark.parametrize("name", REFERENCE_IDS)
def test_step_functions_settle_at_static_gains(name):
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS[name]))
    S_end = basis.step_functions(np.array([0.0, 200.0]))[:, -1]
    static = np.array(
        [num[-1] / den[-1] if num.size else 0.0 for num, den in basis.transfer_functions()]
    )
    # At t = 200 the transient e^{-0.5 * 200} is ~1e-44: S(200) = K(0) = -A^{-1} B exactly.
    np.testing.assert_allclose(S_end, static, rtol=0, atol=1e-13)


# ---------------------------------------------------------------------------- object behaviour
def test_poles_are_in_block_order_with_positive_imaginary_part_first():
    basis = kt.KautzBasis([-0.8 - 2j, -1.1, -0.8 + 2j, -0.5])
    np.testing.assert_array_equal(basis.poles, [-0.8 + 2j, -0.8 - 2j, -1.1, -0.5])
    assert basis.block_kinds == ("pair", "real", "real")
    assert basis.n_functions == 4
    assert basis.n_pairs == 1


def test_conjugate_listed_later_is_paired():
    a = kt.KautzBasis([-0.8 + 2j, -1.1, -0.8 - 2j])
    b = kt.KautzBasis([-0.8 + 2j, -0.8 - 2j, -1.1])
    # Same blocks in the same order: identical matrices.
    np.testing.assert_array_equal(a.A, b.A)


def test_laguerre_is_kautz_with_repeated_pole():
    lag = kt.LaguerreBasis(pole=-0.7, n=5)
    kautz = kt.KautzBasis([-0.7] * 5)
    np.testing.assert_array_equal(lag.A, kautz.A)
    np.testing.assert_array_equal(lag.B, kautz.B)
    assert lag.pole == -0.7
    assert lag.allclose(kautz)


def test_continuous_basis_flags():
    basis = kt.KautzBasis([-1.0, -2.0])
    assert basis.dt == 0.0
    assert not basis.is_discrete
    assert not basis.delayed


def test_arrays_are_read_only():
    basis = kt.KautzBasis(poles_from_blocks(REFERENCE_BLOCKS["b"]))
    for arr in (basis.A, basis.B, basis.poles):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 1.0


def test_setattr_raises():
    basis = kt.LaguerreBasis(pole=-1.0, n=3)
    with pytest.raises(AttributeError, match="immutable"):
        basis.dt = 1.0


def test_state_space_returns_independent_copies():
    basis = kt.LaguerreBasis(pole=-1.0, n=3)
    A, B = basis.state_space()
    A[0, 0] = 99.0
    B[0] = 99.0
    assert basis.A[0, 0] == -1.0
    assert basis.B[0] == np.sqrt(2.0)


def test_input_poles_are_copied():
    poles = np.array([-1.0, -2.0])
    basis = kt.KautzBasis(poles)
    poles[0] = -5.0
    np.testing.assert_array_equal(basis.poles, [-1.0, -2.0])


def test_with_poles_gives_new_basis():
    basis = kt.KautzBasis([-1.0, -2.0])
    other = basis.with_poles([-3.0])
    assert other.n_functions == 1
    assert basis.n_functions == 2
    assert not basis.allclose(other)


def test_allclose_tolerates_rounding_only():
    basis = kt.KautzBasis([-1.0, -0.5 + 2j, -0.5 - 2j])
    assert basis.allclose(kt.KautzBasis([-1.0 * (1 + 1e-13), -0.5 + 2j, -0.5 - 2j]))
    assert not basis.allclose(kt.KautzBasis([-1.001, -0.5 + 2j, -0.5 - 2j]))
    assert not basis.allclose(kt.KautzBasis([-0.5 + 2j, -0.5 - 2j, -1.0]))  # other order


def test_to_dict_lists_poles_as_pairs():
    d = kt.KautzBasis([-1.0, -0.5 + 2j, -0.5 - 2j]).to_dict()
    assert d == {"poles": [[-1.0, 0.0], [-0.5, 2.0], [-0.5, -2.0]], "dt": 0.0, "delayed": False}


def test_near_real_pole_counts_as_real():
    # |Im| below 1e-12 relative is rounding noise of a real pole.
    basis = kt.KautzBasis([-1.0 + 1e-14j, -2.0])
    assert basis.block_kinds == ("real", "real")


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "poles",
    [[-1.0, 0.0], [0.5], [1j, -1j], [-1.0, 0.2 + 1j, 0.2 - 1j]],
    ids=["zero", "positive", "imaginary-axis-pair", "unstable-pair"],
)
def test_unstable_continuous_pole_raises(poles):
    with pytest.raises(UnstableModelError, match=r"Re\(p\) < 0"):
        kt.KautzBasis(poles)


def test_unstable_laguerre_pole_raises():
    with pytest.raises(UnstableModelError, match=r"poles\[0\] = 0\.5 has Re >= 0"):
        kt.LaguerreBasis(pole=0.5, n=3)


@pytest.mark.parametrize(
    "poles",
    [[-1.0 + 2j], [-1.0 + 2j, -1.0 - 2.1j], [-1 + 2j, -1 + 2j], [-1.0, -1 - 2j]],
    ids=["single", "wrong-conjugate", "same-twice", "after-real"],
)
def test_unpaired_complex_pole_raises(poles):
    with pytest.raises(PoleError, match="no conjugate partner"):
        kt.KautzBasis(poles)


@pytest.mark.parametrize(
    "poles",
    [[np.nan], [-1.0, np.inf], [complex(np.nan, 1.0), complex(np.nan, -1.0)]],
    ids=["nan", "inf", "complex-nan"],
)
def test_non_finite_pole_raises(poles):
    with pytest.raises(PoleError, match="not finite"):
        kt.KautzBasis(poles)


@pytest.mark.parametrize("poles", [[], np.zeros((2, 2)) - 1], ids=["empty", "2-D"])
def test_empty_or_nested_poles_raise(poles):
    with pytest.raises(PoleError, match="non-empty 1-D"):
        kt.KautzBasis(poles)


def test_non_numeric_poles_raise():
    with pytest.raises(PoleError, match="must be numbers"):
        kt.KautzBasis(["fast", "slow"])


def test_pole_errors_are_kautztwin_errors():
    with pytest.raises(KautzTwinError):
        kt.KautzBasis([0.1])


def test_complex_laguerre_pole_raises():
    with pytest.raises(PoleError, match="must be real"):
        kt.LaguerreBasis(pole=-1 + 1j, n=3)


@pytest.mark.parametrize("n", [0, -2, 2.5, True], ids=["zero", "negative", "float", "bool"])
def test_invalid_laguerre_order_raises(n):
    with pytest.raises(PoleError, match="n must be a positive integer"):
        kt.LaguerreBasis(pole=-1.0, n=n)


def test_delayed_continuous_basis_raises():
    with pytest.raises(PoleError, match="delayed=True applies to discrete-time"):
        kt.KautzBasis([-1.0], delayed=True)


@pytest.mark.parametrize("dt", [-0.1, np.nan, np.inf], ids=["negative", "nan", "inf"])
def test_invalid_dt_raises(dt):
    with pytest.raises(DataError, match="dt must be 0"):
        kt.KautzBasis([-1.0], dt=dt)


def test_evaluate_nan_time_raises():
    basis = kt.LaguerreBasis(pole=-1.0, n=2)
    with pytest.raises(DataError, match=r"t contains a non-finite value .*nan.* at index 1"):
        basis.evaluate([0.0, np.nan, 1.0])


def test_evaluate_2d_time_raises():
    basis = kt.LaguerreBasis(pole=-1.0, n=2)
    with pytest.raises(DimensionError, match="t must be 1-D"):
        basis.evaluate(np.zeros((2, 3)))


@pytest.mark.parametrize("dt", [0.0, -1.0], ids=["zero", "negative"])
def test_discretize_needs_positive_dt(dt):
    basis = kt.LaguerreBasis(pole=-1.0, n=2)
    with pytest.raises(DataError if dt < 0 else PoleError, match="dt must be"):
        basis.discretize(dt)


def test_discretize_discrete_basis_raises():
    with pytest.raises(PoleError, match="continuous-time bases only"):
        kt.LaguerreBasis(pole=0.5, n=2, dt=0.1).discretize(0.1)


def test_a_basis_pickles_to_an_equal_immutable_copy():
    # what crosses to a worker process (the twin's MPC retuning): rebuilt as the original was
    import pickle

    from kautztwin.basis import KautzBasis, LaguerreBasis

    for basis in (LaguerreBasis(pole=-1.0, n=4),
                  KautzBasis([0.5 + 0.3j, 0.5 - 0.3j, 0.9], dt=0.1, delayed=True),
                  KautzBasis([-1.0, -2.0 + 1.0j, -2.0 - 1.0j])):
        copy = pickle.loads(pickle.dumps(basis))
        assert type(copy) is type(basis) and copy.dt == basis.dt
        for name in ("A", "B", "poles"):
            np.testing.assert_array_equal(getattr(copy, name), getattr(basis, name))
        with pytest.raises(AttributeError, match="immutable"):
            copy._dt = 1.0
