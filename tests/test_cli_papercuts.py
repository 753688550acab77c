"""Issue 17, cases 1, 3 and 4: a new user's wrong numbers, silent garbage and late memory errors.

Each test names the case it covers.  On the code before the fix:

* case 1 - ``approx`` had no ``--input``/``--amplitude`` (usage error) and took every step
  record for a unit step, so a step of 0.5 gave half the gain; the documented example of
  ``simulate hydraulic --help`` ended unconverged;
* case 3 - ``basis --poles '-1e-300,-2'`` printed ``max |Gram - I| = 1.00e+00`` and exited 0,
  ``simulate hydraulic --noise 1e308`` wrote CSV files full of ``inf`` and exited 0;
* case 4 - a basis of 100000 functions, 1e9 training records or 1e9 simulated records went to
  work and ended (much later) in ``unexpected MemoryError``.

The memory tests fix the machine's memory at 16 GiB (``total_memory`` patched), so the
figures in the messages do not depend on the machine that runs them.
"""

from __future__ import annotations

import json
import re
import shlex
import time

import numpy as np
import pytest

from kautztwin import _validation
from kautztwin.basis import KautzBasis, LaguerreBasis
from kautztwin.cli import _simulate
from kautztwin.cli._common import parse_poles
from kautztwin.cli.main import main
from kautztwin.exceptions import DataError, PoleError
from kautztwin.simulators import simulate_step_tests

GIB = 1024**3


def run(capsys, *argv):
    """Run the CLI in-process; return (exit status, stdout, stderr)."""
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line_error(code, out, err, pattern):
    """Exit 2, nothing on stdout, one line ``kautztwin: error: ...`` matching ``pattern``."""
    assert code == 2, err
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("kautztwin: error: "), err
    assert "unexpected" not in err and "Traceback" not in err
    assert re.search(pattern, err), err


@pytest.fixture
def machine_16gib(monkeypatch):
    """Pretend the machine has 16 GiB of memory (so at most 8 GiB per request)."""
    monkeypatch.setattr(_validation, "total_memory", lambda: 16 * GIB)


@pytest.fixture(scope="module")
def hydraulic_dir(tmp_path_factory):
    """One simulated hydraulic step test (a step of 0.5, 1 % noise) and its summary."""
    out = tmp_path_factory.mktemp("hydraulic") / "data"
    assert main(["simulate", "hydraulic", "--records", "1", "--out", str(out)]) == 0
    return out


# --------------------------------------------------------------------------- case 1


def approx_json(capsys, *argv):
    code, out, err = run(capsys, "approx", *argv, "--json")
    assert code == 0, err
    return json.loads(out), err


def test_approx_step_of_any_amplitude_gives_gain_per_unit_command(capsys, hydraulic_dir):
    """Case 1: --input u (or --amplitude 0.5) turns a step of 0.5 into a gain per unit command."""
    summary = json.loads((hydraulic_dir / "summary.json").read_text())
    amplitude = summary["amplitude"]
    static_gain = summary["steady_speed"][0] / amplitude  # rad/s per unit command, ~197
    record = str(hydraulic_dir / "record_01.csv")
    common = (record, "--time", "t", "--response", "y", "--kind", "step")
    by_column, err = approx_json(capsys, *common, "--input", "u", "--optimize-poles", "3")
    assert err == ""
    assert by_column["amplitude"] == pytest.approx(amplitude)
    assert by_column["dc_gain"] == pytest.approx(static_gain, rel=0.02)
    assert by_column["success"] is True
    poles = "--poles=-4.5,-4.5,-25"
    by_flag, _ = approx_json(capsys, *common, "--amplitude", str(amplitude), poles)
    assert by_flag["dc_gain"] == pytest.approx(static_gain, rel=0.02)
    unit, _ = approx_json(capsys, *common, poles)  # taken for a unit step
    assert unit["dc_gain"] == pytest.approx(amplitude * by_flag["dc_gain"], rel=1e-9)
    assert unit["amplitude"] == 1


def test_simulate_help_example_prints_gain_per_unit_command_and_converges(
    capsys, hydraulic_dir, monkeypatch
):
    """Case 1: the approx example at the end of 'simulate hydraulic --help' runs as printed."""
    lines = _simulate.HYDRAULIC_EPILOG.replace("\\\n", " ").splitlines()
    example = next(line for line in lines if line.strip().startswith("kautztwin approx"))
    argv = shlex.split(example)[1:]
    assert "data/record_01.csv" in argv
    monkeypatch.chdir(hydraulic_dir.parent)
    code, out, err = run(capsys, *argv)
    assert code == 0 and err == "", err
    summary = json.loads((hydraulic_dir / "summary.json").read_text())
    gain = float(re.search(r"^DC gain\s+(\S+)", out, re.M).group(1))
    assert gain == pytest.approx(summary["steady_speed"][0] / summary["amplitude"], rel=0.02)
    assert "per unit input" in out
    assert re.search(r"converged\s+True", out), out


@pytest.mark.parametrize(
    ("flags", "pattern"),
    [
        (["--amplitude", "0.5", "--input", "u"], "only one of --amplitude A and --input"),
        (["--input", "u"], r"--input applies to --kind step"),  # default kind impulse
        (["--kind", "step", "--amplitude", "0"], "--amplitude must be a finite nonzero"),
        (["--kind", "step", "--amplitude", "nan"], "--amplitude must be a finite nonzero"),
        (["--kind", "step", "--input", "y"], "already --response"),
        (["--kind", "step", "--input", "temperature_x"], "has no column 'temperature_x'"),
    ],
)
def test_approx_amplitude_flag_errors(capsys, hydraulic_dir, flags, pattern):
    """Case 1: contradicting or bad --amplitude/--input flags give one line and exit 2."""
    code, out, err = run(capsys, "approx", str(hydraulic_dir / "record_01.csv"), "--response", "y",
                         "--poles=-4,-25", *flags)
    assert_one_line_error(code, out, err, pattern)


def test_approx_amplitude_needs_data_and_input_needs_a_step(capsys, tmp_path):
    """Case 1: --amplitude is for DATA; an --input that is not one constant step is refused."""
    code, out, err = run(capsys, "approx", "--poles=-1,-2", "--amplitude", "2")
    assert_one_line_error(code, out, err, "apply to DATA only")
    t = np.linspace(0, 5, 200)
    u = np.where(t < 1, 0.0, 1.0)  # a step at t = 1, not from t = 0
    path = tmp_path / "late.csv"
    np.savetxt(path, np.column_stack([t, u, 1 - np.exp(-t)]), delimiter=",", header="t,u,y",
               comments="")
    code, out, err = run(capsys, "approx", str(path), "--response", "y", "--input", "u",
                         "--kind", "step", "--poles=-1")
    assert_one_line_error(code, out, err,
                          r"--input u: not one step from rest .* ranges from 0 to 1")


# --------------------------------------------------------------------------- case 3


@pytest.mark.parametrize(
    ("flags", "pattern"),
    [
        (["--poles=-1e-300,-2"], r"not orthonormal .*max \|Gram - I\| = 1\.00e\+00"),
        (["--poles=-1e20,-2"], r"not orthonormal .*keep that ratio below"),
        (["--poles=-1e-12+-1j,-2"], r"not orthonormal"),
        (["--laguerre=-1e-300", "--n", "2"], r"not orthonormal .*rescale time"),
        (["--poles=-1e300,-2"], r"poles\[0\] = -1e\+300 is too large to represent"),
    ],
)
def test_basis_refuses_a_basis_that_is_not_orthonormal(capsys, tmp_path, flags, pattern):
    """Case 3: a 'basis' whose Gram matrix is not the identity is an error, and no figure."""
    out = tmp_path / "b.png"
    code, stdout, err = run(capsys, "basis", *flags, "--out", str(out))
    assert_one_line_error(code, stdout, err, pattern)
    assert not out.exists()


def test_basis_still_prints_a_good_basis(capsys, tmp_path):
    """Case 3: ordinary bases pass the orthonormality check unchanged."""
    code, out, err = run(capsys, "basis", "--poles=-1e-6,-2", "--out", str(tmp_path / "b.png"))
    assert (code, err) == (0, "")
    deviation = float(re.search(r"max \|Gram - I\| = (\S+)", out).group(1))
    assert deviation <= 1e-6


def test_pole_pair_shorthand_reads_exponents():
    """Case 3: '-1e-12+-1j' is the pair -1e-12 +- 1j (it used to be unreadable)."""
    assert parse_poles("-1e-12+-1j,-2") == [complex(-1e-12, 1), complex(-1e-12, -1), -2]
    assert parse_poles("1e-3+-2E+1j") == [complex(1e-3, 20), complex(1e-3, -20)]


def test_library_refuses_poles_too_large_to_represent():
    """Case 3: KautzBasis refuses |p| > 1e100 (a pair's block squares it)."""
    with pytest.raises(PoleError, match="too large to represent"):
        KautzBasis([-1e120 + 1j, -1e120 - 1j])


def test_simulate_refuses_absurd_noise_and_writes_nothing(capsys, tmp_path):
    """Case 3: --noise 1e308 (records of inf) is refused before any file is written."""
    out = tmp_path / "s"
    code, stdout, err = run(capsys, "simulate", "hydraulic", "--noise", "1e308", "--out", str(out))
    assert_one_line_error(code, stdout, err, r"--noise must be a fraction >= 0 and at most 10")
    assert not out.exists()


def test_simulate_never_writes_non_finite_numbers(capsys, tmp_path, monkeypatch):
    """Case 3: whatever the simulator returns, a non-finite record is an error, not a file."""
    import kautztwin.simulators as simulators

    real = simulators.simulate_step_tests

    def overflowing(*args, **kwargs):
        rec = real(*args, **kwargs)
        y = rec.y.copy()
        y[0, 3] = np.inf
        object.__setattr__(rec, "y", y)
        return rec

    monkeypatch.setattr(simulators, "simulate_step_tests", overflowing)
    out = tmp_path / "s"
    code, stdout, err = run(capsys, "simulate", "hydraulic", "--records", "2", "--samples", "50",
                            "--out", str(out))
    assert_one_line_error(code, stdout, err, r"simulated y is not finite")
    assert not list(out.glob("*.csv")) and not (out / "summary.json").exists()


def test_library_simulation_refuses_overflowing_noise():
    """Case 3: simulate_step_tests raises instead of returning records of inf."""
    with pytest.raises(DataError, match=r"non-finite .* noise = 1e\+308 of the peak overflows"):
        simulate_step_tests(2, 50, noise=1e308, random_state=0)


# --------------------------------------------------------------------------- case 4


def test_check_memory_names_the_figure(machine_16gib):
    """Case 4: the shared check says what the request would need and what the machine has."""
    assert _validation.check_memory(8 * GIB, "fits") == 8 * GIB
    with pytest.raises(DataError) as info:
        _validation.check_memory(4e11, "1e9 records")
    assert str(info.value) == (
        "1e9 records would need 373 GiB; at most 8 GiB with this machine's 16 GiB of memory"
    )


def test_total_memory_reads_this_machine():
    """Case 4: the machine's memory is found (sysconf, /proc/meminfo or a cgroup limit)."""
    total = _validation.total_memory()
    assert total is None or total > 64 * 1024**2
    assert _validation.format_bytes(1536 * 1024) == "1.5 MiB"


def test_basis_of_100000_functions_is_refused_before_any_work(capsys, tmp_path, machine_16gib):
    """Case 4: 'basis --laguerre -1 --n 100000' is refused at once, with the figure."""
    start = time.perf_counter()
    code, out, err = run(capsys, "basis", "--laguerre=-1", "--n", "100000", "--out",
                         str(tmp_path / "b.png"))
    assert time.perf_counter() - start < 5
    assert_one_line_error(
        code, out, err,
        r"--n 100000 .* would need 448 GiB; at most 8 GiB with this machine's 16 GiB of memory",
    )


def test_library_basis_checks_its_size(machine_16gib):
    """Case 4: LaguerreBasis / KautzBasis refuse an n x n matrix that cannot fit."""
    with pytest.raises(DataError, match=r"a basis of 1000000 functions .* would need 21\.8 TiB"):
        LaguerreBasis(-1.0, 1_000_000)


def test_training_spec_with_1e9_records_is_refused_before_any_work(capsys, tmp_path,
                                                                   machine_16gib):
    """Case 4: a spec asking for 1e9 records fails on reading, before the output folder."""
    spec = tmp_path / "big.toml"
    spec.write_text("[grid]\nn_samples = 50\n\n[training]\nn_records = 1000000000\n")
    out = tmp_path / "out"
    start = time.perf_counter()
    code, stdout, err = run(capsys, "train", "--config", str(spec), "--out", str(out))
    assert time.perf_counter() - start < 5
    assert_one_line_error(
        code, stdout, err,
        r"training\.n_records = 1000000000 .* grid\.n_samples = 50 samples would need 1\.46 TiB; "
        r"at most 8 GiB with this machine's 16 GiB of memory",
    )
    assert not out.exists()


def test_simulate_huge_records_is_refused_before_any_work(capsys, tmp_path, machine_16gib):
    """Case 4: 'simulate hydraulic --records 1000000000' is refused at once, no folder made."""
    out = tmp_path / "s"
    start = time.perf_counter()
    code, stdout, err = run(capsys, "simulate", "hydraulic", "--records", "1000000000",
                            "--out", str(out))
    assert time.perf_counter() - start < 5
    assert_one_line_error(code, stdout, err, r"--records 1000000000 x --samples 900 would need "
                                             r"19\.6 TiB; at most 8 GiB")
    assert not out.exists()
    with pytest.raises(DataError, match="would need"):
        simulate_step_tests(10**9, 900)

