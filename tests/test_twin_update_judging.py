"""The update module's public entries for candidates built outside it (judging, window, buffer).

Oracles: the plant is a cascade of first-order lags simulated independently (a loop over
the difference equations); a candidate fitted to the drifted plant must predict it exactly
(fit ~ 100 %), the nominal model cannot; ``update_from_step_test`` is the path whose
judgement ``judge_candidate`` must repeat bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from kautztwin import KautzBasis, KautzModel
from kautztwin.exceptions import DataError
from kautztwin.ident.kautz_oe import filter_states
from kautztwin.twin.update import RecursiveKautzEstimator, Updater
from kautztwin.twin.update.judging import candidate_verdict
from kautztwin.twin.update.steptest import step_test_record

# the pole worker's test signal and plant (a cascade of lags, simulated independently)
from test_twin_pole_worker import DT, POLES, POLES_SLOW, _binary, _cascade


def _fitted(poles: np.ndarray) -> RecursiveKautzEstimator:
    u = _binary(600, 10)
    return RecursiveKautzEstimator(poles, dt=DT, forgetting=1.0, delta=1e8).fit(
        u, _cascade(u, poles))


def _drifted(**kw) -> Updater:
    """A twin of the nominal plant that has seen 500 samples of the drifted one."""
    upd = Updater(_fitted(POLES).model_, dt=DT, offset=3.0, reidentify=False, fast_update=False,
                  reid_samples=200, burn_in=100, **kw)
    u = _binary(500, 3)
    for uk, yk in zip(u, _cascade(u, POLES_SLOW), strict=True):
        upd.step(uk, yk)
    return upd


def test_a_candidate_of_the_drifted_plant_is_judged_exact_and_adopted():
    upd = _drifted()
    slow = _fitted(POLES_SLOW)
    u, y, n_val = upd.validation_window()
    assert (u.size, n_val) == (300, 60)  # reid_samples + burn_in, 30 % of reid_samples
    counts = upd.counts
    mu = upd.judge_candidate(slow.model_, slow.offset_, u, y, n_val, kind="step-test",
                             k_submitted=7)
    assert mu.accepted and mu.kind == "step-test" and (mu.k, mu.k_submitted) == (500, 7)
    assert mu.fit_candidate > 99.9 > 90.0 > mu.fit_current  # exact versus the old poles
    assert upd.digital_model.version == 2 and upd.digital_model.provenance == "step-test"
    np.testing.assert_array_equal(upd.model.coefficients, slow.model_.coefficients)
    assert upd.counts["accepted"] == counts["accepted"] + 1
    assert upd.counts["attempts"] == counts["attempts"]  # counting is the caller's
    upd.count_attempt()
    assert upd.counts["attempts"] == counts["attempts"] + 1
    # the adopted model predicts the drifted plant from here on
    u_next = _binary(700, 3)
    y_next = _cascade(u_next, POLES_SLOW)
    np.testing.assert_allclose(upd.predict(u_next[500:]), y_next[500:], atol=1e-6)


def test_the_nominal_model_is_rejected_and_nothing_changes():
    upd = _drifted()
    nominal = _fitted(POLES)
    before = upd.model.coefficients.copy()
    mu = upd.judge_candidate(nominal.model_, nominal.offset_, *upd.validation_window(),
                             kind="reidentification")
    assert not mu.accepted and "does not beat" in mu.reason
    assert upd.digital_model.version == 1 and upd.model_updates[-1] is mu
    np.testing.assert_array_equal(upd.model.coefficients, before)


def test_judge_candidate_repeats_the_step_test_judgement_bit_for_bit():
    a, b = _drifted(), _drifted()
    step = _cascade(np.ones(200), POLES_SLOW)
    mu_a = a.update_from_step_test(step, u0=0.0, y0=3.0)  # pole optimisation from core_poles
    mu_b = b.judge_candidate(mu_a.candidate, mu_a.offset, *b.validation_window(),
                             kind="step-test")
    assert mu_a.accepted and mu_b.accepted and mu_a.reason == mu_b.reason
    assert (mu_a.fit_candidate, mu_a.fit_current) == (mu_b.fit_candidate, mu_b.fit_current)
    np.testing.assert_array_equal(a.predict(np.ones(40)), b.predict(np.ones(40)))


def test_a_pole_reoptimisation_continues_the_live_model_on_the_new_basis():
    """``from_live``: the version is the candidate, the fast path the live model re-expressed.

    The candidate's basis holds the live model's poles (and the drifted plant's): the live
    model is then exactly representable on it, so the fast path must go on predicting what
    the live model predicts (an untouched twin is the oracle) - not what the candidate
    predicts - and its coefficients must be the live impulse response's least-squares
    coefficients on the new basis (a long pulse response and ``lstsq``, independent of the
    Stein equation the updater solves).
    """
    live, untouched = _drifted(), _drifted()
    slow = _fitted(POLES_SLOW)
    basis = KautzBasis(np.r_[POLES_SLOW, POLES[0]], dt=DT, delayed=True)
    assert np.allclose(np.sort(basis.poles.real)[:2], np.sort(POLES))  # holds the live poles
    candidate = KautzModel(basis, np.r_[slow.model_.coefficients, 0.0])  # the drifted plant
    mu = live.judge_candidate(candidate, slow.offset_, *live.validation_window(),
                              kind="step-test", from_live=True)
    assert mu.accepted and mu.fit_candidate > 99.9 > 90.0 > mu.fit_current
    assert live.digital_model.version == 2  # the version is the candidate
    np.testing.assert_array_equal(live.digital_model.model.coefficients,
                                  candidate.coefficients)
    pulse = np.zeros(2000)
    pulse[0] = 1.0
    h_live = filter_states(untouched.estimator_.basis_, pulse)[:-1] @ untouched.model.coefficients
    coef, *_ = np.linalg.lstsq(filter_states(basis, pulse)[:-1], h_live, rcond=None)
    np.testing.assert_allclose(live.model.coefficients, coef, rtol=0, atol=1e-10)
    assert live.offset == untouched.offset == 3.0
    u_next = _binary(200, 4)
    np.testing.assert_allclose(live.predict(u_next), untouched.predict(u_next), rtol=0,
                               atol=1e-9)
    # without it, the fast path starts from the candidate: the drifted plant
    plain = _drifted()
    plain.judge_candidate(candidate, slow.offset_, *plain.validation_window(), kind="step-test")
    y_next = _cascade(np.r_[_binary(500, 3), u_next], POLES_SLOW)[500:]
    np.testing.assert_allclose(plain.predict(u_next), y_next, atol=1e-6)
    assert np.max(np.abs(live.predict(u_next) - y_next)) > 0.1


def test_a_step_test_from_the_live_model_carries_it_over_and_a_measured_one_does_not():
    """``update_from_step_test(from_live=True)`` judges as before and carries the live model."""
    a, b, c = _drifted(), _drifted(), _drifted()
    step = _cascade(np.ones(200), POLES_SLOW)
    mu_a = a.update_from_step_test(step, u0=0.0, y0=3.0, from_live=True)
    mu_b = b.judge_candidate(mu_a.candidate, mu_a.offset, *b.validation_window(),
                             kind="step-test", from_live=True)
    mu_c = c.update_from_step_test(step, u0=0.0, y0=3.0)  # a measured step test
    assert mu_a.accepted and mu_b.accepted and mu_c.accepted
    assert (mu_a.fit_candidate, mu_a.fit_current) == (mu_c.fit_candidate, mu_c.fit_current)
    np.testing.assert_array_equal(a.predict(np.ones(40)), b.predict(np.ones(40)))
    np.testing.assert_array_equal(a.digital_model.model.coefficients,
                                  c.digital_model.model.coefficients)
    np.testing.assert_array_equal(c.model.coefficients, mu_c.candidate.coefficients)
    assert not np.allclose(a.model.coefficients, mu_a.candidate.coefficients, atol=1e-3)


def test_a_late_judgement_starts_the_winner_from_its_state_now():
    now, late = _drifted(), _drifted()
    slow = _fitted(POLES_SLOW)
    window, k_window = late.validation_window(), late.k
    u = _binary(560, 3)
    y = _cascade(u, POLES_SLOW)
    for upd in (now, late):
        for uk, yk in zip(u[500:], y[500:], strict=True):
            upd.step(uk, yk)
    now.judge_candidate(slow.model_, slow.offset_, *now.validation_window(), kind="step-test")
    mu = late.judge_candidate(slow.model_, slow.offset_, *window, kind="step-test",
                              k_window=k_window)
    assert mu.accepted and mu.k == 560
    # the winner continues from its filter state at sample 560, run over the input from the
    # window's first sample (200: 300 samples before 500) on; the full history from sample 0
    # differs by the slow pole's decay over 360 samples, exp(-18) ~ 1.5e-8
    basis = slow.model_.basis
    np.testing.assert_allclose(late.estimator_.state_, filter_states(basis, u[200:])[-1],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(late.estimator_.state_, filter_states(basis, u)[-1],
                               rtol=0, atol=1e-7)
    # judged now, on its own window (300 samples), the same state up to exp(-15) ~ 3e-7
    np.testing.assert_allclose(now.estimator_.state_, late.estimator_.state_, rtol=0, atol=2e-6)


def test_recent_samples_core_poles_and_the_empty_window():
    upd = Updater(_fitted(POLES).model_, dt=DT, offset=3.0, extra_poles=[-0.5], burn_in=50)
    assert upd.validation_window() is None  # nothing buffered yet
    upd.step(1.0, 3.0)
    upd.step(1.0, float("nan"))  # a dropout: not used
    u, y = upd.recent_samples()
    np.testing.assert_array_equal(u, [1.0, 1.0])
    assert y[0] == 3.0 and np.isnan(y[1])
    assert upd.estimator_.basis_.n_functions == 3 and upd.n_core_functions == 2
    np.testing.assert_allclose(np.sort(upd.core_poles.real), [-5.0, -2.0], rtol=1e-9)
    u[0] = 99.0  # a copy
    assert upd.recent_samples()[0][0] == 1.0


@pytest.mark.parametrize(("u", "y", "n_val", "match"), [
    (np.zeros(20), np.zeros(19), 5, "one length"),
    (np.zeros((20, 1)), np.zeros((20, 1)), 5, "1-D"),
    (np.zeros(20), np.zeros(20), 0, "n_val"),
    (np.zeros(20), np.zeros(20), 21, "at most len"),
], ids=["lengths", "2-d", "no-held-out", "too-many-held-out"])
def test_judge_candidate_rejects_a_bad_window(u, y, n_val, match):
    upd = _drifted()
    with pytest.raises(DataError, match=match):
        upd.judge_candidate(upd.digital_model.model, 3.0, u, y, n_val, kind="step-test")


def test_the_verdict_and_the_step_record():
    kw = {"min_improvement": 1.0, "min_candidate_fit": 50.0}
    assert candidate_verdict(80.5, 80.0, 60, **kw)[0] is False  # not better by 1 %
    assert candidate_verdict(81.5, float("nan"), 60, **kw)[0] is True  # nothing to beat
    assert candidate_verdict(float("nan"), 10.0, 60, **kw)[0] is False
    ok, why = candidate_verdict(40.0, 10.0, 60, **kw)
    assert not ok and "below min_candidate_fit = 50 %" in why
    assert candidate_verdict(40.0, 10.0, 60, min_improvement=1.0, min_candidate_fit=None)[0]
    u, y = step_test_record(np.array([1.0, 2.0]), u0=0.5, y0=-1.0, amplitude=-2.0, burn_in=0)
    np.testing.assert_array_equal(u, [0.5, -1.5, -1.5])  # at least one sample at rest
    np.testing.assert_array_equal(y, [-1.0, 1.0, 2.0])
