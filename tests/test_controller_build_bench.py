"""Smoke test of benchmarks/bench_controller_build.py in --quick mode (issue #11).

The script must run, time every history length, and its block-built states must equal the
plain recursion's to rounding (a few ulps of the largest state).  Timings are not asserted.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "bench_controller_build.py"


def test_quick_run_times_every_length_and_the_states_agree(tmp_path):
    out = tmp_path / "controller_build.json"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(out)], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    rows = result["rows"]
    assert [r["samples"] for r in rows] == result["settings"]["lengths"] == [1_000, 6_000]
    for r in rows:
        assert r["max_rel_diff"] < 1e-13
        assert r["states_s"] > 0 and r["recursion_s"] > 0 and r["build_s"] > 0
        assert len(r["repeats_states_s"]) == result["settings"]["repeats"]
    assert "samples" in proc.stdout and "wrote" in proc.stdout
