"""Differentiable Kautz machinery in torch against the numpy core (kautz-math.md 2, 4.4).

Oracles: ``KautzBasis.state_space`` / ``evaluate`` and ``kautztwin.project(method='lstsq')``
in float64, the Gram identity of orthonormal functions, and ``torch.autograd.gradcheck``.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import torch

import kautztwin as kt
from kautztwin.exceptions import DataError, DimensionError, PoleError, UnstableModelError
from kautztwin.nn.kautz_torch import (
    block_poles,
    block_structure,
    kautz_functions,
    lstsq_coefficients,
    n_functions,
    network_matrices,
    propagate,
    relative_degree_constraints,
    response_weights,
)

torch.set_num_threads(1)

W = np.sqrt(15) / 2
POLE_SETS = {
    "paper": [-1.0, -3.0, -0.5 + 1j * W, -0.5 - 1j * W],
    "pair-first": [-0.5 + 1j * W, -0.5 - 1j * W, -1.0, -3.0],
    "laguerre": [-1.0] * 4,
    "two-pairs": [-0.8 + 2j, -0.8 - 2j, -0.3 + 0.5j, -0.3 - 0.5j, -1.2],
    "slow-pair": [-0.125 + 0.93j, -0.125 - 0.93j, -4.5],
}
IDS = list(POLE_SETS)
T = np.linspace(0.0, 20.0, 900)


def _random_params(kinds, batch, seed):
    rng = np.random.default_rng(seed)
    cols = []
    for k in kinds:
        cols.append(rng.uniform(0.2, 3.0, batch))
        if k == "pair":
            cols.append(rng.uniform(0.0, 3.0, batch))
    return np.stack(cols, axis=1)


# --------------------------------------------------------------------------- structure
def test_block_structure_matches_parse():
    kinds, params = block_structure(POLE_SETS["two-pairs"])
    assert kinds == ("pair", "pair", "real")
    torch.testing.assert_close(params, torch.tensor([0.8, 2.0, 0.3, 0.5, 1.2], dtype=torch.float64))


@pytest.mark.parametrize("name", IDS, ids=IDS)
def test_block_poles_round_trip(name):
    poles = np.asarray(POLE_SETS[name], dtype=complex)
    kinds, params = block_structure(poles)
    got = block_poles(kinds, params).numpy()
    np.testing.assert_allclose(got, kt.KautzBasis(poles).poles, rtol=0, atol=1e-15)


def test_block_structure_rejects_unstable_pole():
    with pytest.raises(UnstableModelError, match="Re >= 0"):
        block_structure([0.5, -1.0])


def test_unknown_kind_is_rejected():
    with pytest.raises(PoleError, match="'real' or 'pair'"):
        n_functions(("real", "triple"))


def test_params_with_wrong_columns_raise():
    with pytest.raises(DimensionError, match=r"shape \(batch, 3\)"):
        network_matrices(("pair", "real"), torch.ones(2, 4, dtype=torch.float64))


# --------------------------------------------------------------------------- matrices
@pytest.mark.parametrize("name", IDS, ids=IDS)
def test_network_matrices_match_numpy(name):
    poles = POLE_SETS[name]
    kinds, params = block_structure(poles)
    A, B = network_matrices(kinds, params)
    A_np, B_np = kt.KautzBasis(poles).state_space()
    np.testing.assert_allclose(A.numpy(), A_np, rtol=0, atol=1e-14)
    np.testing.assert_allclose(B.numpy(), B_np, rtol=0, atol=1e-14)


def test_network_matrices_satisfy_lyapunov_identity_batched():
    kinds = ("real", "pair", "pair", "real")
    P = torch.as_tensor(_random_params(kinds, 16, seed=3))
    A, B = network_matrices(kinds, P)
    residual = A + A.transpose(1, 2) + B[:, :, None] * B[:, None, :]
    torch.testing.assert_close(residual, torch.zeros_like(residual), rtol=0, atol=1e-13)


# --------------------------------------------------------------------------- functions
@pytest.mark.parametrize("name", IDS, ids=IDS)
def test_functions_match_kautz_basis_evaluate(name):
    poles = POLE_SETS[name]
    kinds, params = block_structure(poles)
    K = kautz_functions(kinds, params, T)
    np.testing.assert_allclose(K.numpy(), kt.KautzBasis(poles).evaluate(T), rtol=0, atol=1e-12)


def test_batched_functions_match_one_basis_at_a_time():
    kinds = ("pair", "real", "real")
    P = _random_params(kinds, 6, seed=4)
    K = kautz_functions(kinds, torch.as_tensor(P), T).numpy()
    for k, row in enumerate(P):
        ref = kt.KautzBasis._from_blocks(kinds, row).evaluate(T)
        np.testing.assert_allclose(K[k], ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "t",
    [np.linspace(1.5, 12.0, 301), np.sort(np.random.default_rng(5).uniform(0, 8, 40))],
    ids=["uniform-late-start", "non-uniform"],
)
def test_functions_on_other_grids(t):
    poles = POLE_SETS["paper"]
    kinds, params = block_structure(poles)
    got = kautz_functions(kinds, params, t).numpy()
    np.testing.assert_allclose(got, kt.KautzBasis(poles).evaluate(t), rtol=0, atol=1e-12)


def test_functions_vanish_before_zero_on_non_uniform_grid():
    kinds, params = block_structure([-1.0])
    t = np.array([-1.0, -0.2, 0.0, 0.7, 3.0])
    got = kautz_functions(kinds, params, t).numpy()[0]
    np.testing.assert_allclose(got, np.r_[0.0, 0.0, np.sqrt(2) * np.exp(-t[2:])], atol=1e-15)


def test_functions_are_orthonormal_on_a_long_grid():
    # Gram matrix by Simpson quadrature over [0, 60] is the identity (kautz-math.md 2.3)
    kinds = ("pair", "real", "real")
    P = torch.as_tensor(_random_params(kinds, 4, seed=6)).clamp_min(0.5)
    t = np.linspace(0.0, 60.0, 12001)
    K = kautz_functions(kinds, P, t)
    w = response_weights(t)
    G = (K * w) @ K.transpose(1, 2)
    # Simpson's O(h^4) error with h = 0.005 and rates up to 3 is about 1e-7
    eye = torch.eye(4, dtype=torch.float64).expand(4, 4, 4)
    torch.testing.assert_close(G, eye, rtol=0, atol=1e-6)


def test_float32_functions_close_to_float64():
    kinds, params = block_structure(POLE_SETS["paper"])
    K64 = kautz_functions(kinds, params, T)
    K32 = kautz_functions(kinds, params.float(), T)
    assert K32.dtype == torch.float32
    torch.testing.assert_close(K32.double(), K64, rtol=0, atol=1e-5)  # |K| <= 2.5


def test_propagate_rejects_bad_grid():
    A, B = network_matrices(("real",), torch.ones(1, 1, dtype=torch.float64))
    with pytest.raises(DataError, match="strictly increasing"):
        propagate(A, B, np.array([0.0, 1.0, 1.0]))
    with pytest.raises(DimensionError, match=r"\(batch, N, N\)"):
        propagate(A[0], B, T)


# --------------------------------------------------------------------------- least squares
@pytest.mark.parametrize("name", IDS, ids=IDS)
def test_lstsq_matches_project_lstsq(name):
    poles = POLE_SETS[name]
    basis = kt.KautzBasis(poles)
    rng = np.random.default_rng(7)
    H = rng.standard_normal((5, T.size)) + basis.evaluate(T)[0]
    kinds, params = block_structure(poles)
    K = kautz_functions(kinds, params, T)
    c = lstsq_coefficients(K, torch.as_tensor(H), response_weights(T), ridge=0.0)
    ref = kt.project(basis, T, H, method="lstsq")
    np.testing.assert_allclose(c.numpy(), ref, rtol=0, atol=1e-12)


def test_lstsq_default_ridge_is_negligible():
    poles = POLE_SETS["paper"]
    kinds, params = block_structure(poles)
    K = kautz_functions(kinds, params, T)
    h = torch.as_tensor(np.random.default_rng(8).standard_normal((3, T.size)))
    w = response_weights(T)
    torch.testing.assert_close(
        lstsq_coefficients(K, h, w), lstsq_coefficients(K, h, w, ridge=0.0), rtol=0, atol=1e-12
    )


def test_lstsq_one_basis_per_record():
    kinds = ("pair", "real")
    P = _random_params(kinds, 4, seed=9)
    K = kautz_functions(kinds, torch.as_tensor(P), T)
    h = torch.as_tensor(np.random.default_rng(10).standard_normal((4, T.size)))
    c = lstsq_coefficients(K, h, response_weights(T))
    for k in range(4):
        basis = kt.KautzBasis._from_blocks(kinds, P[k])
        ref = kt.project(basis, T, h[k].numpy(), method="lstsq")
        np.testing.assert_allclose(c[k].numpy(), ref, rtol=0, atol=1e-12)


def test_lstsq_recovers_a_response_in_the_span_exactly():
    poles = POLE_SETS["paper"]
    kinds, params = block_structure(poles)
    K = kautz_functions(kinds, params, T)
    c_true = torch.tensor([[0.3, -0.2, 0.1, 0.05]], dtype=torch.float64)
    h = c_true @ K
    torch.testing.assert_close(lstsq_coefficients(K, h, ridge=0.0), c_true, rtol=0, atol=1e-13)


def test_uniform_weights_are_ordinary_least_squares():
    kinds, params = block_structure(POLE_SETS["paper"])
    K = kautz_functions(kinds, params, T)
    h = torch.as_tensor(np.random.default_rng(11).standard_normal((2, T.size)))
    c = lstsq_coefficients(K, h, response_weights(T, "uniform"), ridge=0.0)
    ref = np.linalg.lstsq(K.numpy().T, h.numpy().T, rcond=None)[0].T
    np.testing.assert_allclose(c.numpy(), ref, rtol=0, atol=1e-12)


def test_lstsq_shape_errors():
    K = torch.ones(2, 3, 10, dtype=torch.float64)
    with pytest.raises(DimensionError, match="batch, n_samples"):
        lstsq_coefficients(K, torch.ones(10, dtype=torch.float64))
    with pytest.raises(DimensionError, match="must have shape"):
        lstsq_coefficients(K, torch.ones(2, 11, dtype=torch.float64))


def test_unknown_weight_rule():
    with pytest.raises(DataError, match="'simpson' or 'uniform'"):
        response_weights(T, "gauss")


# --------------------------------------------------------------------------- gradients
def test_gradcheck_functions():
    kinds = ("pair", "real")
    t = np.linspace(0.0, 4.0, 9)
    P = torch.tensor([[0.6, 1.7, 1.1], [0.3, 0.0, 2.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: kautz_functions(kinds, p, t), (P,))


def test_gradcheck_functions_late_start_and_non_uniform_grid():
    kinds = ("real", "pair")
    P = torch.tensor([[0.9, 0.5, 1.3]], dtype=torch.float64, requires_grad=True)
    for t in (np.linspace(0.5, 3.0, 6), np.array([0.0, 0.3, 1.1, 1.2, 2.5])):
        assert torch.autograd.gradcheck(lambda p, t=t: kautz_functions(kinds, p, t), (P,))


def test_gradcheck_projection_end_to_end():
    kinds = ("pair", "real")
    t = np.linspace(0.0, 6.0, 13)
    rng = np.random.default_rng(12)
    h = torch.tensor(rng.standard_normal((2, t.size)), requires_grad=True)
    w = response_weights(t)
    P = torch.tensor([[0.6, 1.7, 1.1], [0.4, 0.9, 2.0]], dtype=torch.float64, requires_grad=True)

    def fitted(p, h):
        K = kautz_functions(kinds, p, t)
        c = lstsq_coefficients(K, h, w)
        return torch.einsum("bi,bin->bn", c, K)

    assert torch.autograd.gradcheck(fitted, (P, h))


# --------------------------------------------------------------------------- relative degree
@pytest.mark.parametrize("name", ["paper", "two-pairs", "slow-pair"])
def test_relative_degree_constraints_are_the_leading_markov_parameters(name):
    # oracle: scipy's transfer function of (A, B, c) has a numerator of degree n - r exactly
    # when c is orthogonal to the constraint columns
    kinds, params = block_structure(POLE_SETS[name])
    A, B = network_matrices(kinds, params[None])
    n = B.shape[-1]
    rng = np.random.default_rng(3)
    for r in range(1, n + 1):
        M = relative_degree_constraints(A, B, r)[0].numpy()
        assert M.shape == (n, r - 1)
        np.testing.assert_allclose(M.T @ M, np.eye(r - 1), rtol=0, atol=1e-12)
        N = scipy.linalg.null_space(M.T) if r > 1 else np.eye(n)
        c = N @ rng.standard_normal(N.shape[1])
        num, _ = scipy.signal.ss2tf(A[0].numpy(), B[0].numpy()[:, None], c[None, :], [[0.0]])
        num = num[0]
        assert np.max(np.abs(num[: r])) <= 1e-9 * np.max(np.abs(num))  # leading r - 1 zeros
        assert abs(num[r]) > 1e-6 * np.max(np.abs(num))  # and not one more


def test_relative_degree_constraints_reject_bad_degrees():
    A, B = network_matrices(("real", "real"), torch.tensor([[1.0, 2.0]], dtype=torch.float64))
    for bad in (0, 3, 1.5, True):
        with pytest.raises(DataError, match="relative_degree"):
            relative_degree_constraints(A, B, bad)


def test_constrained_lstsq_matches_null_space_least_squares():
    # oracle: ordinary least squares over the null space of the constraints (numpy)
    kinds, params = block_structure(POLE_SETS["paper"])
    P = torch.as_tensor(_random_params(kinds, 3, 5))
    K = kautz_functions(kinds, P, T)
    A, B = network_matrices(kinds, P)
    h = torch.as_tensor(np.random.default_rng(6).standard_normal((3, T.size)))
    for r in (2, 3, 4):
        M = relative_degree_constraints(A, B, r)
        c = lstsq_coefficients(K, h, constraints=M, ridge=0.0).numpy()
        for i in range(3):
            N = scipy.linalg.null_space(M[i].numpy().T)
            Ki = K[i].numpy()
            ref = N @ np.linalg.lstsq(Ki.T @ N, h[i].numpy(), rcond=None)[0]
            np.testing.assert_allclose(c[i], ref, rtol=0, atol=1e-10)
    empty = relative_degree_constraints(A, B, 1)
    np.testing.assert_array_equal(lstsq_coefficients(K, h, constraints=empty),
                                  lstsq_coefficients(K, h))
    with pytest.raises(DimensionError, match="constraints"):
        lstsq_coefficients(K, h, constraints=M[:, :2])


def test_gradcheck_constrained_projection():
    kinds = ("pair", "real")
    t = np.linspace(0.0, 6.0, 13)
    h = torch.tensor(np.random.default_rng(13).standard_normal((2, t.size)))
    P = torch.tensor([[0.6, 1.7, 1.1], [0.4, 0.9, 2.0]], dtype=torch.float64, requires_grad=True)

    def fitted(p):
        K = kautz_functions(kinds, p, t)
        A, B = network_matrices(kinds, p)
        c = lstsq_coefficients(K, h, constraints=relative_degree_constraints(A, B, 3))
        return torch.einsum("bi,bin->bn", c, K)

    assert torch.autograd.gradcheck(fitted, (P,))


def test_propagate_without_gradient_equals_the_differentiable_path():
    # prediction writes into one preallocated array; training concatenates: same products
    kinds, _ = block_structure(POLE_SETS["two-pairs"])
    P = torch.as_tensor(_random_params(kinds, 4, 8))
    A, B = network_matrices(kinds, P)
    with torch.no_grad():
        fast = propagate(A, B, T)
    slow = propagate(A.requires_grad_(True), B, T).detach()
    assert torch.equal(fast, slow)
