"""Running a benchmark script in ``--quick`` mode for its smoke test."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def run_quick(script: str, out: Path, timeout: float = 600) -> tuple[dict[str, Any], str]:
    """Run ``benchmarks/SCRIPT --quick --out OUT`` (one BLAS thread); its JSON and stdout.

    Asserts that the script exited 0 (the end of its stderr otherwise).
    """
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick",
                           "--out", str(out)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(out.read_text()), proc.stdout
