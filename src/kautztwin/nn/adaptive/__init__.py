"""Adaptive-pole estimator: a network predicts the Kautz poles, least squares the coefficients.

With a fixed basis no estimator can do better than the projection of the
noise-free response onto that basis; for a system with large parameter
uncertainty that ceiling is low (about 69 % mean fit for the paper's system
under +-50 %).  :class:`AdaptivePoleEstimator` removes the ceiling: a network
reads the record and predicts the basis *poles* of that record, kept stable
by construction (a correction stage then adjusts them from the residual of
the fit, a learned Gauss-Newton step), and the coefficients are the
least-squares projection of the record onto the predicted basis (under the
relative degree read from the training records: for a system without zeros the
fit keeps the first Markov parameters at zero, which keeps noise out of those
coefficient directions).  Every step
is differentiable (:mod:`kautztwin.nn.kautz_torch`), so the network is trained
end to end on the error of the fitted response against the noise-free one.
An optional variable-projection refinement (:func:`kautztwin.optimize_poles`, or its
constrained counterpart) starts from the network's poles.  The network is trained in
float32 and kept in float64 once fitted: every prediction runs in float64.

Modules, one job each:

- :mod:`~kautztwin.nn.adaptive.network`: the pole-predicting network
  (:class:`AdaptivePoleNetwork`);
- :mod:`~kautztwin.nn.adaptive.training`: options, structure, feature subspace and the
  stage-wise training (:data:`DEFAULT_ADAPTIVE_CONFIG`);
- :mod:`~kautztwin.nn.adaptive.inference`: network poles, variable-projection refinement,
  least-squares coefficients and responses;
- :mod:`~kautztwin.nn.adaptive.files`: ``save`` and ``load``;
- :mod:`~kautztwin.nn.adaptive.estimator`: :class:`AdaptivePoleEstimator`, the facade.
"""

from __future__ import annotations

from .estimator import AdaptivePoleEstimator
from .network import AdaptivePoleNetwork
from .training import DEFAULT_ADAPTIVE_CONFIG

__all__ = ["AdaptivePoleEstimator", "AdaptivePoleNetwork", "DEFAULT_ADAPTIVE_CONFIG"]
