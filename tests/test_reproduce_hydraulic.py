"""Tests of ``kautztwin reproduce hydraulic`` (the paper's section 3.2) in quick mode."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch  # noqa: E402,F401 - the [nn] extra, part of [test]

from kautztwin.cli.main import main  # noqa: E402
from kautztwin.experiments import hydraulic  # noqa: E402
from kautztwin.experiments.hydraulic import HydraulicSetup, reproduce_hydraulic  # noqa: E402
from kautztwin.experiments.hydraulic_dnn import (  # noqa: E402
    ACCEPTANCE_POINTS,
    per_record_table,
    simulate_step_family,
)

FILES = ("metrics.json", "report.md", "fig9_step_impulse.png", "fig10_training.png",
         "fig11_approximations.png", "fit_vs_temperature.png", "fig12_adaptive_dnn.png")
METHODS = ("nominal_model", "dnn", "projection", "truth_projection", "fixed_basis_ceiling",
           "varpro_per_record", "adaptive_dnn", "adaptive_dnn_refined")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """One quick reproduction, shared by the tests; returns (metrics, out_dir, seconds)."""
    out = tmp_path_factory.mktemp("hydraulic")
    start = time.perf_counter()
    metrics = reproduce_hydraulic(out, quick=True, random_state=0)
    seconds = time.perf_counter() - start
    print(f"\nreproduce hydraulic --quick: {seconds:.1f} s")
    return metrics, out, seconds


def test_writes_metrics_report_and_figures(quick_run):
    metrics, out, _ = quick_run
    for name in FILES:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(metrics))


def test_metrics_have_the_documented_keys(quick_run):
    m, _, _ = quick_run
    assert {"identification", "methods", "train", "setup", "paper_claims", "uncertainty",
            "impulse", "per_record", "sanity", "seconds_total"} <= set(m)
    assert {"num", "den", "poles", "gain", "fit_percent", "fit_percent_per_record"} <= set(
        m["identification"])
    assert m["paper_claims"]["fit_percent"] == 97.31
    assert set(METHODS) <= set(m["methods"])
    for name, stats in m["methods"].items():
        assert {"fit_mean", "fit_min", "fit_max", "seconds_per_record"} <= set(stats), name
        assert stats["fit_min"] <= stats["fit_mean"] <= stats["fit_max"] <= 100.0
        assert stats["n_records"] == m["setup"]["n_records"]
    assert {"seconds", "final_train_loss", "final_val_loss"} <= set(m["train"])
    assert len(m["train"]["final_val_loss"]) == 3  # one network per Kautz coefficient
    assert m["setup"]["quick"] is True and m["setup"]["temperatures"] == [20.0, 60.0]
    assert "paper_dnn" not in m["methods"]  # the paper preset runs in full mode only


def test_identified_model_has_three_real_stable_poles(quick_run):
    ident = quick_run[0]["identification"]
    poles = np.array(ident["poles"])  # [re, im] pairs
    assert poles.shape == (3, 2)
    np.testing.assert_array_less(np.abs(poles[:, 1]), 1e-9 * np.abs(poles[:, 0]) + 1e-12)
    assert np.all(poles[:, 0] < 0)
    assert len(set(np.round(poles[:, 0], 6))) == 3  # distinct
    assert ident["all_poles_real"] and ident["all_poles_stable"]
    assert len(ident["num"]) == 1 and len(ident["den"]) == 4  # no zeros, three poles
    np.testing.assert_allclose(ident["gain"], ident["num"][-1] / ident["den"][-1])
    assert len(ident["fit_percent_per_record"]) == quick_run[0]["setup"]["n_records"]
    # the Kautz basis is built on the identified poles
    np.testing.assert_allclose(sorted(p[0] for p in quick_run[0]["basis_poles"]),
                               sorted(poles[:, 0]))


def test_identification_fits(quick_run):
    """Each record alone is fitted above 90 % (the paper: 97.31 %); one model for all is not.

    The oil warms from 20 to 60 degC over the session and moves the DC gain by about 10 %,
    which no single LTI model follows: the joint model fits the middle records well and the
    extreme ones worse.
    """
    ident = quick_run[0]["identification"]
    per = np.array(ident["per_record_models"]["fit_percent_per_record"])
    assert np.all(per > 90.0), per
    joint = np.array(ident["fit_percent_per_record"])
    assert ident["fit_percent"] > 70.0
    assert joint.max() > 90.0
    assert ident["with_offsets"]["fit_percent"] > 90.0
    # the noise level is estimated from the records (simulated with 1 %)
    assert quick_run[0]["impulse"]["noise_fraction_estimated"] == pytest.approx(0.01, rel=0.15)


def test_approximation_fits_are_consistent(quick_run):
    m = quick_run[0]
    meth, fits = m["methods"], m["per_record"]["fits"]
    assert m["sanity"]["passed"]
    ceiling = np.array(fits["fixed_basis_ceiling"]["step"])
    for name in ("nominal_model", "dnn", "projection", "truth_projection"):
        assert np.all(np.array(fits[name]["step"]) <= ceiling + 1e-9), name
    assert meth["varpro_per_record"]["fit_mean"] > 90.0  # the noise-limited bound
    assert meth["fixed_basis_ceiling"]["fit_mean"] > 85.0
    assert meth["dnn"]["fit_mean"] > 60.0
    assert meth["dnn"]["impulse_fit_noise_free_mean"] > 70.0


def test_report_sets_our_numbers_beside_the_papers(quick_run):
    m, out, _ = quick_run
    report = (out / "report.md").read_text()
    assert "97.31" in report
    assert "simulated, not the paper's measurements" in report
    assert f"{m['identification']['fit_percent']:.2f}" in report
    assert f"{m['methods']['dnn']['fit_mean']:.2f}" in report


def test_cli_runs_the_study(capsys, tmp_path, monkeypatch):
    """``kautztwin reproduce hydraulic --quick`` wires through to the study (tiny budgets)."""
    tiny = HydraulicSetup(n_records=4, n_samples=200, n_train=60, max_epochs=3,
                          paper_preset=False, n_test=10, structure_check=False,
                          adaptive_train=60, adaptive_test=10, adaptive_epochs=1,
                          adaptive_hidden=(16,))
    monkeypatch.setattr(hydraulic.HydraulicSetup, "quick", classmethod(lambda cls: tiny))
    out = tmp_path / "cli"
    before = torch.get_num_threads()
    code = main(["reproduce", "hydraulic", "--quick", "--quiet", "--out", str(out)])
    assert torch.get_num_threads() == before  # the study's one thread is not left behind
    captured = capsys.readouterr()
    assert code == 0
    assert captured.out.startswith("identified model fit ")
    m = json.loads((out / "metrics.json").read_text())
    assert m["setup"]["n_records"] == 4 and m["setup"]["quick"] is True
    assert m["setup"]["torch_threads"] == 1
    assert f"{m['identification']['fit_percent']:.2f} %" in captured.out
    s = m["adaptive"]["per_record"]["summary"]
    assert f"adaptive DNN fit {s['dnn_mean']:.2f} % per record" in captured.out
    assert f"VARPRO bound {s['varpro_bound_mean']:.2f} %" in captured.out
    for name in FILES:
        assert (out / name).is_file(), name


# --------------------------------------------------------------------------- the adaptive DNN
def test_adaptive_stage_reports_every_record(quick_run):
    """``metrics['adaptive']``: one row per record, consistent with the per-record fits."""
    m = quick_run[0]
    block, fits = m["adaptive"], m["per_record"]["fits"]
    n = m["setup"]["n_records"]
    table = block["per_record"]
    assert table["paper_fit_percent"] == 97.31 and table["tolerance"] == ACCEPTANCE_POINTS
    assert [r["record"] for r in table["rows"]] == list(range(1, n + 1))
    dnn = np.array([r["dnn"] for r in table["rows"]])
    ref = np.array([r["dnn_refined"] for r in table["rows"]])
    bound = np.array([r["varpro_bound"] for r in table["rows"]])
    np.testing.assert_array_equal(dnn, fits["adaptive_dnn"]["step"])
    np.testing.assert_array_equal(ref, fits["adaptive_dnn_refined"]["step"])
    np.testing.assert_array_equal(bound, fits["varpro_per_record"]["step"])
    np.testing.assert_allclose([r["gap"] for r in table["rows"]], bound - dnn, atol=1e-12)
    s = table["summary"]
    assert s["dnn_mean"] == pytest.approx(dnn.mean(), abs=1e-12)
    assert s["dnn_within_tolerance"] == bool(np.all(bound - dnn <= ACCEPTANCE_POINTS))
    assert len(block["poles"]) == len(block["poles_refined"]) == n
    poles = np.array(block["poles"])  # (n, 3, [re, im]): stable by construction
    assert poles.shape == (n, 3, 2) and np.all(poles[..., 0] < 0)
    tr = block["train"]
    assert tr["n_records"] == m["setup"]["adaptive_train"]
    assert len(tr["epochs"]) == tr["n_stages"] == 2
    lo, hi = m["setup"]["temperatures"]
    margin = m["setup"]["adaptive_temperature_margin"]
    assert tr["temperatures"] == [lo - margin, hi + margin]


def test_adaptive_dnn_fits_the_records(quick_run):
    """The network's poles fit the records better than any fixed basis, near the bound.

    Refinement is variable projection on the same least-squares objective started at the
    network's poles, so it cannot lower a record's step fit.
    """
    m = quick_run[0]
    fits = m["per_record"]["fits"]
    dnn = np.array(fits["adaptive_dnn"]["step"])
    ref = np.array(fits["adaptive_dnn_refined"]["step"])
    ceiling = np.array(fits["fixed_basis_ceiling"]["step"])
    nominal = np.array(fits["nominal_model"]["step"])
    bound = np.array(fits["varpro_per_record"]["step"])
    np.testing.assert_array_less(dnn - 1e-6, ref)
    # per-record poles beat the best fixed basis (not on every record at the quick budget:
    # near the identified model's temperature the fixed basis is already close to the bound)
    assert dnn.mean() > ceiling.mean() + 1.0 and dnn.min() > ceiling.min() + 1.0
    assert dnn.mean() > nominal.mean() + 10.0  # and the identified model by far
    assert np.mean(bound - dnn) < 1.0  # quick budget; the full run is the acceptance test
    assert np.max(np.abs(bound - ref)) < 0.1  # refined: at the bound (another local optimum)
    # the network generalises to fresh simulated records (noise-free fit)
    assert m["adaptive"]["train"]["test_fit_percent_noise_free"] > 95.0


def test_report_states_which_path_meets_the_bound(quick_run):
    m, out, _ = quick_run
    report = (out / "report.md").read_text()
    s = m["adaptive"]["per_record"]["summary"]
    assert "## The paper's update module: the adaptive DNN on every record" in report
    assert f"**{s['dnn_mean']:.2f}**" in report and f"**{s['varpro_bound_mean']:.2f}**" in report
    if s["dnn_within_tolerance"]:
        assert "**The DNN alone is within 0.5 points of the VARPRO bound on every" in report
    elif s["refined_within_tolerance"]:
        assert "**Only the refined path (DNN + VARPRO) is within 0.5 points" in report
    else:
        assert "**Neither path is within 0.5 points" in report


def test_step_family_matches_the_scalar_simulator():
    """The batch-simulated training records are the drive's own step responses (LSODA)."""
    from kautztwin.simulators import HydraulicServoDrive

    t = np.linspace(0.0, 3.0, 300)
    data = simulate_step_family(3, t, amplitude=0.5, temperatures=(35.0, 35.0), spread=0.0,
                                noise=0.0, basis_poles=[-2.7, -11.0, -80.0], random_state=3)
    drive = HydraulicServoDrive()
    ref = drive.step_response(t, 0.5, 35.0).y_true / 0.5
    for k in range(3):  # spread 0 and one temperature: three identical drives
        np.testing.assert_allclose(data.clean[k], ref, atol=1e-6 * np.abs(ref).max())
    np.testing.assert_array_equal(data.responses, data.clean)
    np.testing.assert_allclose(np.sort(data.poles[0].real),
                               np.sort(drive.linearize(0.5, 35.0).poles.real), rtol=1e-9)
    assert data.kind == "step" and data.parameter_names[0] == "temperature"


def test_step_family_draws_and_noise():
    from kautztwin.simulators import HydraulicParameters

    t = np.linspace(0.0, 3.0, 300)
    data = simulate_step_family(40, t, amplitude=0.5, temperatures=(20.0, 60.0), spread=0.1,
                                noise=0.02, basis_poles=[-2.7, -11.0, -80.0], random_state=0)
    T = data.parameters[:, 0]
    assert T.min() >= 20.0 and T.max() <= 60.0 and np.ptp(T) > 30.0
    nominal = HydraulicParameters()
    rel = data.parameters[:, 1:] / [getattr(nominal, n) for n in data.parameter_names[1:]]
    assert np.all(np.abs(rel - 1) <= 0.1) and np.all(np.ptp(rel, axis=0) > 0.1)
    noise = np.std(data.responses - data.clean, axis=1) / np.abs(data.clean).max(axis=1)
    np.testing.assert_allclose(noise, 0.02, rtol=0.15)  # 300 samples: std error about 4 %
    again = simulate_step_family(40, t, amplitude=0.5, temperatures=(20.0, 60.0), spread=0.1,
                                 noise=0.02, basis_poles=[-2.7, -11.0, -80.0], random_state=0)
    np.testing.assert_array_equal(again.responses, data.responses)  # seeded


@pytest.mark.parametrize(
    ("change", "match"),
    [({"n_records": 1}, "n_records"), ({"t": np.linspace(0.5, 3.0, 50)}, "uniform grid"),
     ({"spread": 1.0}, "spread"), ({"temperatures": (60.0, 20.0)}, "lo <= hi"),
     ({"noise": -0.01}, "noise")],
    ids=["one-record", "grid-not-from-0", "spread-1", "decreasing-range", "negative-noise"],
)
def test_step_family_rejects_bad_input(change, match):
    from kautztwin.exceptions import DataError

    kwargs = {"n_records": 3, "t": np.linspace(0.0, 3.0, 50), "amplitude": 0.5,
              "temperatures": (20.0, 60.0), "spread": 0.1, "noise": 0.01,
              "basis_poles": [-2.7, -11.0, -80.0], **change}
    with pytest.raises(DataError, match=match):
        simulate_step_family(**kwargs)


def test_per_record_table_flags_the_tolerance():
    table = per_record_table([20.0, 40.0], {"dnn": [95.0, 96.4], "refined": [95.9, 96.5],
                                            "bound": [96.0, 96.5]}, 97.31)
    s = table["summary"]
    assert [r["gap"] for r in table["rows"]] == pytest.approx([1.0, 0.1])
    assert s["records_within_tolerance"] == 1 and not s["dnn_within_tolerance"]
    assert s["refined_within_tolerance"] and s["gap_refined_max"] == pytest.approx(0.1)
    assert s["dnn_mean_minus_paper"] == pytest.approx(95.7 - 97.31)


@pytest.mark.slow
def test_full_size_dnn_is_within_half_a_point_of_the_bound(tmp_path):
    """Issue #14 acceptance: 30 x 900 records, full DNN budget, every record within 0.5 points.

    The coefficient networks, the paper preset and the zero-structure check are cut to keep
    the test to a few minutes; they do not feed the DNN stage.
    """
    setup = HydraulicSetup(n_train=200, max_epochs=3, paper_preset=False, n_test=20,
                           structure_check=False)
    m = reproduce_hydraulic(tmp_path, setup=setup, random_state=0)
    s = m["adaptive"]["per_record"]["summary"]
    assert s["n_records"] == 30
    assert s["dnn_within_tolerance"], s
    assert s["refined_within_tolerance"], s
    assert s["varpro_bound_mean"] == pytest.approx(96.18, abs=0.05)
