"""``kautztwin train``/``estimate``: train an estimator from a spec, apply a saved one."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..basis import KautzBasis
from ..datasets import ResponseDataset, draw_parameters, make_dataset
from ..exceptions import DataError
from ..metrics import fit_percent
from .spec import TrainSpec

__all__ = ["EstimateResult", "estimate_records", "load_estimator", "train_from_spec"]

_MODEL_KIND_FILE = "estimator.json"


def _dataset(spec: TrainSpec, n: int, seed: int, basis: KautzBasis) -> ResponseDataset:
    params = draw_parameters(spec.system, spec.uncertainty, n, random_state=seed)
    return make_dataset(
        spec.system,
        params,
        basis,
        spec.t,
        kind=spec.kind,
        noise=spec.noise,
        noise_kind=spec.noise_kind,
        color_pole=spec.color_pole,
        quantization=spec.quantization,
        random_state=seed + 1,
    )


def train_from_spec(
    spec: TrainSpec, out_dir: str | Path, *, progress: bool = False
) -> dict[str, Any]:
    """Train the estimator a spec describes and write it with its curves and summary.

    Draws ``spec.n_records`` systems from the uncertain model, simulates their
    noisy responses, trains either the paper's coefficient networks on the
    fixed basis or the adaptive-pole estimator, evaluates it on
    ``spec.n_test`` fresh records against the noise-free truth, and writes
    ``out_dir/model/`` (weights and metadata), ``out_dir/curves.png`` (the
    training and validation losses) and ``out_dir/summary.json``.

    Parameters
    ----------
    spec : TrainSpec
        The validated specification.
    out_dir : str or Path
        Output folder (created).
    progress : bool, default=False
        Show progress bars.

    Returns
    -------
    dict
        The summary written to ``summary.json``.
    """
    from ..nn import CoefficientEstimator

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    nominal = KautzBasis(spec.system.poles())
    label_basis = nominal if spec.adaptive else KautzBasis(spec.basis_poles)
    train = _dataset(spec, spec.n_records, spec.random_state, label_basis)
    test = _dataset(spec, spec.n_test, spec.random_state + 1000, label_basis)
    config = None if spec.max_epochs is None else {"max_epochs": spec.max_epochs}
    start = time.perf_counter()
    if spec.adaptive:
        from ..nn.adaptive import AdaptivePoleEstimator

        # the adaptive estimator has its own defaults; the paper preset does not apply to it
        est = AdaptivePoleEstimator(
            random_state=spec.random_state, progress=progress, config=config
        ).fit(train)
        kind = "adaptive"
    else:
        est = CoefficientEstimator(
            preset=spec.preset,
            per_coefficient=spec.per_coefficient,
            random_state=spec.random_state,
            progress=progress,
            config=config,
        ).fit(train)
        kind = "coefficients"
    seconds = time.perf_counter() - start
    model_dir = est.save(out / "model")
    (Path(model_dir) / _MODEL_KIND_FILE).write_text(json.dumps({"estimator": kind}))
    t0 = time.perf_counter()
    models = est.predict_models(test.responses)
    per_record = (time.perf_counter() - t0) / len(test)
    fits = np.array(
        [
            fit_percent(clean, m.impulse(spec.t) if spec.kind == "impulse" else m.step(spec.t))
            for clean, m in zip(test.clean, models, strict=True)
        ]
    )
    histories = est.histories_
    _plot_curves(histories, out / "curves.png")
    summary = {
        "estimator": kind,
        "preset": spec.preset,
        "n_records": spec.n_records,
        "n_test": spec.n_test,
        "noise": spec.noise,
        "kind": spec.kind,
        "basis_poles": None if spec.adaptive else [[p.real, p.imag] for p in label_basis.poles],
        "train_seconds": seconds,
        "seconds_per_record": per_record,
        "final_train_loss": [h.train_loss[-1] for h in histories],
        "final_val_loss": [h.val_loss[-1] for h in histories],
        "test_fit_mean": float(np.mean(fits)),
        "test_fit_median": float(np.median(fits)),
        "test_fit_min": float(np.min(fits)),
        "model": str(model_dir),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _plot_curves(histories: list[Any], path: Path) -> None:
    from ..nn.plots import plot_history
    from ..plotting import _new_figure, save_figure

    fig, (ax,) = _new_figure(1, panel_size=(7.0, 4.5))
    for i, h in enumerate(histories, start=1):
        plot_history(h, ax=ax, label=f"net {i}" if len(histories) > 1 else None)
    ax.set_title("training (solid) and validation (dashed) loss")
    save_figure(fig, path)


def load_estimator(model_dir: str | Path) -> Any:
    """Load an estimator written by :func:`train_from_spec` (either kind).

    Parameters
    ----------
    model_dir : str or Path
        The ``model`` folder.

    Returns
    -------
    CoefficientEstimator or AdaptivePoleEstimator

    Raises
    ------
    DataError
        Missing, tampered or unknown model files.
    """
    from ..nn import CoefficientEstimator

    path = Path(model_dir)
    kind_file = path / _MODEL_KIND_FILE
    kind = "coefficients"
    if kind_file.exists():
        try:
            kind = json.loads(kind_file.read_text())["estimator"]
        except (ValueError, KeyError) as exc:
            raise DataError(f"{kind_file} is malformed") from exc
    elif not path.exists():
        raise DataError(f"no model at {path}")
    if kind == "adaptive":
        from ..nn.adaptive import AdaptivePoleEstimator

        return AdaptivePoleEstimator.load(path)
    if kind != "coefficients":
        raise DataError(f"{kind_file} names an unknown estimator {kind!r}")
    return CoefficientEstimator.load(path)


@dataclass(frozen=True)
class EstimateResult:
    """Estimates for records: coefficients, poles and the fit of each model to its record.

    Parameters
    ----------
    coefficients : ndarray of shape (n_records, n_functions)
    poles : ndarray of complex, shape (n_records, n_functions)
    fit_percent : ndarray of shape (n_records,)
        Fit of the estimated model's response to the (noisy) record.
    """

    coefficients: NDArray[np.float64]
    poles: NDArray[np.complex128]
    fit_percent: NDArray[np.float64]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: one entry per record."""
        return {
            "records": [
                {
                    "coefficients": c.tolist(),
                    "poles": [[p.real, p.imag] for p in poles],
                    "fit_percent": float(f),
                }
                for c, poles, f in zip(self.coefficients, self.poles, self.fit_percent, strict=True)
            ]
        }


def estimate_records(estimator: Any, t: ArrayLike, records: ArrayLike) -> EstimateResult:
    """Apply a trained estimator to records sampled on its grid.

    Parameters
    ----------
    estimator : CoefficientEstimator or AdaptivePoleEstimator
    t : array-like of shape (n_samples,)
        The records' sample times; must equal the training grid.
    records : array-like of shape (n_samples,) or (n_records, n_samples)

    Returns
    -------
    EstimateResult

    Raises
    ------
    DataError
        Another grid, NaN, or wrong length.
    """
    t = np.asarray(t, dtype=float)
    estimator.check_grid(t)
    Y = np.atleast_2d(np.asarray(records, dtype=float))
    models = estimator.predict_models(Y, t=t)
    kind = getattr(estimator, "kind_", "impulse")
    fits = []
    for y, m in zip(Y, models, strict=True):
        yhat = m.impulse(t) if kind == "impulse" else m.step(t)
        fits.append(fit_percent(y, yhat))
    return EstimateResult(
        coefficients=np.array([m.coefficients for m in models]),
        poles=np.array([m.poles for m in models]),
        fit_percent=np.array(fits),
    )
