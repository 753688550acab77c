"""Files of the adaptive-pole estimator: ``weights.pt`` and ``metadata.json`` (save and load).

The folder layout and its checks are :mod:`kautztwin.nn.model_files`; this module adds
what the adaptive-pole estimator stores (structure, architecture, options, loss curves;
optionally the calibration of its uncertainty and a description of its training data)
and rebuilds it from that.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...basis._blocks import parse_poles
from ...exceptions import DataError
from ..config import TrainingConfig, TrainingHistory
from ..model_files import check_network, load_verified, load_weights, save_verified, stored_grid
from .network import AdaptivePoleNetwork

__all__ = ["load_estimator", "save_estimator"]

_FORMAT = "kautztwin.AdaptivePoleEstimator"
_FORMAT_VERSION = 1


def save_estimator(est: Any, directory: str | Path) -> Path:
    """Write a fitted ``AdaptivePoleEstimator`` to a directory (created if needed).

    Parameters
    ----------
    est : AdaptivePoleEstimator
        A fitted estimator.
    directory : str or path-like

    Returns
    -------
    pathlib.Path
        The directory.
    """
    state = {k: v.detach().cpu().contiguous() for k, v in est.network_.state_dict().items()}
    net = est.network_
    fields: dict[str, Any] = {
        "kinds": list(est.kinds_),
        "centre_poles": [[float(p.real), float(p.imag)] for p in est.centre_poles_],
        "kind": est.kind_,
        "architecture": {
            "network": type(net).__name__,
            "hidden": list(net.hidden),
            "n_features": int(net.projector.shape[1]),
            "n_stages": net.n_stages,
            "pole_range": net.pole_range,
            "step": net.step,
            "n_parameters": sum(p.numel() for p in net.parameters()),
            "dtype": str(net.projector.dtype).removeprefix("torch."),
            "relative_degree": int(net.relative_degree),
        },
        "fit_relative_degree": int(est.relative_degree_),
        "weights_rule": est.weights,
        "refine": bool(est.refine),
        "refine_max_iter": int(est.refine_max_iter),
        "pretrain_epochs": int(est.pretrain_epochs),
        "random_state": int(est.random_state),
        "n_train": est.n_train_,
        "config": est.config_.to_dict(),
        "histories": [h.to_dict() for h in est.histories_],
        "pretrain_histories": [h.to_dict() for h in est.pretrain_histories_],
    }
    # optional fields (files written before them load with the defaults)
    if getattr(est, "calibration_", None) is not None:
        fields["uncertainty"] = {
            "scale": float(est.uncertainty_scale_),
            "calibration": est.calibration_,
        }
    if getattr(est, "training_data_", None) is not None:
        fields["training_data"] = est.training_data_
    return save_verified(directory, _FORMAT, _FORMAT_VERSION, state, est.t_, fields)


def load_estimator(cls: type, directory: str | Path) -> Any:
    """Read an estimator of class ``cls`` written by :func:`save_estimator`, verified.

    Parameters
    ----------
    cls : type
        ``AdaptivePoleEstimator`` (or a subclass).
    directory : str or path-like

    Returns
    -------
    AdaptivePoleEstimator
        Fitted.

    Raises
    ------
    DataError
        If a file is missing or unreadable, of another format or version,
        malformed, or modified after saving (checksum mismatch).
    """
    return load_verified(
        directory,
        _FORMAT,
        _FORMAT_VERSION,
        "AdaptivePoleEstimator",
        functools.partial(_from_files, cls),
    )


def _from_files(cls: type, meta: dict[str, Any], weights_path: Path) -> Any:
    t = stored_grid(meta)
    arch = meta["architecture"]
    check_network(arch, AdaptivePoleNetwork)
    kinds = tuple(str(k) for k in meta["kinds"])
    centre_poles = [complex(re, im) for re, im in meta["centre_poles"]]
    got_kinds, centre = parse_poles(centre_poles, 0.0)
    if got_kinds != kinds:
        raise DataError("the stored centre poles do not match the block structure")
    dtype = getattr(torch, str(arch["dtype"]))
    state = load_weights(weights_path)
    n_feat = int(arch["n_features"])
    # files written before the option have none: the unconstrained fit
    relative_degree = int(arch.get("relative_degree", 1))
    fit_degree = int(meta.get("fit_relative_degree", relative_degree))
    for r in (relative_degree, fit_degree):
        if not 1 <= r <= len(centre):
            raise DataError(f"stored relative degree {r} is out of range")
    module = AdaptivePoleNetwork(
        kinds,
        centre,
        t,
        np.zeros((t.size, n_feat)),
        hidden=tuple(int(h) for h in arch["hidden"]),
        n_stages=int(arch["n_stages"]),
        pole_range=float(arch["pole_range"]),
        step=float(arch["step"]),
        kind=str(meta["kind"]),
        dtype=dtype,
        relative_degree=relative_degree,
    )
    module.load_state_dict(state, strict=True)
    est = cls(
        structure=centre_poles,
        hidden=tuple(arch["hidden"]),
        n_features=n_feat,
        n_stages=int(arch["n_stages"]),
        pole_range=float(arch["pole_range"]),
        step=float(arch["step"]),
        weights=str(meta["weights_rule"]),
        config=TrainingConfig.from_dict(meta["config"]),
        random_state=int(meta["random_state"]),
        refine=bool(meta["refine"]),
        refine_max_iter=int(meta["refine_max_iter"]),
        pretrain_epochs=int(meta["pretrain_epochs"]),
        relative_degree=fit_degree,
    )
    est._set_fitted(
        module,
        [TrainingHistory.from_dict(h) for h in meta["histories"]],
        [TrainingHistory.from_dict(h) for h in meta["pretrain_histories"]],
        TrainingConfig.from_dict(meta["config"]),
        int(meta["n_train"]),
        fit_degree,
    )
    unc = meta.get("uncertainty")
    if unc is not None:
        try:
            est.uncertainty_scale_ = float(unc["scale"])
            est.calibration_ = dict(unc["calibration"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"malformed 'uncertainty' entry in the metadata: {exc}") from None
    est.training_data_ = meta.get("training_data")
    return est
