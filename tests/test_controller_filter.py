"""The controller's filter states: one fixed function of the history, built in blocks (issue #11).

A model version's controller is built on the whole command history.  The
states are advanced one input at a time, except at every ``MAX_DELAY``-th input,
where the block map replaces the steps; a build therefore costs a product per
block instead of a Python step per input.  Oracles: the plain recursion
``x(k+1) = A x(k) + B w(k)`` (to rounding) and ``scipy.signal.dlsim`` on the
basis' state space; the bit-for-bit contract between a controller built early
and advanced and one built late.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

import kautztwin as kt
from kautztwin.twin.prediction import MPCController, MPCSettings
from kautztwin.twin.prediction.controller import MAX_DELAY, _prepare_controller

U0 = 0.5
SETTINGS = MPCSettings(30, 0.7, 3, 0.1, u_min=0.0, u_max=1.0, du_max=0.2)


def _model() -> kt.KautzModel:
    # a real pole and a complex pair (a Kautz network with a 2x2 section), slow enough
    # that the whole history counts: 0.995^1000 = 0.0067
    p = 0.9 * np.exp(0.3j)
    basis = kt.KautzBasis([0.995, p, np.conj(p)], dt=0.1, delayed=True)
    return kt.KautzModel(basis, [1.0, -0.4, 0.2])


def _histories(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    v = U0 + 0.1 * np.cumsum(rng.standard_normal(n)) / np.sqrt(n)
    d = 0.02 * np.sign(rng.standard_normal(n))
    return v, d


def _recursion(A, B, w):
    """States x(n), x(n-1) of the plain recursion from rest."""
    x = prev = np.zeros(A.shape[0])
    for wk in w:
        prev, x = x, A @ x + B * wk
    return x, prev


@pytest.mark.parametrize("n", [0, 1, 255, 256, 257, 511, 512, 1000, 3 * MAX_DELAY])
def test_states_equal_the_plain_recursion_to_rounding(n):
    model = _model()
    A, B = np.array(model.basis.A), np.array(model.basis.B)
    v, d = _histories(n)
    p = _prepare_controller(model, SETTINGS, v, d, U0)
    xv, xv_prev = _recursion(A, B, v - U0)
    xd, _ = _recursion(A, B, d)
    scale = max(np.abs(xv).max(initial=0.0), 1e-300)
    # summing up to 256 terms in another order: a few ulps of the largest state per block
    for got, want in ((p.xv, xv), (p.xv_prev, xv_prev)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * scale)
    scale_d = max(np.abs(xd).max(initial=0.0), 1e-300)
    np.testing.assert_allclose(p.xd, xd, rtol=0, atol=1e-13 * scale_d)


def test_states_equal_scipy_dlsim():
    model = _model()
    A, B = np.array(model.basis.A), np.array(model.basis.B)
    n = 2000
    v, d = _histories(n, seed=3)
    p = _prepare_controller(model, SETTINGS, v, d, U0)
    # dlsim's state sequence x(0..n-1) and one more step for x(n)
    sys = (A, B.reshape(-1, 1), np.eye(A.shape[0]), np.zeros((A.shape[0], 1)), model.basis.dt)
    _, _, x = signal.dlsim(sys, (v - U0).reshape(-1, 1))
    x_n = A @ x[-1] + B * (v[-1] - U0)
    np.testing.assert_allclose(p.xv, x_n, rtol=0, atol=1e-12 * np.abs(x_n).max())
    np.testing.assert_allclose(p.xv_prev, x[-1], rtol=0, atol=1e-12 * np.abs(x_n).max())


@pytest.mark.parametrize("n0, n", [(n0, n) for n in (256, 513, 1100)
                                   for n0 in (0, 1, 200, 255, 256, 257, 700) if n0 <= n])
def test_built_early_and_advanced_is_built_late_bit_for_bit(n0, n):
    model = _model()
    v, d = _histories(n, seed=n0)
    early = MPCController(input_offset=U0)
    early._install(_prepare_controller(model, SETTINGS, v[:n0], d[:n0], U0), v[n0:], d[n0:])
    late = MPCController(input_offset=U0)
    late.rebuild(model, SETTINGS, v, d)
    for a, b in ((early._filter, late._filter),):
        for name in ("xv", "xv_prev", "xd", "x0"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert a.nb == b.nb == n % MAX_DELAY
    # and they go on alike, across the next boundary
    for k in range(MAX_DELAY + 3):
        for ctl in (early, late):
            ctl.advance(U0 + 0.01 * np.sin(0.1 * k), 0.0)
        np.testing.assert_array_equal(early._filter.xv, late._filter.xv)


def test_a_prepared_controller_installed_twice_starts_from_the_same_states():
    model = _model()
    v, d = _histories(300)
    p = _prepare_controller(model, SETTINGS, v, d, U0)
    xv = p.xv.copy()
    a, b = MPCController(input_offset=U0), MPCController(input_offset=U0)
    a._install(p)
    for _ in range(400):  # across a boundary: the block buffer is written
        a.advance(U0 + 0.05, 0.01)
    b._install(p)
    np.testing.assert_array_equal(p.xv, xv)
    np.testing.assert_array_equal(b._filter.xv, xv)


@pytest.mark.parametrize("n", [100, MAX_DELAY, 2 * MAX_DELAY + 5])
def test_revised_input_equals_the_history_with_the_applied_input(n):
    """revise_last_input (a live plant applied more): the states of the revised history."""
    model = _model()
    v, d = _histories(n + 300, seed=7)
    ctl = MPCController(input_offset=U0)
    ctl.rebuild(model, SETTINGS, v[:n - 1], d[:n - 1])
    ctl.advance(v[n - 1], d[n - 1])
    delta = 0.03
    ctl.revise_last_input(delta)
    applied = v.copy()
    applied[n - 1] += delta
    for k in range(n, n + 300):  # the revision must also reach the next block map
        ctl.advance(v[k], d[k])
    ref = MPCController(input_offset=U0)
    ref.rebuild(model, SETTINGS, applied, d)
    scale = np.abs(ref._filter.xv).max()
    np.testing.assert_allclose(ctl._filter.xv, ref._filter.xv, rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(ctl._filter.xd, ref._filter.xd, rtol=0, atol=1e-13 * scale)


def test_build_calls_scale_with_blocks_not_inputs(monkeypatch):
    """A build over n inputs makes at most MAX_DELAY single steps (the rest are block maps)."""
    from kautztwin.twin.prediction import controller as mod

    calls = {"step": 0, "block": 0}
    advance, close = mod._FilterState.advance, mod._FilterState._close_block

    def counted_advance(self, wv, wd):
        calls["step"] += 1
        advance(self, wv, wd)

    def counted_close(self):
        calls["block"] += 1
        close(self)

    monkeypatch.setattr(mod._FilterState, "advance", counted_advance)
    monkeypatch.setattr(mod._FilterState, "_close_block", counted_close)
    v, d = _histories(20 * MAX_DELAY + 17)
    _prepare_controller(_model(), SETTINGS, v, d, U0)
    assert calls == {"step": 17, "block": 20}
