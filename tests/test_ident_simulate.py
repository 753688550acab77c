"""Tests of kautztwin.ident.simulate: exact simulation of continuous models with sampled inputs.

Oracles: closed-form responses of first- and second-order systems on non-uniform
grids (exact for the hold they assume), scipy.signal.lsim on uniform grids, and
scipy.linalg.expm for the batched matrix exponential.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from kautztwin.exceptions import DataError, DimensionError
from kautztwin.ident import impulse_response, simulate_lti, step_response
from kautztwin.ident.simulate import (
    _blocked,
    _loop,
    expm_batch,
    impulse_input,
    propagate,
    sampled_input,
    step_input,
)

FIRST = ([1.0], [1.0, 1.0])  # 1/(s+1)
SECOND = ([2.0], [1.0, 3.0, 2.0])  # 2/((s+1)(s+2))
THIRD = ([1.0, 2.0], list(np.poly([-0.5, -1.5, -4.0]).real))  # (s+2)/((s+.5)(s+1.5)(s+4))


def random_grid(n: int, span: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, span, n))
    t[0] = 0.0
    return t


def zoh_first_order(t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """1/(s+1) with a held input: x(k+1) = e^-h x(k) + (1 - e^-h) u(k), exactly."""
    y = np.zeros(t.size)
    for k in range(t.size - 1):
        h = t[k + 1] - t[k]
        y[k + 1] = np.exp(-h) * y[k] + (1.0 - np.exp(-h)) * u[k]
    return y


# --------------------------------------------------------------------------- matrix exponential
@pytest.mark.parametrize("scale", [1e-3, 0.3, 4.0, 60.0], ids=lambda s: f"norm~{s:g}")
def test_expm_batch_matches_scipy(scale):
    rng = np.random.default_rng(1)
    M = rng.standard_normal((20, 4, 4)) * scale - 0.5 * scale * np.eye(4)
    ref = np.array([scipy.linalg.expm(m) for m in M])
    err = np.abs(expm_batch(M) - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))
    assert err.max() < 1e-11


def test_blocked_recursion_equals_loop():
    rng = np.random.default_rng(2)
    Phi = rng.standard_normal((3, 3))
    Phi *= 0.9 / np.max(np.abs(np.linalg.eigvals(Phi)))
    x0, w = rng.standard_normal((3, 2)), rng.standard_normal((377, 3, 2))
    np.testing.assert_allclose(_blocked(Phi, x0, w), _loop(np.broadcast_to(Phi, (377, 3, 3)),
                                                            x0, w), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- exactness
def test_zoh_is_exact_on_a_non_uniform_grid():
    t = random_grid(150, 12.0, 3)
    u = np.random.default_rng(3).standard_normal(t.size)
    np.testing.assert_allclose(simulate_lti(FIRST, t, u), zoh_first_order(t, u), atol=1e-13)


def test_foh_is_exact_for_a_ramp_on_a_non_uniform_grid():
    # 1/(s+1) driven by u = t gives y = t - 1 + e^-t; a linear input is exact under FOH
    t = random_grid(80, 8.0, 4)
    y = simulate_lti(FIRST, t, t, intersample="foh")
    np.testing.assert_allclose(y, t - 1.0 + np.exp(-t), atol=1e-13)


@pytest.mark.parametrize("intersample", ["zoh", "foh"])
def test_uniform_grid_matches_scipy_lsim(intersample):
    t = np.arange(400) * 0.05
    u = np.random.default_rng(5).standard_normal(t.size)
    ref = scipy.signal.lsim(THIRD, u, t, interp=intersample == "foh")[1]
    np.testing.assert_allclose(simulate_lti(THIRD, t, u, intersample=intersample), ref,
                               atol=1e-12)


def test_delay_of_whole_samples_shifts_the_input():
    t = np.arange(200) * 0.1
    u = np.random.default_rng(6).standard_normal(t.size)
    shifted = np.concatenate([np.zeros(3), u[:-3]])
    np.testing.assert_allclose(simulate_lti(THIRD, t, u, delay=0.3),
                               simulate_lti(THIRD, t, shifted), atol=1e-12)


def test_fractional_delay_of_a_held_input_is_exact():
    # the delayed held input switches between samples: compare with the first-order recursion
    # on the grid that holds both the samples and the switching instants
    t = random_grid(60, 6.0, 7)
    u = np.random.default_rng(7).standard_normal(t.size)
    tau = 0.237
    fine = np.union1d(t, t + tau)
    fine = fine[fine <= t[-1]]
    j = np.searchsorted(t + tau, fine, side="right") - 1
    u_fine = np.where(j >= 0, u[np.maximum(j, 0)], 0.0)
    ref = np.interp(t, fine, zoh_first_order(fine, u_fine))
    np.testing.assert_allclose(simulate_lti(FIRST, t, u, delay=tau), ref, atol=1e-13)


def test_step_response_closed_form_with_delay():
    t = random_grid(100, 10.0, 8)
    y = step_response(SECOND, t, delay=0.75)
    s = np.maximum(t - 0.75, 0.0)
    np.testing.assert_allclose(y, np.where(t > 0.75, 1 - 2 * np.exp(-s) + np.exp(-2 * s), 0.0),
                               atol=1e-13)


def test_impulse_response_closed_form():
    t = np.linspace(0.0, 10.0, 101)
    np.testing.assert_allclose(impulse_response(SECOND, t), 2 * (np.exp(-t) - np.exp(-2 * t)),
                               atol=1e-13)


def test_step_response_of_a_biproper_system_includes_feedthrough():
    t = np.array([0.0, 0.5, 2.0])
    np.testing.assert_allclose(step_response(([1.0, 2.0], [1.0, 1.0]), t),
                               2.0 - np.exp(-t), atol=1e-14)


def test_initial_state_gives_the_free_response():
    A, B, C, D = np.array([[-1.0]]), np.array([[1.0]]), np.array([[2.0]]), np.array([[0.0]])
    t = random_grid(30, 5.0, 9)
    y = simulate_lti((A, B, C, D), t, np.zeros(t.size), x0=[1.5])
    np.testing.assert_allclose(y, 3.0 * np.exp(-t), atol=1e-14)


def test_u_before_fills_the_delay_window():
    t = np.linspace(0.0, 4.0, 41)
    y = simulate_lti(FIRST, t, np.zeros(t.size), delay=1.0, u_before=1.0)
    s = np.minimum(t, 1.0)  # input 1 on [0, 1), then 0
    expected = (1 - np.exp(-s)) * np.exp(-(t - s))
    np.testing.assert_allclose(y, expected, atol=1e-14)


@pytest.mark.parametrize("kind", ["step", "impulse"])
def test_event_inputs_agree_on_jittered_and_sequential_paths(kind):
    # steps and impulses on non-uniform grids use superposition; compare with the recursion
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    B = np.array([0.0, 1.0])
    t = np.arange(120) * 0.1 + np.random.default_rng(10).uniform(-0.01, 0.01, 120)
    t[0] = 0.0
    inp = step_input(1.234, 2.0) if kind == "step" else impulse_input(0.5, 1.5)
    direct = propagate(A, B, t, inp, X0=np.eye(2))
    seq = np.zeros_like(direct)
    seq[0, :, 1:] = np.eye(2)
    from kautztwin.ident.simulate import hold_matrices

    Phi, G0, _ = hold_matrices(A, B, np.diff(t))
    for k in range(t.size - 1):  # brute force with the exact per-interval transitions
        seq[k + 1] = Phi[k] @ seq[k]
        a, b = t[k], t[k + 1]
        if kind == "step" and a < 1.234 <= b:
            seq[k + 1, :, 0] += hold_matrices(A, B, np.array([b - 1.234]))[1][0] * 2.0
        elif kind == "step" and a >= 1.234:
            seq[k + 1, :, 0] += G0[k] * 2.0
        elif kind == "impulse" and a < 0.5 <= b:
            seq[k + 1, :, 0] += hold_matrices(A, B, np.array([b - 0.5]))[0][0] @ B * 1.5
    np.testing.assert_allclose(direct, seq, atol=1e-12)


def test_piecewise_input_value_is_right_continuous():
    inp = sampled_input(np.array([0.0, 1.0, 2.0]), np.array([1.0, 2.0, 3.0]), delay=0.5)
    np.testing.assert_allclose(inp.value_at(np.array([0.4, 0.5, 1.49, 1.5, 9.0])),
                               [0.0, 1.0, 1.0, 2.0, 3.0])


def test_accepts_scipy_lti():
    t = np.linspace(0.0, 3.0, 31)
    np.testing.assert_allclose(simulate_lti(scipy.signal.lti(*SECOND), t, np.ones(t.size)),
                               step_response(SECOND, t), atol=1e-13)


# --------------------------------------------------------------------------- errors
def test_rejects_unknown_intersample():
    with pytest.raises(DataError, match="intersample"):
        simulate_lti(FIRST, [0.0, 1.0], [1.0, 1.0], intersample="cubic")


def test_rejects_negative_delay():
    with pytest.raises(DataError, match="delay must be"):
        simulate_lti(FIRST, [0.0, 1.0], [1.0, 1.0], delay=-0.1)


def test_rejects_length_mismatch():
    with pytest.raises(DimensionError, match="u has shape"):
        simulate_lti(FIRST, [0.0, 1.0, 2.0], [1.0, 1.0])


def test_rejects_discrete_systems():
    with pytest.raises(DataError, match="continuous-time"):
        simulate_lti(([1.0], [1.0, -0.5], 0.1), [0.0, 1.0], [1.0, 1.0])


def test_rejects_nan_input():
    with pytest.raises(DataError, match="non-finite"):
        simulate_lti(FIRST, [0.0, 1.0], [1.0, np.nan])


def test_rejects_wrong_x0_size():
    with pytest.raises(DimensionError, match="x0 has 2 entries"):
        simulate_lti(FIRST, [0.0, 1.0], [1.0, 1.0], x0=[1.0, 2.0])


def test_impulse_response_rejects_feedthrough():
    with pytest.raises(DataError, match="feedthrough"):
        impulse_response(([1.0, 2.0], [1.0, 1.0]), [0.0, 1.0])


def test_step_response_rejects_negative_times():
    with pytest.raises(DataError, match="t >= 0"):
        step_response(FIRST, [-1.0, 0.0, 1.0])
