"""The amortised estimator on a plant no one trained it for (and how the shipped model was made).

The model shipped with kautztwin (package data in ``src/kautztwin/nn/amortised/shipped_model/``,
loaded by ``AmortisedEstimator.load_default()``; ``kautztwin estimate`` uses it without
``--model``) was trained on random stable systems only (orders 1..5, real and complex
poles, zeros, delays, white and coloured noise) by this script with ``--train`` (the
estimator's defaults: 40 000 records, 40 epochs, several minutes on one core), which
writes the model to ``OUT/amortised_model/``; copying its three files into the package
folder replaces the shipped model.  Without ``--train`` the script loads the shipped model
and estimates an impulse record of a 4th-order plant with a zero, first with the network's
poles alone and then refined by variable projection, and writes the result to
``OUT/amortised_estimate.json``.  ``benchmarks/bench_amortised.py`` measures the model on
the held-out 5th-order family.

Usage::

    python examples/amortised_estimator.py [OUT]            # try the shipped model
    python examples/amortised_estimator.py [OUT] --train    # train a new one (minutes)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import scipy.signal
import torch

from kautztwin.metrics import fit_percent
from kautztwin.nn.amortised import AmortisedEstimator


def main() -> None:
    """Load the shipped amortised model (or train one with ``--train``), estimate a plant."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default=".", help="output folder (default: .)")
    ap.add_argument("--train", action="store_true",
                    help="train a model with the defaults (into OUT/amortised_model) and use it")
    args = ap.parse_args()
    out = Path(args.out)
    torch.set_num_threads(1)
    if args.train:
        est = AmortisedEstimator(progress=True).fit()
        model = est.save(out / "amortised_model")
        print(f"trained in {est.training_seconds_:.0f} s, best validation fit "
              f"{100 * (1 - min(est.history_.val_loss)):.2f} % (random systems); "
              f"saved to {model}")
    else:
        est = AmortisedEstimator.load_default()
    # a plant no one trained it for: 4th order, lightly damped pair, a zero, 3 % noise
    plant = scipy.signal.lti([2.0, 6.0], np.poly([-0.5, -2.0, -0.3 + 1.5j, -0.3 - 1.5j]).real)
    t = np.linspace(0.0, 25.0, 400)
    _, h = scipy.signal.impulse(plant, T=t)
    y = h + 0.03 * np.abs(h).max() * np.random.default_rng(0).standard_normal(t.size)
    result = {}
    for refine in (False, True):
        e = est.estimate(t, y, refine=refine)
        name = "refined" if refine else "network"
        fit = float(fit_percent(h, e.response[0]))
        result[name] = {"fit_to_truth_percent": fit,
                        "poles": [[p.real, p.imag] for p in e.poles[0]],
                        "seconds": e.seconds_per_record}
        print(f"{name}: fit to the noise-free truth {fit:.2f} %, poles "
              + ", ".join(f"{p:.3f}" for p in e.poles[0]))
    out.mkdir(parents=True, exist_ok=True)
    (out / "amortised_estimate.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
