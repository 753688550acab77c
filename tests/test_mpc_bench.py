"""Smoke test of benchmarks/bench_mpc.py in --quick mode (Laguerre MPC against full horizon).

One repeat of the whole protocol: the replayed moves must match the closed loops (the script
raises otherwise), every horizon of the per-call summary must be there with all calls and
active calls reported, and no controller may break a limit.  Timings are not asserted.
"""

from __future__ import annotations

import pytest

from _bench_helpers import run_quick

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    return run_quick("bench_mpc.py", tmp_path_factory.mktemp("bench") / "mpc.json")


def test_every_horizon_and_set_is_compared(quick_run):
    result, stdout = quick_run
    cells = {(a["case"], a["horizon"], "thin" in a["method"]) for a in result["acceptance"]}
    cases = {"reference_dt0.1", "hydraulic_dt0.05"}
    assert cells == {(c, h, t) for c in cases for h in (50, 100, 200) for t in (False, True)}
    assert "Per-call ratio" in stdout and result["horizon_table"] in stdout


def test_full_horizon_has_one_variable_per_step(quick_run):
    result, _ = quick_run
    for res in result["results"]:
        rows = {r["method"]: r for r in res["rows"]}
        assert rows["full"]["n_variables"] == res["horizon"]
        assert rows["laguerre a=0.8 N=8"]["n_variables"] == 8
        # same limits at every step for both: the same constraint rows
        assert rows["full"]["n_constraint_rows"] == rows["laguerre a=0.8 N=8"]["n_constraint_rows"]


def test_acceptance_entries_are_consistent(quick_run):
    result, _ = quick_run
    for acc in result["acceptance"]:
        assert acc["zero_violations"]
        assert 0.0 < acc["active_fraction"] < 1.0
        for key in ("move", "move_active", "move_b2b", "move_b2b_active"):
            assert acc[f"speedup_median_{key}"] > 0.0
        ratio = acc["baseline_move_active_median_us"] / acc["move_active_median_us"]
        assert ratio == pytest.approx(acc["speedup_median_move_active"], rel=1e-12)
        # the bar is judged on all calls, at <= 5 % cost loss
        assert acc["per_call_bar_met"] == (
            acc["speedup_median_move"] >= 5 and abs(acc["cost_ratio"] - 1) <= 0.05
        )
        assert abs(acc["cost_ratio"] - 1.0) < 0.01
