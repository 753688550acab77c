"""Behaviour guard for refactors: run the main commands and compare their metrics.

Runs, on the bundled defaults and data,

- ``kautztwin reproduce simulation --quick`` (the main job),
- ``kautztwin twin run --plant hydraulic --duration 90 --drift 0.4`` (the twin acceptance run),
- ``kautztwin identify --json`` on the bundled TCLab, hair-dryer and actuator data,

collects every number they report (wall-clock timings left out: they are noise, not behaviour)
and either writes them to a JSON file (``--write``) or compares them with one (``--check``),
to the printed digits (relative 1e-9). A refactor that claims "no behaviour change" runs
``--write`` on the old tree and ``--check`` on the new one::

    python benchmarks/metrics_guard.py --write before.json     # on the old commit
    python benchmarks/metrics_guard.py --check before.json     # on the new one

``benchmarks/results/metrics_guard.json`` held the figures of the tree before the
architecture change of issue #10; it is rewritten only with a change that moves figures on
purpose, and docs/service.md lists the figures that moved: so far the controller's filter
states built in blocks (rounding only), the re-identification's estimated initial state,
the re-identification's regressors built with the input's spectrum kept (rounding only),
the monitor's resync hysteresis of the hydraulic profile (22 figures of the twin run), the
output-error fits' variable-projection Jacobian (35 figures of the twin run, at the fit's
resolution), the hydraulic fast path's quadratic input channel with directional
forgetting (37 figures of the twin run: 23 values, 14 of a model version no longer made)
and the output-error fits' starts searched together with ``A^k B`` by doubling (30
figures of the twin run, at the fit's resolution: at most 1.2e-5 relative, two poles of
one version in swapped order).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
# keys whose values are measured times or machine facts, not behaviour
_TIMING_WORDS = ("_ms", "_s_per", "seconds", "wall", "elapsed", "duration_s", "speed", "time_s",
                 "late", "cpu", "per_record", "timing", "timestamp", "created", "started",
                 "finished", "version_info", "python", "platform", "machine", "path", "out",
                 "store", "lt_1ms")

IDENTIFY = {
    "tclab": ["data/tclab_step_tests/step-test-data.csv", "--time", "Time", "--input", "Q1",
              "--output", "T1", "--kind", "step", "--order", "2"],
    "dryer": ["data/daisy_hair_dryer/dryer.dat", "--dt", "0.08", "--input", "1", "--output",
              "2", "--order", "3", "--delay", "--validate-from", "40"],
    "actuator": ["data/hydraulic_actuator/actuator.csv", "--dt", "1", "--input", "u",
                 "--output", "p", "--order", "3", "--zeros", "1", "--validate-from", "512"],
}


def _cli(args: list[str], cwd: Path) -> str:
    env = dict(os.environ, MPLBACKEND="Agg", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "kautztwin", *args]
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(args[:3])} failed ({res.returncode}): {res.stderr[-2000:]}")
    return res.stdout


def _is_timing(key: str) -> bool:
    k = key.lower()
    return any(w in k for w in _TIMING_WORDS)


def _numbers(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Flatten ``obj`` into ``{dotted.key: number or str}``, timings left out."""
    out: dict[str, Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            if _is_timing(str(k)):
                continue
            out.update(_numbers(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, list | tuple):
        for i, v in enumerate(obj):
            out.update(_numbers(v, f"{prefix}[{i}]"))
    elif isinstance(obj, bool) or obj is None or isinstance(obj, str):
        out[prefix] = obj
    elif isinstance(obj, int | float):
        out[prefix] = float(obj)
    return out


def collect() -> dict[str, Any]:
    """Run the guarded commands and return their flattened metrics."""
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        print("reproduce simulation --quick ...", flush=True)
        _cli(["reproduce", "simulation", "--quick", "--out", str(tmp_path / "sim")], ROOT)
        sim = json.loads((tmp_path / "sim" / "metrics.json").read_text())
        figures.update(_numbers(sim, "simulation"))
        print("twin run --plant hydraulic --duration 90 --drift 0.4 ...", flush=True)
        _cli(["twin", "run", "--plant", "hydraulic", "--duration", "90", "--drift", "0.4",
              "--out", str(tmp_path / "twin")], ROOT)
        twin = json.loads((tmp_path / "twin" / "metrics.json").read_text())
        figures.update(_numbers(twin, "twin"))
        for name, args in IDENTIFY.items():
            print(f"identify {name} ...", flush=True)
            out = _cli(["identify", *args, "--json"], ROOT)
            figures.update(_numbers(json.loads(out), f"identify.{name}"))
    return figures


def compare(old: dict[str, Any], new: dict[str, Any], rtol: float = 1e-9) -> list[str]:
    """Return one line per figure that differs (or is missing on one side)."""
    diffs = []
    for key in sorted(set(old) | set(new)):
        if key not in new or key not in old:
            diffs.append(f"{key}: only {'before' if key in old else 'after'}")
            continue
        a, b = old[key], new[key]
        if isinstance(a, float) and isinstance(b, float):
            same = (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=rtol,
                                                                     abs_tol=1e-12)
        else:
            same = a == b
        if not same:
            diffs.append(f"{key}: {a!r} -> {b!r}")
    return diffs


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; exit 1 when ``--check`` finds a difference."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", metavar="JSON", help="write the figures of this tree")
    g.add_argument("--check", metavar="JSON", help="compare this tree with a written file")
    args = p.parse_args(argv)
    figures = collect()
    if args.write:
        Path(args.write).write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")
        print(f"{len(figures)} figures written to {args.write}")
        return 0
    old = json.loads(Path(args.check).read_text())
    diffs = compare(old, figures)
    for line in diffs:
        print(line)
    print(f"{len(figures)} figures compared, {len(diffs)} differ")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
