"""The amortised estimator: one pole network for stable systems up to an order, VARPRO on top.

Modules: ``systems`` (random stable systems on a normalised time axis, the training
draws), ``network`` (record features to second-order blocks, the differentiable basis),
``training`` (end to end on the fit of the noise-free responses), ``estimator``
(:class:`AmortisedEstimator`: fit, estimate, refine, files) and ``pretrained`` (the
shipped model's folder, package data: :meth:`AmortisedEstimator.load_default`).
"""

from __future__ import annotations

from .estimator import AmortisedEstimate, AmortisedEstimator
from .network import AmortisedPoleNetwork
from .systems import SystemDraws, random_systems

__all__ = [
    "AmortisedEstimate",
    "AmortisedEstimator",
    "AmortisedPoleNetwork",
    "SystemDraws",
    "random_systems",
]
