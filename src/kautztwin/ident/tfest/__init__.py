r"""Continuous-time transfer-function estimation from sampled records (MATLAB ``tfest``'s job).

The model of record :math:`r` is

.. math::

    y_r(t) = o_r + \big[G(s)\,e^{-\tau s}\big]\big(u_r - u_{r,\mathrm{before}}\big)(t)
             + \text{free response}_r(t) + e_r(t),\qquad
    G(s) = \frac{b_m s^m + \dots + b_0}{s^n + a_{n-1}s^{n-1} + \dots + a_0},

with one offset :math:`o_r` per record, an optional initial state (for
input/output records) and a shared :math:`G` and delay :math:`\tau`.  The
parameters minimise the *simulation* (output) error over all records.

Method (see ``docs/identification.md``):

1. **Initialisation** from an orthonormal-basis regression.  Step and impulse
   records are normalised to unit responses and given to
   :func:`kautztwin.optimize_poles` (variable projection on a Kautz basis) with
   ``N = n`` functions, and with ``N = n + 2`` followed by balanced truncation
   to order ``n``.  Input/output records are first regressed on a Laguerre
   basis (best pole from a grid); that model's impulse response goes to
   :func:`~kautztwin.optimize_poles`, and the model itself is reduced by
   balanced truncation.  Each candidate set of poles is one start.
2. **Output-error refinement** by variable projection: the output is linear in
   the numerator, the offsets and the initial states, which are solved by
   linear least squares for every denominator (and delay); only the
   denominator and the delay are searched, by bounded nonlinear least squares.
   The denominator is a product of factors :math:`s^2 + e^{\theta_1}s + e^{\theta_2}`
   (and :math:`s + e^{\theta}` for odd orders), so every iterate is stable,
   real poles and complex pairs alike, without fixing which is which.
3. **Uncertainty**: :math:`\operatorname{cov} = \hat\sigma^2 (J^TJ)^{-1}`, with
   :math:`J` the Jacobian of the residual with respect to all parameters
   (numerator, denominator, delay, offsets, initial states) at the optimum and
   :math:`\hat\sigma^2 = \mathrm{RSS}/(N - p)`.

Simulation is exact for the chosen intersample behaviour (``'zoh'`` or
``'foh'``), on any grid, with any delay; step and impulse records use ideal
steps and impulses (:mod:`kautztwin.ident.simulate`).

The package, one job per module: :mod:`.model` (the result,
:class:`TransferFunctionModel`), :mod:`.problem` (the stable denominator
parameterisation and the variable-projection problem), :mod:`.starts`
(initial poles from orthonormal-basis regressions), :mod:`.refine` (the
multi-start output-error refinement of one order), :mod:`.statistics`
(covariance, fits, AIC, validation), :mod:`.structure` (the structure search
of ``n_poles='auto'``), :mod:`.integrator` (integrating models ``G(s)/s``,
fitted as ``G`` on the integrated input) and :mod:`.estimator`
(:class:`TransferFunctionEstimator`: parameters, order selection, prediction).
"""

from __future__ import annotations

from .estimator import TransferFunctionEstimator
from .model import TransferFunctionModel

__all__ = ["TransferFunctionEstimator", "TransferFunctionModel"]
