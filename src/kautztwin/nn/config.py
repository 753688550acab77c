"""Training options and outcomes: ``TrainingConfig`` (presets, fine-tuning), ``TrainingHistory``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from .._validation import check_int, check_nonnegative, check_positive
from ..exceptions import DataError

__all__ = ["PRESETS", "TrainingConfig", "TrainingHistory", "fine_tune_config"]

#: Names accepted by :meth:`TrainingConfig.preset`.
PRESETS: tuple[str, ...] = ("default", "paper")
# default fine-tuning run (the estimators' fine_tune): a share of the epochs and of the
# learning rate of the original configuration
_FINE_TUNE_EPOCHS = 0.25
_FINE_TUNE_LEARNING_RATE = 1.0 / 3.0


def _check_validation_fraction(value: Any) -> float:
    """Return ``validation_fraction`` as a float in ``(0, 1)``, or raise :class:`DataError`."""
    try:
        f = float(value)
    except (TypeError, ValueError) as exc:
        raise DataError(
            f"validation_fraction must be a number in (0, 1), got {value!r}"
        ) from exc
    if not 0.0 < f < 1.0:
        raise DataError(f"validation_fraction must lie in (0, 1), got {value!r}")
    return f


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
        set_(self, "learning_rate", check_positive(self.learning_rate, "learning_rate"))
        set_(self, "max_epochs", check_int(self.max_epochs, "max_epochs", minimum=1))
        set_(self, "batch_size", check_int(self.batch_size, "batch_size", minimum=1))
        if self.grad_clip is not None:
            set_(self, "grad_clip", check_positive(self.grad_clip, "grad_clip"))
        if self.patience is not None:
            set_(self, "patience", check_int(self.patience, "patience", minimum=1))
        set_(self, "weight_decay", check_nonnegative(self.weight_decay, "weight_decay"))
        vf = _check_validation_fraction(self.validation_fraction)
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



def fine_tune_config(
    base: TrainingConfig, config: TrainingConfig | Mapping[str, Any] | None
) -> TrainingConfig:
    """Configuration of a fine-tuning run from the original one (the estimators' ``fine_tune``).

    ``None``: ``base`` with a quarter of its epochs (rounded up) and a third of its
    learning rate; a mapping overrides fields of that default; a ``TrainingConfig``
    is used as it is.
    """
    if isinstance(config, TrainingConfig):
        return config
    default = base.replace(
        max_epochs=math.ceil(base.max_epochs * _FINE_TUNE_EPOCHS),
        learning_rate=base.learning_rate * _FINE_TUNE_LEARNING_RATE,
    )
    if config is None:
        return default
    if not isinstance(config, Mapping):
        raise DataError(
            "config must be a TrainingConfig, a mapping of option overrides or None; "
            f"got {type(config).__name__}"
        )
    return default.replace(**dict(config))
