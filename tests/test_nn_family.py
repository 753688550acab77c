"""Plant-family files (``kautztwin train --family``): parsing, bad input, draws, noise colours."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from kautztwin.exceptions import DataError
from kautztwin.nn.family import PlantFamily, draw_family_parameters, drift_noise, family_dataset

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "family_5th_order.toml"
PLANT = {"zeros": [-3.0], "poles": [-1.0, "-0.5+1.5j", "-0.5-1.5j"], "gain": 2.0}


def _family(**sections):
    return PlantFamily.from_dict({"plant": dict(PLANT), **sections})


def test_example_family_parses_with_defaults():
    fam = PlantFamily.from_toml(EXAMPLE)
    assert fam.system.parameter_names == (
        "gain", "zero0_rate", "pole0_rate", "pole1_wn", "pole1_zeta", "pole2_wn", "pole2_zeta")
    assert fam.system.order == 5
    assert set(fam.tolerance.values()) == {0.3}
    assert (fam.distribution, fam.color, fam.ar1_pole, fam.kind) == ("uniform", "ar1", 0.9,
                                                                     "impulse")
    # default length: ten time constants of the slowest nominal pole (Re = -0.45)
    assert fam.t[-1] == pytest.approx(10.0 / 0.45) and fam.t.size == 500
    assert (fam.n_records, fam.n_calibration, fam.n_validation) == (20000, 1000, 200)
    json.dumps(fam.to_dict())  # JSON-ready: stored in the model's metadata


def test_tolerance_per_pole_factor_and_per_parameter():
    fam = _family(tolerance={"default": 0.2, "pole1": 0.1, "pole1_zeta": 0.05, "gain": 0.0})
    assert fam.tolerance == {"gain": 0.0, "zero0_rate": 0.2, "pole0_rate": 0.2,
                             "pole1_wn": 0.1, "pole1_zeta": 0.05}


def test_transfer_function_plant():
    fam = PlantFamily.from_dict({"plant": {"num": [2.0], "den": [1.0, 3.0, 2.0]}})
    np.testing.assert_allclose(np.sort(fam.system.poles().real), [-2.0, -1.0])


def test_identified_model_file(tmp_path):
    (tmp_path / "m.json").write_text(json.dumps(
        {"num": [1.0, 3.0], "den": [1.0, 3.0, 4.0, 2.0], "delay": 0.0, "fit_percent": 90.0}))
    (tmp_path / "f.toml").write_text('[plant]\nmodel = "m.json"\n')
    fam = PlantFamily.from_toml(tmp_path / "f.toml")  # the path is relative to the file
    num, den = fam.system.transfer_function()
    np.testing.assert_allclose(num, [1.0, 3.0], rtol=1e-12)
    np.testing.assert_allclose(den, [1.0, 3.0, 4.0, 2.0], rtol=1e-12)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"plant": PLANT, "nosie": {}}, r"unknown section \[nosie\]"),
        ({"plant": PLANT, "noise": {"colour": "ar1"}}, "unknown key noise.colour"),
        ({"plant": PLANT, "noise": {"level": "5%"}}, "noise.level has the wrong type"),
        ({"plant": PLANT, "noise": {"level": -0.1}}, "noise.level must be >= 0"),
        ({"plant": PLANT, "noise": {"color": "pink"}}, "noise.color must be"),
        ({"plant": PLANT, "noise": {"color": "ar1", "ar1_pole": 1.0}}, "noise.ar1_pole"),
        ({"plant": PLANT, "noise": {"ar1_pole": 0.5}}, "noise.ar1_pole applies only"),
        ({"plant": PLANT, "tolerance": {"distribution": "cauchy"}}, "tolerance.distribution"),
        ({"plant": PLANT, "tolerance": {"pole7_rate": 0.1}}, "unknown key tolerance.pole7_rate"),
        ({"plant": PLANT, "tolerance": {"default": -0.3}}, "tolerance.default must be >= 0"),
        ({"plant": PLANT, "tolerance": {"gain": True}}, "tolerance.gain must be a number"),
        ({"plant": PLANT, "record": {"kind": "io"}}, "record.kind = 'io' is not supported"),
        ({"plant": PLANT, "record": {"t_end": 0.0}}, "record.t_end must be > 0"),
        ({"plant": PLANT, "record": {"n_samples": 5}}, "record.n_samples must be at least"),
        ({"plant": PLANT, "training": {"n_records": 3}}, "training.n_records must be at least"),
        ({"plant": PLANT, "training": {"max_epochs": 0}}, "training.max_epochs must be positive"),
        ({"plant": PLANT, "estimator": {"hidden": [0]}}, "estimator.hidden must be a list"),
        ({"plant": PLANT, "estimator": {"n_stages": 0}}, "estimator.n_stages must be at least"),
        ({}, r"\[plant\] is required"),
        ({"plant": {"num": [1.0]}}, "plant.num and plant.den go together"),
        ({"plant": {"poles": [-1.0, "a+bj"]}}, r"plant.poles\[1\]: cannot read"),
        ({"plant": {"poles": [1.0]}}, r"\[plant\]: .*Re"),
        ({"plant": {"poles": [-1.0], "gain": 0.0}}, "plant.gain must be a nonzero"),
        ({"plant": {"num": [1.0], "den": [1.0, 1.0], "poles": [-1.0]}}, "cannot be combined"),
    ],
    ids=["section", "key", "type", "negative-noise", "color", "ar1-pole", "ar1-pole-white",
         "distribution", "tolerance-name", "tolerance-negative", "tolerance-bool", "io",
         "t-end", "n-samples", "n-records", "max-epochs", "hidden", "n-stages", "no-plant",
         "num-only", "bad-pole",
         "unstable", "zero-gain", "two-models"],
)
def test_bad_family_is_a_one_line_error_naming_the_key(data, match):
    with pytest.raises(DataError, match=match) as info:
        PlantFamily.from_dict(data)
    assert "\n" not in str(info.value)


def test_bad_files(tmp_path):
    with pytest.raises(DataError, match="cannot read the family file"):
        PlantFamily.from_toml(tmp_path / "missing.toml")
    (tmp_path / "bad.toml").write_text("[plant\n")
    with pytest.raises(DataError, match="is not valid TOML"):
        PlantFamily.from_toml(tmp_path / "bad.toml")
    (tmp_path / "m.json").write_text(json.dumps({"num": [1.0], "den": [1.0, 1.0], "delay": 0.5}))
    (tmp_path / "d.toml").write_text('[plant]\nmodel = "m.json"\n')
    with pytest.raises(DataError, match="plant.model: .*dead time of 0.5 s"):
        PlantFamily.from_toml(tmp_path / "d.toml")


@pytest.mark.parametrize("kind", ["impulse", "step"])
def test_records_without_tolerance_and_noise_are_the_nominal_response(kind):
    fam = _family(tolerance={"default": 0.0}, noise={"level": 0.0},
                  record={"kind": kind, "n_samples": 300})
    data = family_dataset(fam, 3, seed=0)
    z, p, k = [-3.0], [-1.0, -0.5 + 1.5j, -0.5 - 1.5j], 2.0
    lti = scipy.signal.lti(*scipy.signal.zpk2tf(z, p, k))
    _, ref = (scipy.signal.impulse if kind == "impulse" else scipy.signal.step)(lti, T=fam.t)
    for rec in (data.responses, data.clean):
        np.testing.assert_allclose(rec, np.broadcast_to(ref, rec.shape), rtol=0,
                                   atol=1e-8 * np.abs(ref).max())


def test_uniform_draws_stay_in_the_band():
    fam = _family(tolerance={"default": 0.3})
    P = draw_family_parameters(fam.system, fam.tolerance, 400, np.random.default_rng(1))
    rel = P / fam.system.nominal - 1.0
    assert np.abs(rel).max() <= 0.3 + 1e-12
    assert np.abs(rel).max() > 0.28  # and fill it


def test_normal_draws_have_the_tolerance_as_relative_std():
    fam = _family(
        tolerance={"default": 0.0, "gain": 0.1, "pole0": 0.2, "distribution": "normal"})
    n = 1500
    P = draw_family_parameters(fam.system, fam.tolerance, n, np.random.default_rng(2), "normal")
    rel = P / fam.system.nominal - 1.0
    # truncation to stable systems is negligible at 5 and 10 standard deviations:
    # mean 0 and std u to 4 standard errors (se of a std: u / sqrt(2 n))
    for j, u in ((0, 0.1), (2, 0.2)):
        assert abs(rel[:, j].mean()) < 4 * u / np.sqrt(n)
        assert abs(rel[:, j].std() - u) < 4 * u / np.sqrt(2 * n)
    assert np.all(rel[:, [1, 3, 4]] == 0.0)


def test_ar1_noise_has_the_level_and_the_lag1_correlation():
    fam = _family(tolerance={"default": 0.0}, noise={"level": 0.05, "color": "ar1",
                                                       "ar1_pole": 0.9},
                  record={"n_samples": 500})
    data = family_dataset(fam, 200, seed=3)
    e = (data.responses - data.clean) / np.abs(data.clean).max(axis=1, keepdims=True)
    lag1 = np.sum(e[:, 1:] * e[:, :-1]) / np.sum(e[:, :-1] ** 2)
    # 1e5 samples of AR(1): se of the lag-1 estimate sqrt((1 - a^2) / N) = 0.0014
    assert lag1 == pytest.approx(0.9, abs=0.01)
    # effective samples N (1 - a) / (1 + a) = 5e3: se of the std about 1 %
    assert e.std() == pytest.approx(0.05, rel=0.05)


def test_drift_is_a_random_walk_reaching_its_size_at_the_end():
    n_rec, n = 4000, 101
    d = drift_noise(n_rec, n, np.random.default_rng(4))
    assert np.all(d[:, 0] == 0.0)
    inc = np.diff(d, axis=1)
    # white increments of variance 1 / (n - 1): 4e5 of them
    assert np.sum(inc[:, 1:] * inc[:, :-1]) / np.sum(inc**2) == pytest.approx(0.0, abs=0.01)
    assert inc.var() * (n - 1) == pytest.approx(1.0, rel=0.01)
    # variance grows linearly: k / (n - 1); se of a variance from 4000 records: 2.2 %
    for k in (25, 50, 100):
        assert d[:, k].var() == pytest.approx(k / (n - 1), rel=0.1)


def test_drift_family_adds_the_walk_to_white_noise():
    fam = _family(tolerance={"default": 0.0},
                  noise={"level": 0.02, "color": "drift", "drift": 0.1},
                  record={"n_samples": 200})
    data = family_dataset(fam, 800, seed=5)
    e = (data.responses - data.clean) / np.abs(data.clean).max(axis=1, keepdims=True)
    # first sample: white only; last: white + the whole drift (se of a std from 800
    # records: 2.5 %; tolerance 4 se)
    assert e[:, 0].std() == pytest.approx(0.02, rel=0.1)
    assert e[:, -1].std() == pytest.approx(np.hypot(0.02, 0.1), rel=0.1)
    # between: white plus a walk of variance k / (n - 1), pooled over 100 samples
    k = np.arange(100, 200)
    expected = 0.02**2 + 0.1**2 * k / 199
    assert np.mean(e[:, k] ** 2 / expected) == pytest.approx(1.0, rel=0.1)
