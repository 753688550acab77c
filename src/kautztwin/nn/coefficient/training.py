"""Training of the paper's coefficient networks: split, standardise, one fit per target."""

from __future__ import annotations

import copy

import numpy as np
import torch

from ...datasets import ResponseDataset
from ...exceptions import DataError
from ..config import TrainingConfig, TrainingHistory
from ..data import Standardizer, split_indices
from ..networks import PaperNetwork
from ..training import fit_network

__all__ = ["train_coefficient_networks"]


def _child_seed(random_state: int, k: int) -> int:
    return int(np.random.SeedSequence([random_state, k]).generate_state(1)[0])


def _mse(module: torch.nn.Module, batch: tuple[torch.Tensor, ...]) -> torch.Tensor:
    return torch.nn.functional.mse_loss(module(batch[0]), batch[1])


def train_coefficient_networks(
    dataset: ResponseDataset,
    config: TrainingConfig,
    seed: int,
    *,
    per_coefficient: bool,
    progress: bool,
    start: list[PaperNetwork] | None = None,
) -> tuple[list[PaperNetwork], list[TrainingHistory], Standardizer, Standardizer]:
    """Split, standardise and train one network per target (what ``CoefficientEstimator`` fits).

    Parameters
    ----------
    dataset : ResponseDataset
        Labelled records, at least 2.
    config : TrainingConfig
        Options of every :func:`~kautztwin.nn.fit_network` run.
    seed : int
        Seed of the split; target ``k`` uses a child seed for its weights and shuffles.
    per_coefficient : bool
        One single-output network per coefficient, or one multi-output network.
    progress : bool
        Show a progress bar while training.
    start : list of PaperNetwork, optional
        Trained networks to start from (fine-tuning: deep copies are trained, ``start``
        stays unchanged); ``None`` builds fresh networks seeded per target.

    Returns
    -------
    networks : list of PaperNetwork
    histories : list of TrainingHistory
    input_scaler, label_scaler : Standardizer
        Normalisation of the responses and of the coefficients, fitted on the training part.

    Raises
    ------
    DataError
        If ``start`` holds another number of networks than the targets need.
    """
    train_idx, val_idx = split_indices(len(dataset), config.validation_fraction, seed)
    X = np.asarray(dataset.responses, dtype=float)
    Y = np.asarray(dataset.coefficients, dtype=float)
    input_scaler = Standardizer.fit(X[train_idx])
    # a constant label (no uncertainty in it) is predicted exactly, not mean + net output
    label_scaler = Standardizer.fit(Y[train_idx], constant_scale=None)
    Xs = torch.from_numpy(input_scaler.transform(X).astype(np.float32))
    Ys = torch.from_numpy(label_scaler.transform(Y).astype(np.float32))
    tr = torch.from_numpy(train_idx)
    va = torch.from_numpy(val_idx)
    n_functions = Y.shape[1]
    targets = (
        [slice(k, k + 1) for k in range(n_functions)]
        if per_coefficient
        else [slice(0, n_functions)]
    )
    if start is not None and len(start) != len(targets):
        raise DataError(
            f"per_coefficient={per_coefficient!r} needs {len(targets)} network(s) but "
            f"the estimator to fine-tune has {len(start)}"
        )
    networks: list[PaperNetwork] = []
    histories: list[TrainingHistory] = []
    for k, cols in enumerate(targets):
        child = _child_seed(seed, k)
        if start is None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(child)
                net = PaperNetwork(X.shape[1], cols.stop - cols.start)
        else:
            net = copy.deepcopy(start[k])
            net.requires_grad_(True)
        history = fit_network(
            net,
            (Xs[tr], Ys[tr, cols]),
            (Xs[va], Ys[va, cols]),
            _mse,
            config,
            random_state=child,
            progress=bool(progress),
        )
        networks.append(net)
        histories.append(history)
    return networks, histories, input_scaler, label_scaler
