"""Training of the amortised pole network: end to end on the fit of random stable systems.

The loss of a record is ``1 - fit/100`` of its least-squares fit on the predicted basis
against its *noise-free* response (the fit percent of :func:`kautztwin.fit_percent`),
averaged over a mini-batch: no pole labels, so the network learns the poles that give
the best fitted response, whatever the system's order.  Adam with a one-cycle learning
rate, a held-out share of the records for validation, the best validation epoch kept.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence

import numpy as np
import torch
from numpy.typing import NDArray

from ..config import TrainingHistory
from ..kautz_torch import lstsq_coefficients, propagate
from .network import AmortisedPoleNetwork, bin_features, block_matrices

__all__ = ["fit_loss", "train_network"]

#: Relative ridge of the least squares in training (float32 normal equations).
TRAIN_RIDGE = 1e-6


def fit_loss(
    kinds: Sequence[str], theta: torch.Tensor, tau: NDArray, y: torch.Tensor, clean: torch.Tensor
) -> torch.Tensor:
    """Mean ``1 - fit/100`` of the least-squares fits of ``y`` against ``clean``.

    Parameters
    ----------
    kinds : sequence of {'quad', 'real'}
    theta : torch.Tensor of shape (batch, n_params)
        Block parameters on the grid ``tau``'s time unit.
    tau : ndarray of shape (n_samples,)
    y, clean : torch.Tensor of shape (batch, n_samples)
        Noisy records and their noise-free responses.

    Returns
    -------
    torch.Tensor
        A scalar.
    """
    A, B = block_matrices(kinds, theta)
    K = propagate(A, B, tau)
    c = lstsq_coefficients(K, y, ridge=TRAIN_RIDGE)
    yhat = (c[:, None, :] @ K)[:, 0]
    num = torch.linalg.norm(clean - yhat, dim=1)
    den = torch.linalg.norm(clean - clean.mean(dim=1, keepdim=True), dim=1)
    return (num / den).mean()


def train_network(
    network: AmortisedPoleNetwork,
    tau: NDArray[np.float64],
    responses: NDArray[np.float64],
    clean: NDArray[np.float64],
    *,
    max_epochs: int,
    batch_size: int,
    learning_rate: float,
    validation_fraction: float,
    rng: np.random.Generator,
    progress: bool = False,
) -> TrainingHistory:
    """Train ``network`` in place on records of the normalised grid ``tau``.

    Parameters
    ----------
    network : AmortisedPoleNetwork
    tau : ndarray of shape (n_samples,)
    responses, clean : ndarray of shape (n_records, n_samples)
    max_epochs, batch_size : int
    learning_rate : float
        Peak of the one-cycle schedule.
    validation_fraction : float
        Share of the records held out.
    rng : numpy.random.Generator
        Split and shuffles.
    progress : bool, default=False
        A progress bar over the epochs.

    Returns
    -------
    TrainingHistory
        Per-epoch training and validation loss; the network holds the best validation
        epoch's weights (``best_epoch``).
    """
    from tqdm.auto import tqdm

    n = responses.shape[0]
    n_val = max(1, int(round(validation_fraction * n)))
    order = rng.permutation(n)
    val, train = order[:n_val], order[n_val:]
    Z = torch.as_tensor(bin_features(tau, responses, network.n_bins), dtype=torch.float32)
    Y = torch.as_tensor(responses, dtype=torch.float32)
    C = torch.as_tensor(clean, dtype=torch.float32)
    batch_size = min(batch_size, train.size)
    per_epoch = max(1, train.size // batch_size)
    opt = torch.optim.Adam(network.parameters(), lr=learning_rate)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=learning_rate,
                                                total_steps=max_epochs * per_epoch)
    kinds = network.kinds
    train_loss: list[float] = []
    val_loss: list[float] = []
    best, best_state, best_epoch = np.inf, None, 0
    t0 = time.perf_counter()
    for epoch in tqdm(range(max_epochs), desc="amortised", disable=not progress, leave=False):
        network.train()
        perm = rng.permutation(train)
        total = 0.0
        for s in range(per_epoch):
            b = torch.as_tensor(perm[s * batch_size : (s + 1) * batch_size])
            loss = fit_loss(kinds, network(Z[b]), tau, Y[b], C[b])
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(network.parameters(), 1.0)
            opt.step()
            sched.step()
            total += loss.item()
        network.eval()
        with torch.no_grad():
            v = sum(
                float(fit_loss(kinds, network(Z[c]), tau, Y[c], C[c])) * c.numel()
                for c in torch.as_tensor(val).split(1024)
            ) / val.size
        train_loss.append(total / per_epoch)
        val_loss.append(v)
        if v < best:
            best, best_epoch = v, epoch
            best_state = copy.deepcopy(network.state_dict())
    if best_state is not None:
        network.load_state_dict(best_state)
    network.eval()
    return TrainingHistory(train_loss=train_loss, val_loss=val_loss, best_epoch=best_epoch,
                           seconds=time.perf_counter() - t0, stopped_early=False)
