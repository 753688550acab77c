"""Discrete-time Kautz and Laguerre bases (kautz-math.md sections 3 and 9.3).

Oracles: the reference matrices and sequences of section 9.3, Wang's Laguerre
matrices, an independent implementation of the product formulas of section 3.1,
scipy.signal.dimpulse, direct summation, and the continuous basis it is matched to.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import kautztwin as kt
from kautztwin.exceptions import DataError, PoleError, UnstableModelError

# ---------------------------------------------------------------------------- pole sets
# Blocks: ("real", xi) is the pole z = xi, ("pair", x, y) the pair z = x +- j y.


def poles_from_blocks(blocks):
    poles = []
    for block in blocks:
        if block[0] == "real":
            poles.append(block[1])
        else:
            poles += [complex(block[1], block[2]), complex(block[1], -block[2])]
    return poles


E1 = 0.5 * np.exp(1j)
DISCRETE_BLOCKS = {
    # the three sets of kautz-math.md 9.3
    "real3": [("real", 0.5), ("real", -0.3), ("real", 0.7)],
    "mixed": [("real", 0.6), ("real", 0.2), ("pair", E1.real, E1.imag), ("real", 0.4)],
    "pair_first": [("pair", 0.3, 0.6), ("real", 0.8), ("real", 0.2)],
    # Wang's Laguerre example and the N = 3 example of 9.3
    "laguerre_0.6_N5": [("real", 0.6)] * 5,
    "real_then_pair": [("real", 0.6), ("pair", E1.real, E1.imag)],
}
DISCRETE_IDS = list(DISCRETE_BLOCKS)


def random_discrete_blocks(seed):
    """1 to 4 blocks; |xi| <= 0.9, so 0.9^(2 * 3000) underflows: 3000 samples are 'infinite'."""
    rng = np.random.default_rng(1000 + seed)
    blocks = []
    for _ in range(int(rng.integers(1, 5))):
        if rng.random() < 0.5:
            blocks.append(("real", float(rng.uniform(-0.9, 0.9))))
        else:
            r, phi = rng.uniform(0.1, 0.9), rng.uniform(0.1, np.pi - 0.1)
            blocks.append(("pair", float(r * np.cos(phi)), float(r * np.sin(phi))))
    return blocks


RANDOM_SEEDS = [pytest.param(seed, id=f"random{seed:02d}") for seed in range(20)]
ALL_SETS = [pytest.param(DISCRETE_BLOCKS[name], id=name) for name in DISCRETE_IDS] + [
    pytest.param(random_discrete_blocks(seed), id=f"random{seed:02d}") for seed in range(20)
]
Z_POINTS = [1.5, -2.0, 1.2j, np.exp(0.3j), np.exp(2j), -1.0, 3 + 1j]


def product_formula(blocks, z):
    """Undelayed z-transforms z*phi_i(z) from kautz-math.md 3.1 (independent oracle)."""
    z = complex(z)
    prefix = 1.0 + 0.0j
    out = []
    for block in blocks:
        if block[0] == "real":
            xi = block[1]
            out.append(z * np.sqrt(1 - xi**2) / (z - xi) * prefix)
            prefix *= (1 - xi * z) / (z - xi)
        else:
            xi = complex(block[1], block[2])
            b = 2 * xi.real / (1 + abs(xi) ** 2)
            c = -(abs(xi) ** 2)
            den = z**2 - 2 * xi.real * z + abs(xi) ** 2
            out.append(z * np.sqrt(1 - c**2) * (z - b) / den * prefix)
            out.append(z * np.sqrt((1 - c**2) * (1 - b**2)) / den * prefix)
            prefix *= (1 - np.conj(xi) * z) * (1 - xi * z) / den
    return np.array(out)


def basis_of(blocks, **kwargs):
    return kt.KautzBasis(poles_from_blocks(blocks), dt=1.0, **kwargs)


# ---------------------------------------------------------------------------- reference values
def test_laguerre_matrices_match_wang():
    basis = kt.LaguerreBasis(pole=0.6, n=5, dt=1.0)
    A_expected = [
        [0.6, 0, 0, 0, 0],
        [0.64, 0.6, 0, 0, 0],
        [-0.384, 0.64, 0.6, 0, 0],
        [0.2304, -0.384, 0.64, 0.6, 0],
        [-0.13824, 0.2304, -0.384, 0.64, 0.6],
    ]
    # Exact decimals; the library builds them from sqrt(1 - a^2) products: a few roundings.
    np.testing.assert_allclose(basis.A, A_expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(basis.B, [0.8, -0.48, 0.288, -0.1728, 0.10368], rtol=0, atol=1e-15)


@pytest.mark.parametrize("a", [-0.7, 0.0, 0.35, 0.9])
def test_laguerre_matrices_closed_form(a):
    n = 6
    basis = kt.LaguerreBasis(pole=a, n=n, dt=0.5)
    i, k = np.indices((n, n))
    A_expected = np.where(i == k, a, 0.0) + np.where(
        i > k, (-a) ** np.maximum(i - k - 1, 0) * (1 - a**2), 0.0
    )
    B_expected = np.sqrt(1 - a**2) * (-a) ** np.arange(n)
    # Section 3.2 element form; products of at most six numbers of size <= 1.
    np.testing.assert_allclose(basis.A, A_expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(basis.B, B_expected, rtol=0, atol=1e-15)


# 9.3, xi = [0.6, 0.5 e^{j}]: printed with 12 decimals, so the tolerance is the
# rounding of the last digit (the computation is accurate to ~1e-16).
PRINTED = 0.5e-12 + 1e-16


def test_pair_example_state_matrix():
    basis = basis_of(DISCRETE_BLOCKS["real_then_pair"])
    A_expected = [
        [0.6, 0, 0],
        [0.774596669241, 0.108060461174, -0.225439430293],
        [0, 0.901757721173, 0.432241844695],
    ]
    np.testing.assert_allclose(basis.A, A_expected, rtol=0, atol=PRINTED)


def test_pair_example_initial_state():
    basis = basis_of(DISCRETE_BLOCKS["real_then_pair"])
    np.testing.assert_allclose(basis.B, [0.8, -0.580947501931, 0.0], rtol=0, atol=PRINTED)


@pytest.mark.parametrize(
    ("k", "expected"),
    [
        (1, [0.48, 0.556899880417, -0.523873895463]),
        (2, [0.288, 0.55008709168, 0.275748548124]),
        (3, [0.1728, 0.220361909961, 0.615235343353]),
    ],
    ids=["F(1)", "F(2)", "F(3)"],
)
def test_pair_example_sequences(k, expected):
    F = basis_of(DISCRETE_BLOCKS["real_then_pair"]).evaluate(np.arange(5.0))
    np.testing.assert_allclose(F[:, k], expected, rtol=0, atol=PRINTED)


# ---------------------------------------------------------------------------- orthonormality
@pytest.mark.parametrize("blocks", ALL_SETS)
def test_lossless_identity(blocks):
    A, B = basis_of(blocks).state_space()
    # Rows of an orthogonal matrix; entries <= 1, rounding ~1e-16 (9.3: <= 1.2e-15).
    np.testing.assert_allclose(A @ A.T + np.outer(B, B), np.eye(B.size), rtol=0, atol=1e-14)


@pytest.mark.parametrize("blocks", ALL_SETS)
def test_stein_gram_is_identity(blocks):
    basis = basis_of(blocks)
    # Stein solver on a small problem whose solution is exactly I; |xi| <= 0.9 keeps it
    # well conditioned (cond ~ 1/(1 - 0.81)).
    np.testing.assert_allclose(basis.gram(), np.eye(basis.n_functions), rtol=0, atol=1e-13)


@pytest.mark.parametrize("blocks", ALL_SETS)
def test_summed_outer_products_are_identity(blocks):
    basis = basis_of(blocks)
    F = basis.evaluate(np.arange(3000.0))
    # |xi| <= 0.9 and N <= 8: the tail after 3000 samples is far below 1e-300; the
    # sum of 3000 products of numbers <= 1 is accurate to ~1e-15.
    np.testing.assert_allclose(F @ F.T, np.eye(basis.n_functions), rtol=0, atol=1e-13)


@pytest.mark.parametrize("blocks", ALL_SETS[:5])
def test_delayed_sequences_are_orthonormal(blocks):
    basis = basis_of(blocks, delayed=True)
    F = basis.evaluate(np.arange(3001.0))
    # Same argument as for the undelayed sequences (one more sample).
    np.testing.assert_allclose(F @ F.T, np.eye(basis.n_functions), rtol=0, atol=1e-13)


# ---------------------------------------------------------------------------- transfer functions
@pytest.mark.parametrize("blocks", ALL_SETS)
def test_transfer_functions_equal_resolvent(blocks):
    basis = basis_of(blocks)
    n = basis.n_functions
    tfs = basis.transfer_functions()
    for z in Z_POINTS:
        values = np.array([np.polyval(num, z) / np.polyval(den, z) for num, den in tfs])
        undelayed = z * np.linalg.solve(z * np.eye(n) - basis.A, basis.B)
        # |z| >= 1 stays away from the poles (|xi| <= 0.9): values O(10) at most,
        # both sides accurate to ~1e-14.
        np.testing.assert_allclose(values, undelayed, rtol=0, atol=1e-12)


@pytest.mark.parametrize("blocks", ALL_SETS)
def test_transfer_functions_equal_product_formula(blocks):
    tfs = basis_of(blocks).transfer_functions()
    for z in Z_POINTS:
        values = np.array([np.polyval(num, z) / np.polyval(den, z) for num, den in tfs])
        # Same accuracy argument as the resolvent test.
        np.testing.assert_allclose(values, product_formula(blocks, z), rtol=0, atol=1e-12)


@pytest.mark.parametrize("blocks", ALL_SETS[:5])
def test_delayed_transfer_functions_equal_resolvent(blocks):
    basis = basis_of(blocks, delayed=True)
    n = basis.n_functions
    tfs = basis.transfer_functions()
    for z in Z_POINTS:
        values = np.array([np.polyval(num, z) / np.polyval(den, z) for num, den in tfs])
        delayed = np.linalg.solve(z * np.eye(n) - basis.A, basis.B)
        # As for the undelayed functions.
        np.testing.assert_allclose(values, delayed, rtol=0, atol=1e-12)


@pytest.mark.parametrize("delayed", [False, True], ids=["undelayed", "delayed"])
@pytest.mark.parametrize("blocks", ALL_SETS[:5])
def test_sequences_equal_scipy_dimpulse(blocks, delayed):
    basis = basis_of(blocks, delayed=delayed)
    k = np.arange(60)
    F = basis.evaluate(k.astype(float))
    for i, (num, den) in enumerate(basis.transfer_functions()):
        (h,) = scipy.signal.dimpulse((num, den, 1.0), n=k.size)[1]
        # scipy iterates a canonical realisation: ~60 steps of rounding on O(1) values.
        np.testing.assert_allclose(F[i], h[:, 0], rtol=0, atol=1e-12, err_msg=f"function {i}")


# ---------------------------------------------------------------------------- sequences
@pytest.mark.parametrize("blocks", ALL_SETS[:5])
def test_delayed_sequences_are_shifted_by_one_sample(blocks):
    k = np.arange(40.0)
    undelayed = basis_of(blocks).evaluate(k)
    delayed = basis_of(blocks, delayed=True).evaluate(k)
    np.testing.assert_array_equal(delayed[:, 0], 0.0)
    # Both are A^k B from the same table: identical.
    np.testing.assert_allclose(delayed[:, 1:], undelayed[:, :-1], rtol=0, atol=1e-15)


@pytest.mark.parametrize("blocks", ALL_SETS[:5])
def test_sequences_follow_recursion(blocks):
    basis = basis_of(blocks)
    F = basis.evaluate(np.arange(30.0))
    np.testing.assert_array_equal(F[:, 0], basis.B)
    # F(k+1) = A F(k); the blocked recursion reorders products: rounding ~1e-16.
    np.testing.assert_allclose(F[:, 1:], basis.A @ F[:, :-1], rtol=0, atol=1e-14)


@pytest.mark.parametrize("form", ["laguerre", "kautz"])
def test_pole_zero_gives_pure_delays(form):
    n = 5
    basis = (
        kt.LaguerreBasis(pole=0.0, n=n, dt=1.0)
        if form == "laguerre"
        else kt.KautzBasis([0.0] * n, dt=1.0)
    )
    F = basis.evaluate(np.arange(8.0))
    # a = 0: function i (0-based) is delta(k - i), exactly.
    np.testing.assert_array_equal(F, np.eye(n, 8))


def test_pole_zero_delayed_gives_one_more_delay():
    F = kt.LaguerreBasis(pole=0.0, n=4, dt=1.0, delayed=True).evaluate(np.arange(7.0))
    np.testing.assert_array_equal(F, np.eye(4, 7, k=1))


def test_pole_zero_transfer_functions_are_powers_of_inverse_z():
    tfs = kt.LaguerreBasis(pole=0.0, n=4, dt=1.0).transfer_functions()
    for i, (num, den) in enumerate(tfs):
        for z in Z_POINTS:
            # z^{-i} for |z| in [1, 3]: one division, rounding only.
            np.testing.assert_allclose(
                np.polyval(num, z) / np.polyval(den, z), z ** (-i), rtol=1e-14, atol=0
            )


def test_sampling_period_only_labels_the_grid():
    blocks = DISCRETE_BLOCKS["mixed"]
    a = kt.KautzBasis(poles_from_blocks(blocks), dt=0.1).evaluate(0.1 * np.arange(50))
    b = basis_of(blocks).evaluate(np.arange(50.0))
    np.testing.assert_array_equal(a, b)


def test_evaluate_picks_requested_samples_in_any_order():
    basis = basis_of(DISCRETE_BLOCKS["mixed"])
    full = basis.evaluate(np.arange(20.0))
    k = np.array([7, 3, 3, 19, 0])
    np.testing.assert_array_equal(basis.evaluate(k.astype(float)), full[:, k])


@pytest.mark.parametrize("delayed", [False, True], ids=["undelayed", "delayed"])
@pytest.mark.parametrize("blocks", ALL_SETS[:5])
def test_step_functions_are_running_sums(blocks, delayed):
    basis = basis_of(blocks, delayed=delayed)
    k = np.arange(80.0)
    # Closed form (A - I)^{-1}(...) vs a cumulative sum: |1 - xi| >= 0.1 keeps the
    # solve well conditioned; values O(10), rounding ~1e-14.
    np.testing.assert_allclose(
        basis.step_functions(k), np.cumsum(basis.evaluate(k), axis=1), rtol=0, atol=1e-12
    )


def test_discrete_basis_flags():
    basis = kt.LaguerreBasis(pole=0.5, n=3, dt=0.2, delayed=True)
    assert basis.is_discrete
    assert basis.dt == 0.2
    assert basis.delayed


# ------------------------------------------------------------------------ matched discretisation
# Basis (b) and system (b) of kautz-math.md 9.2/9.3.
B_POLES = [-1.1, -0.8, -1.5, -0.8 + 2j, -0.8 - 2j]
SYSTEM_B = ([1.0, 1.0], np.polymul(np.poly([-1.1, -0.8, -1.5]), [1.0, 1.6, 4.64]))
C_SYSTEM_B = [0.037661390328, -0.078853278523, 0.006922904151, 0.017827439640, 0.024304552985]
CD_REF = {
    0.1: [0.112836665102, 0.25037108598, 0.031432087801, -0.061395198554, -0.075839391561],
    0.01: [0.374551989576, 0.788904937188, 0.072483768318, -0.179716087538, -0.243013526573],
}


def sampled_system_b(T):
    """h(kT) for k = 0 .. 60/T: the slowest rate 0.8 leaves e^{-48} ~ 1e-21 at the end."""
    t = T * np.arange(int(round(60.0 / T)) + 1)
    _, h = scipy.signal.impulse(SYSTEM_B, T=t)
    return t, h


@pytest.mark.parametrize("T", [0.1, 0.01], ids=["T=0.1", "T=0.01"])
def test_discretize_maps_poles_through_exponential(T):
    db = kt.KautzBasis(B_POLES).discretize(T)
    assert db.dt == T
    assert not db.delayed
    # exp of the same complex numbers: identical up to rounding.
    np.testing.assert_allclose(db.poles, np.exp(np.array(B_POLES) * T), rtol=1e-15, atol=0)


@pytest.mark.parametrize("T", [0.1, 0.01], ids=["T=0.1", "T=0.01"])
def test_matched_discrete_coefficients_match_reference(T):
    t, h = sampled_system_b(T)
    c_d = kt.project(kt.KautzBasis(B_POLES).discretize(T), t, h)
    # Printed with 12 decimals; plain sums of exact samples are accurate to ~1e-15
    # (9.3: <= 6e-15), so the tolerance is the printing precision.
    np.testing.assert_allclose(c_d, CD_REF[T], rtol=0, atol=0.5e-12 + 1e-14)


@pytest.mark.parametrize("T", [0.1, 0.01], ids=["T=0.1", "T=0.01"])
def test_matched_discrete_basis_reproduces_samples(T):
    t, h = sampled_system_b(T)
    db = kt.KautzBasis(B_POLES).discretize(T)
    c_d = kt.project(db, t, h)
    # The samples lie exactly in the span (3.3.2): the residual is rounding of
    # O(0.1) values, ~1e-16.
    np.testing.assert_allclose(c_d @ db.evaluate(t), h, rtol=0, atol=1e-13)


@pytest.mark.parametrize("T", [0.1, 0.01], ids=["T=0.1", "T=0.01"])
def test_matched_discrete_coefficients_from_discrete_realisation(T):
    A, B, C, _ = scipy.signal.tf2ss(*SYSTEM_B)
    Ad = scipy.linalg.expm(A * T)
    # h(k) = C Ad^k B for k >= 0 is the pulse response of (Ad, B, C Ad, C B).
    system = (Ad, B, C @ Ad, C @ B, T)
    c_d = kt.coefficients_from_system(kt.KautzBasis(B_POLES).discretize(T), system)
    # Stein solve (Kronecker form, 25x25) vs printed 12 decimals.
    np.testing.assert_allclose(c_d, CD_REF[T], rtol=0, atol=0.5e-12 + 1e-14)


def test_matched_discrete_coefficients_approach_scaled_continuous_ones():
    # c^d ~ (-1)^{r_i} c / sqrt(T), r_i = number of real blocks before function i
    # (3.3.2): signs (+, -, +, -, -) for basis (b).
    signs = np.array([1, -1, 1, -1, -1])
    scaled = np.array(CD_REF[0.01]) * np.sqrt(0.01)
    # The approximation error is O(T) here: |c^d sqrt(T) - sign * c| is ~3e-4 at
    # T = 0.01 (and ~3e-3 at T = 0.1); 1e-3 separates "converging" from "wrong sign".
    np.testing.assert_allclose(scaled, signs * np.array(C_SYSTEM_B), rtol=0, atol=1e-3)


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "poles",
    [[1.0], [-1.2], [0.5, 0.8 + 0.7j, 0.8 - 0.7j], [1j, -1j]],
    ids=["one", "minus-1.2", "pair-outside", "pair-on-circle"],
)
def test_unstable_discrete_pole_raises(poles):
    with pytest.raises(UnstableModelError, match="inside the unit circle"):
        kt.KautzBasis(poles, dt=0.1)


def test_unstable_discrete_laguerre_pole_raises():
    with pytest.raises(UnstableModelError, match=r"poles\[0\] = 1 has \|p\| = 1"):
        kt.LaguerreBasis(pole=1.0, n=2, dt=1.0)


def test_unpaired_discrete_complex_pole_raises():
    with pytest.raises(PoleError, match=r"poles\[1\] = 0\.3\+0\.4j has no conjugate partner"):
        kt.KautzBasis([0.5, 0.3 + 0.4j], dt=1.0)


def test_time_off_the_sampling_grid_raises():
    basis = kt.LaguerreBasis(pole=0.5, n=2, dt=0.1)
    with pytest.raises(DataError, match=r"t\[2\] = 0\.25 is not a multiple of the sampling period"):
        basis.evaluate([0.0, 0.1, 0.25])


def test_negative_time_on_discrete_basis_raises():
    basis = kt.LaguerreBasis(pole=0.5, n=2, dt=0.1)
    with pytest.raises(DataError, match=r"t\[0\] = -0\.1 is negative"):
        basis.evaluate([-0.1, 0.0])


@pytest.mark.parametrize("n", [1, 2, 7, 64, 1000])
def test_power_columns_by_doubling_equal_the_one_step_recursion(n):
    """``A^k B`` by doubling against the one-step recursion in extended precision.

    A discrete Kautz cascade (real poles at 0.99 and 0.95, a pair at 0.9 +- 0.3j): its
    ``A`` has norm <= 1 and powers that decay slowly.  The reference runs ``x <- A x`` in
    ``np.longdouble`` (64-bit mantissa on x86; 53 elsewhere, then the bound is the one-step
    recursion's own rounding).  Tolerance: about ``2 log2(n)`` products in double, each
    with ~N eps relative rounding (N = 4: about 2e-14 at n = 1000); 1e-13 of
    ``max |A^k B|`` is 5x that.  Measured: 2.1e-16, at n = 1000 and at n = 100 000.
    """
    from kautztwin.basis._blocks import discrete_matrices, parse_poles
    from kautztwin.basis._propagate import _power_columns, discrete_functions

    kinds, params = parse_poles(np.array([0.99, 0.95, 0.9 + 0.3j, 0.9 - 0.3j]), 1.0)
    A, B = discrete_matrices(kinds, params[None])
    ref = np.empty((B.shape[1], n), dtype=np.longdouble)
    x = B[0].astype(np.longdouble)
    Al = A[0].astype(np.longdouble)
    for k in range(n):
        ref[:, k] = x
        x = Al @ x
    got = _power_columns(A, B, n)[0]
    np.testing.assert_allclose(got, ref.astype(float), rtol=0, atol=1e-13 * np.abs(ref).max())
    k = np.array([n - 1, 0, n // 2])
    np.testing.assert_array_equal(discrete_functions(A, B, k)[0], got[:, k])
