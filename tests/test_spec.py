"""The TOML training spec of ``kautztwin train``."""

from __future__ import annotations

import numpy as np
import pytest

from kautztwin.exceptions import DataError
from kautztwin.experiments import TrainSpec

FULL = """
[system]
model = "paper"

[uncertainty]
default = 0.5
k = 0.2

[noise]
level = 0.1
kind = "colored"
color_pole = 0.8

[grid]
t_end = 20.0
n_samples = 900
response = "impulse"

[basis]
poles = ["-1", "-3", "-0.5+1.9365j", "-0.5-1.9365j"]

[training]
preset = "paper"
n_records = 50
random_state = 3
"""


def test_full_spec_is_read(tmp_path):
    path = tmp_path / "spec.toml"
    path.write_text(FULL)
    spec = TrainSpec.from_toml(path)
    assert spec.uncertainty == {"k": 0.2, "a": 0.5, "b": 0.5, "wn": 0.5, "zeta": 0.5}
    assert spec.noise == 0.1 and spec.noise_kind == "colored" and spec.color_pole == 0.8
    np.testing.assert_array_equal(spec.t, np.linspace(0, 20, 900))
    np.testing.assert_array_equal(spec.basis_poles, [-1, -3, -0.5 + 1.9365j, -0.5 - 1.9365j])
    assert (spec.preset, spec.n_records, spec.random_state) == ("paper", 50, 3)
    assert not spec.adaptive


def test_defaults_and_nominal_and_adaptive_bases():
    spec = TrainSpec.from_dict({})
    assert spec.system.name == "paper" and spec.kind == "impulse" and spec.noise == 0.0
    # nominal basis = the nominal model's poles: -1, -3, -1/2 +- j sqrt(15)/2
    np.testing.assert_allclose(
        np.sort_complex(spec.basis_poles),
        np.sort_complex([-1, -3, -0.5 + 1j * np.sqrt(15) / 2, -0.5 - 1j * np.sqrt(15) / 2]),
        rtol=1e-12,
    )
    assert TrainSpec.from_dict({"basis": {"poles": "adaptive"}}).adaptive


def test_zpk_and_tf_systems():
    spec = TrainSpec.from_dict({"system": {"model": "zpk", "poles": ["-1", "-2"], "gain": 2}})
    assert spec.system.parameter_names == ("gain", "pole0_rate", "pole1_rate")
    spec = TrainSpec.from_dict({"system": {"model": "tf", "num": [1.0], "den": [1.0, 3.0, 2.0]}})
    np.testing.assert_allclose(spec.system.transfer_function()[1], [1, 3, 2])


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"grid": {"foo": 1}}, "unknown key grid.foo"),
        ({"model": {}}, r"unknown section \[model\]"),
        ({"uncertainty": {"gain": 0.1}}, "unknown parameter"),
        ({"uncertainty": {"default": -0.1}}, ">= 0"),
        ({"noise": {"level": "big"}}, "wrong type"),
        ({"noise": {"kind": "pink"}}, "noise.kind"),
        ({"grid": {"n_samples": 3}}, "at least 10"),
        ({"grid": {"response": "ramp"}}, "grid.response"),
        ({"basis": {"poles": "random"}}, "basis.poles"),
        ({"basis": {"poles": ["x"]}}, "cannot read"),
        ({"training": {"preset": "fast"}}, "training.preset"),
        ({"training": {"n_records": True}}, "boolean"),
        ({"system": {"model": "tf", "num": [1.0]}}, "needs system.num and system.den"),
        ({"system": {"model": "paper", "gain": 2}}, "takes no other keys"),
    ],
    ids=["unknown-key", "unknown-section", "unknown-parameter", "negative-uncertainty",
         "noise-type", "noise-kind", "few-samples", "response", "basis-word", "basis-value",
         "preset", "bool", "tf-missing", "paper-extra"],
)
def test_bad_specs_raise_one_line_errors(data, match):
    with pytest.raises(DataError, match=match) as err:
        TrainSpec.from_dict(data)
    assert "\n" not in str(err.value)


def test_bad_files(tmp_path):
    with pytest.raises(DataError, match="cannot read"):
        TrainSpec.from_toml(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid\nt_end = 1")
    with pytest.raises(DataError, match="not valid TOML"):
        TrainSpec.from_toml(bad)
