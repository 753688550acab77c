"""Training loop, presets, data split and normalisation for the kautztwin networks."""

from __future__ import annotations

import contextlib
import copy
import math
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from ..exceptions import ConvergenceWarning, DataError, DimensionError

__all__ = [
    "PRESETS",
    "Standardizer",
    "TrainingConfig",
    "TrainingHistory",
    "fit_network",
    "split_indices",
]

#: Names accepted by :meth:`TrainingConfig.preset`.
PRESETS: tuple[str, ...] = ("default", "paper")
_EVAL_BATCH = 4096  # records per forward pass when evaluating the validation loss


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _positive_number(value: Any, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{name} must be a positive number, got {value!r}") from exc
    if not math.isfinite(v) or v <= 0:
        raise DataError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _positive_int(value: Any, name: str) -> int:
    if not _is_int(value) or value < 1:
        raise DataError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _seed(random_state: Any, name: str = "random_state") -> int:
    if not _is_int(random_state) or random_state < 0:
        raise DataError(f"{name} must be a non-negative integer, got {random_state!r}")
    return int(random_state)


# =========================================================================== config
@dataclass(frozen=True)
class TrainingConfig:
    """Hyper-parameters of :func:`fit_network` (Adam with gradient clipping).

    Parameters
    ----------
    learning_rate : float
        Adam step size, ``> 0``.
    max_epochs : int
        Most passes over the training set, ``>= 1``.
    batch_size : int
        Records per mini-batch, ``>= 1`` (the last batch of an epoch may be smaller).
    grad_clip : float or None
        Largest L2 norm of the gradient of all parameters together; a larger
        gradient is scaled down to this norm before the step (MATLAB's
        ``GradientThresholdMethod='global-l2norm'``).  ``None``: no clipping.
    patience : int or None
        Early stopping: stop after this many epochs without a new best
        validation loss.  ``None``: run all ``max_epochs``.
    weight_decay : float, default=0.0
        L2 penalty of Adam (``torch.optim.Adam(weight_decay=...)``), ``>= 0``.
    validation_fraction : float, default=0.15
        Share of the records held out for validation by the estimators, in ``(0, 1)``.

    Raises
    ------
    DataError
        If a value is out of range.

    See Also
    --------
    TrainingConfig.preset : The named presets ``'paper'`` and ``'default'``.
    fit_network : The loop that uses the configuration.

    Examples
    --------
    >>> from kautztwin.nn import TrainingConfig
    >>> cfg = TrainingConfig.preset("paper")
    >>> cfg.learning_rate, cfg.grad_clip, cfg.max_epochs, cfg.patience
    (1e-05, 0.0001, 1000, None)
    >>> TrainingConfig.preset("paper", max_epochs=5).max_epochs
    5
    """

    learning_rate: float
    max_epochs: int
    batch_size: int
    grad_clip: float | None
    patience: int | None
    weight_decay: float = 0.0
    validation_fraction: float = 0.15

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "learning_rate", _positive_number(self.learning_rate, "learning_rate"))
        set_(self, "max_epochs", _positive_int(self.max_epochs, "max_epochs"))
        set_(self, "batch_size", _positive_int(self.batch_size, "batch_size"))
        if self.grad_clip is not None:
            set_(self, "grad_clip", _positive_number(self.grad_clip, "grad_clip"))
        if self.patience is not None:
            set_(self, "patience", _positive_int(self.patience, "patience"))
        try:
            wd = float(self.weight_decay)
        except (TypeError, ValueError) as exc:
            raise DataError(
                f"weight_decay must be a number >= 0, got {self.weight_decay!r}"
            ) from exc
        if not math.isfinite(wd) or wd < 0:
            raise DataError(f"weight_decay must be a finite number >= 0, got {self.weight_decay!r}")
        set_(self, "weight_decay", wd)
        try:
            vf = float(self.validation_fraction)
        except (TypeError, ValueError) as exc:
            raise DataError(
                f"validation_fraction must be a number in (0, 1), got {self.validation_fraction!r}"
            ) from exc
        if not 0.0 < vf < 1.0:
            raise DataError(
                f"validation_fraction must lie in (0, 1), got {self.validation_fraction!r}"
            )
        set_(self, "validation_fraction", vf)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> TrainingConfig:
        """A named preset, optionally with some fields replaced.

        ========================  ==========  ===========
        field                     ``paper``   ``default``
        ========================  ==========  ===========
        learning_rate             1e-5        1e-3
        max_epochs                1000        150
        batch_size                50          128
        grad_clip (L2 norm)       1e-4        1.0
        patience                  None        20
        weight_decay              0           1e-2
        validation_fraction       0.15        0.15
        ========================  ==========  ===========

        ``paper`` follows the paper's MATLAB options (learning rate 1e-5,
        gradient threshold 1e-4 on the global L2 norm, 1000 epochs, mini-batches
        of 50 records, no early stopping: MATLAB's ``ValidationPatience`` is
        ``Inf`` by default).  ``default`` is tuned on the paper's simulation
        case for accuracy within a CPU budget; the evidence is in
        ``docs/nn-presets.md``.

        Parameters
        ----------
        name : {'default', 'paper'}
            Preset name.
        **overrides
            Fields to replace, e.g. ``max_epochs=50``.

        Returns
        -------
        TrainingConfig

        Raises
        ------
        DataError
            On an unknown preset or field name, or an out-of-range value.
        """
        if name == "paper":
            base = cls(
                learning_rate=1e-5, max_epochs=1000, batch_size=50, grad_clip=1e-4, patience=None
            )
        elif name == "default":
            base = cls(
                learning_rate=1e-3,
                max_epochs=150,
                batch_size=128,
                grad_clip=1.0,
                patience=20,
                weight_decay=1e-2,
            )
        else:
            raise DataError(f"preset must be one of {', '.join(map(repr, PRESETS))}; got {name!r}")
        return base.replace(**overrides) if overrides else base

    def replace(self, **changes: Any) -> TrainingConfig:
        """A copy with some fields replaced.

        Parameters
        ----------
        **changes
            New field values.

        Returns
        -------
        TrainingConfig

        Raises
        ------
        DataError
            On an unknown field name or an out-of-range value.
        """
        known = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise DataError(
                f"unknown training option(s) {', '.join(map(repr, unknown))}; "
                f"valid: {', '.join(sorted(known))}"
            )
        return type(self)(**{**asdict(self), **changes})

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary of the fields."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainingConfig:
        """Rebuild a configuration written by :meth:`to_dict`.

        Parameters
        ----------
        data : mapping

        Returns
        -------
        TrainingConfig

        Raises
        ------
        DataError
            On missing or unknown keys or out-of-range values.
        """
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(known))
        missing = [k for k in known[:5] if k not in data]
        if unknown or missing:
            raise DataError(
                f"training configuration: unknown keys {unknown}, missing keys {missing}"
            )
        return cls(**dict(data))


# =========================================================================== history
@dataclass(frozen=True)
class TrainingHistory:
    """Loss curves and outcome of one :func:`fit_network` run.

    Parameters
    ----------
    train_loss : sequence of float
        Mean training loss of each epoch (averaged over its mini-batches,
        weighted by their sizes, while the weights change).
    val_loss : sequence of float
        Validation loss after each epoch (empty without validation data).
    best_epoch : int
        0-based epoch whose weights were kept (the lowest validation loss, or
        the lowest training loss without validation data).
    seconds : float
        Wall-clock training time.
    stopped_early : bool
        Whether early stopping ended the run before ``max_epochs``.

    See Also
    --------
    kautztwin.nn.plot_history : Plot the curves.
    """

    train_loss: tuple[float, ...]
    val_loss: tuple[float, ...]
    best_epoch: int
    seconds: float
    stopped_early: bool

    def __post_init__(self) -> None:
        object.__setattr__(self, "train_loss", tuple(float(v) for v in self.train_loss))
        object.__setattr__(self, "val_loss", tuple(float(v) for v in self.val_loss))
        object.__setattr__(self, "best_epoch", int(self.best_epoch))
        object.__setattr__(self, "seconds", float(self.seconds))
        object.__setattr__(self, "stopped_early", bool(self.stopped_early))

    @property
    def n_epochs(self) -> int:
        """Number of epochs run."""
        return len(self.train_loss)

    @property
    def best_loss(self) -> float:
        """Loss of the kept weights (validation loss if there was validation data)."""
        curve = self.val_loss or self.train_loss
        return curve[self.best_epoch] if curve else math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (non-finite losses become ``None``)."""

        def clean(v: float) -> float | None:
            return v if math.isfinite(v) else None

        return {
            "train_loss": [clean(v) for v in self.train_loss],
            "val_loss": [clean(v) for v in self.val_loss],
            "best_epoch": self.best_epoch,
            "seconds": self.seconds,
            "stopped_early": self.stopped_early,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainingHistory:
        """Rebuild a history written by :meth:`to_dict`."""

        def curve(key: str) -> tuple[float, ...]:
            return tuple(math.nan if v is None else float(v) for v in data[key])

        return cls(
            train_loss=curve("train_loss"),
            val_loss=curve("val_loss"),
            best_epoch=int(data["best_epoch"]),
            seconds=float(data["seconds"]),
            stopped_early=bool(data["stopped_early"]),
        )


# =========================================================================== split and scaling
def split_indices(
    n: int, validation_fraction: float = 0.15, random_state: int = 0
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Random disjoint training/validation indices (the paper's 85/15 split).

    Parameters
    ----------
    n : int
        Number of records, ``>= 2``.
    validation_fraction : float, default=0.15
        Share of validation records, in ``(0, 1)``; the validation set holds
        ``max(1, round(validation_fraction * n))`` records.
    random_state : int, default=0
        Seed of the shuffle.

    Returns
    -------
    train, val : ndarray of int
        Sorted indices; together a permutation of ``range(n)``.

    Raises
    ------
    DataError
        If ``n < 2``, the fraction is out of range, or the training part would be empty.

    Examples
    --------
    >>> from kautztwin.nn import split_indices
    >>> train, val = split_indices(20, 0.15, random_state=0)
    >>> len(train), len(val)
    (17, 3)
    """
    if not _is_int(n) or n < 2:
        raise DataError(f"n must be an integer >= 2 to split off a validation set, got {n!r}")
    try:
        f = float(validation_fraction)
    except (TypeError, ValueError) as exc:
        raise DataError(
            f"validation_fraction must be a number in (0, 1), got {validation_fraction!r}"
        ) from exc
    if not 0.0 < f < 1.0:
        raise DataError(f"validation_fraction must lie in (0, 1), got {validation_fraction!r}")
    n_val = max(1, int(round(f * n)))
    if n_val >= n:
        raise DataError(f"validation_fraction = {f:g} of {n} records leaves no training records")
    perm = np.random.default_rng(_seed(random_state)).permutation(int(n))
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


@dataclass(frozen=True, eq=False)
class Standardizer:
    r"""Per-feature affine normalisation :math:`z = (x - \mu) / \sigma`.

    Build it with :meth:`fit`.  A feature with (nearly) zero spread gets
    :math:`\sigma = 1`, so constant features pass through shifted only.

    Parameters
    ----------
    mean : array-like of shape (n_features,)
        :math:`\mu`.
    scale : array-like of shape (n_features,)
        :math:`\sigma > 0`.

    Raises
    ------
    DataError
        If the values are not finite or a scale is not positive.
    DimensionError
        If the shapes differ or are not 1-D.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.nn import Standardizer
    >>> s = Standardizer.fit([[1.0, 5.0], [3.0, 5.0]])
    >>> s.mean, s.scale
    (array([2., 5.]), array([1., 1.]))
    >>> s.transform([[3.0, 6.0]])
    array([[1., 1.]])
    """

    mean: NDArray[np.float64]
    scale: NDArray[np.float64]

    def __post_init__(self) -> None:
        mean = np.array(self.mean, dtype=float, copy=True)
        scale = np.array(self.scale, dtype=float, copy=True)
        if mean.ndim != 1 or scale.shape != mean.shape:
            raise DimensionError(
                f"mean and scale must be 1-D of equal length; got shapes {mean.shape} "
                f"and {scale.shape}"
            )
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(scale))):
            raise DataError("standardizer mean and scale must be finite")
        if np.any(scale <= 0):
            raise DataError("standardizer scale must be positive")
        mean.setflags(write=False)
        scale.setflags(write=False)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "scale", scale)

    @property
    def n_features(self) -> int:
        """Number of features."""
        return int(self.mean.size)

    @classmethod
    def fit(
        cls, x: ArrayLike, *, rtol: float = 1e-12, constant_scale: float | None = 1.0
    ) -> Standardizer:
        """Mean and standard deviation (``ddof=0``) of every column.

        Parameters
        ----------
        x : array-like of shape (n_records, n_features)
            At least one row.
        rtol : float, default=1e-12
            A column whose standard deviation is at most ``rtol`` times the
            largest absolute value in ``x`` (or zero) gets ``constant_scale``.
        constant_scale : float or None, default=1.0
            Scale of constant columns.  ``None`` uses the detection threshold
            ``rtol * max|x|``: labels use it, so that a constant label is
            predicted as its value (to ``rtol``) whatever the network outputs.

        Returns
        -------
        Standardizer

        Raises
        ------
        DimensionError
            If ``x`` is not 2-D with at least one row.
        DataError
            If ``x`` holds NaN or inf.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[0] < 1:
            raise DimensionError(f"x must have shape (n_records, n_features); got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise DataError("x contains NaN or inf; cannot fit a standardizer")
        mean = x.mean(axis=0)
        std = x.std(axis=0)
        tiny = rtol * float(np.max(np.abs(x))) if x.size else 0.0
        if constant_scale is None:  # the detection threshold itself: rounding noise stays small
            constant_scale = tiny if tiny > 0 else 1.0
        std = np.where(std > tiny, std, constant_scale)
        return cls(mean, std)

    def _check(self, x: ArrayLike) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=float)
        if x.shape[-1:] != (self.n_features,):
            raise DimensionError(
                f"x has {x.shape[-1] if x.ndim else 0} features but the standardizer was fitted "
                f"with {self.n_features}"
            )
        return x

    def transform(self, x: ArrayLike) -> NDArray[np.float64]:
        """Normalise: ``(x - mean) / scale`` along the last axis."""
        return (self._check(x) - self.mean) / self.scale

    def inverse_transform(self, z: ArrayLike) -> NDArray[np.float64]:
        """Undo :meth:`transform`: ``z * scale + mean`` along the last axis."""
        return self._check(z) * self.scale + self.mean

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-ready dictionary ``{'mean': [...], 'scale': [...]}`` (exact float round trip)."""
        return {"mean": self.mean.tolist(), "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Standardizer:
        """Rebuild a standardizer written by :meth:`to_dict`.

        Raises
        ------
        DataError
            If a key is missing or the values are invalid.
        """
        try:
            mean, scale = data["mean"], data["scale"]
            return cls(np.asarray(mean, dtype=float), np.asarray(scale, dtype=float))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"invalid standardizer data: {exc}") from None


# =========================================================================== training loop
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
    seed = _seed(random_state)
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
