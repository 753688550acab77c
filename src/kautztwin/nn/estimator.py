"""Neural estimator of Kautz coefficients from measured noisy responses (the paper's DNN)."""

from __future__ import annotations

import copy
import hashlib
import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from ..approx import KautzModel
from ..basis import KautzBasis
from ..datasets import ResponseDataset
from ..exceptions import DataError, DimensionError, KautzTwinError, NotFittedError
from .networks import PaperNetwork, paper_parameter_count
from .training import (
    Standardizer,
    TrainingConfig,
    TrainingHistory,
    fit_network,
    split_indices,
)

__all__ = ["CoefficientEstimator"]

_FORMAT = "kautztwin.CoefficientEstimator"
_FORMAT_VERSION = 1
_WEIGHTS = "weights.pt"
_METADATA = "metadata.json"
_PREDICT_BATCH = 4096
_GRID_RTOL = 1e-9  # relative to the grid span: two grids closer than this are the same grid
# default fine-tuning run (the estimators' fine_tune): a share of the epochs and of the
# learning rate of the original configuration
_FINE_TUNE_EPOCHS = 0.25
_FINE_TUNE_LEARNING_RATE = 1.0 / 3.0


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _grid_hash(t: NDArray[np.float64]) -> str:
    return hashlib.sha256(np.ascontiguousarray(t, dtype="<f8").tobytes()).hexdigest()


def _canonical(meta: Mapping[str, Any]) -> bytes:
    body = {k: v for k, v in meta.items() if k != "metadata_sha256"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def _check_seed(value: Any, name: str) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 0:
        raise DataError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


def _check_fine_tune_data(est: Any, dataset: Any) -> None:
    """Fitted ``est``, and ``dataset`` a data set of its kind on its grid (both estimators)."""
    est._check_is_fitted()
    if not isinstance(dataset, ResponseDataset):
        raise DataError(
            f"dataset must be a kautztwin.datasets.ResponseDataset, got {type(dataset).__name__}"
        )
    if dataset.kind != est.kind_:
        raise DataError(
            f"the data set holds {dataset.kind} responses but the estimator was trained on "
            f"{est.kind_} responses"
        )
    est.check_grid(dataset.t)


def _child_seed(random_state: int, k: int) -> int:
    return int(np.random.SeedSequence([random_state, k]).generate_state(1)[0])


def _fine_tune_config(
    base: TrainingConfig, config: TrainingConfig | Mapping[str, Any] | None
) -> TrainingConfig:
    """Configuration of a fine-tuning run from the original one (the estimators' ``fine_tune``).

    ``None``: ``base`` with a quarter of its epochs (rounded up) and a third of its
    learning rate; a mapping overrides fields of that default; a ``TrainingConfig``
    is used as it is.
    """
    if isinstance(config, TrainingConfig):
        return config
    default = base.replace(
        max_epochs=math.ceil(base.max_epochs * _FINE_TUNE_EPOCHS),
        learning_rate=base.learning_rate * _FINE_TUNE_LEARNING_RATE,
    )
    if config is None:
        return default
    if not isinstance(config, Mapping):
        raise DataError(
            "config must be a TrainingConfig, a mapping of option overrides or None; "
            f"got {type(config).__name__}"
        )
    return default.replace(**dict(config))


def _mse(module: torch.nn.Module, batch: tuple[torch.Tensor, ...]) -> torch.Tensor:
    return torch.nn.functional.mse_loss(module(batch[0]), batch[1])


def _save_verified(
    directory: str | Path,
    fmt: str,
    version: int,
    state: dict[str, torch.Tensor],
    t: NDArray[np.float64],
    fields: dict[str, Any],
) -> Path:
    """Write ``weights.pt`` and ``metadata.json`` with checksums (read back by ``_load_verified``).

    The common header (format, versions, time grid and its hash, weights checksum)
    is written here; ``fields`` adds what the estimator needs to rebuild itself.
    """
    from .. import __version__

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    weights = directory / _WEIGHTS
    torch.save(state, weights)
    meta: dict[str, Any] = {
        "format": fmt,
        "format_version": version,
        "kautztwin_version": __version__,
        "torch_version": torch.__version__,
        "time_grid": {
            "t0": float(t[0]),
            "t_end": float(t[-1]),
            "n_samples": int(t.size),
            "sha256": _grid_hash(t),
            "t": t.tolist(),
        },
        **fields,
        "weights": {"file": _WEIGHTS, "sha256": _sha256_file(weights)},
    }
    meta["metadata_sha256"] = hashlib.sha256(_canonical(meta)).hexdigest()
    (directory / _METADATA).write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return directory


def _load_verified(
    directory: str | Path,
    fmt: str,
    version: int,
    label: str,
    from_files: Callable[[dict[str, Any], Path], Any],
) -> Any:
    """Read a model folder, verify format, version and both checksums, then build the model.

    Shared by every estimator that saves ``metadata.json`` + ``weights.pt``; any
    problem is a one-line :class:`DataError`.
    """
    directory = Path(directory)
    meta_path = directory / _METADATA
    weights_path = directory / _WEIGHTS
    for path in (meta_path, weights_path):
        if not path.is_file():
            raise DataError(f"model file {str(path)!r} does not exist")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise DataError(f"cannot read model file {str(meta_path)!r}: {msg}") from None
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        raise DataError(f"{str(meta_path)!r} is not a kautztwin {label} file")
    if meta.get("format_version") != version:
        raise DataError(
            f"model file {str(meta_path)!r} has format version "
            f"{meta.get('format_version')!r}; this kautztwin reads version {version}"
        )
    try:
        expected = hashlib.sha256(_canonical(meta)).hexdigest()
    except ValueError:
        expected = ""
    if meta.get("metadata_sha256") != expected:
        raise DataError(f"model file {str(meta_path)!r} was modified (checksum mismatch)")
    try:
        weights_sha = meta["weights"]["sha256"]
    except (KeyError, TypeError):
        raise DataError(
            f"model file {str(meta_path)!r} is malformed: no weights checksum"
        ) from None
    if _sha256_file(weights_path) != weights_sha:
        raise DataError(f"model file {str(weights_path)!r} was modified (checksum mismatch)")
    try:
        return from_files(meta, weights_path)
    except KautzTwinError as exc:
        raise DataError(f"model {str(directory)!r} is malformed: {exc}") from None
    except (KeyError, TypeError, ValueError, RuntimeError, OSError) as exc:
        msg = " ".join(str(exc).split())[:300]
        raise DataError(
            f"model {str(directory)!r} is malformed: {type(exc).__name__}: {msg}"
        ) from None


def _checked_records(
    est: Any, responses: Any, t: ArrayLike | None, *, copy: bool = False
) -> tuple[NDArray[np.float64], bool]:
    """Records to estimate, checked against a fitted estimator's grid and kind (both estimators).

    ``responses`` is a :class:`ResponseDataset` or an array of one record (1-D)
    or many (2-D); returns the 2-D float array (a copy with ``copy=True``) and
    whether a single record was given.
    """
    est._check_is_fitted()
    if isinstance(responses, ResponseDataset):
        if responses.kind != est.kind_:
            raise DataError(
                f"the data set holds {responses.kind} responses but the estimator was "
                f"trained on {est.kind_} responses"
            )
        t = responses.t if t is None else t
        responses = responses.responses
    if t is not None:
        est.check_grid(t)
    try:
        X = np.array(responses, dtype=float) if copy else np.asarray(responses, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DataError(f"responses must be an array of numbers: {exc}") from None
    if X.ndim not in (1, 2):
        raise DimensionError(
            f"responses must be 1-D (one record) or 2-D (n_records, n_samples), got shape {X.shape}"
        )
    single = X.ndim == 1
    X = np.atleast_2d(X)
    if X.shape[1] != est.n_samples_:
        raise DimensionError(
            f"responses has {X.shape[1]} samples per record but the estimator was trained "
            f"on {est._grid_text()}; resample the records onto the training grid"
        )
    bad = ~np.isfinite(X)
    if bad.any():
        i, k = (int(v) for v in np.argwhere(bad)[0])
        where = f"sample {k}" if single else f"record {i}, sample {k}"
        raise DataError(f"responses contains a non-finite value ({X[i, k]}) at {where}")
    return X, single


class _ParamsMixin:
    """``set_params`` and ``__repr__`` on top of a class's ``get_params`` (scikit-learn style)."""

    def get_params(self, deep: bool = True) -> dict[str, Any]:  # pragma: no cover - overridden
        raise NotImplementedError

    def set_params(self, **params: Any) -> Any:
        """Set constructor parameters (scikit-learn convention); returns ``self``."""
        valid = self.get_params()
        for key, value in params.items():
            if key not in valid:
                raise DataError(
                    f"invalid parameter {key!r} for {type(self).__name__}; "
                    f"valid: {', '.join(sorted(valid))}"
                )
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items() if v is not None)
        return f"{type(self).__name__}({args})"


class CoefficientEstimator(_ParamsMixin):
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
        if not isinstance(dataset, ResponseDataset):
            raise DataError(
                f"dataset must be a kautztwin.datasets.ResponseDataset, got "
                f"{type(dataset).__name__}"
            )
        config = self._resolve_config()
        seed = _check_seed(self.random_state, "random_state")
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
        _check_fine_tune_data(self, dataset)
        if dataset.n_functions != self.n_functions_:
            raise DataError(
                f"the data set is labelled with {dataset.n_functions} Kautz coefficients but the "
                f"estimator predicts {self.n_functions_}; fine-tune on a basis with "
                f"{self.n_functions_} poles"
            )
        seed = _check_seed(
            self.random_state if random_state is None else random_state, "random_state"
        )
        run_config = _fine_tune_config(self.config_, config)
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
        """Split, standardise, train one network per target and set the fitted attributes.

        Shared by :meth:`fit` (fresh networks seeded per target) and
        :meth:`fine_tune` (deep copies of ``start``, which stays unchanged).
        """
        train_idx, val_idx = split_indices(len(dataset), config.validation_fraction, seed)
        X = np.asarray(dataset.responses, dtype=float)
        Y = np.asarray(dataset.coefficients, dtype=float)
        input_scaler = Standardizer.fit(X[train_idx])
        # a constant label (no uncertainty in it) is predicted exactly, not mean + net output
        label_scaler = Standardizer.fit(Y[train_idx], constant_scale=None)
        Xs = torch.from_numpy(input_scaler.transform(X).astype(np.float32))
        Ys = torch.from_numpy(label_scaler.transform(Y).astype(np.float32))
        tr = torch.from_numpy(train_idx)
        va = torch.from_numpy(val_idx)
        n_functions = Y.shape[1]
        targets = (
            [slice(k, k + 1) for k in range(n_functions)]
            if self.per_coefficient
            else [slice(0, n_functions)]
        )
        if start is not None and len(start) != len(targets):
            raise DataError(
                f"per_coefficient={self.per_coefficient!r} needs {len(targets)} network(s) but "
                f"the estimator to fine-tune has {len(start)}"
            )
        networks: list[PaperNetwork] = []
        histories: list[TrainingHistory] = []
        for k, cols in enumerate(targets):
            child = _child_seed(seed, k)
            if start is None:
                with torch.random.fork_rng(devices=[]):
                    torch.manual_seed(child)
                    net = PaperNetwork(X.shape[1], cols.stop - cols.start)
            else:
                net = copy.deepcopy(start[k])
                net.requires_grad_(True)
            history = fit_network(
                net,
                (Xs[tr], Ys[tr, cols]),
                (Xs[va], Ys[va, cols]),
                _mse,
                config,
                random_state=child,
                progress=bool(self.progress),
            )
            networks.append(net)
            histories.append(history)

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

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "networks_"):
            raise NotFittedError(
                "this CoefficientEstimator is not fitted yet; call fit(dataset) or "
                "CoefficientEstimator.load(directory) first"
            )

    # ------------------------------------------------------------------ checks
    def _grid_text(self) -> str:
        return f"{self.n_samples_} samples on [{self.t_[0]:g}, {self.t_[-1]:g}] s"

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
        span = float(self.t_[-1] - self.t_[0]) or 1.0
        diff = np.abs(t - self.t_)
        if not np.all(np.isfinite(t)) or np.max(diff) > _GRID_RTOL * span:
            k = int(np.argmax(np.where(np.isfinite(diff), diff, np.inf)))
            raise DataError(
                f"t differs from the training grid ({self._grid_text()}): t[{k}] = {t[k]:g} "
                f"but the networks expect {self.t_[k]:g}; resample the records onto the "
                "training grid"
            )

    def _records(self, responses: Any, t: ArrayLike | None) -> tuple[NDArray[np.float64], bool]:
        return _checked_records(self, responses, t)

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
        net = self.networks_[0]
        fields: dict[str, Any] = {
            "basis": self.basis_.to_dict(),
            "kind": self.kind_,
            "normalization": {
                "inputs": self.input_scaler_.to_dict(),
                "labels": self.label_scaler_.to_dict(),
            },
            "architecture": {
                "network": type(net).__name__,
                "n_networks": len(self.networks_),
                "n_inputs": net.n_inputs,
                "n_outputs": net.n_outputs,
                "n_parameters": paper_parameter_count(net.n_inputs, net.n_outputs),
                "per_coefficient": bool(self.per_coefficient),
                "dtype": "float32",
            },
            "preset": self.preset,
            "random_state": int(self.random_state),
            "config": self.config_.to_dict(),
            "histories": [h.to_dict() for h in self.histories_],
        }
        return _save_verified(directory, _FORMAT, _FORMAT_VERSION, self._state(), self.t_, fields)

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
        return _load_verified(
            directory, _FORMAT, _FORMAT_VERSION, "CoefficientEstimator", cls._from_files
        )

    @classmethod
    def _from_files(cls, meta: dict[str, Any], weights_path: Path) -> CoefficientEstimator:
        grid = meta["time_grid"]
        t = np.asarray(grid["t"], dtype=float)
        if t.shape != (int(grid["n_samples"]),) or _grid_hash(t) != grid["sha256"]:
            raise DataError("the stored time grid does not match its length or hash")
        b = meta["basis"]
        basis = KautzBasis([complex(re, im) for re, im in b["poles"]], dt=b.get("dt", 0.0))
        arch = meta["architecture"]
        if arch["network"] != PaperNetwork.__name__:
            raise DataError(f"unknown network {arch['network']!r}")
        state = torch.load(weights_path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise DataError("the weights file does not hold a dictionary of tensors")
        networks = []
        for k in range(int(arch["n_networks"])):
            net = PaperNetwork(int(arch["n_inputs"]), int(arch["n_outputs"]))
            prefix = f"net{k}."
            net.load_state_dict(
                {name[len(prefix) :]: v for name, v in state.items() if name.startswith(prefix)},
                strict=True,
            )
            networks.append(net)
        expected = basis.n_functions if arch["per_coefficient"] else 1
        n_out = int(arch["n_outputs"]) * len(networks)
        if len(networks) != expected or n_out != basis.n_functions:
            raise DataError(
                f"{len(networks)} network(s) with {arch['n_outputs']} output(s) do not give the "
                f"{basis.n_functions} coefficients of the basis"
            )
        input_scaler = Standardizer.from_dict(meta["normalization"]["inputs"])
        label_scaler = Standardizer.from_dict(meta["normalization"]["labels"])
        if input_scaler.n_features != t.size or label_scaler.n_features != basis.n_functions:
            raise DataError("the normalisation does not match the grid or the basis")
        est = cls(
            preset=meta["preset"],
            per_coefficient=bool(arch["per_coefficient"]),
            random_state=int(meta["random_state"]),
        )
        est._set_fitted(
            networks=networks,
            histories=[TrainingHistory.from_dict(h) for h in meta["histories"]],
            t=t,
            basis=basis,
            kind=str(meta["kind"]),
            config=TrainingConfig.from_dict(meta["config"]),
            input_scaler=input_scaler,
            label_scaler=label_scaler,
        )
        return est

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
