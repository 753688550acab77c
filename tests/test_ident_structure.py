"""Tests of the structure search of ``TransferFunctionEstimator(n_poles='auto')`` (issue #13).

Oracles: a six-pole resonant system (three lightly damped modes, simulated exactly for a
held input by ``scipy.signal.lsim``) whose order, zeros, modes and fit are recovered from
noisy data; noise-free data, where VARPRO on the high-order ARX model's impulse response
recovers the true poles; and hand-made candidate lists for the choice rule.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.signal

from kautztwin.exceptions import ConvergenceWarning, DataError
from kautztwin.ident import Record, TransferFunctionEstimator
from kautztwin.ident.tfest.structure import (
    MAX_BOUND,
    MIN_BOUND,
    _Candidate,
    _extra_poles,
    _Scorer,
    _Search,
    search_bound,
)

MODES = np.array([1.0, 3.0, 8.0])  # rad/s, damping 0.1, unit DC gain each


def resonant(zeta: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Sum of three second-order modes: six poles, four zeros."""
    num, den = np.zeros(1), np.ones(1)
    for w in MODES:
        d = np.array([1.0, 2 * zeta * w, w * w])
        num = np.polyadd(np.polymul(num, d), w * w * den)
        den = np.polymul(den, d)
    return num, den


def io_record(system, n: int = 1200, dt: float = 0.05, noise: float = 0.05, seed: int = 0):
    """A held random binary input, the exactly simulated output plus white noise."""
    rng = np.random.default_rng(seed)
    t = dt * np.arange(n)
    u = np.repeat(rng.choice([-1.0, 1.0], n // 8 + 1), 8)[:n]
    _, y0, _ = scipy.signal.lsim(system, u, t, interp=False)
    y = y0 + noise * np.std(y0) * rng.standard_normal(n)
    return Record.from_data(t, u, y, kind="io", u_before=0.0), y0


def fit_percent(y, yh):
    return 100.0 * (1.0 - np.linalg.norm(y - yh) / np.linalg.norm(y - np.mean(y)))


@pytest.fixture(scope="module")
def six_pole_fit():
    rec, y0 = io_record(resonant())
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)  # no warning at the bound
        est = TransferFunctionEstimator("auto").fit(rec)
    return est, rec, y0


# --------------------------------------------------------------------------- known order
def test_six_pole_resonant_system_order_and_zeros_are_recovered(six_pole_fit):
    est, _, _ = six_pole_fit
    assert (est.n_poles_, est.n_zeros_) == (6, 4)
    assert est.search_["bound"] >= MIN_BOUND


def test_six_pole_resonant_system_modes_are_recovered(six_pole_fit):
    est, _, _ = six_pole_fit
    p = est.model_.poles
    freq = np.sort(np.abs(p[p.imag > 0]))
    np.testing.assert_allclose(freq, MODES, rtol=0.02)  # 5 % output noise


def test_six_pole_resonant_system_fit_matches_the_true_model(six_pole_fit):
    # the fit to the noisy data is within half a point of the true model's on the same data
    est, rec, y0 = six_pole_fit
    true_fit = fit_percent(np.asarray(rec.y), y0)
    assert est.model_.fit_percent == pytest.approx(true_fit, abs=0.5)


def test_known_third_order_from_step_records_is_chosen_by_holding_out_records():
    t = np.arange(300) * 0.05
    den = np.poly([-4.0, -1.5, -0.5]).real
    rng = np.random.default_rng(4)
    recs = []
    for height, offset in ((1.0, 0.0), (2.5, 3.0)):
        _, y = scipy.signal.step(([2.0 * height], den), T=t)
        y = offset + y + 0.01 * np.ptp(y) * rng.standard_normal(t.size)
        recs.append(Record.step_response(t, y, amplitude=height))
    est = TransferFunctionEstimator("auto", n_zeros=0, max_order=5).fit(recs)
    assert est.n_poles_ == 3
    assert est.search_["criterion"].startswith("leave-one-record-out")


# --------------------------------------------------------------------------- the bound
@pytest.mark.parametrize(("n_samples", "bound"), [(400, 10), (1500, 15), (5000, MAX_BOUND)],
                         ids=["short: at least 10", "longer: more", "long: at most 20"])
def test_search_bound_grows_with_the_record(n_samples, bound):
    rec, _ = io_record(resonant(), n=n_samples)
    got, why = search_bound(TransferFunctionEstimator("auto"), [rec])
    assert got == bound and "estimation samples" in why


def test_search_bound_is_lowered_to_what_the_samples_support():
    rec, _ = io_record(resonant(), n=60)
    got, why = search_bound(TransferFunctionEstimator("auto"), [rec])
    # io record: 3n + 2 parameters (n poles, n zeros at most, n initial states, offset)
    assert got == 6 and 3 * (3 * got + 2) <= 60 < 3 * (3 * (got + 1) + 2)
    assert "lowered" in why


def test_max_order_sets_the_bound():
    rec, _ = io_record(resonant(), n=400)
    assert search_bound(TransferFunctionEstimator("auto", max_order=3), [rec])[0] == 3


def test_a_pick_at_the_bound_warns():
    rec, _ = io_record(resonant(), n=600)
    with pytest.warns(ConvergenceWarning, match="search bound"):
        est = TransferFunctionEstimator("auto", max_order=3).fit(rec)
    assert est.n_poles_ == 3  # six are needed
    assert [r["n_poles"] for r in est.model_.order_selection] == [1, 2, 3]


# --------------------------------------------------------------------------- the choice
def cand(n, crit, m=0, refined=False):
    return _Candidate(n, m, np.full(n, -1.0 + 0j), 0.0, crit, 0.0, 0.0, refined=refined)


@pytest.mark.parametrize(("per_pole", "expect"), [(0.0, 3), (0.5, 2)], ids=["no", "0.5/pole"])
def test_pick_takes_the_best_criterion_a_higher_order_only_if_it_wins(per_pole, expect):
    search = _Search.__new__(_Search)
    search.cands = [cand(2, 80.0), cand(4, 79.9), cand(3, 80.4), cand(5, 80.4), cand(1, 10.0)]
    chosen = search.pick(per_pole)
    assert chosen.n == expect
    lower = [c.criterion for c in search.cands if c.n < chosen.n]
    assert all(chosen.criterion > v for v in lower)


def test_pick_prefers_the_lower_order_on_a_tie():
    search = _Search.__new__(_Search)
    search.cands = [cand(4, 90.0), cand(2, 90.0, refined=True), cand(2, 90.0)]
    chosen = search.pick(0.0)
    assert chosen.n == 2 and chosen.refined


def test_never_returns_a_higher_order_that_validates_worse():
    rec, _ = io_record(resonant(0.2), n=600, noise=0.1, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        est = TransferFunctionEstimator("auto", validate_from=15.0).fit(rec)
    rows = est.model_.order_selection
    chosen = next(r for r in rows if r["n_poles"] == est.n_poles_)
    # the chosen model is the one the criterion scored, its validation fit the reported one
    assert est.model_.validation_fit_percent == pytest.approx(chosen["criterion"], abs=1e-6)
    for r in rows:
        if r["n_poles"] < est.n_poles_:
            assert r["validation_fit_percent"] < est.model_.validation_fit_percent


def honest_cand(n, m, crit, fit, rss, refined=False):
    return _Candidate(n, m, np.full(n, -1.0 + 0j), 0.0, crit, fit, rss, refined=refined)


def test_internal_split_judges_a_structure_by_its_estimate_not_its_luckiest_start():
    # two starts of 3 poles: the one that fits the training rows best (rss 1.0) is the
    # estimate; the other scores better on the held-out rows only by chance and must not
    # decide the order (choosing among starts on held-out rows fits those rows too)
    search = _Search.__new__(_Search)
    search.honest = True
    search.cands = [honest_cand(2, 0, 62.0, 77.8, 1.10),
                    honest_cand(3, 0, 61.0, 77.9, 1.00),
                    honest_cand(3, 0, 68.0, 76.0, 1.30)]
    est = {(c.n, c.m): c for c in search.estimates()}
    assert est[(3, 0)].rss == 1.00 and est[(3, 0)].criterion == 61.0
    assert search.pick(0.5).n == 2
    search.honest = False  # with a validation part every candidate competes, as before
    assert search.pick(0.5).criterion == 68.0


def test_an_estimate_that_fits_worse_than_a_structure_it_contains_does_not_compete():
    # (5, 0) contains (2, 0): fitting the training rows 5 points worse, it is an
    # unconverged start, whatever its held-out score; (4, 1) fits better and competes
    search = _Search.__new__(_Search)
    search.honest = True
    search.cands = [honest_cand(2, 0, 60.0, 77.0, 1.0), honest_cand(5, 0, 70.0, 72.0, 1.5),
                    honest_cand(4, 1, 64.0, 77.5, 0.9)]
    assert {(c.n, c.m) for c in search.estimates()} == {(2, 0), (4, 1)}
    assert (search.pick(0.5).n, search.pick(0.5).m) == (4, 1)  # 64 - 2 > 60 - 1
    assert search.pick(2.0).n == 2  # 64 - 8 < 60 - 4


def test_internal_split_search_stops_screening_when_the_pick_settles():
    # a second-order plant: orders far above 2 are not screened, the pick is 2 poles
    rec, y0 = io_record(([2.0], np.poly([-0.5, -3.0]).real), n=600, dt=0.05, noise=0.05)
    est = TransferFunctionEstimator("auto").fit(rec)
    assert est.n_poles_ == 2
    assert est.search_["screened_to"] < est.search_["bound"]
    assert "last 33%" in est.search_["criterion"]
    assert est.model_.fit_percent == pytest.approx(fit_percent(np.asarray(rec.y), y0), abs=0.5)


# --------------------------------------------------------------------------- warm starts
def test_screening_warm_starts_from_the_lower_orders(six_pole_fit):
    est, rec, _ = six_pole_fit
    fit_recs = [rec.select(rec.t < rec.t[0] + 2 / 3 * rec.duration)]
    train = [rec.t < rec.t[0] + 2 / 3 * rec.duration]
    search = _Search(est, fit_recs, _Scorer(est, [rec], [(train, [~train[0]])]), 8)
    search.screen()
    for n in range(3, 9):
        labels = dict(search.starts[n])
        grown = labels[f"order {n - 1} + real"]
        np.testing.assert_allclose(grown[: n - 1], search.best_poles[n - 1][0])
        assert f"order {n - 2} + pair" in labels or not np.any(
            search.starts[n][0][1].imag > 0)


def test_extra_poles_adds_the_reference_pole_farthest_from_the_lower_order():
    lower = np.array([-1.0 + 0j])
    ref = np.array([-1.01 + 0j, -7.0 + 0j, -2.0 + 3.0j, -2.0 - 3.0j])
    np.testing.assert_allclose(_extra_poles(lower, ref, "real", 100.0), [-7.0])
    np.testing.assert_allclose(_extra_poles(lower, ref, "pair", 100.0), [-2 + 3j, -2 - 3j])


def test_varpro_start_recovers_the_poles_of_an_exact_discrete_model():
    # the VARPRO start fits exponentials to the impulse response of the discrete model
    # (here the exact zero-order-hold model of the plant): its poles are the plant's
    system = ([3.0], np.poly([-0.7, -2.5]).real)
    dt = 0.05
    rec, _ = io_record(system, n=600, dt=dt, noise=0.0, seed=1)
    est = TransferFunctionEstimator("auto")
    search = _Search(est, [rec], _Scorer(est, [rec], [([np.ones(600, bool)],
                                                       [np.zeros(600, bool)])]), 4)
    num_d, den_d, _ = scipy.signal.cont2discrete(system, dt, method="zoh")
    search.high = (den_d, np.ravel(num_d)[1:])
    poles = search.varpro(np.array([-0.5 + 0j, -4.0 + 0j]), max_iter=50)
    np.testing.assert_allclose(np.sort(poles.real), [-2.5, -0.7], rtol=1e-6)


# --------------------------------------------------------------------------- bad input
def test_a_record_too_short_for_any_order_is_a_one_line_error():
    rec = Record.from_data([0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 0.0, 1.0], [0.0, 0.5, 0.2, 0.6])
    with pytest.raises(DataError, match="too short") as err:
        TransferFunctionEstimator("auto").fit(rec)
    assert "\n" not in str(err.value)


def test_an_order_too_high_for_the_record_is_a_one_line_error():
    rec, _ = io_record(resonant(), n=40)
    with pytest.raises(DataError, match="too short") as err:
        TransferFunctionEstimator(12).fit(rec)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("max_order", [0, True, 2.5], ids=["zero", "bool", "float"])
def test_rejects_a_bad_max_order(max_order):
    rec, _ = io_record(resonant(), n=200)
    with pytest.raises(DataError, match="max_order"):
        TransferFunctionEstimator("auto", max_order=max_order).fit(rec)
