"""Files of the coefficient estimator: ``weights.pt`` and ``metadata.json`` (save and load).

The folder layout and its checks are :mod:`kautztwin.nn.model_files`; this module adds
what ``CoefficientEstimator`` stores (basis, normalisation, architecture, options, loss
curves) and rebuilds it from that.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from ...basis import KautzBasis
from ...exceptions import DataError
from ..config import TrainingConfig, TrainingHistory
from ..data import Standardizer
from ..model_files import check_network, load_verified, load_weights, save_verified, stored_grid
from ..networks import PaperNetwork, paper_parameter_count

__all__ = ["load_estimator", "save_estimator"]

_FORMAT = "kautztwin.CoefficientEstimator"
_FORMAT_VERSION = 1


def save_estimator(est: Any, directory: str | Path) -> Path:
    """Write a fitted ``CoefficientEstimator`` to a directory (created if needed).

    Parameters
    ----------
    est : CoefficientEstimator
        A fitted estimator.
    directory : str or path-like

    Returns
    -------
    pathlib.Path
        The directory.
    """
    net = est.networks_[0]
    fields: dict[str, Any] = {
        "basis": est.basis_.to_dict(),
        "kind": est.kind_,
        "normalization": {
            "inputs": est.input_scaler_.to_dict(),
            "labels": est.label_scaler_.to_dict(),
        },
        "architecture": {
            "network": type(net).__name__,
            "n_networks": len(est.networks_),
            "n_inputs": net.n_inputs,
            "n_outputs": net.n_outputs,
            "n_parameters": paper_parameter_count(net.n_inputs, net.n_outputs),
            "per_coefficient": bool(est.per_coefficient),
            "dtype": "float32",
        },
        "preset": est.preset,
        "random_state": int(est.random_state),
        "config": est.config_.to_dict(),
        "histories": [h.to_dict() for h in est.histories_],
    }
    if getattr(est, "calibration_", None) is not None:  # optional: older files lack it
        fields["uncertainty"] = {
            "scale": float(est.uncertainty_scale_),
            "calibration": est.calibration_,
        }
    return save_verified(directory, _FORMAT, _FORMAT_VERSION, est._state(), est.t_, fields)


def load_estimator(cls: type, directory: str | Path) -> Any:
    """Read an estimator of class ``cls`` written by :func:`save_estimator`, verified.

    Parameters
    ----------
    cls : type
        ``CoefficientEstimator`` (or a subclass).
    directory : str or path-like

    Returns
    -------
    CoefficientEstimator
        Fitted.

    Raises
    ------
    DataError
        If a file is missing or unreadable, of another format version,
        malformed, or was modified after saving (checksum mismatch).
    """
    return load_verified(
        directory,
        _FORMAT,
        _FORMAT_VERSION,
        "CoefficientEstimator",
        functools.partial(_from_files, cls),
    )


def _from_files(cls: type, meta: dict[str, Any], weights_path: Path) -> Any:
    t = stored_grid(meta)
    b = meta["basis"]
    basis = KautzBasis([complex(re, im) for re, im in b["poles"]], dt=b.get("dt", 0.0))
    arch = meta["architecture"]
    check_network(arch, PaperNetwork)
    state = load_weights(weights_path)
    networks = []
    for k in range(int(arch["n_networks"])):
        net = PaperNetwork(int(arch["n_inputs"]), int(arch["n_outputs"]))
        prefix = f"net{k}."
        net.load_state_dict(
            {name[len(prefix) :]: v for name, v in state.items() if name.startswith(prefix)},
            strict=True,
        )
        networks.append(net)
    expected = basis.n_functions if arch["per_coefficient"] else 1
    n_out = int(arch["n_outputs"]) * len(networks)
    if len(networks) != expected or n_out != basis.n_functions:
        raise DataError(
            f"{len(networks)} network(s) with {arch['n_outputs']} output(s) do not give the "
            f"{basis.n_functions} coefficients of the basis"
        )
    input_scaler = Standardizer.from_dict(meta["normalization"]["inputs"])
    label_scaler = Standardizer.from_dict(meta["normalization"]["labels"])
    if input_scaler.n_features != t.size or label_scaler.n_features != basis.n_functions:
        raise DataError("the normalisation does not match the grid or the basis")
    est = cls(
        preset=meta["preset"],
        per_coefficient=bool(arch["per_coefficient"]),
        random_state=int(meta["random_state"]),
    )
    est._set_fitted(
        networks=networks,
        histories=[TrainingHistory.from_dict(h) for h in meta["histories"]],
        t=t,
        basis=basis,
        kind=str(meta["kind"]),
        config=TrainingConfig.from_dict(meta["config"]),
        input_scaler=input_scaler,
        label_scaler=label_scaler,
    )
    unc = meta.get("uncertainty")
    if unc is not None:
        try:
            est.uncertainty_scale_ = float(unc["scale"])
            est.calibration_ = dict(unc["calibration"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"malformed 'uncertainty' entry in the metadata: {exc}") from None
    return est
