"""Tests of ``kautztwin simulate hydraulic``: files written, summary, one-line errors (exit 2)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from kautztwin.cli.main import main
from kautztwin.data import read_columns
from kautztwin.simulators import HydraulicServoDrive


def run(capsys, *argv):
    """Run the CLI in-process; return (exit status, stdout, stderr)."""
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def load(path):
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def test_paper_sized_session_writes_30_records_of_900_samples(capsys, tmp_path):
    out = tmp_path / "data"
    code, stdout, err = run(capsys, "simulate", "hydraulic", "--records", "30", "--samples", "900",
                            "--temperature", "20:60", "--out", str(out))
    assert (code, err) == (0, "")
    assert stdout.count("\n") == 1 and stdout.startswith("wrote 30 step tests x 900 samples")
    files = sorted(p.name for p in out.glob("record_*.csv"))
    assert files == [f"record_{k:02d}.csv" for k in range(1, 31)]
    assert (out / "record_01.csv").read_text().splitlines()[0] == "t,u,y,temperature"
    temps = [load(out / name)[0, 3] for name in files]
    np.testing.assert_allclose(temps, np.linspace(20.0, 60.0, 30), atol=1e-8)
    table = load(out / "record_30.csv")
    assert table.shape == (900, 4)
    np.testing.assert_allclose(table[[0, -1], 0], [0.0, 3.0])
    np.testing.assert_array_equal(table[:, 1], 0.5)
    np.testing.assert_array_equal(table[:, 3], 60.0)


def test_summary_holds_parameters_temperatures_and_poles(capsys, tmp_path):
    out = tmp_path / "s"
    code, _, _ = run(capsys, "simulate", "hydraulic", "--records", "3", "--samples", "50",
                     "--temperature", "20:60", "--seed", "4", "--out", str(out))
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_records"] == 3 and summary["n_samples"] == 50
    assert summary["temperatures"] == [20.0, 40.0, 60.0]
    assert summary["files"] == ["record_01.csv", "record_02.csv", "record_03.csv"]
    assert summary["parameters"]["supply_pressure"] == 10.0e6
    poles = np.array(summary["poles"])  # (records, 3 poles, [re, im])
    assert poles.shape == (3, 3, 2)
    np.testing.assert_array_equal(poles[..., 1], 0.0)
    lin = HydraulicServoDrive().linearize(0.5, 40.0)
    np.testing.assert_allclose(poles[1, :, 0], lin.poles.real, rtol=1e-12)
    np.testing.assert_allclose(summary["dc_gain"][1], lin.dc_gain, rtol=1e-12)


def test_json_flag_prints_the_summary(capsys, tmp_path):
    out = tmp_path / "j"
    code, stdout, err = run(capsys, "simulate", "hydraulic", "--records", "2", "--samples", "20",
                            "--out", str(out), "--json")
    assert (code, err) == (0, "")
    printed = json.loads(stdout)
    assert printed == json.loads((out / "summary.json").read_text())


def test_records_are_readable_by_the_csv_loader_and_reproducible(capsys, tmp_path):
    argv = ["simulate", "hydraulic", "--records", "2", "--samples", "40", "--noise", "0.05",
            "--seed", "9", "--amplitude", "-0.4", "--t-end", "2"]
    assert run(capsys, *argv, "--out", str(tmp_path / "a"))[0] == 0
    assert run(capsys, *argv, "--out", str(tmp_path / "b"))[0] == 0
    a = (tmp_path / "a" / "record_02.csv").read_text()
    assert a == (tmp_path / "b" / "record_02.csv").read_text()
    cols = read_columns(tmp_path / "a" / "record_02.csv", ["t", "y"])
    assert cols["t"].shape == cols["y"].shape == (40,)
    assert cols["t"][-1] == 2.0 and cols["y"][-1] < 0  # negative command, reverse rotation


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        (["--records", "0"], "--records must be >= 1"),
        (["--records", "-2"], "--records must be >= 1"),
        (["--samples", "1"], "--samples must be >= 2"),
        (["--temperature", "60:20"], "needs LO <= HI"),
        (["--temperature", "warm"], "--temperature must be LO:HI"),
        (["--temperature", "20:500"], r"must lie in \[-20, 120\]"),
        (["--temperature", "1:2:3"], "--temperature must be LO:HI"),
        (["--t-end", "0"], "--t-end must be a positive number"),
        (["--amplitude", "0"], "--amplitude must be a nonzero number"),
        (["--noise", "-0.1"], "--noise must be a fraction >= 0"),
        (["--samples", "many"], "invalid int value"),
    ],
    ids=["no-records", "negative-records", "one-sample", "reversed-range", "not-a-range",
         "too-hot", "three-values", "zero-length", "zero-step", "negative-noise", "not-a-count"],
)
def test_bad_values_give_one_line_and_exit_2(capsys, tmp_path, flags, match):
    out = tmp_path / "never"
    code, stdout, err = run(capsys, "simulate", "hydraulic", *flags, "--out", str(out))
    assert code == 2 and stdout == ""
    assert err.count("\n") == 1 and err.startswith("kautztwin: error: ")
    assert re.search(match, err)
    assert not out.exists()  # checked before anything is written


def test_unwritable_out_gives_exit_2(capsys, tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a directory")
    for target, match in [(blocker, "exists and is not a directory"),
                          (blocker / "sub", "cannot create the directory")]:
        code, _, err = run(capsys, "simulate", "hydraulic", "--records", "1", "--out", str(target))
        assert code == 2 and err.count("\n") == 1 and match in err


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["simulate"], "required: PLANT"),
        (["simulate", "hydraulic"], "required: --out"),
        (["simulate", "pneumatic"], "invalid choice"),
    ],
    ids=["no-plant", "no-out", "unknown-plant"],
)
def test_usage_errors_exit_2(capsys, argv, match):
    code, _, err = run(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and match in err


def test_help_exits_0(capsys):
    code, stdout, _ = run(capsys, "simulate", "hydraulic", "--help")
    assert code == 0 and "--temperature LO:HI" in stdout
