"""Training-curve plot (the paper's Figure 7); matplotlib is imported inside the function."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..exceptions import DataError
from .training import TrainingHistory

if TYPE_CHECKING:  # pragma: no cover - typing only
    from matplotlib.axes import Axes

__all__ = ["plot_history"]


def plot_history(
    history: TrainingHistory, ax: Axes | None = None, *, label: str | None = None, log: bool = True
) -> Axes:
    """Plot the training and validation loss of one training run against the epoch.

    Parameters
    ----------
    history : TrainingHistory
        Result of :func:`~kautztwin.nn.fit_network`, e.g. an entry of
        ``CoefficientEstimator.histories_``.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure when ``None``.
    label : str, optional
        Prefix of the legend entries (e.g. ``'c1'``).
    log : bool, default=True
        Logarithmic loss axis.

    Returns
    -------
    matplotlib.axes.Axes

    Raises
    ------
    DataError
        If ``history`` is not a :class:`TrainingHistory`.

    Examples
    --------
    >>> from kautztwin.nn import TrainingHistory, plot_history
    >>> h = TrainingHistory([1.0, 0.5, 0.3], [1.1, 0.6, 0.7], best_epoch=1, seconds=0.1,
    ...                     stopped_early=False)
    >>> ax = plot_history(h)
    >>> [line.get_label() for line in ax.get_lines()]
    ['training', 'validation', 'best epoch']
    """
    from ..plotting import _axes

    if not isinstance(history, TrainingHistory):
        raise DataError(f"history must be a TrainingHistory, got {type(history).__name__}")
    ax = _axes(ax)
    prefix = f"{label} " if label else ""
    epochs = np.arange(1, history.n_epochs + 1)
    ax.plot(epochs, history.train_loss, label=f"{prefix}training")
    if history.val_loss:
        ax.plot(
            np.arange(1, len(history.val_loss) + 1), history.val_loss, label=f"{prefix}validation"
        )
    if history.n_epochs:
        ax.axvline(history.best_epoch + 1, color="0.5", linestyle=":", label=f"{prefix}best epoch")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (MSE, normalised)")
    ax.set_title("training progress")
    ax.legend()
    return ax
