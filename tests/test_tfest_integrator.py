"""Integrating models ``G(s)/s`` in ``TransferFunctionEstimator`` (``integrator=...``).

Oracles: the plant ``2 / (s (s + 1))`` driven by a held random binary input about the level
0.3 (not the record's mean input), simulated exactly by ``scipy.signal.lsim``; scipy's
simulation of ``G(s)/s`` for the equivalence of the integrated record with a first-order
hold; and a stable second-order plant, where no integrator may be chosen.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import scipy.signal

from kautztwin._json import to_jsonable
from kautztwin.exceptions import DataError
from kautztwin.ident import Record, TransferFunctionEstimator, simulate_lti
from kautztwin.ident.tfest.integrator import integrated
from kautztwin.metrics import fit_percent

LEVEL = 0.3
PLANT = ([2.0], [1.0, 1.0, 0.0])  # 2 / (s (s + 1))


def integrating_record(n: int = 600, dt: float = 0.1, noise: float = 0.02, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = dt * np.arange(n)
    u = LEVEL + np.repeat(rng.choice([-1.0, 1.0], n // 10 + 1), 10)[:n]
    _, y0, _ = scipy.signal.lsim(PLANT, u - LEVEL, t, interp=False)
    y0 = 5.0 + y0
    y = y0 + noise * np.std(y0) * rng.standard_normal(n)
    return Record.from_data(t, u, y), y0


@pytest.fixture(scope="module")
def auto_fit():
    rec, y0 = integrating_record()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = TransferFunctionEstimator("auto").fit(rec)
    return est, rec, y0


def test_integrated_record_with_first_order_hold_is_the_integrator_with_a_held_input():
    rec, _ = integrating_record(n=200, noise=0.0)
    g = ([3.0], [1.0, 2.0])
    v = integrated(rec, LEVEL)
    via_v = simulate_lti(g, v.t, v.u, intersample="foh")
    _, direct, _ = scipy.signal.lsim(([3.0], [1.0, 2.0, 0.0]), rec.u - LEVEL, rec.t,
                                     interp=False)
    np.testing.assert_allclose(via_v, direct, rtol=1e-7, atol=1e-9)


def test_auto_search_finds_the_integrator_its_level_and_the_plant(auto_fit):
    est, rec, y0 = auto_fit
    m = est.model_
    assert est.search_["integrator"]["chosen"] and m.integrating
    assert (m.n_poles, m.n_zeros) == (2, 0)
    np.testing.assert_allclose(m.den, [1.0, 1.0, 0.0], atol=0.02)
    np.testing.assert_allclose(m.num, [2.0], rtol=0.02)
    # the level is estimated (the record's mean input is 0.45, not 0.3)
    assert abs(float(np.mean(rec.u)) - LEVEL) > 0.05
    assert m.input_level == pytest.approx(LEVEL, abs=0.01)
    # as good as the true model on the same noisy data, and predict simulates that model
    assert m.fit_percent == pytest.approx(fit_percent(np.asarray(rec.y), y0), abs=0.5)
    yh = est.predict(rec)[0]
    assert fit_percent(np.asarray(rec.y), yh) == pytest.approx(m.fit_percent, abs=1e-8)


def test_integrating_model_reports_infinite_gain_and_is_json_ready(auto_fit):
    m = auto_fit[0].model_
    assert m.gain == np.inf and np.isnan(m.gain_std)
    d = m.to_dict()
    assert d["input_level"] == m.input_level
    json.dumps(to_jsonable(d))  # inf -> null


def test_stable_structures_challenge_the_integrating_pick_without_changing_it(auto_fit):
    # the integrating search runs first; the stable structures, screened until their pick
    # settles, come nowhere near its criterion and are not refined; the model returned is
    # the one the integrating search alone (integrator=True) finds
    est, rec, _ = auto_fit
    info = est.search_["integrator"]
    assert info["tried"] and info["chosen"] and info["stable_refined"] is False
    assert info["stable_criterion"] < info["criterion"] - 2.0
    stable = info["stable_search"]
    assert "unrefined" in stable and not stable["refined"]
    assert stable["screened_to"] < stable["bound"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        alone = TransferFunctionEstimator("auto", integrator=True).fit(rec).model_
    m = est.model_
    np.testing.assert_array_equal(m.den, alone.den)
    np.testing.assert_array_equal(m.num, alone.num)
    assert m.input_level == alone.input_level


def test_the_search_bound_counts_the_integrator():
    # G of G(s)/s is searched up to one pole less than the stable structures: the bound is
    # on the model's poles, as n_poles with integrator=True counts the integrator
    from kautztwin.ident.tfest.integrator import inner_estimator
    from kautztwin.ident.tfest.structure import search_bound

    rec, _ = integrating_record()
    for max_order in (None, 5):
        tf = TransferFunctionEstimator("auto", max_order=max_order)
        stable, _ = search_bound(tf, [rec])
        inner, why = search_bound(inner_estimator(tf), [integrated(rec, LEVEL)])
        assert inner == stable - 1 and "integrator" in why


def test_fixed_order_with_integrator_true_recovers_the_plant():
    rec, _ = integrating_record(seed=1)
    est = TransferFunctionEstimator(2, 0, integrator=True).fit(rec)
    m = est.model_
    assert est.n_evaluations_ > 0  # the fit of G on the integrated input is counted
    np.testing.assert_allclose(m.den, [1.0, 1.0, 0.0], atol=0.02)
    np.testing.assert_allclose(m.num, [2.0], rtol=0.02)
    assert m.input_level == pytest.approx(LEVEL, abs=0.01)
    assert m.parameter_names == ("num[0]", "den[1]") and m.std.size == 2


def test_validation_part_is_simulated_from_the_estimated_level():
    rec, y0 = integrating_record(seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = TransferFunctionEstimator(2, 0, integrator=True, validate_from=40.0).fit(rec)
    yh = est.predict(rec)[0]
    v = rec.t >= 40.0
    val = fit_percent(np.asarray(rec.y)[v], yh[v])
    assert est.model_.validation_fit_percent == pytest.approx(val, abs=1e-8)
    assert val > 90.0  # free run over 20 s of an integrating plant, 2 % noise


def test_a_stable_plant_gets_no_integrator():
    rng = np.random.default_rng(3)
    t = 0.05 * np.arange(600)
    u = np.repeat(rng.choice([-1.0, 1.0], 76), 8)[:600]
    _, y, _ = scipy.signal.lsim(([2.0], np.poly([-0.5, -3.0]).real), u, t, interp=False)
    rec = Record.from_data(t, u, y + 0.02 * np.std(y) * rng.standard_normal(t.size))
    est = TransferFunctionEstimator("auto").fit(rec)
    assert not est.model_.integrating and est.model_.input_level is None
    assert not est.search_["integrator"]["chosen"]
    off = TransferFunctionEstimator("auto", integrator=False).fit(rec)
    assert off.search_["integrator"] == {"tried": False, "chosen": False,
                                         "reason": "integrator=False"}


def test_integrator_false_keeps_the_stable_search_on_an_integrating_plant(auto_fit):
    _, rec, _ = auto_fit
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = TransferFunctionEstimator("auto", integrator=False).fit(rec).model_
    assert not m.integrating and m.fit_percent < auto_fit[0].model_.fit_percent


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"integrator": "yes"}, "integrator must be"),
    ({"n_poles": 1, "integrator": True}, "n_poles >= 2"),
    ({"integrator": True, "intersample": "foh"}, "held input"),
], ids=["bad value", "no pole besides the integrator", "first-order hold"])
def test_bad_integrator_settings_are_one_line_errors(kwargs, match):
    rec, _ = integrating_record(n=200)
    with pytest.raises(DataError, match=match) as err:
        TransferFunctionEstimator(**{"n_poles": 2, "n_zeros": 0, **kwargs}).fit(rec)
    assert "\n" not in str(err.value)


def test_step_records_cannot_have_an_integrator():
    t = np.arange(100) * 0.1
    rec = Record.step_response(t, 1.0 - np.exp(-t), amplitude=1.0)
    with pytest.raises(DataError, match="input/output records"):
        TransferFunctionEstimator(2, 0, integrator=True).fit(rec)
    with pytest.raises(DataError, match="input/output records"):
        TransferFunctionEstimator("auto", integrator=True).fit(rec)
