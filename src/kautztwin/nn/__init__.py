"""Neural estimators on PyTorch: the paper's network, its training loop and the estimator.

Importing this subpackage imports torch (``import kautztwin`` alone does not).
Install it with ``pip install 'kautztwin[nn]'``.
"""

from __future__ import annotations

try:
    import torch as _torch  # noqa: F401 - fail early with an actionable message
except ImportError as _exc:  # pragma: no cover - depends on the environment
    raise ImportError(
        "kautztwin.nn needs PyTorch, which is not installed: pip install 'kautztwin[nn]'"
    ) from _exc

from .estimator import CoefficientEstimator
from .networks import PaperNetwork, paper_parameter_count
from .plots import plot_history
from .training import (
    PRESETS,
    Standardizer,
    TrainingConfig,
    TrainingHistory,
    fit_network,
    split_indices,
)

__all__ = [
    "CoefficientEstimator",
    "PRESETS",
    "PaperNetwork",
    "Standardizer",
    "TrainingConfig",
    "TrainingHistory",
    "fit_network",
    "paper_parameter_count",
    "plot_history",
    "split_indices",
]
