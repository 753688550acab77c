"""The paper's estimator: Kautz coefficients in a fixed basis, one network per coefficient.

Modules, one job each: :mod:`~kautztwin.nn.coefficient.training` (split, standardise, one
:func:`~kautztwin.nn.fit_network` run per target), :mod:`~kautztwin.nn.coefficient.files`
(``save`` and ``load``) and :mod:`~kautztwin.nn.coefficient.estimator`
(:class:`CoefficientEstimator`, the facade).  The network is :class:`~kautztwin.nn.PaperNetwork`.
"""

from __future__ import annotations

from .estimator import CoefficientEstimator

__all__ = ["CoefficientEstimator"]
