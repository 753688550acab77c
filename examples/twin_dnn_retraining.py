"""A hydraulic digital twin that carries a DNN estimator and fine-tunes it on every new model.

1. Train a small `CoefficientEstimator` (one multi-output network) on step responses of a
   rough guess of the drive: three real poles at -3, -9 and -9 1/s, +-20 %, 5 % noise,
   labelled on the guess's Kautz basis.  (The twin identifies the real drive itself; the
   estimator only needs the right number of basis functions, 3.)
2. Run the twin of the electro-hydraulic drive for 40 s, its dominant pole slowed by 40 % in
   two steps at 15 s and 25 s, with the estimator attached: every new model version asks the
   optimization module to fine-tune the estimator on simulated records around the new
   version (`Optimizer.retrain_estimator`).  A candidate replaces the running estimator only
   if it fits fresh held-out records better; a version with another number of basis
   functions (a consolidation of the fast path with its extra pole) is refused with the
   reason.
3. Print the estimator events, write them and the run's metrics to OUTPUT_DIR.

Usage: python examples/twin_dnn_retraining.py [OUTPUT_DIR]   (about 10 s on one core)
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

import kautztwin as kt
from kautztwin.datasets import ParametricSystem, draw_parameters, make_dataset
from kautztwin.nn import CoefficientEstimator
from kautztwin.twin.report import compute_metrics
from kautztwin.twin.runtime import DigitalTwin, TwinConfig, make_plant


def initial_estimator() -> CoefficientEstimator:
    """A 3-function estimator of unit-step responses on [0, 4] s, trained on a rough guess."""
    guess = np.array([-3.0, -9.0, -9.0])
    system = ParametricSystem.from_zpk([], guess, 243.0)  # static gain 1
    t = np.linspace(0.0, 4.0, 200)
    params = draw_parameters(system, 0.2, 400, random_state=0)
    data = make_dataset(
        system, params, kt.KautzBasis(guess), t, kind="step", noise=0.05, random_state=1
    )
    return CoefficientEstimator(per_coefficient=False, config={"max_epochs": 40}).fit(data)


def main(out: Path) -> None:
    torch.set_num_threads(1)
    estimator = initial_estimator()
    plant = make_plant("hydraulic", drift=0.4, drift_events=(15.0, 25.0), seed=0)
    config = TwinConfig.for_plant(plant, duration=40.0, quick=True)
    with DigitalTwin(plant, config, estimator=estimator) as twin:
        run = twin.run(progress=False)
        final = twin.estimator
    metrics = compute_metrics(run)
    events = [
        {"t": e.t, "kind": e.kind, "message": e.message}
        for e in run.events
        if e.kind.startswith("estimator")
    ]
    for e in events:
        print(f"t = {e['t']:5.1f} s  {e['kind']}: {e['message']}")
    counts = metrics["estimator_retrainings"]
    print(
        f"estimator retrainings: {counts['accepted']} accepted, {counts['rejected']} rejected; "
        f"sync fit {metrics['sync_fit_min_after_recovery']:.2f} % (min outside recovery), "
        f"{metrics['constraint_violations']} constraint violations"
    )
    assert len(events) == counts["accepted"] + counts["rejected"] > 0
    assert (final is not estimator) == (counts["accepted"] > 0)  # swapped only when accepted
    out.mkdir(parents=True, exist_ok=True)
    summary = {
        "events": events,
        "estimator_retrainings": counts,
        "sync_fit_min_after_recovery": metrics["sync_fit_min_after_recovery"],
        "constraint_violations": metrics["constraint_violations"],
    }
    (out / "twin_dnn_retraining.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"wrote {out / 'twin_dnn_retraining.json'}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()))
