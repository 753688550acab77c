"""``kautztwin twin run``: files written, metrics, resume from the store, one-line errors."""

from __future__ import annotations

import json

import pytest

from kautztwin.cli.main import main
from kautztwin.twin import SQLiteHistory
from kautztwin.twin.runtime import DigitalTwin, TwinConfig, make_plant

ISSUE_KEYS = (
    "sync_fit_mean", "sync_fit_min_after_recovery", "static_twin_sync_fit_mean",
    "reidentifications", "tracking_iae", "constraint_violations", "mpc_solve_ms", "update_ms",
)


def run(capsys, *argv):
    """Run the CLI in-process; return (exit status, stdout, stderr)."""
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_tclab_run_writes_metrics_report_plots_and_history(capsys, tmp_path):
    out = tmp_path / "tclab"
    code, stdout, err = run(capsys, "twin", "run", "--plant", "tclab", "--quick", "--duration",
                            "1200", "--setpoints", "48,42", "--out", str(out))
    assert (code, err) == (0, "")
    assert stdout.count("\n") == 1 and stdout.startswith("twin run tclab: 1200 samples")
    assert "0 constraint violations" in stdout
    names = sorted(p.name for p in out.iterdir())
    assert names == ["history.sqlite", "metrics.json", "outputs.png", "report.md",
                     "sync_fit.png", "timings.png", "tracking.png"]
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ISSUE_KEYS:
        assert key in metrics
    assert metrics["constraint_violations"] == 0 and metrics["status"] == "finished"
    with SQLiteHistory(out / "history.sqlite") as h:
        assert len(h.measurements(1)) == 1200 and h.run_info(1).status == "finished"


def test_json_flag_prints_the_metrics(capsys, tmp_path):
    out = tmp_path / "hyd"
    code, stdout, err = run(capsys, "twin", "run", "--plant", "hydraulic", "--quick",
                            "--duration", "10", "--faults", "dropout=0.02,outlier=0.01",
                            "--no-plots", "--out", str(out), "--json")
    assert (code, err) == (0, "")
    printed = json.loads(stdout)
    assert printed["n_samples"] == 500 and printed["samples"]["dropouts"] > 0
    assert printed == json.loads((out / "metrics.json").read_text())
    assert not list(out.glob("*.png"))


def test_an_interrupted_run_is_resumed_by_the_same_command(capsys, tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    plant = make_plant("tclab", seed=0)
    cfg = TwinConfig.for_plant(plant, duration=1200.0, quick=True, seed=0)
    twin = DigitalTwin(plant, cfg, history=out / "history.sqlite")
    twin.start()
    for _ in range(700):
        twin.step()
    twin.finish()  # killed here: 700 samples committed, run still 'running'
    twin.close()
    code, stdout, err = run(capsys, "twin", "run", "--plant", "tclab", "--quick", "--duration",
                            "1200", "--no-plots", "--out", str(out))
    assert (code, err) == (0, "")
    assert "(resumed after 700)" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["resume"] == {"resumed": True, "resume_k": 700, "replayed": 700,
                                 "replay_mismatches": 0}
    with SQLiteHistory(out / "history.sqlite") as h:
        assert [r.status for r in h.runs()] == ["finished"]
        assert h.measurements(1).k.tolist() == list(range(1200))
    # a finished run is not resumed: the same command starts a new run in the store
    code, stdout, _ = run(capsys, "twin", "run", "--plant", "tclab", "--quick", "--duration",
                          "700", "--no-plots", "--no-static", "--out", str(out))
    assert code == 0 and "resumed" not in stdout
    with SQLiteHistory(out / "history.sqlite") as h:
        assert len(h.runs()) == 2


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--plant", "boiler"], "--plant must be hydraulic, tclab or replay:FILE"),
        (["--plant", "tclab", "--drift", "0.2"], "--drift applies to the hydraulic plant only"),
        (["--plant", "hydraulic", "--setpoints", "0.45,0.55,0.5"],
         "set-point 0.45 lies outside the output limits [70, 130]"),
        (["--plant", "hydraulic", "--setpoints", "97,20:103"], "not both"),
        (["--plant", "hydraulic", "--quick", "--drift", "0.4@2,20"],
         "falls inside the identification phase"),
        (["--plant", "hydraulic", "--drift", "much"], "--drift must be FRACTION"),
        (["--plant", "hydraulic", "--drift", "0.95"], "fraction in (-0.9, 0.9)"),
        (["--plant", "hydraulic", "--faults", "noise=1"], "faults: cannot read 'noise=1'"),
        (["--plant", "hydraulic", "--duration", "-5"], "--duration must be a positive"),
        (["--plant", "hydraulic", "--speedup", "0"], "--speedup must be a positive"),
        (["--plant", "replay:missing.csv"], "cannot read missing.csv"),
        (["--plant", "replay:x.csv", "--setpoints", "1,2"], "do not apply to a replay"),
    ],
    ids=["plant", "drift-tclab", "setpoint-range", "setpoint-forms", "drift-in-ident",
         "drift-text", "drift-size", "faults", "duration", "speedup", "replay-file",
         "replay-setpoints"],
)
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    code, stdout, err = run(capsys, "twin", "run", *argv, "--out", str(tmp_path / "o"))
    assert code == 2 and stdout == ""
    assert err.startswith("kautztwin: error: ") and err.count("\n") == 1
    assert message in err
    assert not (tmp_path / "o").exists()  # nothing is written on a usage error


def test_twin_needs_an_action_and_run_needs_out(capsys):
    code, _, err = run(capsys, "twin")
    assert code == 2 and "action" in err.lower()
    code, _, err = run(capsys, "twin", "run", "--plant", "tclab")
    assert code == 2 and "--out" in err
    assert run(capsys, "twin", "run", "--help")[0] == 0
