"""The training loop of the kautztwin networks: ``fit_network`` (Adam, clipping, early stopping)."""

from __future__ import annotations

import contextlib
import copy
import math
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from .._validation import check_int
from ..exceptions import ConvergenceWarning, DataError, DimensionError
from .config import TrainingConfig, TrainingHistory

__all__ = ["fit_network"]

_EVAL_BATCH = 4096  # records per forward pass when evaluating the validation loss

Batch = tuple[torch.Tensor, ...]


def _check_tensors(data: Any, name: str) -> Batch:
    if isinstance(data, torch.Tensor):
        data = (data,)
    if not isinstance(data, (tuple, list)) or not data:
        raise DataError(f"{name} must be a non-empty tuple of tensors, got {type(data).__name__}")
    out = tuple(data)
    for i, x in enumerate(out):
        if not isinstance(x, torch.Tensor):
            raise DataError(f"{name}[{i}] must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim == 0:
            raise DimensionError(f"{name}[{i}] must have a batch dimension, got a scalar")
        if x.is_floating_point() and not bool(torch.isfinite(x).all()):
            raise DataError(f"{name}[{i}] contains NaN or inf")
    n = out[0].shape[0]
    for i, x in enumerate(out[1:], start=1):
        if x.shape[0] != n:
            raise DimensionError(
                f"{name}[{i}] has {x.shape[0]} records along dim 0 but {name}[0] has {n}"
            )
    if n < 1:
        raise DataError(f"{name} holds no records")
    return out


@contextlib.contextmanager
def _seeded(seed: int, tensors: Sequence[torch.Tensor]) -> Iterator[None]:
    """Seed torch and numpy, force deterministic kernels; restore all global state afterwards."""
    devices = sorted({t.device.index or 0 for t in tensors if t.device.type == "cuda"})
    # the legacy global numpy state is seeded for code in loss_fn that uses it, then restored
    np_state = np.random.get_state()  # noqa: NPY002
    det = torch.are_deterministic_algorithms_enabled()
    det_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    with torch.random.fork_rng(devices=devices):
        try:
            torch.manual_seed(seed)
            np.random.seed(seed % 2**32)  # noqa: NPY002
            torch.use_deterministic_algorithms(True, warn_only=True)
            yield
        finally:
            torch.use_deterministic_algorithms(det, warn_only=det_warn)
            np.random.set_state(np_state)  # noqa: NPY002


def _mean_loss(
    module: torch.nn.Module,
    data: Batch,
    loss_fn: Callable[[torch.nn.Module, Batch], torch.Tensor],
    batch_size: int,
) -> float:
    n = data[0].shape[0]
    total = 0.0
    with torch.no_grad():
        for start in range(0, n, batch_size):
            batch = tuple(x[start : start + batch_size] for x in data)
            total += float(loss_fn(module, batch)) * batch[0].shape[0]
    return total / n


def fit_network(
    module: torch.nn.Module,
    train: Batch,
    val: Batch | None,
    loss_fn: Callable[[torch.nn.Module, Batch], torch.Tensor],
    config: TrainingConfig,
    *,
    random_state: int = 0,
    progress: bool = False,
) -> TrainingHistory:
    """Train a module with Adam, gradient-norm clipping and early stopping, in place.

    Every epoch shuffles the training records, steps Adam once per
    mini-batch (the tensors of ``train`` are sliced together along dim 0),
    clips the global L2 norm of the gradient at ``config.grad_clip`` and then
    evaluates the validation loss in ``eval`` mode.  The weights of the epoch
    with the lowest validation loss (training loss without ``val``) are
    restored at the end, also when the run is not stopped early.

    Parameters
    ----------
    module : torch.nn.Module
        The network, trained in place (its parameters that require gradients).
    train : tuple of torch.Tensor
        Training tensors with equal length along dim 0, e.g. ``(x, y)``.
    val : tuple of torch.Tensor or None
        Validation tensors, same layout as ``train``; ``None`` disables
        validation and early stopping.
    loss_fn : callable
        ``loss_fn(module, batch) -> scalar tensor``, the mean loss of a batch
        (a tuple of slices of the tensors).
    config : TrainingConfig
        Learning rate, epochs, batch size, clipping, patience, weight decay.
    random_state : int, default=0
        Seed of the shuffles and of any randomness in the module or the loss.
        Training is deterministic: the same seed, data, initial weights and
        thread count give bitwise identical weights.
    progress : bool, default=False
        Show a tqdm progress bar with the current losses.

    Returns
    -------
    TrainingHistory

    Raises
    ------
    DataError
        If ``config`` is not a :class:`TrainingConfig`, the data are not
        tuples of finite tensors, or the module has no trainable parameters.
    DimensionError
        If the tensors of ``train`` (or ``val``) differ in length.

    Warns
    -----
    ConvergenceWarning
        If the training loss becomes NaN or inf; training stops and the best
        weights so far are restored.

    Notes
    -----
    The global torch and numpy random states and the
    ``torch.use_deterministic_algorithms`` setting are restored on return;
    the thread count is left to the caller (``torch.set_num_threads``).

    Examples
    --------
    >>> import torch
    >>> from kautztwin.nn import TrainingConfig, fit_network
    >>> x = torch.linspace(-1, 1, 64).reshape(-1, 1)
    >>> y = 3 * x - 1
    >>> net = torch.nn.Linear(1, 1)
    >>> mse = lambda m, b: torch.nn.functional.mse_loss(m(b[0]), b[1])
    >>> cfg = TrainingConfig(learning_rate=0.05, max_epochs=200, batch_size=16,
    ...                      grad_clip=None, patience=None)
    >>> hist = fit_network(net, (x, y), None, mse, cfg)
    >>> hist.train_loss[-1] < 1e-4
    True
    """
    if not isinstance(config, TrainingConfig):
        raise DataError(f"config must be a TrainingConfig, got {type(config).__name__}")
    if not isinstance(module, torch.nn.Module):
        raise DataError(f"module must be a torch.nn.Module, got {type(module).__name__}")
    train = _check_tensors(train, "train")
    val = None if val is None else _check_tensors(val, "val")
    params = [p for p in module.parameters() if p.requires_grad]
    if not params:
        raise DataError("module has no trainable parameters")
    seed = check_int(random_state, "random_state", minimum=0)
    from tqdm.auto import tqdm

    n = train[0].shape[0]
    bs = config.batch_size
    eval_bs = max(bs, _EVAL_BATCH)
    train_curve: list[float] = []
    val_curve: list[float] = []
    best = math.inf
    best_epoch = -1
    best_state: dict[str, torch.Tensor] | None = None
    stopped_early = False
    start = time.perf_counter()
    all_tensors = [*train, *(val or ()), *params]
    with _seeded(seed, all_tensors):
        generator = torch.Generator().manual_seed(seed)
        optimizer = torch.optim.Adam(
            params, lr=config.learning_rate, weight_decay=config.weight_decay
        )
        bar = tqdm(
            range(config.max_epochs),
            desc="training",
            unit="epoch",
            disable=not progress,
            leave=False,
            dynamic_ncols=True,
        )
        try:
            for epoch in bar:
                module.train()
                order = torch.randperm(n, generator=generator)
                total = 0.0
                diverged = False
                for s in range(0, n, bs):
                    idx = order[s : s + bs]
                    batch = tuple(x[idx.to(x.device)] for x in train)
                    optimizer.zero_grad(set_to_none=True)
                    loss = loss_fn(module, batch)
                    value = float(loss.detach())
                    if not math.isfinite(value):
                        diverged = True
                        break
                    loss.backward()
                    if config.grad_clip is not None:
                        torch.nn.utils.clip_grad_norm_(params, config.grad_clip)
                    optimizer.step()
                    total += value * idx.numel()
                if diverged:
                    warnings.warn(
                        f"the training loss became non-finite in epoch {epoch}; training "
                        "stopped and the best weights so far were kept (lower the learning "
                        "rate or clip the gradient)",
                        ConvergenceWarning,
                        stacklevel=2,
                    )
                    break
                train_curve.append(total / n)
                module.eval()
                if val is not None:
                    val_curve.append(_mean_loss(module, val, loss_fn, eval_bs))
                    score = val_curve[-1]
                else:
                    score = train_curve[-1]
                if score < best:
                    best, best_epoch = score, epoch
                    best_state = copy.deepcopy(module.state_dict())
                if progress:
                    post = {"train": f"{train_curve[-1]:.3g}"}
                    if val_curve:
                        post["val"] = f"{val_curve[-1]:.3g}"
                    bar.set_postfix(post, refresh=False)
                if config.patience is not None and epoch - best_epoch >= config.patience:
                    stopped_early = epoch + 1 < config.max_epochs
                    break
        finally:
            bar.close()
        if best_state is not None:
            module.load_state_dict(best_state)
        module.eval()
    return TrainingHistory(
        train_loss=train_curve,
        val_loss=val_curve,
        best_epoch=max(best_epoch, 0),
        seconds=time.perf_counter() - start,
        stopped_early=stopped_early,
    )
