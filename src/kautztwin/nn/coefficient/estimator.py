"""The coefficient estimator (the paper's DNN): a facade over its training and its files.

Size: the file passes 600 lines through the numpydoc of the public methods (fit, predict,
estimate with its uncertainty, calibrate, fine-tune, save/load); each method's code is a few
lines delegating to nn.training, nn.uncertainty and the files module beside it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_int
from ...approx import KautzModel
from ...basis import KautzBasis
from ...datasets import ResponseDataset
from ...exceptions import DataError, KautzTwinError, NotFittedError
from ..config import TrainingConfig, TrainingHistory, fine_tune_config
from ..data import Standardizer
from ..estimator_base import (
    EstimatorMixin,
    check_dataset,
    check_fine_tune_data,
    checked_records,
    grid_difference,
)
from ..networks import PaperNetwork
from ..uncertainty import (
    DEFAULT_LEVEL,
    ResponseEstimate,
    calibrate_estimate,
    fixed_basis_estimate,
)
from .files import load_estimator, save_estimator
from .training import train_coefficient_networks

__all__ = ["CoefficientEstimator"]

_PREDICT_BATCH = 4096


class CoefficientEstimator(EstimatorMixin):
    r"""Deep-network estimator of Kautz coefficients from a sampled noisy response.

    The paper's method: a :class:`~kautztwin.nn.PaperNetwork` maps the
    measured (noisy) impulse or step response of an uncertain system, sampled
    on a fixed time grid, to the Kautz coefficients of its noise-free impulse
    response in a fixed basis.  As in the paper one network is trained per
    coefficient (``per_coefficient=True``); ``per_coefficient=False`` trains a
    single network with ``N`` outputs instead (about ``N`` times cheaper).
    Inputs and labels are standardised per feature with statistics of the
    training part; the records are split 85/15 into training and validation
    sets (``config.validation_fraction``), training uses Adam with gradient
    clipping and early stopping (:func:`~kautztwin.nn.fit_network`).

    The class is a facade: the training is
    :func:`~kautztwin.nn.coefficient.training.train_coefficient_networks`, the
    files :mod:`kautztwin.nn.coefficient.files`.

    Size: it runs past 400 lines only
    through the numpydoc of its public methods.

    Parameters
    ----------
    basis_poles : array-like of complex or None, default=None
        Poles of the Kautz basis of the labels; ``None`` uses the training
        data set's ``basis_poles``.  When given, :meth:`fit` checks that the
        data set is labelled in this basis.
    preset : {'default', 'paper'}, default='default'
        Training preset (:meth:`TrainingConfig.preset`).
    per_coefficient : bool, default=True
        One single-output network per coefficient (the paper), or one
        multi-output network.
    random_state : int, default=0
        Seed of the split, the weight initialisation and the shuffles.
    progress : bool, default=False
        Show a progress bar while training.
    config : TrainingConfig, mapping or None, default=None
        A full configuration replacing the preset, or a mapping of fields to
        override in the preset (e.g. ``{'max_epochs': 50}``).

    Attributes
    ----------
    networks_ : list of PaperNetwork
        The trained networks (``N`` single-output ones, or one multi-output one).
    histories_ : list of TrainingHistory
        Loss curves of each network.
    t_ : ndarray of shape (n_samples,)
        The time grid the networks were trained on (read-only).
    basis_ : KautzBasis
        The basis of the coefficients.
    kind_ : {'impulse', 'step'}
        The kind of response the networks read.
    config_ : TrainingConfig
        The configuration used.
    input_scaler_, label_scaler_ : Standardizer
        Normalisation of the responses and of the coefficients.
    n_samples_ : int
        Samples per record, ``t_.size``.
    n_functions_ : int
        Number of coefficients ``N``.
    uncertainty_scale_ : float
        Calibration scale of :meth:`estimate`'s bands; 1.0 until :meth:`calibrate`.
    calibration_ : dict or None
        What :meth:`calibrate` measured, ``None`` before.

    See Also
    --------
    kautztwin.datasets.make_dataset : Labelled training data of an uncertain system.
    kautztwin.nn.PaperNetwork : The network architecture.
    kautztwin.project : The classical projection of a record, for comparison.
    CoefficientEstimator.fine_tune : Train further on data of a new operating point.

    Notes
    -----
    A fitted estimator only applies to records on its training grid:
    :meth:`predict` rejects records of another length and, given ``t`` or a
    :class:`~kautztwin.datasets.ResponseDataset`, another grid
    (:meth:`check_grid`).  :meth:`save` writes ``weights.pt`` (tensors only,
    read back with ``torch.load(weights_only=True)``, never unpickled objects)
    and ``metadata.json``; :meth:`load` verifies both checksums.

    Examples
    --------
    >>> import numpy as np
    >>> import torch
    >>> import kautztwin as kt
    >>> from kautztwin.datasets import draw_parameters, make_dataset, paper_system
    >>> from kautztwin.nn import CoefficientEstimator
    >>> _ = torch.set_num_threads(1)
    >>> system = paper_system()
    >>> basis = kt.KautzBasis(system.poles())
    >>> t = np.linspace(0.0, 20.0, 100)
    >>> P = draw_parameters(system, 0.2, 60, random_state=0)
    >>> data = make_dataset(system, P, basis, t, noise=0.05, random_state=1)
    >>> est = CoefficientEstimator(per_coefficient=False, config={"max_epochs": 3})
    >>> est.fit(data).predict(data.responses[:2]).shape
    (2, 4)
    """

    def __init__(
        self,
        *,
        basis_poles: ArrayLike | None = None,
        preset: str = "default",
        per_coefficient: bool = True,
        random_state: int = 0,
        progress: bool = False,
        config: TrainingConfig | Mapping[str, Any] | None = None,
    ) -> None:
        self.basis_poles = basis_poles
        self.preset = preset
        self.per_coefficient = per_coefficient
        self.random_state = random_state
        self.progress = progress
        self.config = config

    # ------------------------------------------------------------------ parameters
    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Constructor parameters (scikit-learn convention)."""
        return {
            "basis_poles": self.basis_poles,
            "preset": self.preset,
            "per_coefficient": self.per_coefficient,
            "random_state": self.random_state,
            "progress": self.progress,
            "config": self.config,
        }

    def _resolve_config(self) -> TrainingConfig:
        if isinstance(self.config, TrainingConfig):
            return self.config
        base = TrainingConfig.preset(self.preset)
        if self.config is None:
            return base
        if not isinstance(self.config, Mapping):
            raise DataError(
                "config must be a TrainingConfig, a mapping of option overrides or None; "
                f"got {type(self.config).__name__}"
            )
        return base.replace(**dict(self.config))

    # ------------------------------------------------------------------ fitting
    def fit(self, dataset: ResponseDataset) -> CoefficientEstimator:
        """Train the networks on a labelled data set.

        Parameters
        ----------
        dataset : ResponseDataset
            Noisy responses ``dataset.responses`` on the grid ``dataset.t``
            with labels ``dataset.coefficients`` in the basis
            ``dataset.basis_poles``; at least 2 records.

        Returns
        -------
        CoefficientEstimator
            ``self``, fitted.

        Raises
        ------
        DataError
            If ``dataset`` is not a :class:`ResponseDataset`, is too small to
            split, ``basis_poles`` differs from the data set's basis, or an
            option is invalid.
        """
        check_dataset(dataset)
        config = self._resolve_config()
        seed = check_int(self.random_state, "random_state", minimum=0)
        basis = dataset.basis
        if self.basis_poles is not None:
            try:
                wanted = KautzBasis(self.basis_poles)
            except KautzTwinError as exc:
                raise DataError(f"basis_poles: {exc}") from None
            if not wanted.allclose(basis, rtol=1e-9, atol=1e-12):
                raise DataError(
                    f"basis_poles {wanted!r} differ from the basis the data set is labelled "
                    f"in, {basis!r}; build the data with make_dataset(..., "
                    "basis=KautzBasis(basis_poles), ...)"
                )
        self._train(dataset, config, seed)
        return self

    def fine_tune(
        self,
        dataset: ResponseDataset,
        *,
        config: TrainingConfig | Mapping[str, Any] | None = None,
        random_state: int | None = None,
    ) -> CoefficientEstimator:
        r"""A new estimator trained further, from this one's weights, on another data set.

        Retraining for a new operating point: the networks of the new
        estimator start from deep copies of the trained networks ``networks_``
        and are trained on ``dataset`` with :func:`~kautztwin.nn.fit_network`
        (same split, standardisation, seeds and early stopping as :meth:`fit`).
        ``self`` is left unchanged: fitted estimators are treated as immutable
        because a running digital twin swaps them whole.

        The data set may be labelled in another basis (the poles of the new
        operating point) with the same number of functions; the new
        estimator's ``basis_`` is the data set's basis.  The input and label
        scalers are **re-fitted** on the new training records: the networks
        map standardised responses to standardised coefficients, and around a
        nearby operating point that standardised map changes much less than
        the raw one (the labels of another basis have other means and
        spreads), so the old weights are a good start only in standardised
        coordinates.  Keeping the old scalers would put the new labels off
        the unit scale the weights were trained for, and a label that was
        constant in the old data (scale about ``1e-12``) would blow up.

        Parameters
        ----------
        dataset : ResponseDataset
            Labelled records on this estimator's grid ``t_``, of its ``kind_``,
            with ``n_functions_`` coefficients per record; at least 2 records.
        config : TrainingConfig, mapping or None, default=None
            Options of the fine-tuning run.  ``None`` uses the default
            fine-tuning configuration, derived from ``config_``: a quarter of
            its epochs (rounded up) and a third of its learning rate, the other
            fields unchanged (see Notes).  A mapping overrides fields of that
            default (e.g. ``{'max_epochs': 10}``); a :class:`TrainingConfig`
            replaces it.
        random_state : int or None, default=None
            Seed of the split and the shuffles; ``None`` uses ``random_state``.

        Returns
        -------
        CoefficientEstimator
            A new fitted estimator with the same constructor parameters
            (``random_state`` set to the seed used and ``basis_poles``, if it
            was set, to the new basis) whose ``config_`` and ``histories_``
            describe the fine-tuning run.

        Raises
        ------
        DataError
            If ``dataset`` is not a :class:`ResponseDataset`, is on another
            grid, holds another kind of response or another number of
            coefficients, is too small to split, or an option is invalid.
        NotFittedError
            If the estimator is not fitted.

        See Also
        --------
        fit : Training from scratch.
        kautztwin.twin.Optimizer.retrain_estimator : Fine-tuning for the twin, validated.

        Notes
        -----
        The default is a short, gentle run: with early stopping restoring the
        best epoch, a lower learning rate keeps the warm start from being
        thrown away in the first epochs, and far fewer epochs suffice because
        training starts near a solution.  Fine-tuning never sees the original
        training data, so the new estimator may be worse than the old one
        away from the new operating point; validate it there before it
        replaces the running one (what
        :meth:`kautztwin.twin.Optimizer.retrain_estimator` does).

        Examples
        --------
        >>> import numpy as np
        >>> import torch
        >>> import kautztwin as kt
        >>> from kautztwin.datasets import draw_parameters, make_dataset, paper_system
        >>> from kautztwin.nn import CoefficientEstimator
        >>> _ = torch.set_num_threads(1)
        >>> system, t = paper_system(), np.linspace(0.0, 20.0, 100)
        >>> data = make_dataset(system, draw_parameters(system, 0.2, 60, random_state=0),
        ...                     kt.KautzBasis(system.poles()), t, noise=0.05, random_state=1)
        >>> est = CoefficientEstimator(per_coefficient=False, config={"max_epochs": 3}).fit(data)
        >>> new = est.fine_tune(data, config={"max_epochs": 2})
        >>> new is est, new.config_.max_epochs, est.config_.max_epochs
        (False, 2, 3)
        """
        check_fine_tune_data(self, dataset)
        if dataset.n_functions != self.n_functions_:
            raise DataError(
                f"the data set is labelled with {dataset.n_functions} Kautz coefficients but the "
                f"estimator predicts {self.n_functions_}; fine-tune on a basis with "
                f"{self.n_functions_} poles"
            )
        seed = check_int(
            self.random_state if random_state is None else random_state, "random_state", minimum=0
        )
        run_config = fine_tune_config(self.config_, config)
        params = self.get_params()
        params["random_state"] = seed
        if self.basis_poles is not None:
            params["basis_poles"] = np.array(dataset.basis_poles)
        new = type(self)(**params)
        new._train(dataset, run_config, seed, start=self.networks_)
        return new

    def _train(
        self,
        dataset: ResponseDataset,
        config: TrainingConfig,
        seed: int,
        *,
        start: list[PaperNetwork] | None = None,
    ) -> None:
        """Train the networks (:func:`.train_coefficient_networks`) and set the fitted attributes.

        Shared by :meth:`fit` (fresh networks seeded per target) and
        :meth:`fine_tune` (deep copies of ``start``, which stays unchanged).
        """
        networks, histories, input_scaler, label_scaler = train_coefficient_networks(
            dataset,
            config,
            seed,
            per_coefficient=self.per_coefficient,
            progress=self.progress,
            start=start,
        )
        self._set_fitted(
            networks=networks,
            histories=histories,
            t=dataset.t,
            basis=dataset.basis,
            kind=dataset.kind,
            config=config,
            input_scaler=input_scaler,
            label_scaler=label_scaler,
        )

    def _set_fitted(
        self,
        *,
        networks: list[PaperNetwork],
        histories: list[TrainingHistory],
        t: ArrayLike,
        basis: KautzBasis,
        kind: str,
        config: TrainingConfig,
        input_scaler: Standardizer,
        label_scaler: Standardizer,
    ) -> None:
        t_ = np.array(t, dtype=float, copy=True)
        t_.setflags(write=False)
        for net in networks:
            net.eval()
        self.networks_ = networks
        self.histories_ = histories
        self.t_ = t_
        self.basis_ = basis
        self.kind_ = kind
        self.config_ = config
        self.input_scaler_ = input_scaler
        self.label_scaler_ = label_scaler
        self.n_samples_ = int(t_.size)
        self.n_functions_ = int(basis.n_functions)
        self.uncertainty_scale_ = 1.0
        self.calibration_: dict[str, Any] | None = None

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "networks_"):
            raise NotFittedError(
                "this CoefficientEstimator is not fitted yet; call fit(dataset) or "
                "CoefficientEstimator.load(directory) first"
            )

    # ------------------------------------------------------------------ checks
    def check_grid(self, t: ArrayLike) -> None:
        """Raise if ``t`` is not the time grid the networks were trained on.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Sample times of the records to be estimated.

        Raises
        ------
        DataError
            If ``t`` has another length, span or spacing than ``t_`` (the
            networks read sample ``k`` as the response at ``t_[k]``; records
            on another grid must be resampled first).
        NotFittedError
            If the estimator is not fitted.
        """
        self._check_is_fitted()
        try:
            t = np.asarray(t, dtype=float)
        except (TypeError, ValueError) as exc:
            raise DataError(f"t must be an array of numbers: {exc}") from None
        if t.ndim != 1:
            raise DataError(f"t must be 1-D, got an array of shape {t.shape}")
        if t.size != self.n_samples_:
            got = f"{t.size} samples" + (f" on [{t[0]:g}, {t[-1]:g}] s" if t.size else "")
            raise DataError(
                f"t has {got} but the estimator was trained on {self._grid_text()}; "
                "resample the records onto the training grid"
            )
        k = grid_difference(t, self.t_)
        if k is not None:
            raise DataError(
                f"t differs from the training grid ({self._grid_text()}): t[{k}] = {t[k]:g} "
                f"but the networks expect {self.t_[k]:g}; resample the records onto the "
                "training grid"
            )

    def _records(self, responses: Any, t: ArrayLike | None) -> tuple[NDArray[np.float64], bool]:
        return checked_records(self, responses, t)

    # ------------------------------------------------------------------ prediction
    def predict(
        self, responses: ArrayLike | ResponseDataset, *, t: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """Estimate the Kautz coefficients of measured responses.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            Records on the training grid ``t_``.  A data set is checked for
            its grid and its kind.
        t : array-like of shape (n_samples,), optional
            Sample times of the records; checked with :meth:`check_grid`.

        Returns
        -------
        ndarray of shape (n_functions,) or (n_records, n_functions)
            1-D for one 1-D record.

        Raises
        ------
        DimensionError
            If the records have the wrong number of samples or dimensions.
        DataError
            On NaN/inf values, another grid, or another kind of response.
        NotFittedError
            If the estimator is not fitted.
        """
        X, single = self._records(responses, t)
        Z = self.input_scaler_.transform(X).astype(np.float32)
        out = np.empty((X.shape[0], self.n_functions_))
        with torch.no_grad():
            for start in range(0, X.shape[0], _PREDICT_BATCH):
                xb = torch.from_numpy(Z[start : start + _PREDICT_BATCH])
                parts = [net(xb) for net in self.networks_]
                out[start : start + xb.shape[0]] = torch.cat(parts, dim=1).double().numpy()
        coef = self.label_scaler_.inverse_transform(out)
        return coef[0] if single else coef

    def predict_models(
        self, responses: ArrayLike | ResponseDataset, *, t: ArrayLike | None = None
    ) -> list[KautzModel]:
        """Estimate one :class:`~kautztwin.KautzModel` per record.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            As in :meth:`predict`.
        t : array-like of shape (n_samples,), optional
            Sample times, checked with :meth:`check_grid`.

        Returns
        -------
        list of KautzModel
            One model on ``basis_`` per record (a list of one for a 1-D record).
        """
        coef = np.atleast_2d(self.predict(responses, t=t))
        return [KautzModel(self.basis_, c) for c in coef]

    def estimate(
        self,
        responses: ArrayLike | ResponseDataset,
        *,
        t: ArrayLike | None = None,
        level: float = DEFAULT_LEVEL,
    ) -> ResponseEstimate:
        """Estimate every record's model with its uncertainty (:mod:`kautztwin.nn.uncertainty`).

        The estimate is :meth:`predict_models`' (the networks' coefficients on
        ``basis_``); its uncertainty is the least-squares covariance of the
        coefficients on the fixed basis with an AR(1) noise model read from the
        residual, times ``uncertainty_scale_`` (1 until :meth:`calibrate`).  The
        poles are fixed, so their block of the covariance is zero.

        Parameters
        ----------
        responses : array-like of shape (n_samples,) or (n_records, n_samples), or ResponseDataset
            Records on the training grid ``t_``.
        t : array-like of shape (n_samples,), optional
            Sample times, checked with :meth:`check_grid`.
        level : float, default=0.9
            Level of the bands and of ``relative_width``.

        Returns
        -------
        ResponseEstimate
            With a record axis; ``relative_width`` is one number per record.
        """
        X, _ = checked_records(self, responses, t)
        return fixed_basis_estimate(
            self.basis_, self.t_, self.kind_, X, self.predict(X),
            scale=self.uncertainty_scale_, calibrated=self.calibration_ is not None,
            level=level,
        )

    def calibrate(
        self, dataset: ResponseDataset, *, level: float = DEFAULT_LEVEL
    ) -> CoefficientEstimator:
        """Fit the calibration scale of :meth:`estimate`'s bands on fresh records.

        Parameters
        ----------
        dataset : ResponseDataset
            Fresh noisy records with their noise-free responses ``dataset.clean``.
        level : float, default=0.9

        Returns
        -------
        CoefficientEstimator
            ``self``, with ``uncertainty_scale_`` and ``calibration_`` set.
        """
        check_dataset(dataset)
        X, _ = checked_records(self, dataset, None)
        raw = fixed_basis_estimate(self.basis_, self.t_, self.kind_, X, self.predict(X),
                                   level=level)
        self.uncertainty_scale_, self.calibration_ = calibrate_estimate(raw, dataset.clean)
        return self

    # ------------------------------------------------------------------ files
    def _state(self) -> dict[str, torch.Tensor]:
        return {
            f"net{k}.{name}": tensor.detach().cpu().contiguous()
            for k, net in enumerate(self.networks_)
            for name, tensor in net.state_dict().items()
        }

    def save(self, directory: str | Path) -> Path:
        """Write the fitted estimator to a directory (created if needed).

        Two files: ``weights.pt``, a flat dictionary of tensors written with
        ``torch.save`` (loaded back with ``weights_only=True``), and
        ``metadata.json`` with the format version, the kautztwin version, the
        basis, the time grid (its ends, length, the samples and their sha256),
        the kind, the normalisation, the architecture, the training options,
        the loss curves, the sha256 of ``weights.pt`` and its own checksum.

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
    def load(cls, directory: str | Path) -> CoefficientEstimator:
        """Read an estimator written by :meth:`save`, verifying its checksums.

        Parameters
        ----------
        directory : str or path-like

        Returns
        -------
        CoefficientEstimator
            Fitted, ready to :meth:`predict`.

        Raises
        ------
        DataError
            If a file is missing or unreadable, of another format version,
            malformed, or was modified after saving (checksum mismatch).
        """
        return load_estimator(cls, directory)

    # ------------------------------------------------------------------ summaries
    @property
    def n_parameters_(self) -> int:
        """Trainable parameters of all networks together."""
        self._check_is_fitted()
        return sum(p.numel() for net in self.networks_ for p in net.parameters())

    @property
    def training_seconds_(self) -> float:
        """Total training time of all networks, in seconds."""
        self._check_is_fitted()
        return math.fsum(h.seconds for h in self.histories_)
