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


# --------------------------------------------------------------------------- scoring, cost
def joint_scores(prob, den, folds, ms):
    """Oracle of ``_Scorer.score``: for every ``m`` and fold, one weighted least-squares
    problem over the training rows of all records, numerator and every record's nuisance
    columns together (block diagonal), solved by ``numpy.linalg.lstsq``; a record without
    training rows gets its nuisance from its test rows; pooled test and training sums."""
    cols = prob.all_columns(den, 0.0)
    ys = [np.asarray(r.y) for r in prob.records]
    ws = [np.asarray(r.weights) for r in prob.records]
    out = {}
    for m in ms:
        err = spread = 0.0
        first = None
        for train, test in folds:
            q = [N.shape[1] for _, N in cols]
            rows, tgt = [], []
            for j, ((R, N), y, w, tr) in enumerate(zip(cols, ys, ws, train, strict=True)):
                if not tr.any():
                    continue
                block = np.zeros((int(tr.sum()), sum(q)))
                block[:, sum(q[:j]): sum(q[: j + 1])] = N[tr]
                sw = np.sqrt(w[tr])[:, None]
                rows.append(np.hstack([R[tr][:, : m + 1], block]) * sw)
                tgt.append(y[tr] * sw[:, 0])
            theta = np.linalg.lstsq(np.vstack(rows), np.concatenate(tgt), rcond=None)[0]
            b = theta[: m + 1]
            sums = np.zeros(4)
            for j, ((R, N), y, w, tr, te) in enumerate(zip(cols, ys, ws, train, test,
                                                          strict=True)):
                if tr.any():
                    c = theta[m + 1 + sum(q[:j]): m + 1 + sum(q[: j + 1])]
                else:
                    sw = np.sqrt(w[te])
                    c = np.linalg.lstsq(N[te] * sw[:, None], (y[te] - R[te][:, : m + 1] @ b)
                                        * sw, rcond=None)[0]
                yh = R[:, : m + 1] @ b + N @ c
                for k, mask in ((0, te), (2, tr)):
                    if mask.any():
                        e = y[mask] - np.average(y[mask], weights=w[mask])
                        sums[k] += np.sum(w[mask] * (y[mask] - yh[mask]) ** 2)
                        sums[k + 1] += np.sum(w[mask] * e**2)
            err, spread = err + sums[0], spread + sums[1]
            first = sums if first is None else first
        out[m] = (100 * (1 - np.sqrt(err / spread)), 100 * (1 - np.sqrt(first[2] / first[3])),
                  first[2])
    return out


@pytest.mark.parametrize("folds_kind", ["split", "leave one record out"])
def test_scorer_equals_one_joint_least_squares_fit_per_number_of_zeros(folds_kind):
    # the scorer projects the nuisance columns out once for all m and solves every m from
    # one QR factorisation; the oracle solves each m as one plain least-squares problem
    from kautztwin.ident.tfest.problem import _Problem

    system = ([1.0, 2.0], np.poly([-0.6, -1.5 + 2.0j, -1.5 - 2.0j]).real)
    r1, _ = io_record(system, n=300, noise=0.05, seed=4)
    r2, _ = io_record(system, n=240, noise=0.05, seed=5)
    r2 = Record(r2.t, r2.u, r2.y + 3.0, kind="io", u_before=0.0,
                weights=np.where(np.arange(240) % 7 == 0, 2.0, 1.0))  # merged rows
    recs = [r1, r2]
    if folds_kind == "split":
        folds = [([r.t < 10.0 for r in recs], [r.t >= 10.0 for r in recs])]
    else:
        whole = [np.ones(r.n_samples, bool) for r in recs]
        none = [np.zeros(r.n_samples, bool) for r in recs]
        folds = [([none[0], whole[1]], [whole[0], none[1]]),
                 ([whole[0], none[1]], [none[0], whole[1]])]
    est = TransferFunctionEstimator("auto")
    den = np.poly([-0.7, -1.2 + 1.8j, -1.2 - 1.8j]).real
    got = _Scorer(est, recs, folds).score(den, 0.0, [0, 1, 2])
    want = joint_scores(_Problem(recs, 3, 2, intersample="zoh", offset=True,
                                 initial_state="auto"), den, folds, [0, 1, 2])
    for m in (0, 1, 2):
        np.testing.assert_allclose(got[m], want[m], rtol=1e-9)


@pytest.mark.parametrize("validate_from", [None, 40.0])
def test_a_screened_start_costs_its_training_rss_with_the_full_numerator(validate_from):
    # with the internal split and with a validation part, the screening ranks a start by
    # the scorer's training RSS of n - 1 zeros instead of a separate simulation of the
    # estimation records: the two are the same least-squares problem
    from kautztwin.ident.tfest.problem import _Problem
    from kautztwin.ident.tfest.structure import _prepare

    rec, _ = io_record(([2.0], np.poly([-0.5, -3.0]).real), n=1200, noise=0.05, seed=2)
    est = TransferFunctionEstimator("auto", validate_from=validate_from)
    estimation = est._split([rec])[0]
    search = _prepare(est, [rec], estimation).search
    assert search.cost_from_score
    for n in (2, 3, 5):
        den = np.poly(-np.linspace(0.4, 4.0, n)).real
        rss = search.scorer.score(den, 0.0, [n - 1])[n - 1][2]
        prob = _Problem(search.fit_recs, n, n - 1, intersample="zoh", offset=True,
                        initial_state="auto")
        r = prob.residual(den, 0.0)
        assert rss == pytest.approx(float(r @ r), rel=1e-9)


def test_the_challenger_gate_refines_only_a_pick_within_reach():
    # a challenger family (reach given) is screened with patience and refined only when
    # its screened pick comes within _NEAR points of the criterion it must reach
    from kautztwin.ident.tfest.structure import _NEAR, _PATIENCE, _prepare

    rec, _ = io_record(([2.0], np.poly([-0.5, -3.0]).real), n=1200, noise=0.05, seed=2)
    est = TransferFunctionEstimator("auto", validate_from=40.0)
    est.n_evaluations_ = 0
    estimation = est._split([rec])[0]
    far = _prepare(est, [rec], estimation).search
    pick = far.run(0.02, reach=200.0)
    assert far.unrefined and not far.refined and all(c.sol is None for c in far.cands)
    assert pick.criterion < 200.0 - _NEAR
    assert far.screened_to <= pick.n + _PATIENCE < far.bound
    near = _prepare(est, [rec], estimation).search
    chosen = near.run(0.02, reach=pick.criterion)
    assert not near.unrefined and any(c.sol is not None for c in near.cands)
    # the same screening plus refined candidates: the pick's penalised criterion can only rise
    assert chosen.criterion - 0.02 * chosen.n >= pick.criterion - 0.02 * pick.n


def test_only_the_search_s_refinement_to_convergence_may_stop_at_a_slow_mode(monkeypatch):
    # brief refinements can pass through models with a mode slower than the records and come
    # back, so only the final refinement of the pick (and not the refit of the internal
    # split on the whole records) is stopped there
    import kautztwin.ident.tfest.structure as structure

    calls = []
    real = structure.refine_order

    def spy(tf, est, n, m, **kw):
        calls.append((kw.get("max_iter"), kw.get("stop_unresolved", False), len(est[0].t)))
        return real(tf, est, n, m, **kw)

    monkeypatch.setattr(structure, "refine_order", spy)
    rec, _ = io_record(([2.0], np.poly([-0.5, -3.0]).real), n=600, noise=0.05, seed=2)
    TransferFunctionEstimator("auto", validate_from=20.0).fit(rec)
    assert any(it is None for it, _, _ in calls) and any(it is not None for it, _, _ in calls)
    assert all(stop == (it is None) for it, stop, _ in calls)
    calls.clear()
    TransferFunctionEstimator("auto").fit(rec)  # internal split: the refit is not stopped
    refit = [c for c in calls if c[2] == rec.n_samples]
    assert refit and not any(stop for _, stop, _ in refit)


def test_a_refinement_may_be_stopped_at_a_mode_slower_than_the_records():
    # an integrating plant fitted with stable poles: the output-error descent drives a pole
    # towards 0; with stop_unresolved it stops at the first such iterate (the search rejects
    # that model), on a plant whose modes the record resolves nothing changes
    from kautztwin.ident.tfest.refine import refine_order

    def refine(system, start, stop):
        rec, _ = io_record(system, n=600, noise=0.02, seed=6)
        tf = TransferFunctionEstimator(2, 1)
        tf.n_evaluations_ = 0
        limit = 1.0 / rec.duration
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)  # the slow pole, expected
            _, den, _, sol = refine_order(tf, [rec], 2, 1, starts=[(start, 0.0)],
                                          min_rate=limit, stop_unresolved=stop)
        return den, sol, limit

    start = np.array([-0.8 + 0j, -2.0 + 0j])
    den, sol, limit = refine(([2.0], [1.0, 1.0, 0.0]), start, stop=False)
    assert np.min(-np.roots(den).real) < limit  # the unstopped refinement ends there
    den_s, sol_s, _ = refine(([2.0], [1.0, 1.0, 0.0]), start, stop=True)
    assert sol_s.status == -2 and np.min(-np.roots(den_s).real) < limit
    assert sol_s.nfev < sol.nfev
    stable = ([2.0], np.poly([-0.5, -3.0]).real)
    a, sol_a, _ = refine(stable, start, stop=False)
    b, sol_b, _ = refine(stable, start, stop=True)
    np.testing.assert_array_equal(a, b)
    assert sol_a.success and sol_b.nfev == sol_a.nfev


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
