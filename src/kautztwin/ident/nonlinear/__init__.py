"""Nonlinear Kautz models: Wiener, Hammerstein, Wiener-Hammerstein and Kautz-Volterra.

A discrete Kautz filter bank (:mod:`.filters`) carries the dynamics; static maps
(:mod:`.maps`: polynomials, small MLPs) carry the nonlinearity.  Structures whose map is
linear in its parameters (Kautz-Volterra, polynomial Hammerstein and Wiener) are fitted by
variable projection (:mod:`.varpro`, numpy/scipy only); the MLP structures by gradient
descent through the filter recursion (:mod:`.training`, torch, imported only when used).
:func:`identify_nonlinear` (:mod:`.selection`) chooses structure and order by block
cross-validation and averages the fold models; the fitted models (:mod:`.model`) simulate
with numpy alone and save to JSON.  :func:`choose_model_class` (:mod:`.choice`) decides
between a linear model already identified and these models on held-out data: the default of
``kautztwin identify``.
"""

from __future__ import annotations

from .choice import ModelClassChoice, choose_model_class
from .filters import filter_bank_states
from .maps import MLPMap, PolynomialMap
from .model import NonlinearKautzEnsemble, NonlinearKautzModel, load_nonlinear_model
from .selection import NonlinearFit, identify_nonlinear
from .training import TorchOptions

__all__ = [
    "MLPMap",
    "ModelClassChoice",
    "NonlinearFit",
    "NonlinearKautzEnsemble",
    "NonlinearKautzModel",
    "PolynomialMap",
    "TorchOptions",
    "choose_model_class",
    "filter_bank_states",
    "identify_nonlinear",
    "load_nonlinear_model",
]
