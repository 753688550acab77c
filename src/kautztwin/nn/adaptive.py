"""Adaptive-pole estimator: a network predicts the Kautz poles, least squares the coefficients.

With a fixed basis no estimator can do better than the projection of the
noise-free response onto that basis; for a system with large parameter
uncertainty that ceiling is low (about 69 % mean fit for the paper's system
under +-50 %).  :class:`AdaptivePoleEstimator` removes the ceiling: a network
reads the record and predicts the basis *poles* of that record, kept stable
by construction (a correction stage then adjusts them from the residual of
the fit, a learned Gauss-Newton step), and the coefficients are the
least-squares projection of the record onto the predicted basis.  Every step
is differentiable (:mod:`kautztwin.nn.kautz_torch`), so the network is trained
end to end on the error of the fitted response against the noise-free one.
An optional variable-projection refinement (:func:`kautztwin.optimize_poles`)
starts from the network's poles.
"""

from __future__ import annotations

import copy
import functools
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import nn

from ..approx import KautzModel, optimize_poles
from ..basis import KautzBasis
from ..basis._blocks import PAIR, REAL, parse_poles
from ..datasets import ParametricSystem, ResponseDataset, draw_parameters, make_dataset
from ..exceptions import (
    ConvergenceWarning,
    DataError,
    KautzTwinError,
    NotFittedError,
)
from ..metrics import fit_percent
from .estimator import (
    _check_fine_tune_data,
    _check_seed,
    _checked_records,
    _fine_tune_config,
    _grid_hash,
    _load_verified,
    _ParamsMixin,
    _save_verified,
)
from .kautz_torch import (
    block_poles,
    kautz_functions,
    lstsq_coefficients,
    network_matrices,
    propagate,
    response_weights,
)
from .training import Standardizer, TrainingConfig, TrainingHistory, fit_network, split_indices

__all__ = ["AdaptivePoleEstimator", "AdaptivePoleNetwork", "DEFAULT_ADAPTIVE_CONFIG"]

_FORMAT = "kautztwin.AdaptivePoleEstimator"
_FORMAT_VERSION = 1
_WEIGHTS = "weights.pt"
_METADATA = "metadata.json"
_PREDICT_BATCH = 256  # records per batch at prediction: small blocks stay in cache
_PCA_RECORDS = 4000  # clean training records used for the feature subspace
_GRID_RTOL = 1e-9

#: Training configuration used when ``config`` is ``None`` (tuned on the paper's
#: system under +-50 % uncertainty; see ``benchmarks/bench_adaptive.py``).
DEFAULT_ADAPTIVE_CONFIG = TrainingConfig(
    learning_rate=3e-4, max_epochs=6, batch_size=256, grad_clip=1.0, patience=3
)


# =========================================================================== module
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
       in them (:func:`~kautztwin.nn.kautz_torch.lstsq_coefficients`).

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
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
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
        K = self.design(torch.exp(log_params))
        c = lstsq_coefficients(K, x, self.ls_weights())
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
        c = lstsq_coefficients(K, x, self.ls_weights())
        fitted = (c[:, None, :] @ K)[:, 0]
        return params, c, fitted

    def extra_repr(self) -> str:
        """Summary shown by ``repr(module)``."""
        return (
            f"kinds={self.kinds}, kind={self.kind!r}, n_samples={self._t.size}, "
            f"n_features={self.projector.shape[1]}, n_stages={self.n_stages}, "
            f"pole_range={self.pole_range:g}, step={self.step:g}"
        )


def _nrmse(
    module: AdaptivePoleNetwork,
    x: torch.Tensor,
    clean: torch.Tensor,
    spread: torch.Tensor,
    log_params: torch.Tensor,
) -> torch.Tensor:
    """Mean of ``||clean - fitted|| / ||clean - mean(clean)||`` (= 1 - fit/100)."""
    _, _, fitted = module.fit_records(x, torch.exp(log_params))
    return ((clean - fitted).norm(dim=1) / spread).mean()


def _initial_fit_loss(module: nn.Module, batch: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """End-to-end loss of stage 0: batch ``(x, clean, spread, z)``."""
    x, clean, spread, z = batch
    return _nrmse(module, x, clean, spread, module.initial(z))


def _initial_label_loss(module: nn.Module, batch: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Warm-start loss of stage 0: squared error of the log parameters, batch ``(z, target)``."""
    z, target = batch
    return ((module.initial(z) - target) ** 2).mean()


def _correction_fit_loss(
    k: int, module: nn.Module, batch: tuple[torch.Tensor, ...]
) -> torch.Tensor:
    """End-to-end loss of stage ``k``: batch ``(x, clean, spread, inp, previous)``."""
    x, clean, spread, inp, previous = batch
    return _nrmse(module, x, clean, spread, module.correct(k, inp, previous))


def _correction_label_loss(
    k: int, module: nn.Module, batch: tuple[torch.Tensor, ...]
) -> torch.Tensor:
    """Warm-start loss of stage ``k``: batch ``(inp, previous, target)``."""
    inp, previous, target = batch
    return ((module.correct(k, inp, previous) - target) ** 2).mean()


def _moments(x: torch.Tensor) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean and scale of the columns of ``x`` (a :class:`Standardizer` fit)."""
    scaler = Standardizer.fit(x.double().numpy())
    return scaler.mean, scaler.scale


def _match_labels(
    kinds: tuple[str, ...], centre: NDArray, poles: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """True poles of every record as block parameters of ``kinds``, where they fit.

    Within each kind, blocks and poles are matched in order of rate (real) or
    frequency (pair).  Records whose poles have another real/pair make-up get
    ``valid = False``.
    """
    real_cols, pair_cols = [], []
    col = 0
    for k in kinds:
        if k == REAL:
            real_cols.append(col)
            col += 1
        else:
            pair_cols.append(col)
            col += 2
    real_cols = [real_cols[i] for i in np.argsort([centre[c] for c in real_cols], kind="stable")]
    order = np.argsort([centre[c + 1] for c in pair_cols], kind="stable")
    pair_cols = [pair_cols[i] for i in order]
    out = np.tile(centre, (poles.shape[0], 1))
    valid = np.zeros(poles.shape[0], dtype=bool)
    for i, p in enumerate(poles):
        try:
            got_kinds, params = parse_poles(p, 0.0)
        except KautzTwinError:
            continue
        rates, pairs = [], []
        col = 0
        for k in got_kinds:
            if k == REAL:
                rates.append(params[col])
                col += 1
            else:
                pairs.append((params[col + 1], params[col]))
                col += 2
        if len(rates) != len(real_cols) or len(pairs) != len(pair_cols):
            continue
        for c, r in zip(real_cols, sorted(rates), strict=True):
            out[i, c] = r
        for c, (omega, sigma) in zip(pair_cols, sorted(pairs), strict=True):
            out[i, c], out[i, c + 1] = sigma, omega
        valid[i] = bool(np.all(out[i] > 0))
    return out, valid


# =========================================================================== estimator
def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _spread(clean: NDArray) -> NDArray[np.float64]:
    """Norm of every noise-free record about its mean (the fit's denominator); none may be 0."""
    spread = np.linalg.norm(clean - clean.mean(axis=1, keepdims=True), axis=1)
    if np.any(spread == 0):
        raise DataError(
            f"noise-free record {int(np.argmin(spread))} is constant; the fit is undefined"
        )
    return spread


def _centre_from_kinds(
    kinds: tuple[str, ...], t: NDArray, clean: NDArray, kind: str
) -> NDArray[np.float64]:
    """Centre parameters of a bare block structure: poles fitted to typical noise-free records."""
    H = clean if kind == "impulse" else np.gradient(clean, t, axis=1)
    sig = np.abs(np.mean(H, axis=0))
    centroid = float(np.sum(t * sig) / max(np.sum(sig), 1e-300) - t[0])
    p0 = 1.0 / max(centroid, (t[-1] - t[0]) / t.size)
    poles: list[complex] = []
    n_real = sum(k == REAL for k in kinds)
    r = k_pair = 0
    for k in kinds:
        if k == REAL:
            poles.append(-p0 * 2.0 ** (r - (n_real - 1) / 2))
            r += 1
        else:
            k_pair += 1
            poles += [complex(-p0, p0 * k_pair), complex(-p0, -p0 * k_pair)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = optimize_poles(t, clean[:64], poles, kind=kind, max_iter=50)
    got_kinds, params = parse_poles(res.basis.poles, 0.0)
    if got_kinds != kinds:  # pragma: no cover - parse keeps the structure of the start
        return parse_poles(poles, 0.0)[1]
    return params


class AdaptivePoleEstimator(_ParamsMixin):
    r"""Kautz models with record-specific poles: network poles, least-squares coefficients.

    The network (:class:`AdaptivePoleNetwork`) predicts the poles of the
    basis for each record, stable by construction; the coefficients are the
    least-squares projection of the record onto that basis.  It is trained
    end to end on the fit of the resulting model to the *noise-free*
    responses of the training records, so the poles it learns are the ones
    that make the fitted response closest to the truth, not labels of any
    kind.  Training data are free: :meth:`fit_distribution` draws them from
    the uncertain system.  ``refine=True`` polishes every record's poles by
    variable projection (:func:`kautztwin.optimize_poles`) started from the
    network's output.

    Parameters
    ----------
    structure : array-like of complex, sequence of {'real', 'pair'}, or None, default=None
        Block structure of the predicted basis.  Pole locations fix the
        structure and the centre of the pole range; block kinds fix only the
        structure (the centre is fitted to the training responses); ``None``
        uses the training data set's basis poles (or ``system.poles()`` in
        :meth:`fit_distribution`).
    hidden : sequence of int, default=(256, 256, 256)
        Hidden layer widths of the pole network.
    n_features : int, default=32
        Dimension of the feature subspace (principal subspace of noise-free
        training responses).
    n_stages : int, default=2
        Stage 0 (poles from the record) plus ``n_stages - 1`` correction
        stages (learned Gauss-Newton steps from the residual of the current
        fit; each costs one more basis evaluation).  Every stage is trained
        end to end in turn, the earlier ones frozen.
    pole_range : float, default=10.0
        Each block parameter stays within this factor of the centre.
    step : float, default=0.5
        Largest change of a log block parameter per correction stage.
    weights : {'uniform', 'simpson'}, default='uniform'
        Least-squares weights of the samples: ordinary least squares (the
        maximum-likelihood choice for white noise and the norm of the fit
        percent), or Simpson's rule (the weights of
        :func:`kautztwin.project` with ``method='lstsq'``).
    config : TrainingConfig, mapping, str or None, default=None
        Training options: a full :class:`~kautztwin.nn.TrainingConfig`, a
        mapping of fields to override in :data:`DEFAULT_ADAPTIVE_CONFIG`, the name of a
        preset (:meth:`TrainingConfig.preset`), or ``None`` for
        :data:`DEFAULT_ADAPTIVE_CONFIG`.
    random_state : int, default=0
        Seed of the split, the weights, the shuffles and (in
        :meth:`fit_distribution`) the training data.
    progress : bool, default=False
        Show a progress bar while training.
    refine : bool, default=False
        Refine each record's poles by variable projection after the network
        (:func:`kautztwin.optimize_poles`, about 100x slower than the network).
    refine_max_iter : int, default=50
        ``max_iter`` of the refinement.
    pretrain_epochs : int, default=30
        Warm start before the end-to-end training: at most this many epochs
        of regression of the log block parameters on the records' true poles
        (``dataset.poles``, matched to the blocks by kind and in order of
        rate or frequency; records whose poles do not fit the structure are
        left out).  It costs little (features in, no basis) and shortens the
        end-to-end phase several times.  ``0`` trains end to end from the centre.

    Attributes
    ----------
    network_ : AdaptivePoleNetwork
        The trained module (``eval`` mode).
    histories_ : list of TrainingHistory
        Loss curves of the end-to-end training of each stage (the loss is
        ``1 - fit/100`` of the noise-free responses).
    pretrain_histories_ : list of TrainingHistory
        Loss curves of the warm start of each stage (empty without one).
    kinds_ : tuple of str
        Block structure.
    centre_poles_ : ndarray of complex, shape (n_functions,)
        Poles of the centre of the pole range.
    t_ : ndarray of shape (n_samples,)
        Time grid of the records (read-only).
    kind_ : {'impulse', 'step'}
        What the records are.
    config_ : TrainingConfig
        The configuration used.
    n_samples_, n_functions_ : int
        Samples per record and basis functions.
    n_train_ : int
        Records the network was trained on (training part of the split).

    See Also
    --------
    kautztwin.nn.CoefficientEstimator : The paper's estimator on a fixed basis.
    kautztwin.optimize_poles : Variable projection, the refinement.
    kautztwin.nn.oracle.oracle_fit : The statistical limit used in the benchmark.

    Notes
    -----
    For any fixed poles the least-squares coefficients are optimal, so the
    error of the fitted response has two parts: the distance of the
    noise-free response from the predicted basis' span (the pole error) and
    the noise that the projection lets through (``N`` of the ``n_samples``
    noise dimensions).  The loss is the mean normalised error
    :math:`\|h - \hat h\| / \|h - \bar h\| = 1 - \mathrm{fit}/100` of the
    noise-free response ``h``.

    Each stage is trained in two steps with :func:`~kautztwin.nn.fit_network`:
    a warm start on the true poles (cheap, no basis evaluation) and then the
    end-to-end loss above, which decides.  The correction stage matters at
    low noise, where the fit is limited by how precisely the poles are
    placed: on the paper's system (+-50 % uncertainty, 900 samples) stage 0
    alone reaches a mean fit of about 96.4 % (10 % noise) and 99.15 % (1 %
    noise), two stages about 96.6 % and 99.62 %, against 97.1 % and 99.70 %
    for least squares in the true model structure started at the true
    parameters (``benchmarks/bench_adaptive.py``).  The variable-projection
    refinement finds the least-squares poles of the record itself; at high
    noise that fits more of the noise than the network's estimate does (the
    network has learned the distribution of the poles), so ``refine=True``
    pays off only at low noise or for records unlike the training data.

    Examples
    --------
    >>> import numpy as np
    >>> import torch
    >>> from kautztwin.datasets import paper_system
    >>> from kautztwin.nn.adaptive import AdaptivePoleEstimator
    >>> _ = torch.set_num_threads(1)
    >>> t = np.linspace(0.0, 20.0, 200)
    >>> est = AdaptivePoleEstimator(hidden=(32,), n_features=16, config={"max_epochs": 2})
    >>> est = est.fit_distribution(paper_system(), 0.5, t, noise=0.1, n_train=300)
    >>> poles, coef = est.predict(np.zeros((2, 200)) + np.exp(-t))
    >>> poles.shape, coef.shape, bool(np.all(poles.real < 0))
    ((2, 4), (2, 4), True)
    """

    def __init__(
        self,
        *,
        structure: ArrayLike | Sequence[str] | None = None,
        hidden: Sequence[int] = (256, 256, 256),
        n_features: int = 32,
        n_stages: int = 2,
        pole_range: float = 10.0,
        step: float = 0.5,
        weights: str = "uniform",
        config: TrainingConfig | Mapping[str, Any] | str | None = None,
        random_state: int = 0,
        progress: bool = False,
        refine: bool = False,
        refine_max_iter: int = 50,
        pretrain_epochs: int = 30,
    ) -> None:
        self.structure = structure
        self.hidden = hidden
        self.n_features = n_features
        self.n_stages = n_stages
        self.pole_range = pole_range
        self.step = step
        self.weights = weights
        self.config = config
        self.random_state = random_state
        self.progress = progress
        self.refine = refine
        self.refine_max_iter = refine_max_iter
        self.pretrain_epochs = pretrain_epochs

    # ------------------------------------------------------------------ parameters
    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Constructor parameters (scikit-learn convention)."""
        return {
            "structure": self.structure,
            "hidden": self.hidden,
            "n_features": self.n_features,
            "n_stages": self.n_stages,
            "pole_range": self.pole_range,
            "step": self.step,
            "weights": self.weights,
            "config": self.config,
            "random_state": self.random_state,
            "progress": self.progress,
            "refine": self.refine,
            "refine_max_iter": self.refine_max_iter,
            "pretrain_epochs": self.pretrain_epochs,
        }

    # ------------------------------------------------------------------ validation
    def _resolve_config(self) -> TrainingConfig:
        if isinstance(self.config, TrainingConfig):
            return self.config
        if self.config is None:
            return DEFAULT_ADAPTIVE_CONFIG
        if isinstance(self.config, str):
            return TrainingConfig.preset(self.config)
        if isinstance(self.config, Mapping):
            return DEFAULT_ADAPTIVE_CONFIG.replace(**dict(self.config))
        raise DataError(
            "config must be a TrainingConfig, a mapping of option overrides, a preset name or "
            f"None; got {type(self.config).__name__}"
        )

    def _check_options(self) -> tuple[int, tuple[int, ...], int, int, float, float]:
        if not _is_int(self.random_state) or self.random_state < 0:
            raise DataError(
                f"random_state must be a non-negative integer, got {self.random_state!r}"
            )
        try:
            hidden = tuple(self.hidden)
        except TypeError:
            raise DataError(
                f"hidden must be a sequence of positive integers, got {self.hidden!r}"
            ) from None
        if not all(_is_int(h) and h >= 1 for h in hidden):
            raise DataError(f"hidden must be a sequence of positive integers, got {self.hidden!r}")
        if not _is_int(self.n_features) or self.n_features < 1:
            raise DataError(f"n_features must be a positive integer, got {self.n_features!r}")
        try:
            pole_range = float(self.pole_range)
        except (TypeError, ValueError):
            pole_range = math.nan
        if not (math.isfinite(pole_range) and pole_range > 1.0):
            raise DataError(f"pole_range must be a number > 1, got {self.pole_range!r}")
        if not _is_int(self.n_stages) or self.n_stages < 1:
            raise DataError(f"n_stages must be a positive integer, got {self.n_stages!r}")
        try:
            step = float(self.step)
        except (TypeError, ValueError):
            step = math.nan
        if not (math.isfinite(step) and step > 0.0):
            raise DataError(f"step must be a number > 0, got {self.step!r}")
        if self.weights not in ("uniform", "simpson"):
            raise DataError(f"weights must be 'uniform' or 'simpson', got {self.weights!r}")
        if not _is_int(self.pretrain_epochs) or self.pretrain_epochs < 0:
            raise DataError(
                f"pretrain_epochs must be a non-negative integer, got {self.pretrain_epochs!r}"
            )
        if not _is_int(self.refine_max_iter) or self.refine_max_iter < 1:
            raise DataError(
                f"refine_max_iter must be a positive integer, got {self.refine_max_iter!r}"
            )
        return (
            int(self.random_state),
            hidden,
            int(self.n_features),
            int(self.n_stages),
            pole_range,
            step,
        )

    def _structure(
        self, default_poles: ArrayLike, t: NDArray, clean: NDArray, kind: str
    ) -> tuple[tuple[str, ...], NDArray[np.float64]]:
        s = self.structure
        if s is None:
            return parse_poles(default_poles, 0.0)
        if isinstance(s, str):
            raise DataError(
                f"structure must be pole locations or a sequence of block kinds, got {s!r}"
            )
        items = list(s) if not isinstance(s, np.ndarray) else s.tolist()
        if items and all(isinstance(k, str) for k in items):
            bad = [k for k in items if k not in (REAL, PAIR)]
            if bad:
                raise DataError(f"structure: block kinds must be 'real' or 'pair'; got {bad[0]!r}")
            kinds = tuple(items)
            return kinds, _centre_from_kinds(kinds, t, clean, kind)
        try:
            return parse_poles(s, 0.0)
        except KautzTwinError as exc:
            raise DataError(f"structure: {exc}") from None

    # ------------------------------------------------------------------ fitting
    def fit(self, dataset: ResponseDataset) -> AdaptivePoleEstimator:
        """Train the pole network on noisy records and their noise-free responses.

        The records are split into training and validation parts
        (``config.validation_fraction``).  Then, stage by stage (the earlier
        stages frozen): a warm start that regresses the log block parameters
        on the records' true poles (``pretrain_epochs``, cheap: no basis is
        evaluated), and end-to-end training on the mean
        ``1 - fit/100`` of the fitted responses against the noise-free ones
        (``config``), both with :func:`~kautztwin.nn.fit_network`.

        Parameters
        ----------
        dataset : ResponseDataset
            Noisy records ``dataset.responses`` (the inputs), noise-free
            ``dataset.clean`` (the targets of the fit) and true poles
            ``dataset.poles`` (the warm start), at least 2 records.  The
            Kautz labels ``dataset.coefficients`` are not used;
            ``dataset.basis_poles`` is the default structure.

        Returns
        -------
        AdaptivePoleEstimator
            ``self``, fitted.

        Raises
        ------
        DataError
            If ``dataset`` is not a :class:`ResponseDataset`, a noise-free
            record is constant, or an option is invalid.
        """
        if not isinstance(dataset, ResponseDataset):
            raise DataError(
                "dataset must be a kautztwin.datasets.ResponseDataset, got "
                f"{type(dataset).__name__}"
            )
        config = self._resolve_config()
        seed, hidden, n_features, n_stages, pole_range, step = self._check_options()
        t = np.asarray(dataset.t, dtype=float)
        kind = dataset.kind
        clean = np.asarray(dataset.clean, dtype=float)
        _spread(clean)
        kinds, centre = self._structure(dataset.basis_poles, t, clean, kind)
        centre = _omega_floor(kinds, centre)
        train_idx, val_idx = split_indices(len(dataset), config.validation_fraction, seed)

        # feature subspace: principal directions of unit-norm noise-free training responses
        rng = np.random.default_rng(seed)
        pick = (
            train_idx
            if train_idx.size <= _PCA_RECORDS
            else rng.choice(train_idx, _PCA_RECORDS, replace=False)
        )
        Hn = clean[pick] / np.linalg.norm(clean[pick], axis=1, keepdims=True)
        _, _, Vt = np.linalg.svd(Hn, full_matrices=False)
        projector = Vt[: min(n_features, Vt.shape[0])].T
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            module = AdaptivePoleNetwork(
                kinds,
                centre,
                t,
                projector,
                hidden=hidden,
                n_stages=n_stages,
                pole_range=pole_range,
                step=step,
                weights=response_weights(t, self.weights).numpy(),
                kind=kind,
            )
        labels, valid = _match_labels(kinds, centre, np.asarray(dataset.poles))
        self._train(module, dataset, config, seed, warm_start=(labels, valid))
        return self

    def fine_tune(
        self,
        dataset: ResponseDataset,
        *,
        config: TrainingConfig | Mapping[str, Any] | None = None,
        random_state: int | None = None,
    ) -> AdaptivePoleEstimator:
        """A new estimator trained further, from this one's weights, on another data set.

        Retraining for a new operating point: the new estimator's network is
        a deep copy of ``network_``, trained stage by stage on the end-to-end
        loss of :meth:`fit` (the earlier stages frozen), without the warm
        start (the old weights are the warm start).  ``self`` is left
        unchanged: fitted estimators are treated as immutable because a
        running digital twin swaps them whole.

        Unlike :meth:`CoefficientEstimator.fine_tune
        <kautztwin.nn.CoefficientEstimator.fine_tune>`, the normalisation is
        **kept**: the feature subspace, the standardisation of each stage's
        input, the centre and the range of the poles.  The network's output
        is not standardised (it is the poles themselves, relative to the fixed
        centre), so re-fitting the input standardisation on records of a new
        operating point would map them to what the old weights read as the
        centre of the old one.  Poles outside ``pole_range`` of the centre
        stay out of reach.

        Parameters
        ----------
        dataset : ResponseDataset
            Noisy records and their noise-free responses on this estimator's
            grid ``t_``, of its ``kind_``; at least 2 records.  The labels and
            their basis are not used.
        config : TrainingConfig, mapping or None, default=None
            Options of the fine-tuning run.  ``None`` uses the default
            fine-tuning configuration, derived from ``config_``: a quarter of
            its epochs (rounded up) and a third of its learning rate.  A
            mapping overrides fields of that default; a
            :class:`~kautztwin.nn.TrainingConfig` replaces it.
        random_state : int or None, default=None
            Seed of the split and the shuffles; ``None`` uses ``random_state``.

        Returns
        -------
        AdaptivePoleEstimator
            A new fitted estimator with the same constructor parameters
            (``random_state`` set to the seed used) whose ``config_`` and
            ``histories_`` describe the fine-tuning run
            (``pretrain_histories_`` is empty).

        Raises
        ------
        DataError
            If ``dataset`` is not a :class:`ResponseDataset`, is on another
            grid, holds another kind of response, has a constant noise-free
            record or is too small to split, or an option is invalid.
        NotFittedError
            If the estimator is not fitted.

        See Also
        --------
        fit : Training from scratch.
        kautztwin.twin.Optimizer.retrain_estimator : Fine-tuning for the twin, validated.
        """
        _check_fine_tune_data(self, dataset)
        seed = _check_seed(
            self.random_state if random_state is None else random_state, "random_state"
        )
        run_config = _fine_tune_config(self.config_, config)
        new = type(self)(**{**self.get_params(), "random_state": int(seed)})
        module = copy.deepcopy(self.network_)
        module.requires_grad_(True)
        new._train(module, dataset, run_config, int(seed), warm_start=None)
        return new

    def _train(
        self,
        module: AdaptivePoleNetwork,
        dataset: ResponseDataset,
        config: TrainingConfig,
        seed: int,
        *,
        warm_start: tuple[NDArray[np.float64], NDArray[np.bool_]] | None,
    ) -> None:
        """Train ``module`` stage by stage on ``dataset`` and set the fitted attributes.

        Shared by :meth:`fit` (``warm_start`` = the records' log-pole labels
        and their validity: the stage inputs are standardised on the data and
        each stage is warm-started on the labels) and :meth:`fine_tune`
        (``None``: a trained module, its normalisation kept, no warm start).
        """
        clean = np.asarray(dataset.clean, dtype=float)
        noisy = np.asarray(dataset.responses, dtype=float)
        spread = _spread(clean)
        train_idx, val_idx = split_indices(len(dataset), config.validation_fraction, seed)
        fresh = warm_start is not None
        n_stages = module.n_stages
        X = torch.from_numpy(noisy.astype(np.float32))
        C = torch.from_numpy(clean.astype(np.float32))
        S = torch.from_numpy(spread.astype(np.float32))
        tr, va = torch.from_numpy(train_idx), torch.from_numpy(val_idx)
        with torch.no_grad():
            Z, norm = module.coordinates(X)
        warm = False
        if warm_start is not None:
            module.stages[0].set_normalization(*_moments(Z[tr]))
            labels, valid = warm_start
            L = torch.from_numpy(np.log(labels).astype(np.float32))
            tr_l, va_l = tr[valid[train_idx]], va[valid[val_idx]]
            warm = bool(self.pretrain_epochs) and tr_l.numel() > 0 and va_l.numel() > 0
        pre_config = TrainingConfig(
            learning_rate=1e-3,
            max_epochs=max(1, int(self.pretrain_epochs)),
            batch_size=256,
            grad_clip=1.0,
            patience=10,
            validation_fraction=config.validation_fraction,
        )

        def train(k: int, loss: Any, train_data: tuple, val_data: tuple, cfg: TrainingConfig):
            for j, stage in enumerate(module.stages):  # only stage k learns
                stage.requires_grad_(j == k)
            try:
                return fit_network(
                    module,
                    train_data,
                    val_data,
                    loss,
                    cfg,
                    random_state=seed + k,
                    progress=bool(self.progress),
                )
            finally:
                module.requires_grad_(True)

        pre_histories: list[TrainingHistory] = []
        histories: list[TrainingHistory] = []
        if warm:
            pre_histories.append(
                train(0, _initial_label_loss, (Z[tr_l], L[tr_l]), (Z[va_l], L[va_l]), pre_config)
            )
        histories.append(
            train(
                0,
                _initial_fit_loss,
                (X[tr], C[tr], S[tr], Z[tr]),
                (X[va], C[va], S[va], Z[va]),
                config,
            )
        )
        with torch.no_grad():
            previous = module.initial(Z)
        for k in range(1, n_stages):
            with torch.no_grad():
                inp = torch.cat(
                    [
                        module.stage_input(X[i], Z[i], norm[i], previous[i])
                        for i in torch.arange(X.shape[0]).split(_PREDICT_BATCH)
                    ]
                )
            if fresh:
                module.stages[k].set_normalization(*_moments(inp[tr]))
            if warm:
                pre_histories.append(
                    train(
                        k,
                        functools.partial(_correction_label_loss, k),
                        (inp[tr_l], previous[tr_l], L[tr_l]),
                        (inp[va_l], previous[va_l], L[va_l]),
                        pre_config,
                    )
                )
            histories.append(
                train(
                    k,
                    functools.partial(_correction_fit_loss, k),
                    (X[tr], C[tr], S[tr], inp[tr], previous[tr]),
                    (X[va], C[va], S[va], inp[va], previous[va]),
                    config,
                )
            )
            with torch.no_grad():
                previous = module.correct(k, inp, previous)
        self._set_fitted(module, histories, pre_histories, config, int(train_idx.size))

    def fit_distribution(
        self,
        system: ParametricSystem,
        uncertainty: float | Mapping[str, float],
        t: ArrayLike,
        *,
        noise: float,
        n_train: int = 20000,
        kind: str = "impulse",
        noise_kind: str = "white",
        color_pole: float = 0.9,
    ) -> AdaptivePoleEstimator:
        """Train on records drawn from an uncertain system (free training data).

        Draws ``n_train`` parameter vectors uniformly within the relative
        ``uncertainty`` (:func:`~kautztwin.datasets.draw_parameters`), simulates
        their noisy responses (:func:`~kautztwin.datasets.make_dataset`) and
        calls :meth:`fit`.  The default of 20,000 records (400 times the
        paper's 50) is chosen for the default network (two stages, about
        290,000 weights): on the paper's system under +-50 % uncertainty its
        validation fit stays within 0.05 points of its training fit, so more
        records would not help, while the end-to-end epochs (a basis per
        record) dominate the training time.  The data cost only simulation
        time (20-40 s for 20,000 records on a shared 2-core machine).

        Parameters
        ----------
        system : ParametricSystem
            The nominal model; its poles are the default structure.
        uncertainty : float or mapping of str to float
            Relative half-width of the uniform parameter distribution.
        t : array-like of shape (n_samples,)
            Sample times of the records, ``t[0] >= 0``.
        noise : float
            Noise standard deviation as a fraction of each record's peak.
        n_train : int, default=20000
            Records simulated (split into training and validation parts).
        kind : {'impulse', 'step'}, default='impulse'
            Response recorded.
        noise_kind : {'white', 'colored'}, default='white'
            Noise colour (see :func:`~kautztwin.datasets.make_dataset`).
        color_pole : float, default=0.9
            AR(1) pole of colored noise.

        Returns
        -------
        AdaptivePoleEstimator
            ``self``, fitted.

        Raises
        ------
        DataError
            On invalid options (see :func:`~kautztwin.datasets.make_dataset`).
        """
        if not isinstance(system, ParametricSystem):
            raise DataError(f"system must be a ParametricSystem, got {type(system).__name__}")
        if not _is_int(n_train) or n_train < 2:
            raise DataError(f"n_train must be an integer >= 2, got {n_train!r}")
        seed = self._check_options()[0]
        ss = np.random.SeedSequence([seed, 1])
        draw_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
        P = draw_parameters(system, uncertainty, int(n_train), random_state=draw_rng)
        poles = system.poles()
        s = self.structure
        if s is not None and not (len(s) and all(isinstance(k, str) for k in s)):
            try:
                poles = KautzBasis(s).poles
            except KautzTwinError as exc:
                raise DataError(f"structure: {exc}") from None
        data = make_dataset(
            system,
            P,
            KautzBasis(poles),
            t,
            kind=kind,
            noise=noise,
            noise_kind=noise_kind,
            color_pole=color_pole,
            random_state=noise_rng,
        )
        return self.fit(data)

    def _set_fitted(
        self,
        module: AdaptivePoleNetwork,
        histories: list[TrainingHistory],
        pretrain_histories: list[TrainingHistory],
        config: TrainingConfig,
        n_train: int,
    ) -> None:
        module.eval()
        t = module._t.copy()
        t.setflags(write=False)
        self.network_ = module
        self.histories_ = list(histories)
        self.pretrain_histories_ = list(pretrain_histories)
        self.config_ = config
        self.kinds_ = module.kinds
        centre = np.exp(module.log_centre.detach().double().numpy())
        self.centre_poles_ = block_poles(self.kinds_, torch.from_numpy(centre)).numpy()
        self.t_ = t
        self.kind_ = module.kind
        self.n_samples_ = int(t.size)
        self.n_functions_ = int(module.n_functions)
        self.n_train_ = int(n_train)

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "network_"):
            raise NotFittedError(
                "this AdaptivePoleEstimator is not fitted yet; call fit(dataset), "
                "fit_distribution(...) or AdaptivePoleEstimator.load(directory) first"
            )

    # ------------------------------------------------------------------ checks
    def _grid_text(self) -> str:
        return f"{self.n_samples_} samples on [{self.t_[0]:g}, {self.t_[-1]:g}] s"

    def check_grid(self, t: ArrayLike) -> None:
        """Raise if ``t`` is not the time grid the network was trained on.

        Parameters
        ----------
        t : array-like of shape (n_samples,)

        Raises
        ------
        DataError
            If ``t`` differs from ``t_`` (length, span or spacing).
        NotFittedError
            If the estimator is not fitted.
        """
        self._check_is_fitted()
        t = np.asarray(t, dtype=float)
        if t.ndim != 1 or t.size != self.n_samples_:
            raise DataError(
                f"t has shape {t.shape} but the estimator was trained on {self._grid_text()}; "
                "resample the records onto the training grid"
            )
        span = float(self.t_[-1] - self.t_[0]) or 1.0
        diff = np.abs(t - self.t_)
        if not np.all(np.isfinite(t)) or np.max(diff) > _GRID_RTOL * span:
            k = int(np.argmax(np.where(np.isfinite(diff), diff, np.inf)))
            raise DataError(
                f"t differs from the training grid ({self._grid_text()}): t[{k}] = {t[k]:g} "
                f"but the estimator expects {self.t_[k]:g}"
            )

    def _records(self, responses: Any, t: ArrayLike | None) -> tuple[NDArray[np.float64], bool]:
        X, single = _checked_records(self, responses, t, copy=True)  # a writable copy
        if np.any(np.all(X == 0, axis=1)):
            i = int(np.argmax(np.all(X == 0, axis=1)))
            raise DataError(f"record {i} is all zeros; there are no poles to estimate")
        return X, single

    # ------------------------------------------------------------------ prediction
    def _predict_params(self, X: NDArray) -> NDArray[np.float64]:
        out = np.empty((X.shape[0], self.n_functions_))
        dtype = self.network_.projector.dtype
        with torch.no_grad():
            for s in range(0, X.shape[0], _PREDICT_BATCH):
                xb = torch.as_tensor(X[s : s + _PREDICT_BATCH], dtype=dtype)
                out[s : s + xb.shape[0]] = self.network_(xb).double().numpy()
        return out

    def _refine(self, X: NDArray, params: NDArray) -> NDArray[np.float64]:
        out = params.copy()
        for i in range(X.shape[0]):
            start = block_poles(self.kinds_, torch.from_numpy(params[i])).numpy()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                try:
                    res = optimize_poles(
                        self.t_, X[i], start, kind=self.kind_, max_iter=int(self.refine_max_iter)
                    )
                except (KautzTwinError, np.linalg.LinAlgError):
                    continue
            kinds, p = parse_poles(res.basis.poles, 0.0)
            if kinds == self.kinds_ and np.all(np.isfinite(p)):
                out[i] = p
        return out

    def _weights_tensor(self, dtype: torch.dtype) -> torch.Tensor | None:
        if self.weights == "uniform":
            return None  # ordinary least squares: skip the multiplication
        return response_weights(self.t_, self.weights, dtype=dtype)

    def _coefficients(self, X: NDArray, params: NDArray, dtype: torch.dtype) -> NDArray:
        out = np.empty_like(params)
        w = self._weights_tensor(dtype)
        for s in range(0, X.shape[0], _PREDICT_BATCH):
            P = torch.as_tensor(params[s : s + _PREDICT_BATCH], dtype=dtype)
            h = torch.as_tensor(X[s : s + _PREDICT_BATCH], dtype=dtype)
            with torch.no_grad():
                K = self._design(P)
                out[s : s + P.shape[0]] = lstsq_coefficients(K, h, w).double().numpy()
        return out

    def _design(self, P: torch.Tensor) -> torch.Tensor:
        return self.network_.design(P)

    def _estimate(
        self, responses: Any, t: ArrayLike | None, refine: bool | None, dtype: torch.dtype
    ) -> tuple[NDArray, NDArray, bool]:
        X, single = self._records(responses, t)
        params = self._predict_params(X)
        if self.refine if refine is None else refine:
            params = self._refine(X, params)
        return params, self._coefficients(X, params, dtype), single

    def predict(
        self,
        responses: ArrayLike | ResponseDataset,
        *,
        t: ArrayLike | None = None,
        refine: bool | None = None,
    ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """Estimate the poles and coefficients of every record.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            Records on the training grid ``t_``.
        t : array-like of shape (n_samples,), optional
            Sample times of the records, checked with :meth:`check_grid`.
        refine : bool, optional
            Override the ``refine`` option for this call.

        Returns
        -------
        poles : ndarray of complex, shape (n_records, n_functions)
            Pole locations (``Re < 0``) in block order, pairs as ``(p, conj p)``.
        coefficients : ndarray of shape (n_records, n_functions)
            Least-squares coefficients of each record on its basis (float64).
            Both without the record axis for one 1-D record.

        Raises
        ------
        DimensionError
            If the records have the wrong number of samples or dimensions.
        DataError
            On NaN/inf values, an all-zero record, another grid or kind.
        NotFittedError
            If the estimator is not fitted.
        """
        params, coef, single = self._estimate(responses, t, refine, torch.float64)
        poles = block_poles(self.kinds_, torch.from_numpy(params)).numpy()
        if single:
            return poles[0], coef[0]
        return poles, coef

    def predict_models(
        self,
        responses: ArrayLike | ResponseDataset,
        *,
        t: ArrayLike | None = None,
        refine: bool | None = None,
    ) -> list[KautzModel]:
        """Estimate one :class:`~kautztwin.KautzModel` (own poles) per record.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            As in :meth:`predict`.
        t : array-like of shape (n_samples,), optional
            Sample times, checked with :meth:`check_grid`.
        refine : bool, optional
            Override the ``refine`` option for this call.

        Returns
        -------
        list of KautzModel
            One model per record (a list of one for a 1-D record).
        """
        params, coef, _ = self._estimate(responses, t, refine, torch.float64)
        return [
            KautzModel(KautzBasis._from_blocks(self.kinds_, p), c)
            for p, c in zip(params, coef, strict=True)
        ]

    def predict_responses(
        self,
        responses: ArrayLike | ResponseDataset,
        *,
        t: ArrayLike | None = None,
        refine: bool | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> NDArray[np.float64]:
        """Noise-free estimate of every record: the fitted model's response on ``t_``.

        Batched end to end (no per-record Python loop without refinement);
        this is what the benchmark times.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            As in :meth:`predict`.
        t : array-like of shape (n_samples,), optional
            Sample times, checked with :meth:`check_grid`.
        refine : bool, optional
            Override the ``refine`` option for this call.
        dtype : torch.dtype, default=torch.float64
            Dtype of the basis and the least squares (``torch.float32`` is
            about 3x faster and accurate to about 1e-6 relative).

        Returns
        -------
        ndarray of shape (n_samples,) or (n_records, n_samples)
            Impulse (or step, for step records) responses of the fitted models.
        """
        X, single = self._records(responses, t)
        params = self._predict_params(X)
        if self.refine if refine is None else refine:
            params = self._refine(X, params)
        out = np.empty_like(X)
        w = self._weights_tensor(dtype)
        with torch.no_grad():
            for s in range(0, X.shape[0], _PREDICT_BATCH):
                P = torch.as_tensor(params[s : s + _PREDICT_BATCH], dtype=dtype)
                h = torch.as_tensor(X[s : s + _PREDICT_BATCH], dtype=dtype)
                K = self._design(P)
                c = lstsq_coefficients(K, h, w)
                out[s : s + P.shape[0]] = (c[:, None, :] @ K)[:, 0].double().numpy()
        return out[0] if single else out

    def score(self, dataset: ResponseDataset, *, refine: bool | None = None) -> float:
        """Mean fit percent of the fitted responses against the noise-free ones.

        Parameters
        ----------
        dataset : ResponseDataset
            Records with their noise-free responses ``dataset.clean``.
        refine : bool, optional
            Override the ``refine`` option for this call.

        Returns
        -------
        float
        """
        if not isinstance(dataset, ResponseDataset):
            raise DataError(
                "dataset must be a kautztwin.datasets.ResponseDataset, got "
                f"{type(dataset).__name__}"
            )
        yhat = self.predict_responses(dataset, refine=refine)
        return float(np.mean(fit_percent(dataset.clean, yhat)))

    # ------------------------------------------------------------------ files
    def save(self, directory: str | Path) -> Path:
        """Write the fitted estimator to a directory (created if needed).

        ``weights.pt`` holds the module's tensors (``state_dict``: weights,
        feature projector, standardisation, centre and least-squares weights),
        written with ``torch.save`` and read back with ``weights_only=True``;
        ``metadata.json`` holds the format version, the structure, the time
        grid, the options, the loss curves, the sha256 of ``weights.pt`` and
        its own checksum.

        Parameters
        ----------
        directory : str or path-like

        Returns
        -------
        pathlib.Path
            The directory.

        Raises
        ------
        NotFittedError
            If the estimator is not fitted.
        """
        self._check_is_fitted()
        state = {k: v.detach().cpu().contiguous() for k, v in self.network_.state_dict().items()}
        net = self.network_
        fields: dict[str, Any] = {
            "kinds": list(self.kinds_),
            "centre_poles": [[float(p.real), float(p.imag)] for p in self.centre_poles_],
            "kind": self.kind_,
            "architecture": {
                "network": type(net).__name__,
                "hidden": list(net.hidden),
                "n_features": int(net.projector.shape[1]),
                "n_stages": net.n_stages,
                "pole_range": net.pole_range,
                "step": net.step,
                "n_parameters": sum(p.numel() for p in net.parameters()),
                "dtype": str(net.projector.dtype).removeprefix("torch."),
            },
            "weights_rule": self.weights,
            "refine": bool(self.refine),
            "refine_max_iter": int(self.refine_max_iter),
            "pretrain_epochs": int(self.pretrain_epochs),
            "random_state": int(self.random_state),
            "n_train": self.n_train_,
            "config": self.config_.to_dict(),
            "histories": [h.to_dict() for h in self.histories_],
            "pretrain_histories": [h.to_dict() for h in self.pretrain_histories_],
        }
        return _save_verified(directory, _FORMAT, _FORMAT_VERSION, state, self.t_, fields)

    @classmethod
    def load(cls, directory: str | Path) -> AdaptivePoleEstimator:
        """Read an estimator written by :meth:`save`, verifying its checksums.

        Parameters
        ----------
        directory : str or path-like

        Returns
        -------
        AdaptivePoleEstimator
            Fitted, ready to :meth:`predict`.

        Raises
        ------
        DataError
            If a file is missing or unreadable, of another format or version,
            malformed, or modified after saving (checksum mismatch).
        """
        return _load_verified(
            directory, _FORMAT, _FORMAT_VERSION, "AdaptivePoleEstimator", cls._from_files
        )

    @classmethod
    def _from_files(cls, meta: dict[str, Any], weights_path: Path) -> AdaptivePoleEstimator:
        grid = meta["time_grid"]
        t = np.asarray(grid["t"], dtype=float)
        if t.shape != (int(grid["n_samples"]),) or _grid_hash(t) != grid["sha256"]:
            raise DataError("the stored time grid does not match its length or hash")
        arch = meta["architecture"]
        if arch["network"] != AdaptivePoleNetwork.__name__:
            raise DataError(f"unknown network {arch['network']!r}")
        kinds = tuple(str(k) for k in meta["kinds"])
        centre_poles = [complex(re, im) for re, im in meta["centre_poles"]]
        got_kinds, centre = parse_poles(centre_poles, 0.0)
        if got_kinds != kinds:
            raise DataError("the stored centre poles do not match the block structure")
        dtype = getattr(torch, str(arch["dtype"]))
        state = torch.load(weights_path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise DataError("the weights file does not hold a dictionary of tensors")
        n_feat = int(arch["n_features"])
        module = AdaptivePoleNetwork(
            kinds,
            centre,
            t,
            np.zeros((t.size, n_feat)),
            hidden=tuple(int(h) for h in arch["hidden"]),
            n_stages=int(arch["n_stages"]),
            pole_range=float(arch["pole_range"]),
            step=float(arch["step"]),
            kind=str(meta["kind"]),
            dtype=dtype,
        )
        module.load_state_dict(state, strict=True)
        est = cls(
            structure=centre_poles,
            hidden=tuple(arch["hidden"]),
            n_features=n_feat,
            n_stages=int(arch["n_stages"]),
            pole_range=float(arch["pole_range"]),
            step=float(arch["step"]),
            weights=str(meta["weights_rule"]),
            config=TrainingConfig.from_dict(meta["config"]),
            random_state=int(meta["random_state"]),
            refine=bool(meta["refine"]),
            refine_max_iter=int(meta["refine_max_iter"]),
            pretrain_epochs=int(meta["pretrain_epochs"]),
        )
        est._set_fitted(
            module,
            [TrainingHistory.from_dict(h) for h in meta["histories"]],
            [TrainingHistory.from_dict(h) for h in meta["pretrain_histories"]],
            TrainingConfig.from_dict(meta["config"]),
            int(meta["n_train"]),
        )
        return est

    # ------------------------------------------------------------------ summaries
    @property
    def n_parameters_(self) -> int:
        """Trainable parameters of the pole network."""
        self._check_is_fitted()
        return sum(p.numel() for p in self.network_.parameters())

    @property
    def training_seconds_(self) -> float:
        """Training time of all stages (warm starts included), in seconds."""
        self._check_is_fitted()
        return math.fsum(h.seconds for h in [*self.histories_, *self.pretrain_histories_])


def _omega_floor(kinds: tuple[str, ...], centre: NDArray) -> NDArray[np.float64]:
    """Replacement centre for a zero pair frequency: the pair's own damping."""
    out = centre.copy()
    col = 0
    for k in kinds:
        if k == PAIR:
            if out[col + 1] <= 0:
                out[col + 1] = out[col]
            col += 2
        else:
            col += 1
    return out
