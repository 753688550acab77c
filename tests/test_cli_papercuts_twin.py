"""Issue 17, cases 4 (``twin run --duration``), 5, 6, 7 and 8: the twin and long commands.

Each test names the case it covers.  On the code before the fix (``d678f0a``):

* case 4 - ``twin run --duration 1e9`` went to work and ended in ``unexpected MemoryError``;
* case 5 - ``reproduce`` and ``simulate hydraulic --records N`` said nothing about how long they
  would take and stayed silent while a stage ran (no ``kautztwin.experiments.progress``);
* case 6 - ``twin run`` on a folder whose last run did not finish silently started a new run
  with other options and left the old one ``running`` forever (no ``--new``);
* case 7 - there was no ``twin history`` command and the ``predictions`` table stayed empty;
* case 8 - the summary printed ``static twin -302.5 %`` without a word.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import sqlite3
import time

import pytest

from kautztwin import _validation
from kautztwin.cli import _reproduce, _simulate, _twin
from kautztwin.cli.main import main
from kautztwin.experiments.progress import Counter, Pulse, about
from kautztwin.twin.history import SQLiteHistory

GIB = 1024**3


def run(capsys, *argv):
    """Run the CLI in-process; return (exit status, stdout, stderr)."""
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line_error(code, out, err, pattern):
    """Exit 2, nothing on stdout, one line ``kautztwin: error: ...`` matching ``pattern``."""
    assert code == 2, err
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("kautztwin: error: "), err
    assert "unexpected" not in err and "Traceback" not in err
    assert re.search(pattern, err), err


QUICK = ("--plant", "hydraulic", "--quick", "--no-plots", "--no-progress")


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished quick hydraulic twin run of 20 s (1000 samples, 400 of identification)."""
    out = tmp_path_factory.mktemp("twin") / "run"
    assert main(["twin", "run", *QUICK, "--duration", "20", "--out", str(out)]) == 0
    return out


# --------------------------------------------------------------------------- case 4


def test_twin_run_huge_duration_is_refused_before_any_work(capsys, tmp_path, monkeypatch):
    """Case 4: --duration 1e9 names the figure and the limit, at once, and writes nothing."""
    monkeypatch.setattr(_validation, "total_memory", lambda: 16 * GIB)
    out = tmp_path / "d"
    start = time.perf_counter()
    code, o, e = run(capsys, "twin", "run", "--plant", "hydraulic", "--duration", "1e9",
                     "--out", out)
    assert time.perf_counter() - start < 5
    assert_one_line_error(code, o, e, r"--duration 1e\+09 s \(5e\+10 samples at dt 0\.02 s\) "
                          r"would need [\d.]+ TiB; at most 8(\.0)? GiB")
    assert not out.exists()


# --------------------------------------------------------------------------- case 5


def test_about_words_durations():
    """Case 5: the first line's estimate reads as a rough duration."""
    assert about(3) == "about 3 s"
    assert about(42) == "about 40 s"
    assert about(250) == "about 4 min"
    assert about(float("nan")) == "an unknown time"


def test_counter_writes_a_line_at_least_every_interval_off_a_terminal():
    """Case 5: work counted in items writes a line with the time left every `every` s."""
    buf = io.StringIO()
    now = [0.0]
    c = Counter(100, "records", stream=buf, every=15.0, clock=lambda: now[0])
    for _ in range(100):
        now[0] += 0.5  # 0.5 s per record: 50 s in all
        c.update()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 3  # at 15, 30 and 45 s
    assert lines[0] == "  ... 30/100 records (30 %), 15 s elapsed, about 40 s left"


def test_pulse_speaks_while_a_stage_is_silent():
    """Case 5: a silent stage gets a line every `every` s, naming the stage and the time."""
    buf = io.StringIO()
    with Pulse(60.0, stream=buf, every=0.1) as pulse:
        pulse.say("identifying a model")
        time.sleep(0.45)
        pulse.say("  done")
    lines = buf.getvalue().splitlines()
    assert lines[0] == "identifying a model" and lines[-1] == "  done"
    beats = lines[1:-1]
    assert 2 <= len(beats) <= 6, lines
    assert all(b.startswith("  ... identifying a model: ") and "left" in b for b in beats)


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_pulse_draws_a_bar_on_a_terminal():
    """Case 5: on a terminal the elapsed time is a bar against the expected time."""
    term = _Terminal()
    with Pulse(4.0, stream=term, every=0.1) as pulse:
        pulse.say("training")
        time.sleep(1.2)
    text = term.getvalue()
    assert "training\n" in text and "s expected" in text and "|" in text
    assert "  ... " not in text  # no "still working" lines on a terminal


def test_reproduce_first_line_says_how_long_and_it_keeps_talking(capsys, monkeypatch, tmp_path):
    """Case 5: 'reproduce hydraulic' starts with its expected time and never stays silent."""
    import kautztwin.experiments.hydraulic as hyd

    def fake(out, *, quick, random_state, log):
        log("identifying a 3rd-order model")
        time.sleep(0.5)
        return {"identification": {"fit_percent": 80.0}}

    monkeypatch.setattr(hyd, "reproduce_hydraulic", fake)
    monkeypatch.setattr(_reproduce, "PULSE_EVERY_S", 0.1)
    code, out, err = run(capsys, "reproduce", "hydraulic", "--out", tmp_path / "r")
    assert code == 0
    lines = err.splitlines()
    assert re.fullmatch(r"reproduce hydraulic: about \d+ min on a 2-core machine "
                        r"\(--quick: a smoke run in \d+ s\)", lines[0]), lines[0]
    assert any(ln.startswith("  ... identifying a 3rd-order model: ") for ln in lines[2:])
    assert "identified model fit 80.00 %" in out


def test_simulate_many_records_says_how_long(capsys, monkeypatch, tmp_path):
    """Case 5: a large 'simulate hydraulic --records' starts with its expected time."""
    monkeypatch.setattr(_simulate, "LONG_S", 0.0)  # treat this small run as a long one
    code, out, err = run(capsys, "simulate", "hydraulic", "--records", "3", "--samples", "100",
                         "--out", tmp_path / "s")
    assert code == 0 and out.startswith("wrote 3 step tests")
    assert re.match(r"simulating 3 step tests x 100 samples: about \d+ s on a 2-core machine\n",
                    err), err
    # and a small one stays quiet
    monkeypatch.setattr(_simulate, "LONG_S", 10.0)
    code, _, err = run(capsys, "simulate", "hydraulic", "--records", "2", "--out", tmp_path / "q")
    assert code == 0 and err == ""


# --------------------------------------------------------------------------- case 6


def _kill(store, keep):
    """What kill -9 leaves: the last run 'running' with only its first ``keep`` samples."""
    with sqlite3.connect(store) as conn:
        conn.execute("UPDATE runs SET status = 'running', finished = NULL")
        conn.execute("DELETE FROM measurements WHERE k >= ?", (keep,))
        conn.execute("DELETE FROM predictions WHERE k >= ?", (keep - 1,))


def test_killed_run_resumes_or_refuses_or_starts_over(capsys, tmp_path):
    """Case 6: same options resume; other options refuse (one line, how to go on); --new."""
    out = tmp_path / "d"
    first = ("twin", "run", *QUICK, "--duration", "20", "--out", out)
    assert run(capsys, *first)[0] == 0
    store = out / "history.sqlite"
    _kill(store, 700)

    code, o, e = run(capsys, "twin", "run", *QUICK, "--duration", "24", "--out", out)
    assert_one_line_error(
        code, o, e,
        r"holds an unfinished run \(run 1, 700 of 1000 samples\) started with other options "
        r"\(duration 20\.0, now 24\.0.*\): resume it with 'kautztwin twin run --plant hydraulic "
        r"--duration 20 --quick --no-plots --no-progress|resume it with 'kautztwin twin run "
        r"--plant hydraulic --duration 20 --quick .*--out .*', or add --new to start over")
    with SQLiteHistory(store) as h:
        assert [r.status for r in h.runs()] == ["running"]  # nothing changed

    code, o, e = run(capsys, *first)  # the same options: resumed where it stopped
    assert code == 0 and "(resumed after 700)" in o, o + e

    _kill(store, 500)
    code, o, e = run(capsys, "twin", "run", *QUICK, "--duration", "24", "--new", "--out", out)
    assert code == 0 and "resumed" not in o
    with SQLiteHistory(store) as h:
        runs = h.runs()
        assert [r.status for r in runs] == ["abandoned", "finished"]
        assert [ev.kind for ev in h.events(runs[0].run_id, "abandoned")] == ["abandoned"]


# --------------------------------------------------------------------------- case 7


def test_twin_records_a_prediction_for_every_twin_sample(finished_run):
    """Case 7: the predictions table holds the twin's one-step prediction of each sample."""
    with SQLiteHistory(finished_run / "history.sqlite") as h:
        (info,) = h.runs()
        preds = h.predictions(info.run_id)
        n_ident = int(round(info.config["twin"]["ident_duration"] / info.config["twin"]["dt"]))
        n = h.measurements(info.run_id).k.size
        versions = {v.version for v in h.model_versions(info.run_id)}
    assert len(preds) == n - n_ident  # every sample the twin predicted (not the identification)
    assert [p.k for p in preds] == list(range(n_ident - 1, n - 1))
    assert all(p.horizon == 1 and math.isfinite(p.y_pred[0]) for p in preds)
    assert {p.model_version for p in preds} <= versions


def test_twin_history_reads_the_store_back(capsys, finished_run, tmp_path):
    """Case 7: 'twin history' answers "what did the twin predict at t = 12 s"."""
    code, out, err = run(capsys, "twin", "history", finished_run, "--json",
                         "--start", "12", "--end", "12.1")
    assert code == 0, err
    r = json.loads(out)
    assert r["status"] == "finished" and r["n_committed"] == 1000
    s = r["samples"]
    assert s["t"] == pytest.approx([12.0, 12.02, 12.04, 12.06, 12.08, 12.1])
    assert set(s) == {"k", "t", "y", "u", "prediction", "setpoint"}
    assert all(abs(p - y) < 0.05 * abs(y) for p, y in zip(s["prediction"], s["y"], strict=True))
    assert r["versions"][0]["version"] == 1

    table = tmp_path / "h.csv"
    code, out, err = run(capsys, "twin", "history", finished_run, "--signals", "y,prediction",
                         "--csv", table)
    assert code == 0 and "wrote 1000 samples" in out
    rows = list(csv.reader(table.open()))
    assert rows[0] == ["k", "t", "y", "prediction"] and len(rows) == 1001
    assert rows[1][3] == ""  # no prediction during identification: an empty cell, never 'nan'

    code, out, err = run(capsys, "twin", "history", finished_run, "--start", "8", "--end", "8.04")
    assert code == 0 and out.startswith("run 1 (finished) of hydraulic: 1000 committed samples")


@pytest.mark.parametrize(("flags", "pattern"), [
    (("--signals", "y,speed"), r"unknown signal 'speed'"),
    (("--start", "5", "--end", "1"), r"--end \(1 s\) is before --start \(5 s\)"),
    (("--run", "7"), r"--run 7: no such run in the store \(runs: 1\)"),
    (("--start", "nan"), r"--start must be a finite time"),
])
def test_twin_history_errors(capsys, finished_run, flags, pattern):
    """Case 7: bad read-back requests are one-line errors."""
    assert_one_line_error(*run(capsys, "twin", "history", finished_run, *flags), pattern)


def test_twin_history_without_a_store(capsys, tmp_path):
    """Case 7: a folder without a store says where a store comes from."""
    assert_one_line_error(*run(capsys, "twin", "history", tmp_path),
                          r"no twin history here .*'kautztwin twin run --out DIR' writes one")


# --------------------------------------------------------------------------- case 8


def test_summary_explains_a_negative_fit(tmp_path):
    """Case 8: a fit below zero comes with a word on what it means."""
    m = {"plant_name": "hydraulic", "n_samples": 4500, "resume": {}, "sync_fit_mean": 96.1,
         "static_twin_sync_fit_mean": -302.5, "drift_events_s": [30.0, 60.0],
         "sync_fit_min_after_recovery": 80.0, "recovery_window_s": 10.0,
         "reidentifications": 2, "tracking_iae": 1.0, "constraint_violations": 0,
         "mpc_solve_ms": {"median": 0.1}, "update_ms": {"median": 0.1},
         "samples": {"dropouts": 0, "outliers": 0, "late": 0}}
    line = _twin._summary(m, tmp_path, 0)
    assert "static twin -302.5 %" in line
    assert "below 0 %" in line and "mean" in line
    m["static_twin_sync_fit_mean"] = 50.0
    assert "below 0 %" not in _twin._summary(m, tmp_path, 0)
