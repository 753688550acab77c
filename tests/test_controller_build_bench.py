"""Smoke test of benchmarks/bench_controller_build.py in --quick mode (issue #11).

The script must run, time every history length, and its block-built states must equal the
plain recursion's to rounding (a few ulps of the largest state).  Timings are not asserted.
"""

from __future__ import annotations

from _bench_helpers import run_quick


def test_quick_run_times_every_length_and_the_states_agree(tmp_path):
    result, stdout = run_quick("bench_controller_build.py", tmp_path / "controller_build.json",
                               timeout=300)
    rows = result["rows"]
    assert [r["samples"] for r in rows] == result["settings"]["lengths"] == [1_000, 6_000]
    for r in rows:
        assert r["max_rel_diff"] < 1e-13
        assert r["states_s"] > 0 and r["recursion_s"] > 0 and r["build_s"] > 0
        assert len(r["repeats_states_s"]) == result["settings"]["repeats"]
    assert "samples" in stdout and "wrote" in stdout
