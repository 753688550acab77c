"""``kautztwin reproduce simulation|hydraulic``: the paper's two case studies."""

from __future__ import annotations

import argparse
import sys

__all__ = ["register", "run"]

DESCRIPTION = """\
Reproduce one of the paper's case studies end to end and write metrics.json,
report.md and the figures into --out.

  simulation  section 3.1: the uncertain 4th-order system, the paper's networks,
              projection, the fixed-basis ceiling, our adaptive-pole estimator and
              the oracle (nonlinear least squares with the true structure), plus an
              uncertainty x noise sweep.  Full run: minutes; --quick: under a minute.
  hydraulic   section 3.2: step tests of the electro-hydraulic servo drive
              (simulated), identification of a 3rd-order model, coefficient
              networks, approximation of every record.
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``reproduce`` command to the parser."""
    p = subparsers.add_parser(
        "reproduce", parents=[common], allow_abbrev=False,
        help="reproduce the paper's case studies (simulation, hydraulic)",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("study", choices=("simulation", "hydraulic"), help="which case study")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--quick", action="store_true", help="small budgets (a smoke run)")
    p.add_argument("--seed", type=int, default=0, help="master random seed (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run)


# rough wall-clock times on a 2-core machine (the first line of the command quotes them)
PULSE_EVERY_S = 15.0  # seconds of silence before a "still working" line (not on a terminal)
EXPECTED_S = {("simulation", False): 600.0, ("simulation", True): 40.0,
              ("hydraulic", False): 600.0, ("hydraulic", True): 45.0}


def run(args: argparse.Namespace) -> int:
    """Run ``kautztwin reproduce``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed flags.

    Returns
    -------
    int
        Exit status (0).
    """
    from ..experiments.progress import Pulse, about

    expected = EXPECTED_S[(args.study, bool(args.quick))]
    with Pulse(expected, every=PULSE_EVERY_S, enabled=not args.quiet) as pulse:
        say = pulse.say
        say(f"reproduce {args.study}{' --quick' if args.quick else ''}: {about(expected)} on "
            "a 2-core machine" + ("" if args.quick else " (--quick: a smoke run in "
                                  f"{about(EXPECTED_S[(args.study, True)])[6:]})"))
        if args.study == "simulation":
            from ..experiments.simulation import reproduce_simulation

            m = reproduce_simulation(args.out, quick=args.quick, random_state=args.seed, log=say)
        else:
            from ..experiments.hydraulic import reproduce_hydraulic

            m = reproduce_hydraulic(args.out, quick=args.quick, random_state=args.seed, log=say)
    if args.study == "simulation":
        rows = [f"{name:<22}{s['fit_mean']:>9.2f} %{s['seconds_per_record']:>12.2e} s/record"
                for name, s in m["methods"].items()]
        sys.stdout.write("method                 fit mean   time\n" + "\n".join(rows) + "\n")
    else:
        sys.stdout.write(f"identified model fit {m['identification']['fit_percent']:.2f} %\n")
    sys.stdout.write(f"wrote {args.out}/metrics.json, report.md, figures\n")
    return 0
