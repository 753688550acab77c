"""Tests of ``kautztwin identify``: JSON output, records, plots, one-line errors with exit 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kautztwin.cli.main import main
from kautztwin.ident import TransferFunctionEstimator, load_records, step_response

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TCLAB = "data/tclab_step_tests/step-test-data.csv"
JSON_KEYS = ("num", "den", "poles", "zeros", "gain", "delay", "fit_percent",
             "fit_percent_per_record", "aic")


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def run_json(capsys, *argv):
    code, out, err = run(capsys, *argv, "--json")
    assert (code, err) == (0, ""), err
    return json.loads(out)


def write_step_csv(path, *, height=2.0, offset=1.0, n=120, dt=0.1, index=False, record=None):
    """A step test of 2/((s+1)(s+2)) with the step at the second row (same time stamp)."""
    t = np.arange(n) * dt
    y = offset + height * step_response(([2.0], [1.0, 3.0, 2.0]), t)
    rows = [(0.0, 0.0, offset)] + [(ti, height, yi) for ti, yi in zip(t, y, strict=True)]
    header = "time,u,y" if record is None else "time,u,y,run"
    lines = [("," if index else "") + header]
    for i, row in enumerate(rows):
        fields = [f"{v:.12g}" for v in row] + ([] if record is None else [str(record)])
        lines.append((f"{i}," if index else "") + ",".join(fields))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def tclab_json():
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["identify", TCLAB, "--time", "Time", "--input", "Q1", "--output", "T1",
                     "--kind", "step", "--order", "2", "--zeros", "0", "--json"])
    assert code == 0
    return json.loads(buf.getvalue())


# --------------------------------------------------------------------------- output
def test_json_has_the_documented_keys(tclab_json):
    for key in JSON_KEYS:
        assert key in tclab_json
    assert "validation_fit_percent" not in tclab_json
    assert len(tclab_json["poles"]) == 2 and len(tclab_json["poles"][0]) == 2  # [re, im]


def test_json_matches_the_library(tclab_json):
    recs = load_records(TCLAB, time="Time", input="Q1", output="T1", kind="step")
    model = TransferFunctionEstimator(n_poles=2, n_zeros=0).fit(recs).model_
    np.testing.assert_allclose(tclab_json["den"], model.den, rtol=1e-10)
    assert tclab_json["fit_percent"] == pytest.approx(model.fit_percent)
    assert tclab_json["fit_percent"] >= 97.75
    assert tclab_json["delay"] == 0.0


def test_several_files_are_several_records(capsys, tmp_path):
    a = write_step_csv(tmp_path / "a.csv", height=2.0, offset=1.0)
    b = write_step_csv(tmp_path / "b.csv", height=-1.0, offset=5.0, dt=0.15)
    d = run_json(capsys, "identify", a, b, "--time", "time", "--input", "u", "--output", "y",
                 "--kind", "step", "--order", "2", "--zeros", "0")
    assert len(d["fit_percent_per_record"]) == 2
    np.testing.assert_allclose(d["den"], [1.0, 3.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(d["offsets"], [1.0, 5.0], atol=1e-6)


def test_record_column_splits_one_long_file(capsys, tmp_path):
    a = write_step_csv(tmp_path / "a.csv", record=1).read_text().splitlines()
    b = write_step_csv(tmp_path / "b.csv", height=3.0, record=2).read_text().splitlines()
    long = tmp_path / "long.csv"
    long.write_text("\n".join(a + b[1:]) + "\n")
    d = run_json(capsys, "identify", long, "--time", "time", "--input", "u", "--output", "y",
                 "--record", "run", "--kind", "step", "--order", "2", "--zeros", "0")
    assert len(d["fit_percent_per_record"]) == 2
    assert d["fit_percent"] > 99.999


def test_unnamed_index_column_is_ignored(capsys, tmp_path):
    path = write_step_csv(tmp_path / "indexed.csv", index=True)
    d = run_json(capsys, "identify", path, "--time", "time", "--input", "u", "--output", "y",
                 "--kind", "step", "--order", "2", "--zeros", "0")
    np.testing.assert_allclose(d["gain"], 1.0, rtol=1e-6)


def test_validate_from_reports_the_validation_fit(capsys, tmp_path):
    rng = np.random.default_rng(0)
    t = np.arange(300) * 0.1
    u = np.repeat(rng.choice([0.0, 1.0], 30), 10)
    from kautztwin.ident import simulate_lti

    y = simulate_lti(([2.0], [1.0, 3.0, 2.0]), t, u)
    path = tmp_path / "io.csv"
    np.savetxt(path, np.column_stack([t, u, y]), delimiter=",", header="t,u,y", comments="")
    d = run_json(capsys, "identify", path, "--time", "t", "--input", "u", "--output", "y",
                 "--order", "2", "--zeros", "0", "--validate-from", "15")
    assert d["validation_fit_percent"] > 99.99
    assert d["n_samples"] == 150


def test_headerless_file_takes_column_numbers(capsys, tmp_path):
    rng = np.random.default_rng(1)
    u = np.repeat(rng.choice([3.0, 6.0], 20), 8)
    y = 4.0 + 0.5 * np.convolve(u - u.mean(), np.exp(-np.arange(10) / 3.0), "full")[: u.size]
    path = tmp_path / "plain.dat"
    np.savetxt(path, np.column_stack([u, y]), delimiter="\t")
    d = run_json(capsys, "identify", path, "--dt", "0.1", "--input", "1", "--output", "2",
                 "--order", "1")
    assert d["n_poles"] == 1


def test_auto_order_reports_the_selection(capsys, tmp_path):
    path = write_step_csv(tmp_path / "a.csv")
    d = run_json(capsys, "identify", path, "--time", "time", "--input", "u", "--output", "y",
                 "--kind", "step", "--zeros", "0", "--max-order", "3")
    assert [r["n_poles"] for r in d["order_selection"]] == [1, 2, 3]
    assert d["n_poles"] == 2  # the record's true order, below the bound: no warning


def test_auto_order_at_the_search_bound_warns(capsys, tmp_path):
    path = write_step_csv(tmp_path / "a.csv")
    code, out, err = run(capsys, "identify", path, "--time", "time", "--input", "u",
                         "--output", "y", "--kind", "step", "--zeros", "0", "--max-order", "1",
                         "--json")
    assert code == 0
    assert json.loads(out)["n_poles"] == 1
    assert "bound" in err


def test_plot_and_table(capsys, tmp_path):
    a = write_step_csv(tmp_path / "a.csv")
    b = write_step_csv(tmp_path / "b.csv", height=-1.0)
    png = tmp_path / "fit.png"
    code, out, err = run(capsys, "identify", a, b, "--time", "time", "--input", "u",
                         "--output", "y", "--kind", "step", "--order", "2", "--zeros", "0",
                         "--plot", png)
    assert (code, err) == (0, "")
    assert png.read_bytes().startswith(PNG_SIGNATURE)
    assert "fit percent" in out and "record 2" in out and "wrote" in out


def test_help_lists_identify(capsys):
    code, out, _ = run(capsys, "--help")
    assert code == 0 and "identify" in out


# --------------------------------------------------------------------------- errors
def assert_one_line_error(code, out, err, match):
    assert code == 2 and out == ""
    assert err.startswith("kautztwin: error: ") and err.count("\n") == 1
    assert match in err, err


@pytest.mark.parametrize(
    ("rows", "flags", "match"),
    [
        ("t,u,y\n0,0,1\n1,1,2\n2,1,3\n3,1,3\n", ["--output", "z"], "no column 'z'"),
        ("t,u,y\n0,0,1\n1,1,2\n2,1,3\n", [], "too short"),
        ("t,u,y\n0,1,1\n1,1,2\n2,1,3\n3,1,3\n4,1,3\n", ["--kind", "io"], "input is constant"),
        ("t,u,y\n0,0,1\n1,1,nan\n2,1,3\n3,1,3\n4,1,3\n", [], "NaN"),
        ("t,u,y\n0,0,1\n2,1,2\n1,1,3\n3,1,3\n4,1,3\n", [], "must not decrease"),
        ("t,u,y\n0,0,1\n1,1,2\n2,0,3\n3,1,3\n4,1,3\n", ["--kind", "step"], "single step"),
    ],
    ids=["missing-column", "too-short", "constant-input", "nan", "decreasing-time", "two-steps"],
)
def test_data_errors_are_one_line_exit_2(capsys, tmp_path, rows, flags, match):
    path = tmp_path / "bad.csv"
    path.write_text(rows)
    argv = ["identify", path, "--time", "t", "--input", "u", "--output", "y", "--order", "1"]
    if "--output" in flags:
        argv[argv.index("--output") + 1] = flags[1]
        flags = []
    code, out, err = run(capsys, *argv, *flags)
    assert_one_line_error(code, out, err, match)


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        (["--order", "0"], "--order must be"),
        (["--order", "two"], "--order must be"),
        (["--order", "1", "--zeros", "2"], "improper"),
        (["--dt", "0.1"], "exactly one of the two"),
        (["--delay", "--fixed-delay", "0.1"], "only one of --delay"),
        (["--kind", "step", "--validate-from", "100"], "no validation samples"),
        (["--kind", "ramp"], "invalid choice"),
    ],
    ids=["order-0", "order-text", "improper", "time-and-dt", "two-delays", "late-validation",
         "kind"],
)
def test_flag_errors_are_one_line_exit_2(capsys, tmp_path, flags, match):
    path = write_step_csv(tmp_path / "a.csv")
    code, out, err = run(capsys, "identify", path, "--time", "time", "--input", "u",
                         "--output", "y", *flags)
    assert_one_line_error(code, out, err, match)


def test_missing_file_is_one_line_exit_2(capsys, tmp_path):
    code, out, err = run(capsys, "identify", tmp_path / "none.csv", "--time", "t", "--input",
                         "u", "--output", "y")
    assert_one_line_error(code, out, err, "no such file")


def test_named_columns_in_a_headerless_file_are_an_error(capsys, tmp_path):
    path = tmp_path / "plain.dat"
    np.savetxt(path, np.ones((10, 2)))
    code, out, err = run(capsys, "identify", path, "--dt", "1", "--input", "u", "--output", "y")
    assert_one_line_error(code, out, err, "no header row")


# --------------------------------------------------------------------------- --report
def write_noisy_io_csv(path, *, seed=0, n=1200, dt=0.05, noise=0.02):
    """Input/output record of 2 / (s^2 + 1.2 s + 1) with white measurement noise."""
    from kautztwin.ident import simulate_lti

    rng = np.random.default_rng(seed)
    t = dt * np.arange(n)
    u = np.repeat(rng.choice([0.0, 1.0], n // 10), 10)
    y = 3.0 + simulate_lti(([2.0], [1.0, 1.2, 1.0]), t, u) + noise * rng.standard_normal(n)
    np.savetxt(path, np.column_stack([t, u, y]), delimiter=",", header="t,u,y", comments="")
    return path


REPORT_FILES = ("report.md", "report.json", "compare.png", "residuals.png", "bode.png",
                "step.png")


@pytest.mark.parametrize(("order", "white"), [(2, True), (1, False)],
                         ids=["right-order", "under-modelled"])
def test_report_writes_the_files_and_the_verdict(capsys, tmp_path, order, white):
    data = write_noisy_io_csv(tmp_path / "io.csv")
    out = tmp_path / "report" / "sub"  # made with its parents
    code, text, err = run(capsys, "identify", data, "--time", "t", "--input", "u", "--output",
                          "y", "--order", order, "--zeros", "0", "--validate-from", "30",
                          "--report", out)
    assert (code, err) == (0, "")
    for name in REPORT_FILES:
        assert (out / name).stat().st_size > 0, name
    for name in REPORT_FILES[2:]:
        assert (out / name).read_bytes().startswith(PNG_SIGNATURE), name
    verdict = json.loads((out / "report.json").read_text())
    assert verdict["tested_on"] == "validation"
    assert verdict["residuals_white"] is white
    assert verdict["residuals_independent_of_input"] is white
    assert 0.0 <= verdict["whiteness_p_value"] <= 1.0
    assert [p["name"] for p in verdict["parameters"]][-1] == f"den[{order}]"
    assert len(verdict["poles"]) == order
    md = (out / "report.md").read_text()
    yes_no = "yes" if white else "no"
    assert f"residuals white: {yes_no} (Ljung-Box p = " in md
    assert f"residuals independent of input: {yes_no} (p = " in md
    assert "validation" in md and "| den[1] |" in md
    assert f"residuals white (validation data): {yes_no}" in text


def test_report_summary_in_json(capsys, tmp_path):
    data = write_noisy_io_csv(tmp_path / "io.csv", n=600)
    d = run_json(capsys, "identify", data, "--time", "t", "--input", "u", "--output", "y",
                 "--order", "2", "--zeros", "0", "--report", tmp_path / "rep")
    assert d["report"]["tested_on"] == "estimation"
    assert d["report"]["residuals_white"] is True
    assert sorted(d["report"]["files"]) == sorted(REPORT_FILES)


def test_report_of_a_step_record_without_input_variation(capsys, tmp_path):
    """TCLab: the input is constant over the record, so there is no cross-correlation test."""
    out = tmp_path / "tclab"
    code, text, err = run(capsys, "identify", TCLAB, "--time", "Time", "--input", "Q1",
                          "--output", "T1", "--kind", "step", "--order", "2", "--zeros", "0",
                          "--report", out)
    assert (code, err) == (0, "")
    verdict = json.loads((out / "report.json").read_text())
    assert verdict["residuals_independent_of_input"] is None
    assert "n/a" in (out / "report.md").read_text()


@pytest.mark.parametrize("where", ["file", "under-a-file"])
def test_report_dir_that_cannot_be_a_folder_is_one_line_exit_2(capsys, tmp_path, where):
    data = write_step_csv(tmp_path / "a.csv")
    blocker = tmp_path / "taken"
    blocker.write_text("x")
    target = blocker if where == "file" else blocker / "report"
    code, out, err = run(capsys, "identify", data, "--time", "time", "--input", "u",
                         "--output", "y", "--kind", "step", "--order", "2", "--report", target)
    assert_one_line_error(code, out, err, "--report")
    assert "not a directory" in err
