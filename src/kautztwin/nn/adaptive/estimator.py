"""The adaptive-pole estimator: a facade over the network, its training and its inference.

Size: the file passes 600 lines only through the numpydoc of the public methods; the code of each
is a few lines delegating to the sibling modules.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_int
from ...approx import KautzModel
from ...basis import KautzBasis
from ...datasets import ParametricSystem, ResponseDataset
from ...exceptions import DataError, NotFittedError
from ...metrics import fit_percent
from ..config import TrainingConfig, TrainingHistory, fine_tune_config
from ..estimator_base import EstimatorMixin, check_dataset, check_fine_tune_data, grid_difference
from ..kautz_torch import block_poles
from ..uncertainty import (
    DEFAULT_LEVEL,
    ResponseEstimate,
    calibrate_estimate,
    laplace_response_covariance,
)
from .files import load_estimator, save_estimator
from .inference import (
    check_records,
    least_squares_fit,
    predict_params,
    refine_constrained,
    refine_params,
    response_jacobian,
    weights_tensor,
)
from .network import TRAINING_DTYPE, AdaptivePoleNetwork
from .training import (
    draw_training_data,
    keep_relative_degree,
    new_network,
    resolve_config,
    train_stages,
)

__all__ = ["AdaptivePoleEstimator"]


class AdaptivePoleEstimator(EstimatorMixin):
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

    The class is a facade over :mod:`kautztwin.nn.adaptive`: the network is
    :class:`~kautztwin.nn.adaptive.network.AdaptivePoleNetwork`, its training
    :mod:`~kautztwin.nn.adaptive.training`, the estimates and the refinement
    :mod:`~kautztwin.nn.adaptive.inference`, the files
    :mod:`~kautztwin.nn.adaptive.files`; it runs past 400 lines only through
    the numpydoc of its public methods (each body is a few delegating lines).

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
        (:func:`kautztwin.optimize_poles`; under a relative-degree constraint the
        same for the constrained fit,
        :func:`~kautztwin.nn.adaptive.inference.refine_constrained`), about 100x
        slower than the network.
    refine_max_iter : int, default=50
        ``max_iter`` of the refinement.
    pretrain_epochs : int, default=30
        Warm start before the end-to-end training: at most this many epochs
        of regression of the log block parameters on the records' true poles
        (``dataset.poles``, matched to the blocks by kind and in order of
        rate or frequency; records whose poles do not fit the structure are
        left out).  It costs little (features in, no basis) and shortens the
        end-to-end phase several times.  ``0`` trains end to end from the centre.
    relative_degree : int or 'auto', default=1
        Relative degree ``r`` imposed on every fitted model: the least squares keep
        the first ``r - 1`` Markov parameters :math:`y^{(k)}(0)` at zero
        (:func:`~kautztwin.nn.kautz_torch.relative_degree_constraints`), so the
        coefficients have ``r - 1`` fewer degrees of freedom to fit noise with.
        ``'auto'`` reads ``r`` from the noise-free training records and their true
        poles (the largest ``r`` that every record satisfies; ``1``, no
        constraint, when the poles do not fit the structure), and after training
        keeps it only if the validation records are fitted at least as well as
        without it (a constrained fit cannot absorb errors of the poles, which a
        small or briefly trained network makes); ``1`` is the unconstrained fit.
        ``'auto'`` pays with a training budget like the simulation benchmark's (12
        epochs, 20 000 records); with a small budget the constrained training itself
        costs fit even after the fallback (the smoke run of ``reproduce simulation``:
        0.7 points; a 4-epoch, 400-record step-test family: its held-out fit halves), so
        it is not the default.

    Attributes
    ----------
    network_ : AdaptivePoleNetwork
        The trained module (``eval`` mode), trained in ``float32`` and kept in
        ``float64`` (an exact cast): every prediction runs in ``float64``.
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
    relative_degree_ : int
        The relative degree the final least squares impose (``1``: none); the
        network's correction stages keep the degree they were trained with
        (``network_.relative_degree``).
    uncertainty_scale_ : float
        Calibration scale of the uncertainty (:meth:`calibrate`); 1.0 until calibrated.
    calibration_ : dict or None
        What :meth:`calibrate` measured (level, scale, records, coverage), ``None`` before.
    training_data_ : dict or None
        Description of the training distribution when the trainer recorded one (the
        plant family of ``kautztwin train --family``), else ``None``.

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
    end-to-end loss above, which decides.  On the paper's system (+-50 %
    uncertainty, 900 samples, 20 000 training records, 12 epochs per stage)
    with the relative-degree constraint (``'auto'``: 4) the mean fit at 10 %
    noise is 97.04 %, against 97.06 % for least squares in the true model
    structure started at the true parameters (the oracle); the unconstrained
    fit with 6 epochs per stage reached 96.63 % (``benchmarks/bench_adaptive.py``;
    at 1 % noise 99.65 % against 99.70 %).  The constraint removes
    ``r - 1`` coefficient directions from the noise; it cannot absorb errors
    of the poles, which is why ``'auto'`` keeps it for the final fit only where
    the validation records are fitted better with it.  The variable-projection
    refinement finds the least-squares poles of the record itself; under the
    constraint (a system without zeros) that is the oracle's model, and
    ``refine=True`` then matches the oracle, at about the oracle's cost;
    without the constraint it fits more of the noise than the network's
    estimate does at high noise (the network has learned the distribution of
    the poles), so it pays off only at low noise or for records unlike the
    training data.

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
        relative_degree: int | str = 1,
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
        self.relative_degree = relative_degree

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
            "relative_degree": self.relative_degree,
        }


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
        check_dataset(dataset)
        config = resolve_config(self.config)
        module, warm_start, seed = new_network(self.get_params(), dataset, config)
        self._train(module, dataset, config, seed, warm_start=warm_start)
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
        check_fine_tune_data(self, dataset)
        seed = check_int(
            self.random_state if random_state is None else random_state, "random_state", minimum=0
        )
        run_config = fine_tune_config(self.config_, config)
        new = type(self)(**{**self.get_params(), "random_state": int(seed)})
        module = copy.deepcopy(self.network_).cast(TRAINING_DTYPE)
        module.requires_grad_(True)
        new._train(
            module, dataset, run_config, int(seed), warm_start=None,
            fit_degree=self.relative_degree_,
        )
        return new

    def _train(
        self,
        module: AdaptivePoleNetwork,
        dataset: ResponseDataset,
        config: TrainingConfig,
        seed: int,
        *,
        warm_start: tuple[NDArray[np.float64], NDArray[np.bool_]] | None,
        fit_degree: int | None = None,
    ) -> None:
        """Train ``module`` stage by stage on ``dataset`` and set the fitted attributes.

        Shared by :meth:`fit` (``warm_start`` = the records' log-pole labels
        and their validity: the stage inputs are standardised on the data and
        each stage is warm-started on the labels) and :meth:`fine_tune`
        (``None``: a trained module, its normalisation kept, no warm start).
        ``fit_degree`` is the relative degree of the final fit to keep (fine-tuning);
        ``None`` chooses it (:func:`~kautztwin.nn.adaptive.training.keep_relative_degree`).
        """
        histories, pre_histories, n_train = train_stages(
            module,
            dataset,
            config,
            seed,
            warm_start=warm_start,
            pretrain_epochs=self.pretrain_epochs,
            progress=self.progress,
        )
        degree = module.relative_degree if fit_degree is None else int(fit_degree)
        if (
            fit_degree is None
            and self.relative_degree == "auto"
            and degree > 1
            and not keep_relative_degree(module, dataset, config, seed)
        ):
            degree = 1  # the poles are not precise enough for the constrained final fit
        self._set_fitted(module, histories, pre_histories, config, n_train, degree)

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
        data = draw_training_data(
            self.get_params(),
            system,
            uncertainty,
            t,
            noise=noise,
            n_train=n_train,
            kind=kind,
            noise_kind=noise_kind,
            color_pole=color_pole,
        )
        return self.fit(data)

    def _set_fitted(
        self,
        module: AdaptivePoleNetwork,
        histories: list[TrainingHistory],
        pretrain_histories: list[TrainingHistory],
        config: TrainingConfig,
        n_train: int,
        relative_degree: int,
    ) -> None:
        module.cast(torch.float64).eval()  # exact: float64 inference of the trained weights
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
        self.relative_degree_ = int(relative_degree)
        self.uncertainty_scale_ = 1.0
        self.calibration_: dict[str, Any] | None = None
        self.training_data_: dict[str, Any] | None = None

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "network_"):
            raise NotFittedError(
                "this AdaptivePoleEstimator is not fitted yet; call fit(dataset), "
                "fit_distribution(...) or AdaptivePoleEstimator.load(directory) first"
            )

    # ------------------------------------------------------------------ checks
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
        k = grid_difference(t, self.t_)
        if k is not None:
            raise DataError(
                f"t differs from the training grid ({self._grid_text()}): t[{k}] = {t[k]:g} "
                f"but the estimator expects {self.t_[k]:g}"
            )

    # ------------------------------------------------------------------ prediction
    def _estimate_params(
        self, responses: Any, t: ArrayLike | None, refine: bool | None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], bool]:
        """Checked records, their block parameters (refined if asked) and whether one was given."""
        X, single = check_records(self, responses, t)
        params = predict_params(self.network_, X)
        if (self.refine if refine is None else refine) and self.relative_degree_ > 1:
            w = weights_tensor(self.t_, self.weights, torch.float64)
            params = refine_constrained(
                self.network_, X, params, w, self.refine_max_iter, self.relative_degree_
            )
        elif self.refine if refine is None else refine:
            params = refine_params(
                self.t_, self.kinds_, self.kind_, X, params, self.refine_max_iter
            )
        return X, params, single

    def _estimate(
        self, responses: Any, t: ArrayLike | None, refine: bool | None, dtype: torch.dtype
    ) -> tuple[NDArray, NDArray, bool]:
        X, params, single = self._estimate_params(responses, t, refine)
        w = weights_tensor(self.t_, self.weights, dtype)
        coef = least_squares_fit(
            self.network_, X, params, w, dtype, relative_degree=self.relative_degree_
        )
        return params, coef, single

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
            Dtype of the basis and the least squares (the network itself always
            runs in float64; ``torch.float32`` here is somewhat faster and
            accurate to about 1e-6 relative).

        Returns
        -------
        ndarray of shape (n_samples,) or (n_records, n_samples)
            Impulse (or step, for step records) responses of the fitted models.
        """
        X, params, single = self._estimate_params(responses, t, refine)
        w = weights_tensor(self.t_, self.weights, dtype)
        out = least_squares_fit(
            self.network_, X, params, w, dtype, responses=True,
            relative_degree=self.relative_degree_,
        )
        return out[0] if single else out

    def _uncertainty(
        self, responses: Any, t: ArrayLike | None, refine: bool | None, level: float, scale: float
    ) -> ResponseEstimate:
        X, params, _ = self._estimate_params(responses, t, refine)
        w = weights_tensor(self.t_, self.weights, torch.float64)
        coef = least_squares_fit(
            self.network_, X, params, w, torch.float64, relative_degree=self.relative_degree_
        )
        fitted, jac, lift = response_jacobian(self.network_, params, coef, self.relative_degree_)
        std, cov, noise_std, rho = laplace_response_covariance(jac, X - fitted)
        if lift is not None:  # free coefficient directions -> Kautz coefficients
            cov = lift @ cov @ lift.transpose(0, 2, 1)
        return ResponseEstimate(
            t=self.t_, kind=self.kind_, kinds=self.kinds_, params=params, coefficients=coef,
            response=fitted, std=scale * std, covariance=scale * scale * cov,
            noise_std=noise_std, noise_correlation=rho, scale=float(scale),
            calibrated=self.calibration_ is not None, level=float(level),
        )

    def estimate(
        self,
        responses: ArrayLike | ResponseDataset,
        *,
        t: ArrayLike | None = None,
        refine: bool | None = None,
        level: float = DEFAULT_LEVEL,
    ) -> ResponseEstimate:
        """Estimate every record's model with a calibrated uncertainty.

        The estimate is that of :meth:`predict_models`; its uncertainty is the
        linearised least-squares (Laplace) covariance of the fit with an AR(1)
        noise model read from the record's residual, times the calibration scale
        ``uncertainty_scale_`` (see :mod:`kautztwin.nn.uncertainty` for the method
        and why).  Until :meth:`calibrate` has run, the scale is 1 and
        ``result.calibrated`` is ``False``: the bands then have the right shape
        but not a guaranteed level.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            Records on the training grid ``t_``.
        t : array-like of shape (n_samples,), optional
            Sample times, checked with :meth:`check_grid`.
        refine : bool, optional
            Override the ``refine`` option (with ``True`` the covariance is the
            Laplace approximation at the VARPRO optimum).
        level : float, default=0.9
            Level of the bands and of ``relative_width``.

        Returns
        -------
        ResponseEstimate
            Always with a record axis (one row for a 1-D record); ``relative_width``
            is the one number per record a digital twin compares with a threshold
            to accept or defer an update, and ``impulse_band``, ``step_band``,
            ``frequency_band`` give the bands.

        Raises
        ------
        DataError
            As :meth:`predict`, or a ``level`` outside ``(0, 1)``.
        NotFittedError
            If the estimator is not fitted.
        """
        return self._uncertainty(responses, t, refine, level, self.uncertainty_scale_)

    def calibrate(
        self,
        dataset: ResponseDataset,
        *,
        level: float = DEFAULT_LEVEL,
        refine: bool | None = None,
    ) -> AdaptivePoleEstimator:
        """Fit the calibration scale of the uncertainty on fresh records with known truth.

        Sets ``uncertainty_scale_`` to the split-conformal scale that makes the
        ``level`` bands of :meth:`estimate` contain a share ``level`` of the
        noise-free samples of ``dataset`` (:func:`~kautztwin.nn.uncertainty.calibration_scale`),
        and ``calibration_`` to what was measured.  Use records the network was
        not trained on, drawn like the ones it will see.

        Parameters
        ----------
        dataset : ResponseDataset
            Fresh noisy records with their noise-free responses ``dataset.clean``.
        level : float, default=0.9
        refine : bool, optional
            Override the ``refine`` option (calibrate the way you will estimate).

        Returns
        -------
        AdaptivePoleEstimator
            ``self``, calibrated.

        Raises
        ------
        DataError
            If ``dataset`` is not a data set on this grid, or the bands cannot be calibrated.
        NotFittedError
            If the estimator is not fitted.
        """
        check_dataset(dataset)
        raw = self._uncertainty(dataset, None, refine, level, 1.0)
        kappa, report = calibrate_estimate(
            raw, dataset.clean, refine=bool(self.refine if refine is None else refine)
        )
        self.uncertainty_scale_ = kappa
        self.calibration_ = report
        return self

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
        check_dataset(dataset)
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
        return save_estimator(self, directory)

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
        return load_estimator(cls, directory)

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
