"""Neural estimators on PyTorch: the paper's network, its training loop and the estimators.

Modules: ``networks`` (the paper's network), ``config`` (training options and loss curves),
``data`` (split and standardisation), ``training`` (the loop ``fit_network``),
``coefficient`` (:class:`CoefficientEstimator`: training, files, estimator), ``adaptive``
(:class:`AdaptivePoleEstimator`: network, training, inference, files, estimator), and what
both estimators share: ``estimator_base`` (parameters, checks) and ``model_files`` (save/load).
``uncertainty`` gives every adaptive estimate a calibrated band (:class:`ResponseEstimate`),
and ``family`` trains an estimator for a plant family (``kautztwin train --family``).

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

from .adaptive import DEFAULT_ADAPTIVE_CONFIG, AdaptivePoleEstimator, AdaptivePoleNetwork
from .coefficient import CoefficientEstimator
from .config import PRESETS, TrainingConfig, TrainingHistory
from .data import Standardizer, split_indices
from .family import PlantFamily, train_family
from .networks import PaperNetwork, paper_parameter_count
from .oracle import OracleFit, oracle_fit, simulate_parametric
from .plots import plot_history
from .training import fit_network
from .uncertainty import ResponseEstimate

__all__ = [
    "DEFAULT_ADAPTIVE_CONFIG",
    "AdaptivePoleEstimator",
    "AdaptivePoleNetwork",
    "CoefficientEstimator",
    "OracleFit",
    "PRESETS",
    "PaperNetwork",
    "PlantFamily",
    "ResponseEstimate",
    "Standardizer",
    "TrainingConfig",
    "TrainingHistory",
    "fit_network",
    "oracle_fit",
    "paper_parameter_count",
    "plot_history",
    "simulate_parametric",
    "split_indices",
    "train_family",
]
