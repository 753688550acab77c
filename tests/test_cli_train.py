"""``kautztwin train`` / ``estimate`` and the simulation reproduction pipeline (small budgets)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch  # noqa: E402 - the [nn] extra, part of [test]

from kautztwin.cli.main import main  # noqa: E402
from kautztwin.data import reference_response  # noqa: E402

SPEC = """
[uncertainty]
default = 0.2
[noise]
level = 0.02
[grid]
n_samples = 200
[training]
n_records = 40
n_test = 10
max_epochs = 3
per_coefficient = false
"""


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("train")
    (d / "spec.toml").write_text(SPEC)
    assert main(["train", "--config", str(d / "spec.toml"), "--out", str(d / "run"),
                 "--quiet", "--json"]) == 0
    return d


def test_train_writes_model_curves_and_summary(trained):
    run = trained / "run"
    assert (run / "model" / "metadata.json").exists()
    assert (run / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["estimator"] == "coefficients" and summary["n_test"] == 10
    assert np.isfinite(summary["test_fit_mean"])


def _record_csv(path, n=200, noise=0.02):
    t, h = reference_response(n_samples=n, noise=noise)
    np.savetxt(path, np.c_[t, h, 2 * h], delimiter=",", header="t,h,h2", comments="")


def test_estimate_prints_json_per_record(trained, capsys):
    _record_csv(trained / "rec.csv")
    capsys.readouterr()
    code = main(["estimate", str(trained / "rec.csv"), "--model", str(trained / "run" / "model"),
                 "--response", "h,h2", "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["records"]) == 2
    assert len(out["records"][0]["coefficients"]) == 4
    # the estimator is linear in nothing: but the reported fit must be that of the model
    assert all(np.isfinite(r["fit_percent"]) for r in out["records"])


def test_estimate_rejects_another_grid(trained, capsys):
    _record_csv(trained / "long.csv", n=300)
    capsys.readouterr()
    code = main(["estimate", str(trained / "long.csv"), "--model", str(trained / "run" / "model")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "kautztwin: error:" in err[0]


def test_estimate_rejects_a_tampered_model(trained, tmp_path, capsys):
    import shutil

    model = tmp_path / "model"
    shutil.copytree(trained / "run" / "model", model)
    weights = next(p for p in model.iterdir() if p.suffix == ".pt")
    data = bytearray(weights.read_bytes())
    data[-10] ^= 0xFF
    weights.write_bytes(bytes(data))
    _record_csv(tmp_path / "rec.csv")
    capsys.readouterr()
    code = main(["estimate", str(tmp_path / "rec.csv"), "--model", str(model)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "checksum" in err[0]


def test_train_rejects_unknown_spec_key(tmp_path, capsys):
    (tmp_path / "bad.toml").write_text("[training]\nepochs = 3\n")
    code = main(["train", "--config", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "training.epochs" in err[0]


def test_estimate_rejects_nan(trained, tmp_path, capsys):
    t, h = reference_response(n_samples=200)
    h[5] = np.nan
    np.savetxt(tmp_path / "nan.csv", np.c_[t, h], delimiter=",", header="t,h", comments="")
    capsys.readouterr()
    code = main(["estimate", str(tmp_path / "nan.csv"), "--model", str(trained / "run" / "model")])
    assert code == 2


def test_simulation_pipeline_small(tmp_path):
    from kautztwin.experiments.simulation import SimulationSetup, reproduce_simulation

    torch.set_num_threads(1)
    setup = SimulationSetup(
        n_train=50, n_test=60, n_sweep=8, paper_epochs=5, adaptive_train=400, adaptive_epochs=1,
        oracle_records=6, uncertainties=(0.0, 0.5), noises=(0.1,),
    )
    m = reproduce_simulation(tmp_path, setup=setup)
    assert set(m["methods"]) == {"paper_dnn", "projection", "fixed_basis_ceiling", "adaptive",
                                 "oracle"}
    for stats in m["methods"].values():
        assert {"fit_mean", "fit_median", "fit_p10", "fit_min", "seconds_per_record"} <= set(stats)
    assert "coef_mse" in m["methods"]["paper_dnn"] and "coef_mse" in m["methods"]["projection"]
    assert m["sanity"]["passed"]
    # no estimator on the nominal basis can beat the ceiling (the built-in check, on the means)
    ceiling = m["methods"]["fixed_basis_ceiling"]["fit_mean"]
    assert m["methods"]["projection"]["fit_mean"] <= ceiling + 1e-9
    assert {(r["uncertainty"], r["noise"]) for r in m["sweep"]} == {(0.0, 0.1), (0.5, 0.1)}
    for name in ("metrics.json", "report.md", "fig7_training.png", "fig8_approximations.png",
                 "sweep.png"):
        assert (tmp_path / name).exists(), name
    # with no uncertainty every label is the nominal one: the paper networks predict it exactly
    cell = [r for r in m["sweep"] if r["uncertainty"] == 0.0 and r["method"] == "paper_dnn"]
    ceiling0 = [r for r in m["sweep"] if r["uncertainty"] == 0.0
                and r["method"] == "fixed_basis_ceiling"]
    assert cell[0]["fit_mean"] == pytest.approx(ceiling0[0]["fit_mean"], abs=1e-6)


@pytest.mark.slow
def test_reproduce_simulation_quick_cli(tmp_path):
    assert main(["reproduce", "simulation", "--quick", "--quiet", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["setup"]["quick"] is True


# --------------------------------------------------------------------------- train --family
FAMILY = """
[plant]
zeros = [-3.0]
poles = [-1.0, "-0.5+1.5j", "-0.5-1.5j"]
gain = 2.0
[noise]
level = 0.05
color = "drift"
[record]
n_samples = 80
[training]
n_records = 120
n_calibration = 30
n_validation = 4
max_epochs = 1
[estimator]
hidden = [16]
n_features = 8
pretrain_epochs = 2
"""


def test_train_family_writes_a_calibrated_model_and_a_report(tmp_path, capsys):
    torch.set_num_threads(1)
    (tmp_path / "fam.toml").write_text(FAMILY)
    out = tmp_path / "run"
    assert main(["train", "--family", str(tmp_path / "fam.toml"), "--out", str(out),
                 "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "oracle" in text and "90 % bands cover" in text
    report = json.loads((out / "report.json").read_text())
    v = report["validation"]
    assert v["n_records"] == 4 and len(v["oracle_fit_per_record"]) == 4
    assert set(v["coverage"]) == {"0.5", "0.8", "0.9", "0.95"}
    assert report["calibration"]["n_records"] == 30
    meta = json.loads((out / "model" / "metadata.json").read_text())
    assert meta["training_data"]["family"]["noise"]["color"] == "drift"
    assert meta["uncertainty"]["scale"] == report["calibration"]["scale"]
    assert (out / "curves.png").exists()
    # the model is usable by 'estimate', which reports the uncertainty
    from kautztwin.nn.family import PlantFamily, family_dataset

    data = family_dataset(PlantFamily.from_toml(tmp_path / "fam.toml"), 2, seed=9)
    np.savetxt(tmp_path / "rec.csv", np.c_[data.t, data.responses.T], delimiter=",",
               header="t,a,b", comments="")
    assert main(["estimate", str(tmp_path / "rec.csv"), "--model", str(out / "model"),
                 "--response", "a,b", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["uncertainty"]["calibrated"] is True
    assert len(got["uncertainty"]["relative_width"]) == 2


@pytest.mark.parametrize(
    ("text", "match"),
    [("[plant]\npoles = [-1.0]\n[noise]\ncolour = 'ar1'\n", "unknown key noise.colour"),
     ("[plant]\npoles = [-1.0]\n[record]\nkind = 'io'\n", "record.kind = 'io'"),
     ("[noise]\nlevel = 0.1\n", r"\[plant\] is required")],
    ids=["key", "io", "no-plant"],
)
def test_train_family_bad_file_is_a_one_line_usage_error(tmp_path, capsys, text, match):
    (tmp_path / "fam.toml").write_text(text)
    code = main(["train", "--family", str(tmp_path / "fam.toml"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    import re

    assert re.search(match, err)


def test_train_needs_family_or_config(tmp_path, capsys):
    assert main(["train", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "one of the arguments --family --config --amortised is required" in err
