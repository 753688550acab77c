"""Smoke test of benchmarks/bench_api_load.py (issue #12's load benchmark) with tiny counts.

It runs the whole benchmark - a twin serving the HTTP API, load clients in a process of
their own, the loop timed - for about a second per phase, so that the script cannot rot.
No speed is asserted (figures belong to benchmarks/results/api_load.json): only that every
phase ran, every request was answered and the loop's timing was recorded.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "bench_api_load.py"


@pytest.fixture(scope="module")
def bench_module():
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import bench_api_load

        yield bench_api_load
    finally:
        sys.path.remove(str(SCRIPT.parent))


def test_quick_run_reports_every_phase(tmp_path):
    out = tmp_path / "api_load.json"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--quick", "--clients", "4", "--seconds", "0.5",
         "--out", str(out)],
        capture_output=True, text=True, timeout=240, env=env, cwd=ROOT, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "wrote" in proc.stdout and "history" in proc.stdout
    result = json.loads(out.read_text())
    assert result["benchmark"] == "api_load" and result["quick"] is True
    assert result["settings"]["clients"] == 4
    (run,) = result["runs"]
    assert run["gc_freeze"] is True
    assert run["speed"] == 10 and [p["phase"] for p in run["phases"]] == [
        "idle", "state", "history", "mixed", "idle-after"]
    for phase in run["phases"]:
        loop = phase["loop"]
        assert loop["samples"] > 10, phase  # 0.5 s at 500 samples/s (fewer on a busy machine)
        assert 0 < loop["step_ms_p50"] <= loop["step_ms_p99"] <= loop["step_ms_max"]
        assert loop["late"] >= 0 and loop["rate"] > 0
        expected = {"state": {"state"}, "history": {"history"},
                    "mixed": {"state", "history"}}.get(phase["phase"], set())
        assert set(phase.get("requests", {})) == expected
        for r in phase.get("requests", {}).values():
            assert r["requests"] > 0 and r["errors"] == 0, phase
            assert 0 < r["p50_ms"] <= r["p99_ms"] <= r["max_ms"]
    assert set(run["summary"]) >= {"step_ms_p99_idle", "step_ms_p99_load_max",
                                   "late_under_load", "keeps_up"}


def test_loop_stats_by_hand(bench_module):
    """Ten ticks 0.1 s apart at x10 (dt 0.02 s): one slow step, one sample 0.05 s late."""
    ticks = [(0.1 * i, 0.001, 0.0) for i in range(10)]
    ticks[4] = (0.4, 0.005, 0.0)
    ticks[6] = (0.6, 0.001, 0.05)
    ticks.append((5.0, 0.001, 0.0))  # outside the window
    s = bench_module.loop_stats(ticks, 0.0, 0.9, speed=10.0)
    assert s["samples"] == 10
    assert s["rate"] == pytest.approx(10 / (0.9 * 10 / 0.02), abs=1e-4)
    assert s["step_ms_p50"] == pytest.approx(1.0) and s["step_ms_max"] == pytest.approx(5.0)
    assert s["late"] == 1 and s["behind_ms_max"] == pytest.approx(5.0)  # 0.05 s / 10 in ms


def test_request_stats_by_hand(bench_module):
    records = [(0.001 * (i + 1), 200) for i in range(100)] + [(0.5, 503)]
    s = bench_module.request_stats(records, seconds=2.0)
    assert s["requests"] == 101 and s["rps"] == 50.5 and s["errors"] == 1
    assert s["p50_ms"] == pytest.approx(51.0) and s["max_ms"] == pytest.approx(500.0)
