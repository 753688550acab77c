"""Smoke test of benchmarks/bench_update.py in --quick mode (issue #11).

The script must run and time the fast path: its recursion must give the coefficients of
the weighted least-squares fit over the forgetting factor's memory, to what the window
leaves out (the weights beyond 3 / (1 - forgetting) samples, about 5 % of the first one,
and the initial covariance; measured 5e-4 of the largest coefficient).  It must time every
captured re-identification window with both fits (the starts searched together and one
after another), and both must give
the same candidate to the fit's resolution: the
held-out predictions within 1e-4 of the output's spread (the output-error cost is flat
along some pole directions, so rounding differences move the poles by up to about 1e-4;
a wrong regressor moves the prediction by whole percent).  Timings are not asserted.
"""

from __future__ import annotations

from _bench_helpers import run_quick


def test_quick_run_times_the_fast_path_and_every_window_and_the_results_agree(tmp_path):
    result, stdout = run_quick("bench_update.py", tmp_path / "update.json")
    fast = result["fast_path"]
    assert fast["coef_rel_diff"] < 1e-2
    assert fast["recursion_s"] > 0 and fast["updater_step_s"] > 0 and fast["refit_s"] > 0
    assert len(fast["repeats_recursion_s"]) == result["settings"]["repeats"]
    rows = result["rows"]
    assert len(rows) == result["summary"]["fits"] == 4
    for r in rows:
        assert r["held_out_rel_diff"] < 1e-4
        assert abs(r["fit_current"] - r["fit_baseline"]) < 1e-3
        assert r["current_s"] > 0 and r["baseline_s"] > 0
        assert len(r["repeats_current_s"]) == result["settings"]["repeats"]
    assert "fast path" in stdout and "speed-up" in stdout and "wrote" in stdout
