"""Tests of the ``kautztwin`` command line: commands, JSON output, exit codes, one-line errors.

Most tests call :func:`kautztwin.cli.main.main` in-process; one runs
``python -m kautztwin --help`` in a subprocess.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest

import kautztwin
from kautztwin.cli.main import build_parser, main
from kautztwin.data import reference_poles, reference_response
from kautztwin.exceptions import ConvergenceWarning

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
REF_POLES = "-1,-3,-0.5+1.9364916731j,-0.5-1.9364916731j"
# Exact coefficients of G(s) = 6/((s+1)(s+3)(s^2+s+4)) in the Kautz basis of its own
# poles (kautz-math.md 9.2): sqrt(2)/8, -3 sqrt(6)/32, 5 sqrt(2)/32, sqrt(2)/16.
REF_COEFFICIENTS = [0.176776695297, -0.229639663386, 0.220970869121, 0.088388347648]


def run(capsys, *argv):
    """Run the CLI in-process; return (exit status, stdout, stderr)."""
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def run_json(capsys, *argv):
    code, out, err = run(capsys, *argv, "--json")
    assert (code, err) == (0, "")
    return json.loads(out)


def assert_png(path):
    data = path.read_bytes()
    assert len(data) > 0 and data.startswith(PNG_SIGNATURE)


def write_csv(path, t, y, header="t,h"):
    np.savetxt(path, np.column_stack([t, y]), delimiter=",", header=header, comments="",
               fmt="%.17g")
    return path


# --------------------------------------------------------------------------- help and version
def test_module_help_in_subprocess():
    proc = subprocess.run([sys.executable, "-m", "kautztwin", "--help"],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: kautztwin")
    for command in ("basis", "approx", "sensitivity"):
        assert command in proc.stdout


def test_version(capsys):
    code, out, _ = run(capsys, "--version")
    assert (code, out.strip()) == (0, f"kautztwin {kautztwin.__version__}")


def _subparsers(parser):
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


@pytest.mark.parametrize("command", ["basis", "approx", "sensitivity"])
def test_help_explains_every_flag(capsys, command):
    sub = _subparsers(build_parser())[command]
    code, out, _ = run(capsys, command, "--help")
    assert code == 0
    for action in sub._actions:
        if action.help is argparse.SUPPRESS:
            continue
        assert action.help, f"{command}: {action.option_strings or action.dest} has no help"
        for flag in action.option_strings:
            assert flag in out


def test_top_level_help_lists_commands_and_flags(capsys):
    code, out, _ = run(capsys, "--help")
    assert code == 0
    for text in ("basis", "approx", "sensitivity", "--debug", "--version", "exit status"):
        assert text in out


def test_missing_command_is_usage_error(capsys):
    code, out, err = run(capsys)
    assert (code, out) == (2, "")
    assert err.count("\n") == 1 and err.startswith("kautztwin: error: missing command")


# --------------------------------------------------------------------------- basis
def test_basis_writes_png_and_reports(capsys, tmp_path):
    out_file = tmp_path / "fig2.png"
    code, out, err = run(capsys, "basis", "--poles", "-1.1,-0.8,-2.1", "--out", str(out_file))
    assert (code, err) == (0, "")
    assert_png(out_file)
    assert "3 functions" in out and str(out_file) in out


def test_basis_json_matches_library(capsys, tmp_path):
    out_file = tmp_path / "k.png"
    data = run_json(capsys, "basis", "--poles", "-1, -3, -0.5+1.9365i, -0.5-1.9365i",
                    "--out", str(out_file))
    basis = kautztwin.KautzBasis([-1, -3, -0.5 + 1.9365j, -0.5 - 1.9365j])
    A, B = basis.state_space()
    np.testing.assert_array_equal(data["A"], A)
    np.testing.assert_array_equal(data["B"], B)
    assert data["poles"] == [[-1.0, 0.0], [-3.0, 0.0], [-0.5, 1.9365], [-0.5, -1.9365]]
    assert data["n_functions"] == 4 and data["dt"] == 0.0
    assert 0 <= data["gram_deviation"] < 1e-12  # Gram = I by construction, to rounding
    assert_png(out_file)


def test_basis_pair_shorthand_equals_explicit_pair(capsys, tmp_path):
    a = run_json(capsys, "basis", "--poles", "-1,-0.5+-2j", "--out", str(tmp_path / "a.png"))
    b = run_json(capsys, "basis", "--poles=-1,-0.5+2j,-0.5-2j", "--out", str(tmp_path / "b.png"))
    assert a["A"] == b["A"] and a["poles"] == b["poles"]


def test_basis_laguerre(capsys, tmp_path):
    data = run_json(capsys, "basis", "--laguerre", "-2", "--n", "3", "--t-end", "5",
                    "--samples", "50", "--out", str(tmp_path / "l.png"))
    assert data["poles"] == [[-2.0, 0.0]] * 3
    assert (data["t_end"], data["n_samples"]) == (5.0, 50)


def test_basis_discrete(capsys, tmp_path):
    data = run_json(capsys, "basis", "--poles", "0.8,0.5+0.3j,0.5-0.3j", "--dt", "0.1",
                    "--t-end", "2", "--out", str(tmp_path / "d.png"))
    assert data["dt"] == 0.1 and data["n_samples"] == 21
    assert data["gram_deviation"] < 1e-12
    assert_png(tmp_path / "d.png")


# --------------------------------------------------------------------------- approx
def test_approx_reference_impulse_recovers_exact_coefficients(capsys):
    data = run_json(capsys, "approx", "--poles", REF_POLES)
    assert {"coefficients", "poles", "ise", "fit_percent", "kind"} <= set(data)
    assert data["kind"] == "impulse"
    assert data["fit_percent"] > 99.99
    # The record lies in the basis span; the only error is Simpson quadrature on the
    # 900-sample grid (h = 20/899, error O(h^4) ~ 1e-8) plus the truncated tail at
    # t = 20 (~e^-20); 1e-6 leaves a wide margin.
    np.testing.assert_allclose(data["coefficients"], REF_COEFFICIENTS, rtol=0, atol=1e-6)
    np.testing.assert_allclose(data["poles"], [[-1, 0], [-3, 0], [-0.5, 1.9364916731],
                                               [-0.5, -1.9364916731]], rtol=0, atol=1e-12)
    assert 0 <= data["ise"] < 1e-12


def test_approx_table_output(capsys):
    code, out, err = run(capsys, "approx", "--poles", REF_POLES)
    assert (code, err) == (0, "")
    assert "coefficient" in out and "fit percent" in out and "ISE" in out
    for c in REF_COEFFICIENTS:
        assert f"{c:.6f}"[:7] in out  # leading digits of every coefficient


@pytest.mark.parametrize("method", ["quadrature", "lstsq"])
def test_approx_step_response(capsys, method):
    data = run_json(capsys, "approx", "--poles", REF_POLES, "--kind", "step", "--method", method)
    assert data["kind"] == "step"
    assert data["fit_percent"] > 99.99
    np.testing.assert_allclose(data["coefficients"], REF_COEFFICIENTS, rtol=0, atol=1e-5)


def test_approx_noise_is_seeded(capsys):
    a = run_json(capsys, "approx", "--poles", REF_POLES, "--noise", "0.1", "--seed", "3")
    b = run_json(capsys, "approx", "--poles", REF_POLES, "--noise", "0.1", "--seed", "3")
    c = run_json(capsys, "approx", "--poles", REF_POLES)
    assert a["coefficients"] == b["coefficients"]
    assert a["fit_percent"] < c["fit_percent"]


def test_approx_csv_equals_builtin_reference(capsys, tmp_path):
    t, h = reference_response(kind="impulse")
    path = write_csv(tmp_path / "ref.csv", t, h, header="time,y")
    from_file = run_json(capsys, "approx", str(path), "--time", "time", "--response", "y",
                         "--poles", REF_POLES)
    builtin = run_json(capsys, "approx", "--poles", REF_POLES)
    np.testing.assert_allclose(from_file["coefficients"], builtin["coefficients"],
                               rtol=0, atol=1e-14)  # %.17g round-trips float64 exactly


def test_approx_plot(capsys, tmp_path):
    out_file = tmp_path / "fit.png"
    code, out, err = run(capsys, "approx", "--poles", REF_POLES, "--plot", str(out_file))
    assert (code, err) == (0, "")
    assert_png(out_file)
    assert f"wrote {out_file}" in out


def test_approx_optimize_poles_finds_reference_poles(capsys, tmp_path):
    out_file = tmp_path / "opt.png"
    data = run_json(capsys, "approx", "--optimize-poles", "4", "--plot", str(out_file))
    assert {"coefficients", "poles", "ise", "fit_percent", "kind", "success"} <= set(data)
    assert data["kind"] == "impulse" and len(data["coefficients"]) == 4
    assert data["fit_percent"] > 99.99
    found = np.sort_complex(np.array([complex(re, im) for re, im in data["poles"]]))
    np.testing.assert_allclose(found, np.sort_complex(reference_poles()), rtol=0, atol=1e-6)
    assert_png(out_file)


def test_approx_optimize_poles_step_table(capsys):
    code, out, err = run(capsys, "approx", "--optimize-poles", "2", "--kind", "step",
                         "--max-iter", "20")
    assert code == 0
    assert err == "" or err.startswith("kautztwin: warning:")  # a short budget may not converge
    assert "optimized poles" in out and "start poles" in out


# --------------------------------------------------------------------------- sensitivity
def test_sensitivity_reference_maps(capsys, tmp_path):
    out_file = tmp_path / "fig3.png"
    data = run_json(capsys, "sensitivity", "--poles", REF_POLES, "--grid", "7",
                    "--span", "0.5:1.5", "--out", str(out_file))
    assert_png(out_file)
    assert [m["type"] for m in data["maps"]] == ["real", "real", "pair"]
    assert [m["index"] for m in data["maps"]] == [0, 1, 2]
    assert data["grid"] == 7 and data["span"] == [0.5, 1.5]
    # the poles are the system's: the exact ISE is zero up to cancellation (||h||^2 = 0.14)
    assert 0 <= data["ise"] < 1e-10
    # with 7 points on 0.5..1.5 the factor 1 is on the grid: the best location is the pole
    for m in data["maps"]:
        np.testing.assert_allclose(m["best"], m["pole"], rtol=0, atol=1e-12)
        assert 0 <= m["best_ise"] < 1e-10


def test_sensitivity_with_csv_data_and_table(capsys, tmp_path):
    t, y = reference_response(kind="step")
    path = write_csv(tmp_path / "step.csv", t, y)
    out_file = tmp_path / "s.png"
    code, out, err = run(capsys, "sensitivity", str(path), "--kind", "step", "--poles",
                         "-1.2,-2.5", "--grid", "5", "--out", str(out_file))
    assert (code, err) == (0, "")
    assert_png(out_file)
    assert "best location" in out and str(path) in out


# --------------------------------------------------------------------------- errors
ERROR_CASES = {
    "unstable-pole": (["approx", "--poles", "1,-2"], r"Re >= 0"),
    "unpaired-complex": (["approx", "--poles", "-1,-0.5+2j"], r"no conjugate partner"),
    "unparsable-pole": (["approx", "--poles", "-1,abc"], r"cannot read 'abc'"),
    "empty-pole-entry": (["approx", "--poles", "-1,,-2"], r"entry 2 .* is empty"),
    "both-pole-flags": (["approx", "--poles", "-1", "--optimize-poles", "2"], r"only one of"),
    "neither-pole-flag": (["approx"], r"give the basis poles with --poles"),
    "method-with-optimize": (["approx", "--optimize-poles", "2", "--method", "lstsq"],
                             r"--method applies to --poles only"),
    "negative-noise": (["approx", "--poles", "-1", "--noise", "-0.1"], r"--noise must be"),
    "bad-kind": (["approx", "--poles", "-1", "--kind", "ramp"], r"invalid choice: 'ramp'"),
    "unknown-flag": (["approx", "--poles", "-1", "--bogus"], r"unrecognized arguments"),
    "basis-no-poles": (["basis", "--out", "{tmp}/x.png"], r"exactly one of --poles"),
    "basis-missing-out": (["basis", "--poles", "-1"], r"required: --out"),
    "basis-unstable-discrete": (["basis", "--poles", "1.2", "--dt", "0.1", "--out",
                                 "{tmp}/x.png"], r"inside the unit circle"),
    "laguerre-without-n": (["basis", "--laguerre", "-1", "--out", "{tmp}/x.png"], r"needs --n"),
    "out-dir-missing": (["basis", "--poles", "-1", "--out", "{tmp}/no/x.png"],
                        r"does not exist"),
    "out-format": (["basis", "--poles", "-1", "--out", "{tmp}/x.xyz"], r"unknown figure format"),
    "bad-span": (["sensitivity", "--poles", "-1", "--span", "3:1", "--out", "{tmp}/s.png"],
                 r"0 < LO < HI"),
    "bad-grid": (["sensitivity", "--poles", "-1", "--grid", "1", "--out", "{tmp}/s.png"],
                 r"--grid must be"),
    "sensitivity-unpaired": (["sensitivity", "--poles", "-1,-1+1j", "--out", "{tmp}/s.png"],
                             r"no conjugate partner"),
}


@pytest.mark.parametrize(("argv", "match"), ERROR_CASES.values(), ids=ERROR_CASES.keys())
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path, argv, match):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code, out, err = run(capsys, *argv)
    assert code == 2
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("kautztwin: error: ")
    assert "Traceback" not in err
    assert re.search(match, err), err


CSV_CASES = {
    "nan": ("t,h\n0,1\n1,nan\n2,0\n", [], r"column 'h', row 2 \(line 3\) is 'nan'"),
    "inf": ("t,h\n0,1\n1,inf\n2,0\n", [], r"is 'inf'; values must be finite"),
    "empty-cell": ("t,h\n0,1\n1,\n2,0\n", [], r"column 'h', row 2 \(line 3\) is empty"),
    "short-row": ("t,h\n0,1\n1\n2,0\n", [], r"row 2 \(line 3\) is empty"),
    "non-increasing-time": ("t,h\n0,1\n2,2\n1,3\n", [],
                            r"strictly increasing, but row 3 \(t = 1\)"),
    "missing-column": ("t,h\n0,1\n1,2\n", ["--response", "y"],
                       r"no column 'y'; available columns: 't', 'h'"),
    "empty-file": ("", [], r"is empty"),
    "no-header": ("0,1\n1,2\n", [], r"no header row"),
    "non-numeric": ("t,h\n0,1\n1,x\n", [], r"'x' is not a number"),
}


@pytest.mark.parametrize(("text", "extra", "match"), CSV_CASES.values(), ids=CSV_CASES.keys())
def test_bad_csv_is_one_line_and_exit_2(capsys, tmp_path, text, extra, match):
    path = tmp_path / "data.csv"
    path.write_text(text)
    code, out, err = run(capsys, "approx", str(path), "--poles", "-1", *extra)
    assert (code, out) == (2, "")
    assert err.count("\n") == 1 and err.startswith("kautztwin: error: ")
    assert re.search(match, err), err


def test_missing_file_is_exit_2(capsys, tmp_path):
    code, _, err = run(capsys, "approx", str(tmp_path / "absent.csv"), "--poles", "-1")
    assert code == 2
    assert err == f"kautztwin: error: {tmp_path / 'absent.csv'}: no such file\n"


def test_noise_with_data_file_is_rejected(capsys, tmp_path):
    path = write_csv(tmp_path / "d.csv", np.arange(5.0), np.ones(5))
    code, _, err = run(capsys, "approx", str(path), "--poles", "-1", "--noise", "0.1")
    assert code == 2 and "built-in reference only" in err


def test_debug_shows_traceback_then_the_line(capsys):
    code, _, err = run(capsys, "--debug", "approx", "--poles", "1")
    assert code == 2
    assert err.startswith("Traceback") and "UnstableModelError" in err
    assert err.splitlines()[-1].startswith("kautztwin: error: poles[0] = 1 has Re >= 0")


def test_debug_after_the_command(capsys):
    code, _, err = run(capsys, "approx", "--poles", "1", "--debug")
    assert code == 2 and err.startswith("Traceback")


def test_unexpected_error_is_exit_1(capsys, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(kautztwin, "approximate", boom)
    code, out, err = run(capsys, "approx", "--poles", "-1")
    assert (code, out) == (1, "")
    assert err.count("\n") == 1
    assert err.startswith("kautztwin: error: unexpected RuntimeError: simulated bug")


def test_library_warnings_are_one_line_each(capsys, monkeypatch):
    original = kautztwin.approximate

    def warn_then_fit(*args, **kwargs):
        warnings.warn("a test warning\nover two lines", ConvergenceWarning, stacklevel=2)
        return original(*args, **kwargs)

    monkeypatch.setattr(kautztwin, "approximate", warn_then_fit)
    code, _, err = run(capsys, "approx", "--poles", REF_POLES)
    assert code == 0
    assert err == "kautztwin: warning: a test warning over two lines\n"
