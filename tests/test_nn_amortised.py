"""The amortised estimator (issue #14 item 2): blocks, draws, projection, refinement, files, CLI."""

from __future__ import annotations

import fnmatch
import json
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
import scipy.signal
import torch

import kautztwin as kt
from kautztwin.cli.main import main
from kautztwin.exceptions import DataError, DimensionError, NotFittedError
from kautztwin.nn.amortised import AmortisedEstimator, random_systems
from kautztwin.nn.amortised import pretrained as pretrained_module
from kautztwin.nn.amortised.network import (
    bin_features,
    block_kinds,
    block_matrices,
    block_roots,
)
from kautztwin.nn.amortised.refine import noise_model, theta_from_poles
from kautztwin.nn.kautz_torch import propagate

ROOT = Path(__file__).resolve().parent.parent
# the shipped model's folder in the source tree, read by path (AmortisedEstimator.load)
SHIPPED = ROOT / "src" / "kautztwin" / "nn" / "amortised" / "shipped_model"


@pytest.fixture(scope="module")
def tiny():
    """A small estimator trained in a few seconds (API and file tests)."""
    torch.set_num_threads(1)
    return AmortisedEstimator(max_order=3, hidden=(32,), n_records=400, n_samples=128,
                              max_epochs=3, random_state=1).fit()


@pytest.fixture(scope="module")
def shipped():
    """The model shipped in the package, AmortisedEstimator.load_default (accuracy tests)."""
    torch.set_num_threads(1)
    return AmortisedEstimator.load_default()


def _theta(rng, kinds, n):
    cols = []
    for k in kinds:
        cols += [rng.uniform(0.3, 5.0, n), rng.uniform(0.3, 3.0, n)] if k == "quad" \
            else [rng.uniform(0.3, 5.0, n)]
    return np.column_stack(cols)


# ------------------------------------------------------------------ blocks
def test_block_realisation_is_orthonormal_for_real_and_complex_quads():
    # A + A^T + B B^T = 0 (kautz-math 2.1) holds for any b, c > 0, real roots included
    rng = np.random.default_rng(0)
    kinds = block_kinds(5)
    theta = _theta(rng, kinds, 50)
    disc = theta[:, 0] ** 2 - 4 * theta[:, 1] ** 2
    assert (disc > 0).any() and (disc < 0).any()
    A, B = block_matrices(kinds, torch.as_tensor(theta))
    lyap = A + A.transpose(1, 2) + B[:, :, None] * B[:, None, :]
    torch.testing.assert_close(lyap, torch.zeros_like(lyap), atol=1e-13, rtol=0)


def test_block_roots_are_the_roots_of_each_block_polynomial():
    rng = np.random.default_rng(1)
    kinds = block_kinds(5)
    theta = _theta(rng, kinds, 20)
    roots = block_roots(kinds, theta)
    for row, th in zip(roots, theta, strict=True):
        want = np.concatenate([np.roots([1, th[0], th[1] ** 2]),
                               np.roots([1, th[2], th[3] ** 2]), [-th[4]]])
        np.testing.assert_allclose(np.sort_complex(row), np.sort_complex(want), rtol=1e-10)
        assert np.all(row.real < 0)


def test_quad_blocks_span_the_kautz_basis_of_their_roots():
    # the least-squares fit on the (b, c) realisation equals the fit on KautzBasis(roots):
    # the span depends only on the denominator (kautz-math 4.2)
    rng = np.random.default_rng(2)
    kinds = block_kinds(5)
    theta = _theta(rng, kinds, 6)
    t = np.linspace(0.0, 12.0, 300)
    y = rng.standard_normal(t.size)
    K = propagate(*block_matrices(kinds, torch.as_tensor(theta)), t).numpy()
    for Ki, roots in zip(K, block_roots(kinds, theta), strict=True):
        Kb = kt.KautzBasis(roots).evaluate(t)
        fit_a = Ki.T @ np.linalg.lstsq(Ki.T, y, rcond=None)[0]
        fit_b = Kb.T @ np.linalg.lstsq(Kb.T, y, rcond=None)[0]
        np.testing.assert_allclose(fit_a, fit_b, atol=1e-9)


def test_bin_features_are_exact_bin_means_of_a_linear_record():
    t = np.linspace(0.0, 2.0, 37)
    y = (3.0 - 2.0 * t)[None]
    F = bin_features(t, y, 8)
    mid = (np.arange(8) + 0.5) * 2.0 / 8
    want = 3.0 - 2.0 * mid
    np.testing.assert_allclose(F[0], want / np.sqrt(np.mean(want**2)), rtol=1e-12)


# ------------------------------------------------------------------ training draws
def test_random_systems_lie_in_the_span_of_their_own_poles():
    # undelayed records are sums of their modes: projecting on KautzBasis(true poles)
    # reproduces them (kautz-math 4.2), an oracle independent of the generator
    d = random_systems(40, 400, np.random.default_rng(3), max_order=4)
    assert set(d.order) <= {1, 2, 3, 4}
    checked = 0
    for i in np.flatnonzero(d.delay == 0)[:10]:
        poles = d.poles[i, : d.order[i]]
        K = kt.KautzBasis(poles).evaluate(d.tau)
        c = np.linalg.lstsq(K.T, d.clean[i], rcond=None)[0]
        assert kt.fit_percent(d.clean[i], c @ K) > 99.9999
        checked += 1
    assert checked >= 5
    np.testing.assert_allclose(np.abs(d.clean).max(axis=1), 1.0)
    assert np.all(d.poles[~np.isnan(d.poles)].real < 0)


def test_random_systems_are_reproducible_from_the_generator():
    a = random_systems(5, 64, np.random.default_rng(4))
    b = random_systems(5, 64, np.random.default_rng(4))
    np.testing.assert_array_equal(a.responses, b.responses)


# ------------------------------------------------------------------ projection
def test_simpson_projection_matches_kautztwin_project(tiny):
    t = np.linspace(0.0, 8.0, 201)
    h = np.exp(-t) * np.sin(2 * t) + 0.01 * np.random.default_rng(5).standard_normal(t.size)
    poles = [-0.9 + 1.8j, -0.9 - 1.8j, -2.5]
    est = AmortisedEstimator(**{**tiny.get_params(), "weights": "simpson"})
    est._set_fitted(tiny.network_, tiny.tau_, tiny.history_, 0.0)
    want = kt.project(kt.KautzBasis(poles), t, h, method="lstsq")
    np.testing.assert_allclose(est.project(t, h, poles), want, rtol=1e-9, atol=1e-12)


def test_uniform_projection_leaves_a_residual_orthogonal_to_the_basis(tiny):
    t = np.linspace(0.0, 8.0, 201)
    h = np.random.default_rng(6).standard_normal((3, t.size))
    poles = [-0.5, -1.5, -3.0]
    C = tiny.project(t, h, poles)
    K = kt.KautzBasis(poles).evaluate(t)
    np.testing.assert_allclose(K @ (h - C @ K).T, 0.0, atol=1e-10)


def test_estimate_coefficients_are_the_projection_on_its_poles(tiny):
    t = np.linspace(0.0, 10.0, 250)
    h = np.exp(-0.7 * t) - 0.5 * np.exp(-2.0 * t)
    e = tiny.estimate(t, h)
    np.testing.assert_allclose(e.coefficients[0], tiny.project(t, h, e.poles[0]), rtol=1e-12)
    np.testing.assert_allclose(e.response[0], e.model().impulse(t), atol=1e-10)


def test_poles_scale_with_the_record_length(tiny):
    # time is measured in record lengths: stretching a record by 4 divides its poles by 4
    t = np.linspace(0.0, 6.0, 300)
    h = np.exp(-t) * np.cos(3 * t)
    p1 = tiny.predict_poles(t, h)
    p4 = tiny.predict_poles(4.0 * t, h)
    np.testing.assert_allclose(p4, p1 / 4.0, rtol=1e-5)


# ------------------------------------------------------------------ VARPRO refinement
SYSTEMS = {
    "second_order_real": ([2.0], [-1.0, -3.0]),
    "pair_and_real": ([1.0, 1.0], [-0.4 + 2.0j, -0.4 - 2.0j, -1.5]),
    "fifth_order_with_zero": ([3.0, 6.0], [-0.8, -0.45 + 1.43j, -0.45 - 1.43j,
                                           -1.5 + 2.6j, -1.5 - 2.6j]),
}


def _impulse(name):
    num, poles = SYSTEMS[name]
    t = np.linspace(0.0, 10.0 / min(-np.real(poles)), 500)
    _, h = scipy.signal.impulse(scipy.signal.lti(num, np.poly(poles).real), T=t)
    return t, h, poles


@pytest.mark.parametrize("name", list(SYSTEMS), ids=list(SYSTEMS))
def test_varpro_refinement_reaches_the_projection_optimal_fit_on_noise_free_records(
    shipped, name
):
    t, h, poles = _impulse(name)
    # the oracle: least squares on the basis of the true poles is exact (kautz-math 4.2),
    # so the projection-optimal fit is 100 %
    oracle = kt.KautzBasis(poles).evaluate(t)
    c = np.linalg.lstsq(oracle.T, h, rcond=None)[0]
    assert kt.fit_percent(h, c @ oracle) > 99.9999
    est = AmortisedEstimator.load(SHIPPED).set_params(refine_method="varpro")
    e = est.estimate(t, h, refine=True)
    assert e.refined
    assert e.fit_percent[0] > 99.99
    assert e.fit_percent[0] >= shipped.estimate(t, h).fit_percent[0] - 1e-9


@pytest.mark.parametrize("name", list(SYSTEMS), ids=list(SYSTEMS))
def test_map_refinement_approaches_the_exact_fit_on_noise_free_records(shipped, name):
    # with no noise the data term dominates the prior: the fit goes most of the way from
    # the network's to the exact 100 %
    t, h, _ = _impulse(name)
    raw = shipped.estimate(t, h)
    ref = shipped.estimate(t, h, refine=True)
    assert 100.0 - ref.fit_percent[0] <= 0.1 * (100.0 - raw.fit_percent[0]) + 1e-3


def test_theta_from_poles_inverts_block_roots():
    rng = np.random.default_rng(8)
    kinds = block_kinds(5)
    theta = _theta(rng, kinds, 20)
    for roots in block_roots(kinds, theta):
        back = theta_from_poles(kinds, rng.permutation(roots))
        np.testing.assert_allclose(np.sort_complex(block_roots(kinds, back[None])[0]),
                                   np.sort_complex(roots), rtol=1e-9)


def test_noise_model_recovers_an_ar1_pole_and_its_innovation_scale():
    # e_k = 0.8 e_{k-1} + w_k with std(w) = 0.3: whitened innovations have std 0.3 / sqrt(1-a^2)
    w = 0.3 * np.random.default_rng(9).standard_normal(40000)
    e = scipy.signal.lfilter([1.0], [1.0, -0.8], w)
    a, sigma = noise_model(e)
    assert abs(a - 0.8) < 0.01  # standard error about 0.003
    assert abs(sigma - 0.3 / np.sqrt(1 - 0.64)) < 0.01


def test_varpro_refinement_never_increases_the_residual(tiny):
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 10.0, 200)
    h = np.exp(-0.5 * t) * np.sin(1.3 * t) + 0.05 * rng.standard_normal((4, t.size))
    raw = tiny.estimate(t, h)
    est = AmortisedEstimator(**{**tiny.get_params(), "refine_method": "varpro"})
    est._set_fitted(tiny.network_, tiny.tau_, tiny.history_, 0.0)
    ref = est.refine(t, h, raw)
    r_raw = np.sum((h - raw.response) ** 2, axis=1)
    r_ref = np.sum((h - ref.response) ** 2, axis=1)
    assert np.all(r_ref <= r_raw * (1 + 1e-12))
    assert np.all(ref.poles.real < 0)


# ------------------------------------------------------------------ files and errors
def test_save_load_round_trip_and_tampering(tiny, tmp_path):
    path = tiny.save(tmp_path / "m")
    assert json.loads((path / "estimator.json").read_text()) == {"estimator": "amortised"}
    again = AmortisedEstimator.load(path)
    t = np.linspace(0.0, 5.0, 100)
    h = np.exp(-2 * t)
    np.testing.assert_array_equal(again.predict_poles(t, h), tiny.predict_poles(t, h))
    assert again.get_params() == tiny.get_params()
    with (path / "weights.pt").open("ab") as fh:
        fh.write(b"x")
    with pytest.raises(DataError, match="checksum"):
        AmortisedEstimator.load(path)


def test_bad_input_is_a_one_line_error(tiny):
    t = np.linspace(0.0, 5.0, 100)
    with pytest.raises(NotFittedError, match="not fitted"):
        AmortisedEstimator().predict_poles(t, np.exp(-t))
    with pytest.raises(DataError, match="constant"):
        tiny.estimate(t, np.ones(t.size))
    with pytest.raises(DataError, match="t\\[0\\] >= 0"):
        tiny.estimate(t - 1.0, np.exp(-t))
    with pytest.raises(DimensionError, match="samples per record"):
        tiny.estimate(t, np.exp(-t)[:-1])
    with pytest.raises(DataError, match="weights"):
        AmortisedEstimator(weights="huber").fit()
    with pytest.raises(DataError, match="refine_method"):
        AmortisedEstimator(refine_method="newton").fit()
    with pytest.raises(DataError, match="poles has 2 rows"):
        tiny.project(t, np.exp(-np.outer([1, 2, 3], t)), [[-1, -2, -3], [-1, -2, -3]])


# ------------------------------------------------------------------ the shipped model
def _records():
    """Three impulse records on different grids: real poles, a pair with a zero, noise."""
    rng = np.random.default_rng(11)
    out = []
    for num, poles, t_end, n in (([2.0], [-1.0, -3.0], 8.0, 160),
                                 ([1.0, 1.0], [-0.4 + 2.0j, -0.4 - 2.0j, -1.5], 20.0, 400),
                                 ([3.0], [-0.2, -0.9], 40.0, 300)):
        t = np.linspace(0.0, t_end, n)
        _, h = scipy.signal.impulse(scipy.signal.lti(num, np.poly(poles).real), T=t)
        out.append((t, h + 0.02 * np.abs(h).max() * rng.standard_normal(n)))
    return out


def test_shipped_model_files_are_package_data():
    # the wheel carries exactly what pyproject.toml declares: every file of the shipped
    # folder must match a package-data pattern of its package
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    patterns = pyproject["tool"]["setuptools"]["package-data"]["kautztwin.nn.amortised"]
    files = sorted(p.name for p in SHIPPED.iterdir())
    assert files == sorted(pretrained_module.PRETRAINED_FILES)
    for name in files:
        assert any(fnmatch.fnmatch(f"shipped_model/{name}", pat) for pat in patterns), name


def test_load_default_reads_the_shipped_files(shipped):
    with pretrained_module.pretrained_folder() as folder:
        for name in pretrained_module.PRETRAINED_FILES:
            assert (folder / name).read_bytes() == (SHIPPED / name).read_bytes()
    assert shipped.max_order == 5 and shipped.get_params()["n_records"] == 40000


def test_load_default_predicts_exactly_as_loading_the_folder_by_path(shipped):
    by_path = AmortisedEstimator.load(SHIPPED)
    assert by_path.get_params() == shipped.get_params()
    for key, value in by_path.network_.state_dict().items():
        torch.testing.assert_close(shipped.network_.state_dict()[key], value, rtol=0, atol=0)
    for t, y in _records():
        np.testing.assert_array_equal(shipped.predict_poles(t, y), by_path.predict_poles(t, y))
        a, b = shipped.estimate(t, y), by_path.estimate(t, y)
        np.testing.assert_array_equal(a.poles, b.poles)
        np.testing.assert_array_equal(a.coefficients, b.coefficients)
        np.testing.assert_array_equal(a.response, b.response)


def _zipped_package(tmp_path, names):
    """A zip holding the shipped files under kautztwin/nn/amortised/shipped_model/."""
    archive = tmp_path / "kautztwin.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for name in names:
            zf.write(SHIPPED / name, f"kautztwin/nn/amortised/shipped_model/{name}")
    return zipfile.Path(archive, "kautztwin/nn/amortised/")


def test_load_default_works_from_a_zip_import(shipped, tmp_path, monkeypatch):
    # a package imported from a zip has no folder on disk: the files are copied out first
    root = _zipped_package(tmp_path, pretrained_module.PRETRAINED_FILES)
    monkeypatch.setattr(pretrained_module.resources, "files", lambda package: root)
    est = AmortisedEstimator.load_default()
    t, y = _records()[1]
    np.testing.assert_array_equal(est.estimate(t, y).coefficients,
                                  shipped.estimate(t, y).coefficients)
    with pretrained_module.pretrained_folder() as folder:
        assert folder != SHIPPED
        assert (folder / "weights.pt").read_bytes() == (SHIPPED / "weights.pt").read_bytes()
    assert not folder.exists()  # the temporary copy is removed


def test_load_default_reports_a_missing_file_in_one_line(tmp_path, monkeypatch):
    root = _zipped_package(tmp_path, ["estimator.json", "metadata.json"])
    monkeypatch.setattr(pretrained_module.resources, "files", lambda package: root)
    with pytest.raises(DataError, match="cannot read the shipped amortised model's "
                                        "'weights.pt'"):
        AmortisedEstimator.load_default()


# ------------------------------------------------------------------ command line
def test_cli_estimate_without_model_uses_the_shipped_model(shipped, tmp_path, capsys):
    t, y = _records()[0]
    np.savetxt(tmp_path / "rec.csv", np.c_[t, y], delimiter=",", header="t,h", comments="",
               fmt="%.17g")
    capsys.readouterr()
    assert main(["estimate", str(tmp_path / "rec.csv"), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["model"] == "shipped" and got["estimator"] == "amortised"
    want = shipped.estimate(t, y)  # the CSV holds the record to the last bit (%.17g)
    rec = got["records"][0]
    np.testing.assert_array_equal(rec["coefficients"], want.coefficients[0])
    np.testing.assert_array_equal([complex(*p) for p in rec["poles"]], want.poles[0])
    assert rec["fit_percent"] == want.fit_percent[0]
    assert main(["estimate", str(tmp_path / "rec.csv")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("model: the amortised model shipped with kautztwin")
    assert lines[1] == f"h: fit {want.fit_percent[0]:.3f} %"


def test_cli_estimate_help_names_the_shipped_default(capsys):
    assert main(["estimate", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "default: the amortised model shipped with kautztwin" in text
    assert "Without --model, the amortised model shipped with kautztwin is used" in text


def test_cli_estimate_without_model_reports_bad_input_in_one_line(tmp_path, capsys):
    assert main(["estimate", str(tmp_path / "missing.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.csv" in err
    t = np.linspace(0.0, 5.0, 50)
    np.savetxt(tmp_path / "flat.csv", np.c_[t, np.ones(t.size)], delimiter=",",
               header="t,h", comments="")
    assert main(["estimate", str(tmp_path / "flat.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "constant" in err


def test_cli_trains_and_estimates_with_refinement(tmp_path, capsys):
    torch.set_num_threads(1)
    out = tmp_path / "run"
    assert main(["train", "--amortised", "--max-order", "3", "--n-records", "300",
                 "--epochs", "1", "--out", str(out), "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["estimator"] == "amortised" and report["params"]["max_order"] == 3
    t = np.linspace(0.0, 8.0, 160)
    h = np.exp(-t) - np.exp(-2.5 * t)
    np.savetxt(tmp_path / "rec.csv", np.c_[t, h], delimiter=",", header="t,h", comments="")
    fits = {}
    for flags in ([], ["--refine"]):
        assert main(["estimate", str(tmp_path / "rec.csv"), "--model", str(out / "model"),
                     *flags, "--json"]) == 0
        got = json.loads(capsys.readouterr().out)
        assert got["refined"] == bool(flags) and len(got["records"][0]["poles"]) == 3
        fits[bool(flags)] = got["records"][0]["fit_percent"]
    assert fits[True] > fits[False]
    assert main(["estimate", str(tmp_path / "rec.csv"), "--model", str(out / "model")]) == 0
    assert "h: fit" in capsys.readouterr().out


def test_cli_rejects_amortised_options_elsewhere(tmp_path, capsys):
    code = main(["train", "--family", "x.toml", "--max-order", "3", "--out", str(tmp_path)])
    assert code == 2
    assert "--max-order applies to --amortised only" in capsys.readouterr().err


def test_a_second_map_round_brings_a_noise_free_fit_closer_to_exact():
    # the second search takes its noise scale from the first one's (smaller) residual, so
    # on a noise-free record the data term weighs more and the fit moves towards 100 %
    t, h, _ = _impulse("pair_and_real")
    one = AmortisedEstimator.load_default().estimate(t, h, refine=True)
    two = AmortisedEstimator.load_default().set_params(refine_rounds=2).estimate(
        t, h, refine=True)
    assert 100.0 - two.fit_percent[0] < 0.5 * (100.0 - one.fit_percent[0])
