"""The fast path's quadratic input channel and directional forgetting (RecursiveKautzEstimator)."""

from __future__ import annotations

import numpy as np
import pytest

import kautztwin as kt
from kautztwin.exceptions import DataError, DimensionError
from kautztwin.ident.kautz_oe import filter_states
from kautztwin.twin.runtime.config import TwinConfig
from kautztwin.twin.update import RecursiveKautzEstimator, Updater

DT = 0.05
POLES = np.exp(np.array([-2.0, -5.0]) * DT)
U0, SCALE = 0.5, 0.2


def _levels(n: int, seed: int, amp: float = 0.3, hold: tuple[int, int] = (3, 15)) -> np.ndarray:
    """Random multi-level steps around U0 (a binary signal would make (u - u0)^2 constant)."""
    rng = np.random.default_rng(seed)
    out: list[float] = []
    while len(out) < n:
        out += [U0 + amp * rng.uniform(-1.0, 1.0)] * int(rng.integers(*hold))
    return np.array(out[:n])


def _hammerstein(u: np.ndarray, c: np.ndarray, cq: np.ndarray, d: float) -> np.ndarray:
    """y = c^T x(u - u0) + d + cq^T x((u - u0)^2 / s), both banks on the delayed basis."""
    basis = kt.KautzBasis(POLES, dt=DT, delayed=True)
    v = u - U0
    return (filter_states(basis, v)[:-1] @ c + d
            + filter_states(basis, v * v / SCALE)[:-1] @ cq)


C, CQ, D = np.array([1.0, -0.5]), np.array([0.3, 0.2]), 2.0


def test_quadratic_channel_recovers_a_hammerstein_system_inside_the_span():
    u = _levels(1500, seed=0)
    y = _hammerstein(u, C, CQ, D)
    est = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=1e8, max_trace=1e12,
                                  input_offset=U0, quadratic_scale=SCALE).fit(u, y)
    # oracle 1: without forgetting (and no trace clamp) RLS is the ridge solution of its
    # prior, theta 0 with P = delta I
    X = est.regressors(u)
    ridge = np.linalg.solve(X.T @ X + np.eye(5) / 1e8, X.T @ y)
    np.testing.assert_allclose(est.parameters_, ridge, rtol=1e-10, atol=1e-12)
    # oracle 2: the truth, up to that prior's pull (about 1e-10 here)
    np.testing.assert_allclose(est.coef_, C, atol=1e-8)
    np.testing.assert_allclose(est.quadratic_coef_, CQ, atol=1e-8)
    assert est.offset_ == pytest.approx(D, abs=1e-8)
    np.testing.assert_allclose(est.simulate(u), y, atol=1e-8)
    # the linear part alone is what model_ holds
    lin = filter_states(est.basis_, u - U0)[:-1] @ C + D
    np.testing.assert_allclose(est.simulate(u, linear=True), lin, atol=1e-8)
    assert est.parameters_.size == 5 and est.state_.shape == (4,)
    np.testing.assert_allclose(est.model_.coefficients, est.coef_)
    # a linear fast path cannot: its best fit leaves a bias
    lin_est = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=1e8, max_trace=1e12,
                                      input_offset=U0).fit(u, y)
    assert np.max(np.abs(lin_est.simulate(u) - y)) > 0.01


def test_regressors_continue_from_the_live_state_and_the_final_row_is_the_next_state():
    u = _levels(400, seed=1)
    y = _hammerstein(u, C, CQ, D)
    est = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=1e8, max_trace=1e12,
                                  input_offset=U0, quadratic_scale=SCALE).fit(u[:300], y[:300])
    X = est.regressors(u[300:], est.state_, final=True)
    assert X.shape == (101, 5)
    np.testing.assert_allclose(X[0], est._phi)  # the estimator's own regressor now
    np.testing.assert_allclose(est.simulate(u[300:], x0=est.state_), y[300:], atol=1e-8)
    est.partial_fit(u[300:], y[300:])
    np.testing.assert_allclose(X[-1], est._phi, atol=1e-12)
    with pytest.raises(DimensionError, match="x0"):
        est.regressors(u, np.zeros(2))


def test_revise_last_input_moves_both_banks_as_the_applied_input_would_have():
    u = _levels(60, seed=2)
    a = RecursiveKautzEstimator(POLES, dt=DT, input_offset=U0, quadratic_scale=SCALE)
    b = RecursiveKautzEstimator(POLES, dt=DT, input_offset=U0, quadratic_scale=SCALE)
    y = _hammerstein(u, C, CQ, D)
    a.partial_fit(u[:-1], y[:-1])
    b.partial_fit(u[:-1], y[:-1])
    a.update(0.9, y[-1])
    b.update(0.2, y[-1])
    b.revise_last_input(0.2, 0.9)
    np.testing.assert_allclose(b.state_, a.state_, atol=1e-14)


def test_steady_input_inverts_the_static_map():
    u = _levels(1500, seed=3)
    y = _hammerstein(u, C, CQ, D)
    est = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=1e8, max_trace=1e12,
                                  input_offset=U0, quadratic_scale=SCALE).fit(u, y)
    for target in (2.1, 2.6, 1.9):
        u_ss = est.steady_input(target)
        assert abs(u_ss - U0) < 0.5
        tail = est.simulate(np.full(2000, u_ss))[-1]  # the model settles at the target
        assert tail == pytest.approx(target, abs=1e-6)
    lin = RecursiveKautzEstimator(POLES, dt=DT, coef_init=C, offset_init=D,
                                  input_offset=U0).reset()
    gain = float(kt.KautzModel(lin.basis_, C).dc_gain)
    assert lin.steady_input(2.5) == pytest.approx(U0 + 0.5 / gain, rel=1e-12)


def test_directional_forgetting_without_forgetting_is_plain_rls():
    u = np.random.default_rng(4).standard_normal(300)
    y = _hammerstein(U0 + 0.2 * u, C, CQ, D) + 0.01 * np.random.default_rng(5).standard_normal(300)
    a = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=10.0).fit(u, y)
    b = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=10.0,
                                directional=True).fit(u, y)
    np.testing.assert_allclose(b.parameters_, a.parameters_, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b.covariance_, a.covariance_, rtol=1e-9, atol=1e-12)


def test_directional_forgetting_step_matches_the_information_form():
    # oracle: R <- R - (1 - lam) R phi phi^T R / (phi^T R phi) + phi phi^T, by explicit inverses
    lam = 0.9
    est = RecursiveKautzEstimator(POLES, dt=DT, forgetting=lam, delta=2.0, directional=True)
    u = np.random.default_rng(6).standard_normal(40)
    y = np.random.default_rng(7).standard_normal(40)
    est.partial_fit(u[:-1], y[:-1])
    P0, th0, phi = est.covariance_, est.parameters_, est._phi.copy()
    R0 = np.linalg.inv(P0)
    Rphi = R0 @ phi
    R1 = R0 - (1 - lam) * np.outer(Rphi, Rphi) / (phi @ Rphi) + np.outer(phi, phi)
    P1 = np.linalg.inv(R1)
    th1 = th0 + P1 @ phi * (y[-1] - th0 @ phi)
    est.update(u[-1], y[-1])
    np.testing.assert_allclose(est.covariance_, P1, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(est.parameters_, th1, rtol=1e-8, atol=1e-12)
    # the information along phi decays by lam before the measurement's is added
    assert phi @ (R1 - np.outer(phi, phi)) @ phi == pytest.approx(lam * (phi @ R0 @ phi))


def test_directional_forgetting_keeps_unexcited_directions_from_winding_up():
    # a constant input excites one direction; exponential forgetting winds the rest up
    u = np.concatenate([np.random.default_rng(8).standard_normal(200), np.full(800, 0.3)])
    y = _hammerstein(U0 + 0.2 * u, C, CQ, D)
    kw = dict(dt=DT, forgetting=0.95, delta=1.0, max_trace=1e6, quadratic_scale=SCALE,
              input_offset=U0)
    expo = RecursiveKautzEstimator(POLES, **kw).fit(U0 + 0.2 * u, y)
    dirf = RecursiveKautzEstimator(POLES, directional=True, **kw).fit(U0 + 0.2 * u, y)
    assert np.trace(expo.covariance_) > 1e3 * np.trace(dirf.covariance_)
    assert np.trace(dirf.covariance_) <= 5.0  # never above its start, delta I of 5 parameters
    assert dirf.n_clamped_ == 0
    np.testing.assert_allclose(dirf.covariance_ @ np.linalg.inv(dirf.covariance_),
                               np.eye(5), atol=1e-9)


def test_directional_forgetting_tracks_a_change_more_slowly_than_exponential_forgetting():
    # noise-free Hammerstein data whose linear gain and offset change at sample 1200
    u = _levels(4800, seed=9)
    y = np.concatenate([_hammerstein(u[:1200], C, CQ, D),
                        _hammerstein(u, 1.5 * C, CQ, D + 0.5)[1200:]])
    truth = np.r_[1.5 * C, D + 0.5, CQ]

    def error_after_change(**kw) -> np.ndarray:
        est = RecursiveKautzEstimator(POLES, dt=DT, delta=100.0, input_offset=U0,
                                      quadratic_scale=SCALE, **kw).fit(u[:1200], y[:1200])
        errs = []
        for k in range(1200, 4800, 600):
            est.partial_fit(u[k:k + 600], y[k:k + 600])
            errs.append(np.max(np.abs(est.parameters_ - truth)))
        return np.array(errs)

    expo = error_after_change(forgetting=0.97)
    dirf = error_after_change(forgetting=0.97, directional=True)
    stuck = error_after_change(forgetting=1.0)
    assert expo[0] < 1e-3  # exponential forgetting: converged within 600 samples
    # directional forgetting forgets only along the regressor, so its memory is longer
    # (here about 0.1 -> 0.01 over 3600 samples), but it does converge: no forgetting stays
    # at a compromise of the two systems
    assert dirf[0] > 10 * expo[0] and np.all(np.diff(dirf) < 0) and dirf[-1] < 0.02
    assert stuck[-1] > 0.1


def test_reseed_takes_both_banks_states_and_restarts_the_quadratic_coefficients():
    est = RecursiveKautzEstimator(POLES, dt=DT, input_offset=U0, quadratic_scale=SCALE,
                                  directional=True)
    u = _levels(300, seed=10)
    est.fit(u, _hammerstein(u, C, CQ, D))
    model = kt.KautzModel(est.basis_, np.array([0.7, 0.1]))
    est.reseed(model, offset=1.0, state=np.arange(4.0), delta=3.0)
    np.testing.assert_allclose(est.state_, np.arange(4.0))
    np.testing.assert_allclose(est.quadratic_coef_, 0.0)
    np.testing.assert_allclose(est.covariance_, 3.0 * np.eye(5))
    est.reseed(model, state=np.ones(2))  # the linear bank's state alone: the other at rest
    np.testing.assert_allclose(est.state_, [1.0, 1.0, 0.0, 0.0])
    with pytest.raises(DimensionError, match="state"):
        est.reseed(model, state=np.ones(3))


def test_new_option_errors():
    with pytest.raises(DataError, match="quadratic_scale"):
        RecursiveKautzEstimator(POLES, dt=DT, quadratic_scale=0.0).reset()
    with pytest.raises(DataError, match="directional"):
        RecursiveKautzEstimator(POLES, dt=DT, directional="yes").reset()
    assert RecursiveKautzEstimator(POLES, dt=DT).reset().quadratic_coef_.size == 0


def test_updater_judges_the_running_model_with_its_quadratic_channel_and_refills_its_state():
    u = _levels(1200, seed=11)
    y = _hammerstein(u, C, CQ, D)
    model = kt.KautzModel(kt.KautzBasis(POLES, dt=DT, delayed=True), C)
    upd = Updater(model, dt=DT, offset=D, input_offset=U0, forgetting=1.0, delta=1e6,
                  quadratic_scale=SCALE, directional_forgetting=True, reidentify=False,
                  buffer_size=600)
    for k in range(u.size):
        upd.step(u[k], y[k])
    est = upd.estimator_
    np.testing.assert_allclose(est.quadratic_coef_, CQ, atol=1e-4)
    u_buf, y_buf = upd.recent_samples()
    fit_c, fit_m, _ = upd._validate(model, D, u_buf, y_buf, 200)
    assert fit_m > 99.9 > fit_c  # the running model has the quadratic part, the candidate not
    upd._adopt("test", model, D, fit_c, u_buf, filter_states(model.basis, u_buf - U0)[-1], None)
    xq = filter_states(est.basis_, (u_buf - U0) ** 2 / SCALE)[-1]
    np.testing.assert_allclose(est.state_[2:], xq, atol=1e-12)
    np.testing.assert_allclose(est.quadratic_coef_, 0.0)
    upd.close()


def test_the_hydraulic_profile_uses_both_and_the_others_neither():
    hyd = TwinConfig.for_plant("hydraulic")
    assert hyd.updater["quadratic_scale"] == hyd.ident_amplitude
    assert hyd.updater["directional_forgetting"] is True
    for name in ("tclab",):
        cfg = TwinConfig.for_plant(name)
        assert "quadratic_scale" not in cfg.updater and "directional_forgetting" not in cfg.updater


def test_switching_the_forgetting_mode_keeps_the_estimate_and_rebuilds_the_information():
    u = _levels(300, seed=12)
    y = _hammerstein(u, C, CQ, D)
    est = RecursiveKautzEstimator(POLES, dt=DT, forgetting=0.95, input_offset=U0,
                                  quadratic_scale=SCALE, directional=True).fit(u[:200], y[:200])
    assert est.directional_
    est.set_directional(False)  # exponential: the plain recursion from the same estimate
    ref = RecursiveKautzEstimator(POLES, dt=DT, forgetting=0.95, input_offset=U0,
                                  quadratic_scale=SCALE).fit(u[:200], y[:200])
    ref._theta[:] = est.parameters_
    ref._P[:] = est.covariance_
    est.partial_fit(u[200:250], y[200:250])
    ref.partial_fit(u[200:250], y[200:250])
    np.testing.assert_allclose(est.parameters_, ref.parameters_, rtol=1e-12, atol=1e-14)
    est.set_directional(True)  # back: R rebuilt as the inverse of P
    assert est.directional_
    np.testing.assert_allclose(est._R @ est.covariance_, np.eye(5), atol=1e-9)
    est.reset()
    assert est.directional_  # a reset returns to the parameter


def test_updater_forgets_exponentially_while_desynchronised():
    from kautztwin.twin.update import SyncMonitor

    u = _levels(1600, seed=13)
    y = np.concatenate([_hammerstein(u[:800], C, 0 * CQ, D),  # the model, then the gain
                        _hammerstein(u, 2.0 * C, CQ, D)[800:]])  # doubles and bends at 800
    model = kt.KautzModel(kt.KautzBasis(POLES, dt=DT, delayed=True), C)
    upd = Updater(model, dt=DT, offset=D, input_offset=U0, forgetting=0.98,
                  quadratic_scale=SCALE, directional_forgetting=True, reidentify=False,
                  monitor=SyncMonitor(window=100, stride=20, threshold=95.0))
    modes, kinds = [], []
    for k in range(u.size):
        r = upd.step(u[k], y[k])
        kinds += [ev.kind for ev in r.events]
        modes.append(upd.estimator_.directional_)
        if r.events and r.events[0].kind == "desync":
            assert not upd.estimator_.directional_
    assert "desync" in kinds and "resync" in kinds
    assert all(modes[:800]) and not all(modes[800:]) and modes[-1]  # in sync again at the end
    upd.close()


def _regime_updater(**kw) -> Updater:
    from kautztwin.twin.update import SyncMonitor

    model = kt.KautzModel(kt.KautzBasis(POLES, dt=DT, delayed=True), C)
    kw.setdefault("directional_forgetting", True)
    return Updater(model, dt=DT, offset=D, input_offset=U0, forgetting=0.98,
                   quadratic_scale=SCALE, reidentify=False,
                   monitor=SyncMonitor(window=100, stride=20, threshold=95.0,
                                       resync_margin=1.0), **kw)


def _stepped(n: int, n_steps: int, seed: int, **kw) -> tuple[Updater, np.ndarray, np.ndarray]:
    """An updater of :func:`_regime_updater` stepped over the first ``n_steps`` of ``n``
    samples of the Hammerstein system (the model's own regime: every window fits)."""
    u = _levels(n, seed=seed)
    y = _hammerstein(u, C, CQ, D)
    upd = _regime_updater(**kw)
    for k in range(n_steps):
        upd.step(u[k], y[k])
    return upd, u, y


def test_a_new_regime_forgets_exponentially_until_a_window_of_its_own_fits():
    upd, u, y = _stepped(900, 300, seed=14)
    fits_before = upd.monitor.n_fits
    assert upd.estimator_.directional_ and fits_before > 0 and upd.monitor.fit >= 96.0
    upd.enter_new_regime()
    assert not upd.estimator_.directional_
    modes, n_fits = [], []
    for k in range(300, 600):
        upd.step(u[k], y[k])
        modes.append(upd.estimator_.directional_)
        n_fits.append(upd.monitor.n_fits)
    # windows completed in the regime's first 99 samples hold older samples: they do not
    # count, however well they fit; the first window of 100 samples of its own (completed
    # at the 100th or, with the stride, up to 19 samples later) ends it
    first_own = next(j for j in range(99, 300) if n_fits[j] > n_fits[j - 1])
    assert first_own < 120 and any(n_fits[j] > n_fits[j - 1] for j in range(1, 99))
    assert not any(modes[:first_own]) and all(modes[first_own:])
    upd.close()


def test_a_new_regime_that_does_not_fit_stays_exponential_and_a_desync_takes_it_over():
    u = _levels(1400, seed=15)
    # the new regime's gain is 4.5 % higher: the windows fit about 95.5 % at first,
    # then a bent and doubled gain makes the twin desynchronise
    y = np.concatenate([_hammerstein(u[:400], C, 0 * CQ, D),
                        _hammerstein(u, 1.045 * C, 0 * CQ, D)[400:700],
                        _hammerstein(u, 2.0 * C, CQ, D)[700:]])
    upd = _regime_updater(fast_update=False)  # frozen parameters: the fits stay where they are
    for k in range(400):
        upd.step(u[k], y[k])
    upd.enter_new_regime()
    fits, modes, kinds = [], [], []
    for k in range(400, u.size):
        r = upd.step(u[k], y[k])
        kinds += [ev.kind for ev in r.events]
        fits.append(upd.monitor.fit)
        modes.append(upd.estimator_.directional_)
    own = np.array(fits[120:300])
    assert np.all(own < 96.0) and np.median(own) >= 95.0  # never at the resync level ...
    assert upd.events[0].k >= 700  # ... nor desynchronised before the bend ...
    assert not any(modes[:300]) and upd.monitor.n_fits > 10  # ... so exponential throughout
    assert kinds[0] == "desync" and upd._regime_left is None  # the recovery owns it now
    upd.close()


def test_a_new_regime_with_a_fresh_covariance_and_without_directional_forgetting():
    upd, _, _ = _stepped(300, 300, seed=16)
    upd.enter_new_regime(fresh_covariance=True)
    np.testing.assert_array_equal(upd.estimator_.covariance_, upd.delta * np.eye(5))
    plain, _, _ = _stepped(300, 300, seed=16, directional_forgetting=False)
    before = plain.estimator_.covariance_
    plain.enter_new_regime()  # exponential forgetting already: nothing to change
    assert not plain.estimator_.directional_ and plain._regime_left is None
    np.testing.assert_array_equal(plain.estimator_.covariance_, before)
    upd.close()
    plain.close()


def test_a_new_version_ends_a_new_regime():
    upd, u, y = _stepped(400, 200, seed=17)
    upd.enter_new_regime()
    for k in range(200, 230):
        upd.step(u[k], y[k])
    assert not upd.estimator_.directional_ and upd._regime_left is not None
    u_buf, _ = upd.recent_samples()
    model = upd.digital_model.model
    upd._adopt("test", model, D, 99.0, u_buf, filter_states(model.basis, u_buf - U0)[-1], None)
    assert upd.estimator_.directional_ and upd._regime_left is None
    upd.close()
