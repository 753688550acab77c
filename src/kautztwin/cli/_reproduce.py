"""``kautztwin reproduce simulation|hydraulic``: the paper's two case studies."""

from __future__ import annotations

import argparse
import sys
import textwrap
from typing import Any

__all__ = ["low_fit_notes", "register", "run"]

#: a paper_dnn mean fit this many points below the fixed-basis ceiling gets an explanation
LOW_FIT_MARGIN = 10.0
#: the paper preset's epoch budget (TrainingConfig.preset("paper").max_epochs)
PAPER_EPOCHS = 1000

DESCRIPTION = """\
Reproduce one of the paper's case studies end to end and write metrics.json,
report.md and the figures into --out.

  simulation  section 3.1: the uncertain 4th-order system, the paper's networks,
              projection, the fixed-basis ceiling, our adaptive-pole estimator and
              the oracle (nonlinear least squares with the true structure), plus an
              uncertainty x noise sweep.  Full run: minutes; --quick: under a minute.
  hydraulic   section 3.2: step tests of the electro-hydraulic servo drive
              (simulated), identification of a 3rd-order model, coefficient
              networks, approximation of every record, and the adaptive DNN
              (the paper's update module) against the per-record VARPRO bound.
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


def low_fit_notes(m: dict[str, Any]) -> dict[str, str]:
    """Explanations of a low or negative ``paper_dnn`` figure of ``reproduce simulation``.

    Parameters
    ----------
    m : dict
        The metrics of :func:`kautztwin.experiments.simulation.reproduce_simulation`.

    Returns
    -------
    dict of str to str
        ``{'paper_dnn': note}`` when its mean fit is negative or more than
        :data:`LOW_FIT_MARGIN` points below the fixed-basis ceiling, else empty.
    """
    methods = m.get("methods", {})
    p, ceil = methods.get("paper_dnn"), methods.get("fixed_basis_ceiling")
    if p is None or ceil is None or p["fit_mean"] >= ceil["fit_mean"] - LOW_FIT_MARGIN:
        return {}
    setup = m.get("setup", {})
    epochs = setup.get("paper_epochs") or PAPER_EPOCHS
    n_train = setup.get("n_train", 50)
    head = (
        f"note: paper_dnn's mean fit {p['fit_mean']:.2f} % is below 0. A record's fit "
        "(100 (1 - |h - h_est| / |h - mean h|)) is negative when the estimate is further from "
        "the true response than the response's own mean is, and has no lower bound, so a few "
        f"such records pull the mean under 0 (median {p['fit_median']:.2f} %, worst record "
        f"{p['fit_min']:.0f} %). "
        if p["fit_mean"] < 0
        else f"note: paper_dnn's mean fit {p['fit_mean']:.2f} % is low (median "
        f"{p['fit_median']:.2f} %, worst record {p['fit_min']:.0f} %). "
    )
    text = head
    if setup.get("quick") and epochs < PAPER_EPOCHS:
        text += (
            f"The quick run trains the paper's networks for {epochs} epochs at the paper's "
            f"learning rate 1e-5 (the paper: {PAPER_EPOCHS}) on {n_train} records, so they have "
            "barely left their initial weights. The full run (without --quick) reaches about "
            "51 %. "
        )
    text += (
        f"With {n_train} training records, as in the paper, the networks stay well below the "
        f"fixed-basis ceiling ({ceil['fit_mean']:.2f} %, the best any estimator on the nominal "
        "basis can do); more records close the gap (benchmarks/bench_data_budget.py), and the "
        "adaptive estimator removes the ceiling."
    )
    return {"paper_dnn": text}


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
        notes = low_fit_notes(m)
        rows = [f"{name:<22}{s['fit_mean']:>9.2f} %{s['seconds_per_record']:>12.2e} s/record"
                + ("  (see note)" if name in notes else "")
                for name, s in m["methods"].items()]
        sys.stdout.write("method                 fit mean   time\n" + "\n".join(rows) + "\n")
        for text in notes.values():
            sys.stdout.write(textwrap.fill(text, width=92, subsequent_indent="  ") + "\n")
    else:
        sys.stdout.write(f"identified model fit {m['identification']['fit_percent']:.2f} %\n")
        if "adaptive" in m:
            s = m["adaptive"]["per_record"]["summary"]
            sys.stdout.write(
                f"adaptive DNN fit {s['dnn_mean']:.2f} % per record (DNN + VARPRO "
                f"{s['dnn_refined_mean']:.2f} %, VARPRO bound {s['varpro_bound_mean']:.2f} %, "
                f"paper {m['paper_claims']['fit_percent']} %), largest gap to the bound "
                f"{s['gap_max']:.2f} points\n")
    sys.stdout.write(f"wrote {args.out}/metrics.json, report.md, figures\n")
    return 0
