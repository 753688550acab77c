"""Training for a plant family: estimator, calibrated uncertainty, validation against the oracle.

:func:`train_family` draws the family's records, trains an
:class:`~kautztwin.nn.AdaptivePoleEstimator` on them (its defaults), calibrates its
uncertainty on fresh records, and validates it on other fresh records against the
oracle (:func:`~kautztwin.nn.oracle.oracle_fit`: least squares in the true structure,
started at the true parameters).  :func:`write_family_model` writes the model folder
with the family and the report in its metadata.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ...metrics import fit_percent
from ..adaptive import AdaptivePoleEstimator
from ..oracle import oracle_fit
from ..uncertainty import band_coverage
from .records import family_dataset
from .spec import PlantFamily

__all__ = ["COVERAGE_LEVELS", "train_family", "validation_report", "write_family_model"]

#: Levels whose per-sample coverage the validation report measures.
COVERAGE_LEVELS: tuple[float, ...] = (0.5, 0.8, 0.9, 0.95)
#: Seed offsets of the three record sets (training, calibration, validation).
_SEEDS = {"train": 0, "calibration": 1, "validation": 2}
#: The estimator file that ``kautztwin estimate`` reads to pick the estimator class.
_KIND_FILE = "estimator.json"


def _summary(values: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(values)), "median": float(np.median(values)),
            "p10": float(np.percentile(values, 10)), "min": float(np.min(values))}


def validation_report(
    estimator: AdaptivePoleEstimator,
    family: PlantFamily,
    *,
    n: int | None = None,
    seed: int | None = None,
    oracle: bool = True,
    progress: bool = False,
) -> dict[str, Any]:
    """Fit and band coverage of a trained estimator on fresh records of its family.

    Parameters
    ----------
    estimator : AdaptivePoleEstimator
        Trained (and normally calibrated) on the family.
    family : PlantFamily
    n : int, optional
        Records (default ``family.n_validation``).
    seed : int, optional
        Seed of the records (default: the family's validation seed).
    oracle : bool, default=True
        Also fit the oracle to every record (about 0.05 s per record).
    progress : bool, default=False
        Progress bar over the oracle fits.

    Returns
    -------
    dict
        ``fit`` (mean, median, p10, min of the fit percent against the noise-free
        responses), ``oracle_fit`` and ``gap_to_oracle`` (mean estimator minus mean
        oracle, points) when ``oracle``, ``coverage`` (per-sample coverage of the
        noise-free responses by the bands at each of :data:`COVERAGE_LEVELS`),
        ``relative_width`` (median and 90th percentile at 90 %), ``seconds_per_record``.
    """
    n = family.n_validation if n is None else int(n)
    seed = family.random_state + _SEEDS["validation"] if seed is None else int(seed)
    data = family_dataset(family, n, seed)
    t0 = time.perf_counter()
    est = estimator.estimate(data)
    per_record = (time.perf_counter() - t0) / n
    fits = fit_percent(data.clean, est.response)
    report: dict[str, Any] = {
        "n_records": n,
        "seed": seed,
        "fit": _summary(fits),
        "calibrated": est.calibrated,
        "coverage": {
            f"{lv:g}": band_coverage(data.clean, e.lower, e.upper)
            for lv in COVERAGE_LEVELS
            for e in [est.with_level(lv)]
        },
        "relative_width": {"median": float(np.median(est.relative_width)),
                           "p90": float(np.percentile(est.relative_width, 90))},
        "seconds_per_record": per_record,
    }
    if oracle:
        from tqdm.auto import tqdm

        ofits = np.empty(n)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for i in tqdm(range(n), desc="oracle", disable=not progress, leave=False):
                res = oracle_fit(data.t, data.responses[i], family.system, data.parameters[i],
                                 kind=family.kind)
                ofits[i] = fit_percent(data.clean[i], res.response)
        report["oracle_fit"] = _summary(ofits)
        report["oracle_seconds_per_record"] = (time.perf_counter() - t0) / n
        report["gap_to_oracle"] = report["fit"]["mean"] - report["oracle_fit"]["mean"]
        report["fit_per_record"] = fits.tolist()
        report["oracle_fit_per_record"] = ofits.tolist()
    return report


def train_family(
    family: PlantFamily,
    *,
    progress: bool = False,
    oracle: bool = True,
    estimator_params: dict[str, Any] | None = None,
) -> tuple[AdaptivePoleEstimator, dict[str, Any]]:
    """Train, calibrate and validate an adaptive-pole estimator for a plant family.

    Parameters
    ----------
    family : PlantFamily
        The family (records, budget, seed).
    progress : bool, default=False
        Progress bars (training stages, oracle fits).
    oracle : bool, default=True
        Compare with the oracle in the validation report.
    estimator_params : dict, optional
        Constructor parameters of :class:`~kautztwin.nn.AdaptivePoleEstimator` to
        change (``hidden``, ``n_features``, ...), on top of ``family.estimator``;
        default: the family's (normally the estimator's defaults).

    Returns
    -------
    estimator : AdaptivePoleEstimator
        Fitted and calibrated; ``training_data_`` holds the family and the report.
    report : dict
        ``simulate_seconds`` (drawing the training records), ``train_seconds``
        (simulation and training together), the calibration and the
        :func:`validation_report`.

    Examples
    --------
    >>> import torch
    >>> from kautztwin.nn.family import PlantFamily, train_family
    >>> _ = torch.set_num_threads(1)
    >>> fam = PlantFamily.from_dict({
    ...     "plant": {"poles": [-1.0, -2.0], "gain": 2.0},
    ...     "record": {"n_samples": 100},
    ...     "training": {"n_records": 200, "n_calibration": 50, "n_validation": 20,
    ...                  "max_epochs": 2}})
    >>> est, report = train_family(fam, oracle=False,
    ...                            estimator_params={"hidden": (16,), "n_features": 8})
    >>> sorted(report["validation"]["coverage"])
    ['0.5', '0.8', '0.9', '0.95']
    """
    def say(msg: str) -> None:
        if progress:
            sys.stderr.write(msg + "\n")
            sys.stderr.flush()

    seed = family.random_state
    params: dict[str, Any] = {"random_state": seed, "progress": progress}
    if family.max_epochs is not None:
        params["config"] = {"max_epochs": family.max_epochs}
    params.update(family.estimator)
    params.update(estimator_params or {})
    say(f"simulating {family.n_records} training records of {family.system.name!r}")
    t0 = time.perf_counter()
    train = family_dataset(family, family.n_records, seed + _SEEDS["train"])
    simulate_seconds = time.perf_counter() - t0
    say("training the adaptive-pole estimator (warm start and end to end, per stage)")
    est = AdaptivePoleEstimator(**params).fit(train)
    train_seconds = time.perf_counter() - t0
    say(f"calibrating the uncertainty on {family.n_calibration} fresh records")
    cal = family_dataset(family, family.n_calibration, seed + _SEEDS["calibration"])
    est.calibrate(cal)
    say(f"validating on {family.n_validation} fresh records"
        + (" against the oracle" if oracle else ""))
    report = {
        "estimator": "adaptive",
        "family": family.to_dict(),
        "n_records": family.n_records,
        "simulate_seconds": simulate_seconds,
        "train_seconds": train_seconds,
        "calibration": est.calibration_,
        "validation": validation_report(est, family, oracle=oracle, progress=progress),
    }
    est.training_data_ = {
        "family": family.to_dict(),
        "validation": {k: v for k, v in report["validation"].items()
                       if not k.endswith("per_record") or k == "seconds_per_record"},
    }
    return est, report


def write_family_model(
    estimator: AdaptivePoleEstimator, report: dict[str, Any], out_dir: str | Path
) -> dict[str, Path]:
    """Write ``OUT/model/`` (weights, metadata, estimator kind), ``report.json``, ``curves.png``.

    Parameters
    ----------
    estimator : AdaptivePoleEstimator
        From :func:`train_family`.
    report : dict
        From :func:`train_family`.
    out_dir : str or Path
        Output folder (created).

    Returns
    -------
    dict of str to Path
        ``model``, ``report`` and ``curves``.
    """
    from ...plotting import _new_figure, save_figure
    from ..plots import plot_history

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model_dir = Path(estimator.save(out / "model"))
    (model_dir / _KIND_FILE).write_text(json.dumps({"estimator": "adaptive"}))
    report_path = out / "report.json"
    report_path.write_text(json.dumps({**report, "model": str(model_dir)}, indent=2))
    fig, (ax,) = _new_figure(1, panel_size=(7.0, 4.5))
    for i, h in enumerate(estimator.histories_, start=1):
        plot_history(h, ax=ax, label=f"stage {i}")
    ax.set_title("training (solid) and validation (dashed) loss")
    curves = out / "curves.png"
    save_figure(fig, curves)
    return {"model": model_dir, "report": report_path, "curves": curves}
