"""The pole-predicting network: record to poles to basis to least-squares fit, differentiable."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike
from torch import nn

from ..kautz_torch import (
    kautz_functions,
    lstsq_coefficients,
    network_matrices,
    propagate,
    relative_degree_constraints,
)

__all__ = ["RECORD_BATCH", "TRAINING_DTYPE", "AdaptivePoleNetwork"]

#: Dtype the network is trained in (the fitted estimator predicts in float64).
TRAINING_DTYPE = torch.float32

#: Records per batch when the network is applied without gradients (prediction, stage
#: inputs): small blocks stay in cache.
RECORD_BATCH = 256


class _Stage(nn.Module):
    """Standardisation followed by a SiLU perceptron whose last layer starts at zero."""

    def __init__(self, n_in: int, hidden: tuple[int, ...], n_out: int, dtype: torch.dtype) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(n_in, dtype=dtype))
        self.register_buffer("scale", torch.ones(n_in, dtype=dtype))
        layers: list[nn.Module] = []
        fan_in = n_in
        for width in hidden:
            layers += [nn.Linear(fan_in, width, dtype=dtype), nn.SiLU()]
            fan_in = width
        last = nn.Linear(fan_in, n_out, dtype=dtype)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        layers.append(last)
        self.body = nn.Sequential(*layers)

    def set_normalization(self, mean: ArrayLike, scale: ArrayLike) -> None:
        with torch.no_grad():
            self.mean.copy_(torch.as_tensor(np.array(mean, dtype=float)))
            self.scale.copy_(torch.as_tensor(np.array(scale, dtype=float)))

    def forward(self, inp: torch.Tensor) -> torch.Tensor:
        return self.body((inp - self.mean) / self.scale)


class AdaptivePoleNetwork(nn.Module):
    r"""Record to poles to basis to least-squares fit, differentiable end to end.

    1. **Features.**  The record :math:`y` is projected onto a fixed
       orthonormal subspace :math:`V` (``projector``, the principal subspace
       of noise-free training responses) and normalised to unit length,
       :math:`z = V^T y / \|V^T y\|` (the poles do not depend on the gain).
       When every noise-free response lies in :math:`\mathrm{span}\,V`, the
       coordinates :math:`V^T y` are a sufficient statistic of the record
       under white noise: nothing useful is lost, and the noise outside the
       subspace is discarded.
    2. **Poles.**  Stage 0, a perceptron, maps :math:`z` to one number
       :math:`u` per block parameter (rates, ``sigma``, ``omega``):

       .. math:: \log\theta = \log\theta_0 + \rho\,\tanh u ,

       so every parameter is positive (a stable basis by construction) and
       stays within a factor :math:`e^{\rho}` (``pole_range``) of the centre
       :math:`\theta_0`.
    3. **Corrections.**  Each further stage sees what the current poles leave
       unexplained: the least-squares fit :math:`\hat y` of the record on the
       current basis, the residual coordinates
       :math:`V^T(y - \hat y) / \|V^T y\|`, the coefficients and the current
       parameters, and adds a bounded correction
       :math:`\Delta = \delta \tanh u` to :math:`\log\theta` (clamped to the
       pole range).  This is a learned Gauss-Newton step: to first order the
       residual is the Jacobian of the fit times the pole error.
    4. **Coefficients.**  The Kautz functions of the final poles
       (:func:`~kautztwin.nn.kautz_torch.kautz_functions`, or their step
       responses) and the weighted least-squares coefficients of the record
       in them (:func:`~kautztwin.nn.kautz_torch.lstsq_coefficients`), under the
       constraints of the relative degree :math:`r` when :math:`r > 1`
       (:func:`~kautztwin.nn.kautz_torch.relative_degree_constraints`: the model's
       first :math:`r - 1` Markov parameters vanish, so the fit spends
       :math:`r - 1` fewer coefficients on the noise).

    Every last layer starts at zero: an untrained network predicts the centre.

    Parameters
    ----------
    kinds : sequence of {'real', 'pair'}
        Block structure of the predicted basis.
    centre : array-like of shape (n_params,)
        Centre block parameters :math:`\theta_0` (rates, ``sigma, omega``), all ``> 0``.
    t : array-like of shape (n_samples,)
        The time grid of the records.
    projector : array-like of shape (n_samples, n_features)
        Orthonormal columns spanning the feature subspace.
    hidden : sequence of int, default=(256, 256, 256)
        Hidden layer widths of every stage (SiLU activations).
    n_stages : int, default=2
        Stage 0 plus ``n_stages - 1`` correction stages.
    pole_range : float, default=10.0
        :math:`e^{\rho}`: each parameter stays within this factor of the centre.
    step : float, default=0.5
        :math:`\delta`, the largest change of a log-parameter per correction stage.
    weights : array-like of shape (n_samples,), optional
        Least-squares weights of the samples; default ones (ordinary least squares).
    kind : {'impulse', 'step'}, default='impulse'
        What the records are.
    dtype : torch.dtype, default=torch.float32
        Dtype of the weights and the computation.
    relative_degree : int, default=1
        Relative degree imposed on the fitted models (``1``: none).

    Attributes
    ----------
    kinds : tuple of str
        The block structure.
    stages : torch.nn.ModuleList
        The perceptrons, stage 0 first; each standardises its input with the
        buffers ``mean`` and ``scale`` set by the estimator.
    n_functions : int
        Number of basis functions (equal to the number of block parameters).

    See Also
    --------
    AdaptivePoleEstimator : Builds, trains and applies this module.
    """

    def __init__(
        self,
        kinds: Sequence[str],
        centre: ArrayLike,
        t: ArrayLike,
        projector: ArrayLike,
        *,
        hidden: Sequence[int] = (256, 256, 256),
        n_stages: int = 2,
        pole_range: float = 10.0,
        step: float = 0.5,
        weights: ArrayLike | None = None,
        kind: str = "impulse",
        dtype: torch.dtype = TRAINING_DTYPE,
        relative_degree: int = 1,
    ) -> None:
        super().__init__()
        self.relative_degree = int(relative_degree)
        self.kinds = tuple(str(k) for k in kinds)
        self.kind = str(kind)
        centre = np.asarray(centre, dtype=float)
        t = np.array(t, dtype=float)
        projector = np.asarray(projector, dtype=float)
        self.n_functions = int(centre.size)
        self.hidden = tuple(int(h) for h in hidden)
        self.n_stages = int(n_stages)
        self.pole_range = float(pole_range)
        self.step = float(step)
        self._t = t.copy()
        self.register_buffer("t", torch.from_numpy(t))
        self.register_buffer("projector", torch.as_tensor(projector, dtype=dtype))
        self.register_buffer("log_centre", torch.as_tensor(np.log(centre), dtype=dtype))
        w = np.ones(t.size) if weights is None else np.asarray(weights, dtype=float)
        self.register_buffer("weights", torch.as_tensor(w, dtype=dtype))
        m, n = projector.shape[1], self.n_functions
        sizes = [m] + [2 * m + 2 * n] * (self.n_stages - 1)
        self.stages = nn.ModuleList(_Stage(k, self.hidden, n, dtype) for k in sizes)

    def cast(self, dtype: torch.dtype) -> AdaptivePoleNetwork:
        """Cast the weights and buffers to ``dtype`` in place; the time grid stays float64.

        The estimator trains in ``float32`` (:data:`TRAINING_DTYPE`) and predicts in
        ``float64``: casting ``float32`` weights to ``float64`` is exact, and the
        ``float64`` evaluation is the one other implementations (the ONNX graph) can
        reproduce to rounding.

        Parameters
        ----------
        dtype : torch.dtype

        Returns
        -------
        AdaptivePoleNetwork
            ``self``.
        """
        t = self.t
        self.to(dtype)
        self.t = t
        for name, buf in self._buffers.items():  # one memory layout: the same rounding as
            if buf is not None:  # a module loaded from a file (load_state_dict copies)
                self._buffers[name] = buf.contiguous()
        return self

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of the weights and the computation."""
        return self.projector.dtype

    def _load_from_state_dict(self, state_dict: Any, prefix: str, *args: Any) -> None:
        super()._load_from_state_dict(state_dict, prefix, *args)
        self._t = self.t.detach().cpu().numpy().copy()

    def ls_weights(self) -> torch.Tensor | None:
        """Least-squares weights of the samples.

        Returns
        -------
        torch.Tensor of shape (n_samples,) or None
            ``None`` when all weights are one (ordinary least squares), which
            skips a multiplication per basis function.
        """
        w = self.weights
        return None if bool(torch.all(w == 1)) else w

    def constraints(
        self, params: torch.Tensor, relative_degree: int | None = None
    ) -> torch.Tensor | None:
        """Constraints of the relative degree on the coefficients, ``None`` without one.

        Parameters
        ----------
        params : torch.Tensor of shape (batch, n_params)
            Block parameters.
        relative_degree : int, optional
            Another degree than the module's own (the estimator's final fit may drop it).

        Returns
        -------
        torch.Tensor of shape (batch, n_functions, relative_degree - 1) or None
            :func:`~kautztwin.nn.kautz_torch.relative_degree_constraints` of the
            parameters' realisation; ``None`` when ``relative_degree == 1``.
        """
        r = self.relative_degree if relative_degree is None else int(relative_degree)
        if r <= 1:
            return None
        A, B = network_matrices(self.kinds, params)
        return relative_degree_constraints(A, B, r)

    def least_squares(
        self,
        K: torch.Tensor,
        x: torch.Tensor,
        params: torch.Tensor,
        weights: torch.Tensor | None = None,
        relative_degree: int | None = None,
    ) -> torch.Tensor:
        """Least-squares coefficients of records on their bases, under the relative degree.

        Parameters
        ----------
        K : torch.Tensor of shape (batch, n_functions, n_samples)
            Basis signals (:meth:`design` of ``params``).
        x : torch.Tensor of shape (batch, n_samples)
            Records.
        params : torch.Tensor of shape (batch, n_params)
            Block parameters of ``K`` (for the constraints).
        weights : torch.Tensor of shape (n_samples,), optional
            Least-squares weights; default ones.
        relative_degree : int, optional
            Another degree than the module's own (:meth:`constraints`).

        Returns
        -------
        torch.Tensor of shape (batch, n_functions)
        """
        M = self.constraints(params, relative_degree)
        return lstsq_coefficients(K, x, weights, constraints=M)

    def coordinates(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r"""Unit-length coordinates of the records in the feature subspace, and their norms.

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_samples)

        Returns
        -------
        z : torch.Tensor of shape (batch, n_features)
            :math:`V^T x / \|V^T x\|`.
        norm : torch.Tensor of shape (batch, 1)
            :math:`\|V^T x\|`.
        """
        z = x @ self.projector
        norm = z.norm(dim=1, keepdim=True).clamp_min(torch.finfo(z.dtype).tiny)
        return z / norm, norm

    def _bound(self, log_params: torch.Tensor) -> torch.Tensor:
        rho = math.log(self.pole_range)
        return torch.minimum(
            torch.maximum(log_params, self.log_centre - rho), self.log_centre + rho
        )

    def initial(self, z: torch.Tensor) -> torch.Tensor:
        """Stage 0: log block parameters from unit-length coordinates.

        Parameters
        ----------
        z : torch.Tensor of shape (batch, n_features)

        Returns
        -------
        torch.Tensor of shape (batch, n_params)
        """
        return self.log_centre + math.log(self.pole_range) * torch.tanh(self.stages[0](z))

    def stage_input(
        self, x: torch.Tensor, z: torch.Tensor, norm: torch.Tensor, log_params: torch.Tensor
    ) -> torch.Tensor:
        """Input of a correction stage: what the current poles leave unexplained.

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_samples)
            Records.
        z, norm : torch.Tensor
            Output of :meth:`coordinates`.
        log_params : torch.Tensor of shape (batch, n_params)
            Current log block parameters.

        Returns
        -------
        torch.Tensor of shape (batch, 2 n_features + 2 n_functions)
            ``[z, residual coordinates, log_params - log_centre, coefficients / norm]``.
        """
        params = torch.exp(log_params)
        K = self.design(params)
        c = self.least_squares(K, x, params, self.ls_weights())
        fitted = (c[:, None, :] @ K)[:, 0]
        residual = ((x - fitted) @ self.projector) / norm
        return torch.cat([z, residual, log_params - self.log_centre, c / norm], dim=1)

    def correct(self, k: int, inp: torch.Tensor, log_params: torch.Tensor) -> torch.Tensor:
        """Correction stage ``k >= 1``: new log block parameters.

        Parameters
        ----------
        k : int
            Stage number.
        inp : torch.Tensor of shape (batch, 2 n_features + 2 n_functions)
            Output of :meth:`stage_input`.
        log_params : torch.Tensor of shape (batch, n_params)
            Current log block parameters.

        Returns
        -------
        torch.Tensor of shape (batch, n_params)
        """
        return self._bound(log_params + self.step * torch.tanh(self.stages[k](inp)))

    def log_params(self, x: torch.Tensor, n_stages: int | None = None) -> torch.Tensor:
        """Log block parameters after the first ``n_stages`` stages (default all).

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_samples)
        n_stages : int, optional

        Returns
        -------
        torch.Tensor of shape (batch, n_params)
        """
        z, norm = self.coordinates(x)
        out = self.initial(z)
        for k in range(1, self.n_stages if n_stages is None else n_stages):
            out = self.correct(k, self.stage_input(x, z, norm, out), out)
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Predict the block parameters of a batch of records.

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_samples)
            Records on the grid ``t``.

        Returns
        -------
        torch.Tensor of shape (batch, n_params)
            Positive block parameters (rates; ``sigma, omega`` of pairs).
        """
        return torch.exp(self.log_params(x))

    def design(self, params: torch.Tensor) -> torch.Tensor:
        """Basis signals the records are combinations of, for a batch of parameters.

        Parameters
        ----------
        params : torch.Tensor of shape (batch, n_params)

        Returns
        -------
        torch.Tensor of shape (batch, n_functions, n_samples)
            Kautz functions (impulse records) or their step responses
            :math:`A^{-1}(e^{At} - I) B` (step records).
        """
        if self.kind == "impulse":
            return kautz_functions(self.kinds, params, self._t)
        A, B = network_matrices(self.kinds, params)
        K = propagate(A, B, self._t)
        return torch.linalg.solve(A, K - B[:, :, None])

    def fit_records(
        self, x: torch.Tensor, params: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Poles, least-squares coefficients and fitted responses of a batch of records.

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_samples)
        params : torch.Tensor of shape (batch, n_params), optional
            Block parameters to use instead of the network's prediction.

        Returns
        -------
        params : torch.Tensor of shape (batch, n_params)
        coefficients : torch.Tensor of shape (batch, n_functions)
        fitted : torch.Tensor of shape (batch, n_samples)
            ``coefficients @ design(params)``.
        """
        if params is None:
            params = self(x)
        K = self.design(params)
        c = self.least_squares(K, x, params, self.ls_weights())
        fitted = (c[:, None, :] @ K)[:, 0]
        return params, c, fitted

    def extra_repr(self) -> str:
        """Summary shown by ``repr(module)``."""
        return (
            f"kinds={self.kinds}, kind={self.kind!r}, n_samples={self._t.size}, "
            f"n_features={self.projector.shape[1]}, n_stages={self.n_stages}, "
            f"pole_range={self.pole_range:g}, step={self.step:g}, "
            f"relative_degree={self.relative_degree}"
        )
