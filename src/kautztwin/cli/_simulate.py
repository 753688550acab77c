"""``kautztwin simulate``: write simulated step-test data of a physical plant as CSV files."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .._validation import check_memory
from ._common import CLIError, print_json

__all__ = ["register", "run_hydraulic"]

#: largest --noise: a standard deviation of ten times the peak is noise with no record in it
MAX_NOISE = 10.0

DESCRIPTION = """\
Simulate step tests of a physical plant and write them as CSV files, one per
record, plus a summary.json.  The plants stand in for the paper's test rigs,
whose measurements are not public.
"""

HYDRAULIC_DESCRIPTION = """\
Step tests of the electro-hydraulic servo drive of the paper's section 3.2: a
throttle-controlled hydraulic motor (proportional valve with a saturating
spool, turbulent orifice flow, oil compressibility, leakage, viscous friction)
whose leakage, friction and bulk modulus drift with the oil temperature.
Each record is a step of the valve command from rest at t = 0, the shaft speed
sampled on [0, T] s; the oil warms linearly from LO (first record) to HI (last
record).  See docs/hydraulic.md for the equations and parameters.

Writes DIR/record_01.csv ... (columns t [s], u [valve command], y [speed,
rad/s], temperature [degC], a header row, comma separated) and
DIR/summary.json (parameters, temperatures, and the poles and DC gain of the
drive linearised at the step's end point for every record).
"""

HYDRAULIC_EPILOG = """\
examples:
  kautztwin simulate hydraulic --records 30 --samples 900 --temperature 20:60 --out data
  kautztwin simulate hydraulic --amplitude 0.9 --noise 0 --seed 1 --out big --json
  kautztwin simulate hydraulic --temperature=-10:40 --out cold   (negative values need '=')
  kautztwin approx data/record_01.csv --time t --response y --input u --kind step \\
      --optimize-poles 3

The records are steps of A (--amplitude, default 0.5), not unit steps: give
approx the input column (--input u) or the height (--amplitude 0.5) and it
reports the model per unit command.  Its DC gain (about 197 at 20 degC) is the
step's static gain, summary.json's steady_speed / A; summary.json's dc_gain
(156) is the slope of the drive linearised at u0 = A, which differs because
the valve's orifice flow is nonlinear.
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``simulate`` command (with its ``hydraulic`` plant) to the parser."""
    p = subparsers.add_parser(
        "simulate", parents=[common], allow_abbrev=False,
        help="simulate step tests of a physical plant (hydraulic servo drive) as CSV data",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    plants = p.add_subparsers(dest="plant", title="plants", metavar="PLANT", required=True)
    h = plants.add_parser(
        "hydraulic", parents=[common], allow_abbrev=False,
        help="electro-hydraulic servo drive (throttle-controlled hydraulic motor)",
        description=HYDRAULIC_DESCRIPTION, epilog=HYDRAULIC_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    h.add_argument("--records", type=int, default=30, metavar="N",
                   help="number of step responses (default: %(default)s, as in the paper)")
    h.add_argument("--samples", type=int, default=900, metavar="N",
                   help="samples per response (default: %(default)s, as in the paper)")
    h.add_argument(
        "--temperature", default="20:60", metavar="LO:HI",
        help="oil temperature of the first and the last record in degC, or one value for all "
        "(range -20 to 120; default: %(default)s)",
    )
    h.add_argument("--t-end", type=float, default=None, metavar="T",
                   help="record length in seconds (default: 3)")
    h.add_argument(
        "--amplitude", type=float, default=0.5, metavar="A",
        help="step of the valve command as a fraction of the rated input; |A| > 1 saturates "
        "the spool (default: %(default)s)",
    )
    h.add_argument(
        "--noise", type=float, default=0.01, metavar="FRACTION",
        help="sensor noise: standard deviation as a fraction of each record's peak "
        f"(0.01 = 1%%; 0 to {MAX_NOISE:g}; default: %(default)s)",
    )
    h.add_argument("--seed", type=int, default=0, help="seed of the noise (default: %(default)s)")
    h.add_argument("--out", required=True, metavar="DIR",
                   help="directory for the CSV files and summary.json (created if missing)")
    h.add_argument("--json", action="store_true",
                   help="print the summary as one JSON object instead of one line")
    h.set_defaults(run=run_hydraulic)


def _parse_temperatures(text: str) -> tuple[float, float]:
    from ..simulators.hydraulic import TEMPERATURE_RANGE

    parts = text.split(":")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (1, 2):
        raise CLIError(
            f"--temperature must be LO:HI (or one value) in degC, such as 20:60; got {text!r}"
        )
    lo, hi = values[0], values[-1]
    r_lo, r_hi = TEMPERATURE_RANGE
    if not all(math.isfinite(v) and r_lo <= v <= r_hi for v in (lo, hi)):
        raise CLIError(
            f"--temperature {text}: temperatures must lie in [{r_lo:g}, {r_hi:g}] degC"
        )
    if lo > hi:
        raise CLIError(f"--temperature {text}: needs LO <= HI (the oil warms up)")
    return lo, hi


def _check_flags(args: argparse.Namespace) -> tuple[float, float, float]:
    """Reject bad values before anything is computed; return (lo, hi, t_end)."""
    from ..simulators.hydraulic import DEFAULT_T_END

    if args.records < 1:
        raise CLIError(f"--records must be >= 1, got {args.records}")
    if args.samples < 2:
        raise CLIError(f"--samples must be >= 2, got {args.samples}")
    lo, hi = _parse_temperatures(args.temperature)
    t_end = DEFAULT_T_END if args.t_end is None else args.t_end
    if not (math.isfinite(t_end) and t_end > 0):
        raise CLIError(f"--t-end must be a positive number of seconds, got {t_end:g}")
    if not (MIN_DT * (args.samples - 1) <= t_end <= MAX_T_END):
        raise CLIError(
            f"--t-end must lie between {MIN_DT * (args.samples - 1):g} s (a sampling interval "
            f"of {MIN_DT:g} s with --samples {args.samples}) and {MAX_T_END:g} s, got {t_end:g}"
        )
    if not (math.isfinite(args.amplitude) and args.amplitude != 0):
        raise CLIError(f"--amplitude must be a nonzero number, got {args.amplitude:g}")
    if not (math.isfinite(args.noise) and 0 <= args.noise <= MAX_NOISE):
        raise CLIError(
            f"--noise must be a fraction >= 0 and at most {MAX_NOISE:g} (a standard deviation "
            f"of {MAX_NOISE:g} times the record's peak), got {args.noise:g}"
        )
    if args.seed < 0:
        raise CLIError(f"--seed must be >= 0, got {args.seed}")
    from ..simulators.hydraulic.steptests import step_tests_nbytes

    check_memory(
        step_tests_nbytes(args.records, args.samples),
        f"--records {args.records} x --samples {args.samples}",
    )
    return lo, hi, t_end


def _prepare_dir(path: str) -> Path:
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {path}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CLIError(
            f"--out {path}: cannot create the directory ({exc.strerror or type(exc).__name__})"
        ) from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise CLIError(f"--out {path}: the directory is not writable")
    return out


def _pairs(poles: Any) -> list[list[float]]:
    return [[float(p.real), float(p.imag)] for p in poles]


def _fmt_poles(poles: Any) -> str:
    return ", ".join(
        f"{p.real:.3g}" if abs(p.imag) <= 1e-9 * abs(p) else f"{p.real:.3g}{p.imag:+.3g}j"
        for p in poles
    )


MIN_DT = 1e-6  # s: finer sampling makes the ODE solver crawl (t_end 1e-300 never ends)
MAX_T_END = 3600.0  # s: the drive settles in seconds; a longer record only adds cost
SIM_S_PER_RECORD = 0.03
WRITE_S_PER_RECORD = 0.02
LONG_S = 10.0  # commands expected to take longer than this show progress on stderr


class _NullStream:
    """A stream that writes nothing and is not a terminal."""

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


def run_hydraulic(args: argparse.Namespace) -> int:
    """Run ``kautztwin simulate hydraulic``; return the exit status."""
    from ..experiments.progress import Counter, Pulse, about
    from ..simulators import HydraulicServoDrive, simulate_step_tests

    lo, hi, t_end = _check_flags(args)
    out = _prepare_dir(args.out)
    # rough cost on a 2-core machine: simulation and writing of one 900-sample record
    per_record = (SIM_S_PER_RECORD + WRITE_S_PER_RECORD) * args.samples / 900
    expected = args.records * per_record
    talk = expected >= LONG_S
    if talk:
        sys.stderr.write(f"simulating {args.records} step tests x {args.samples} samples: "
                         f"{about(expected)} on a 2-core machine\n")
    with Pulse(args.records * SIM_S_PER_RECORD * args.samples / 900, every=15.0,
               enabled=talk) as pulse:
        pulse.stage = "simulating the step tests"
        records = simulate_step_tests(
            args.records, args.samples, (lo, hi), t_end=t_end, amplitude=args.amplitude,
            noise=args.noise, random_state=args.seed,
        )
    for name in ("t", "u", "y", "y_true"):  # never write a file with non-finite numbers
        if not np.all(np.isfinite(getattr(records, name))):
            raise CLIError(f"the simulated {name} is not finite; lower --noise or --amplitude")
    drive = HydraulicServoDrive(records.parameters)
    width = max(2, len(str(records.n_records)))
    files: list[str] = []
    poles: list[Any] = []
    gains: list[float] = []
    speeds: list[float] = []
    counter = Counter(records.n_records, "records written",
                      stream=sys.stderr if talk else _NullStream(), every=15.0)
    for k in range(records.n_records):
        name = f"record_{k + 1:0{width}d}.csv"
        T = float(records.temperature[k])
        table = np.column_stack(
            [records.t, records.u[k], records.y[k], np.full(records.n_samples, T)]
        )
        np.savetxt(out / name, table, delimiter=",", header="t,u,y,temperature",
                   comments="", fmt="%.10g")
        lin = drive.linearize(args.amplitude, T)
        files.append(name)
        poles.append(lin.poles)
        gains.append(lin.dc_gain)
        speeds.append(lin.y0)
        counter.update(1)
    counter.close()
    summary: dict[str, Any] = {
        "plant": "hydraulic",
        "out": str(out),
        "files": files,
        "n_records": records.n_records,
        "n_samples": records.n_samples,
        "t_end": t_end,
        "dt": t_end / (records.n_samples - 1),
        "amplitude": args.amplitude,
        "noise": args.noise,
        "seed": args.seed,
        "temperature_range": [lo, hi],
        "temperatures": records.temperature.tolist(),
        "columns": {"t": "s", "u": "valve command (fraction of rated)", "y": "shaft speed, rad/s",
                    "temperature": "oil temperature, degC"},
        "operating_point": args.amplitude,
        "poles": [_pairs(p) for p in poles],
        "dc_gain": gains,
        "steady_speed": speeds,
        "parameters": records.parameters.to_dict(),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    if args.json:
        print_json(summary)
        return 0
    sys.stdout.write(
        f"wrote {records.n_records} step tests x {records.n_samples} samples "
        f"(on [0, {t_end:g}] s, oil {lo:g} to {hi:g} degC, step {args.amplitude:g}, "
        f"noise {args.noise:g}) "
        f"and summary.json to {out}; linearised poles {_fmt_poles(poles[0])} rad/s at {lo:g} degC"
        + ("" if records.n_records == 1 else
           f", {_fmt_poles(poles[-1])} rad/s at {hi:g} degC") + "\n"
    )
    return 0
