"""Training of the adaptive-pole network: options, structure, features, stage-wise fit.

What :meth:`AdaptivePoleEstimator.fit <kautztwin.nn.AdaptivePoleEstimator.fit>` and
``fine_tune`` do, as functions: check the options (:func:`check_options`), choose the block
structure and its centre (:func:`resolve_structure`) and the relative degree of the fit
(:func:`resolve_relative_degree`), build a fresh network on the principal
subspace of the noise-free records (:func:`new_network`), train it stage by stage
(:func:`train_stages`: a warm start on the true poles, then the end-to-end loss
``1 - fit/100``), and draw free training data from an uncertain system
(:func:`draw_training_data`).

Size: it is one job in one file, about 700 lines with the numpydoc of its functions; the
loss functions, the label matching and the reading of the relative degree from the
labelled records (:func:`resolve_relative_degree`) belong to it.
"""

from __future__ import annotations

import copy
import functools
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import nn

from ..._validation import check_choice, check_int, check_positive
from ...approx import optimize_poles
from ...basis import KautzBasis
from ...basis._blocks import PAIR, REAL, parse_poles
from ...datasets import ParametricSystem, ResponseDataset, draw_parameters, make_dataset
from ...exceptions import ConvergenceWarning, DataError, KautzTwinError
from ..config import TrainingConfig, TrainingHistory
from ..data import Standardizer, split_indices
from ..kautz_torch import (
    kautz_functions,
    lstsq_coefficients,
    network_matrices,
    response_weights,
)
from ..training import fit_network
from .network import RECORD_BATCH, AdaptivePoleNetwork

__all__ = [
    "DEFAULT_ADAPTIVE_CONFIG",
    "check_options",
    "draw_training_data",
    "new_network",
    "keep_relative_degree",
    "resolve_config",
    "resolve_relative_degree",
    "resolve_structure",
    "train_stages",
]

_PCA_RECORDS = 4000  # clean training records used for the feature subspace

#: Training configuration used when ``config`` is ``None`` (tuned on the paper's
#: system under +-50 % uncertainty; see ``benchmarks/bench_adaptive.py``).
DEFAULT_ADAPTIVE_CONFIG = TrainingConfig(
    learning_rate=3e-4, max_epochs=6, batch_size=256, grad_clip=1.0, patience=3
)


# =========================================================================== losses
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



# =========================================================================== labels and data
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


# =========================================================================== options
def resolve_config(config: TrainingConfig | Mapping[str, Any] | str | None) -> TrainingConfig:
    """The training configuration an estimator's ``config`` option stands for.

    Parameters
    ----------
    config : TrainingConfig, mapping, str or None
        A full configuration, a mapping of fields to override in
        :data:`DEFAULT_ADAPTIVE_CONFIG`, a preset name, or ``None`` for that default.

    Returns
    -------
    TrainingConfig

    Raises
    ------
    DataError
        On another type, an unknown preset or field, or an out-of-range value.
    """
    if isinstance(config, TrainingConfig):
        return config
    if config is None:
        return DEFAULT_ADAPTIVE_CONFIG
    if isinstance(config, str):
        return TrainingConfig.preset(config)
    if isinstance(config, Mapping):
        return DEFAULT_ADAPTIVE_CONFIG.replace(**dict(config))
    raise DataError(
        "config must be a TrainingConfig, a mapping of option overrides, a preset name or "
        f"None; got {type(config).__name__}"
    )


def check_options(
    params: Mapping[str, Any],
) -> tuple[int, tuple[int, ...], int, int, float, float]:
    """Check an estimator's constructor parameters (its ``get_params()``).

    Parameters
    ----------
    params : mapping
        The constructor parameters of an ``AdaptivePoleEstimator``.

    Returns
    -------
    random_state, hidden, n_features, n_stages, pole_range, step
        The checked options the network is built from.

    Raises
    ------
    DataError
        If an option is out of range.
    """
    seed = check_int(params["random_state"], "random_state", minimum=0)
    try:
        hidden = tuple(params["hidden"])
        for h in hidden:
            check_int(h, "hidden", minimum=1)
    except (TypeError, DataError):
        raise DataError(
            f"hidden must be a sequence of positive integers, got {params['hidden']!r}"
        ) from None
    n_features = check_int(params["n_features"], "n_features", minimum=1)
    try:
        pole_range = float(params["pole_range"])
    except (TypeError, ValueError):
        pole_range = math.nan
    if not (math.isfinite(pole_range) and pole_range > 1.0):
        raise DataError(f"pole_range must be a number > 1, got {params['pole_range']!r}")
    n_stages = check_int(params["n_stages"], "n_stages", minimum=1)
    step = check_positive(params["step"], "step")
    check_choice(params["weights"], "weights", ("uniform", "simpson"))
    check_int(params["pretrain_epochs"], "pretrain_epochs", minimum=0)
    check_int(params["refine_max_iter"], "refine_max_iter", minimum=1)
    return seed, hidden, n_features, n_stages, pole_range, step


def resolve_structure(
    structure: ArrayLike | Sequence[str] | None,
    default_poles: ArrayLike,
    t: NDArray,
    clean: NDArray,
    kind: str,
) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    """Block structure and centre parameters an estimator's ``structure`` option stands for.

    Parameters
    ----------
    structure : array-like of complex, sequence of {'real', 'pair'}, or None
        Pole locations (structure and centre), block kinds (structure only: the centre
        is fitted to typical noise-free records), or ``None`` for ``default_poles``.
    default_poles : array-like of complex
        The data set's basis poles.
    t : ndarray of shape (n_samples,)
        Time grid of the records.
    clean : ndarray of shape (n_records, n_samples)
        Noise-free records.
    kind : {'impulse', 'step'}
        What the records are.

    Returns
    -------
    kinds : tuple of str
    centre : ndarray of shape (n_params,)

    Raises
    ------
    DataError
        On text, unknown block kinds or invalid poles.
    """
    s = structure
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


_RELATIVE_DEGREE_RECORDS = 500  # labelled noise-free records the 'auto' relative degree reads
_MARKOV_TOL = 1e-6  # a Markov parameter below this (relative) counts as zero
_EXACT_FIT_TOL = 1e-6  # a record is in its true poles' span below this relative residual


def resolve_relative_degree(
    option: int | str | None,
    kinds: tuple[str, ...],
    t: NDArray,
    clean: NDArray,
    kind: str,
    labels: NDArray,
    valid: NDArray,
) -> int:
    """Relative degree an estimator's ``relative_degree`` option stands for.

    ``'auto'`` reads it from the noise-free training records whose true poles fit the
    block structure (at most 500): each is projected onto the basis of its *own* poles
    (exact to rounding when the record lies in that span) and its Markov parameters
    :math:`c^T A^k B = y^{(k)}(0)` are computed; the relative degree is one more than the
    number of leading ones that vanish (below ``1e-6`` relative) in every such record.
    Without any (no poles that fit, or a record outside its poles' span) it is ``1``: no
    constraint, the generic fit.

    Parameters
    ----------
    option : int, 'auto' or None
        The option (``None`` means ``1``).
    kinds : tuple of str
        Block structure.
    t : ndarray of shape (n_samples,)
    clean : ndarray of shape (n_records, n_samples)
        Noise-free records.
    kind : {'impulse', 'step'}
        What the records are.
    labels, valid : ndarray
        The records' true poles as block parameters and which fit the structure
        (``_match_labels``).

    Returns
    -------
    int
        In ``[1, n_functions]``.

    Raises
    ------
    DataError
        If the option is neither ``'auto'``, ``None`` nor an integer in ``[1, n_functions]``.
    """
    n = int(labels.shape[1])
    if option is None:
        return 1
    if isinstance(option, str):
        if option != "auto":
            raise DataError(f"relative_degree must be 'auto' or an integer; got {option!r}")
        return _measured_relative_degree(kinds, t, clean, kind, labels, valid)
    r = check_int(option, "relative_degree", minimum=1)
    if r > n:
        raise DataError(
            f"relative_degree must be at most the number of basis functions ({n}); got {r}"
        )
    return r


def _measured_relative_degree(
    kinds: tuple[str, ...],
    t: NDArray,
    clean: NDArray,
    kind: str,
    labels: NDArray,
    valid: NDArray,
) -> int:
    """The ``'auto'`` relative degree of :func:`resolve_relative_degree`."""
    idx = np.flatnonzero(valid)[:_RELATIVE_DEGREE_RECORDS]
    if idx.size == 0:
        return 1
    n = int(labels.shape[1])
    P = torch.as_tensor(labels[idx], dtype=torch.float64)
    y = torch.as_tensor(clean[idx], dtype=torch.float64)
    with torch.no_grad():
        A, B = network_matrices(kinds, P)
        K = kautz_functions(kinds, P, t)
        if kind == "step":
            K = torch.linalg.solve(A, K - B[:, :, None])
        c = lstsq_coefficients(K, y, ridge=0.0)
        residual = (y - (c[:, None, :] @ K)[:, 0]).norm(dim=1) / y.norm(dim=1)
        if bool(torch.any(~torch.isfinite(residual))) or float(residual.max()) > _EXACT_FIT_TOL:
            return 1
        r = 1
        v = B
        while r < n:
            markov = (c * v).sum(dim=1).abs()
            if bool(torch.any(markov > _MARKOV_TOL * c.norm(dim=1) * v.norm(dim=1))):
                break
            r += 1
            v = (A @ v[..., None])[..., 0]
    return r


def keep_relative_degree(
    module: AdaptivePoleNetwork, dataset: ResponseDataset, config: TrainingConfig, seed: int
) -> bool:
    """Whether the trained ``module`` fits its validation records better with its constraint.

    The constraint removes ``relative_degree - 1`` coefficient directions from the fit: less
    noise gets through, but nothing absorbs an error of the poles.  For a network whose poles
    are precise (a well-trained one) that pays; for a small or briefly trained one it can
    cost more than it saves.  The ``'auto'`` option therefore checks, on the validation part
    of the split, the mean ``1 - fit/100`` of the constrained fit against the unconstrained
    fit on the same poles (float64), and keeps the constraint only if it is not worse.

    Parameters
    ----------
    module : AdaptivePoleNetwork
        Trained, with ``relative_degree > 1``.
    dataset : ResponseDataset
        The training data set (its validation part is read).
    config : TrainingConfig
        Its ``validation_fraction`` gives the split.
    seed : int
        Seed of the split.

    Returns
    -------
    bool
    """
    _, val_idx = split_indices(len(dataset), config.validation_fraction, seed)
    if val_idx.size == 0:
        return True
    probe = copy.deepcopy(module).cast(torch.float64).eval()
    x = torch.as_tensor(np.asarray(dataset.responses)[val_idx], dtype=torch.float64)
    clean = torch.as_tensor(np.asarray(dataset.clean)[val_idx], dtype=torch.float64)
    spread = torch.as_tensor(_spread(clean.numpy()))
    w = probe.ls_weights()
    losses = []
    with torch.no_grad():
        # the poles as trained (the correction stages keep their constraint either way)
        params = torch.cat([probe(xb) for xb in x.split(RECORD_BATCH)])
        for r in (probe.relative_degree, 1):
            total = 0.0
            for s in range(0, x.shape[0], RECORD_BATCH):
                b = slice(s, s + RECORD_BATCH)
                K = probe.design(params[b])
                c = probe.least_squares(K, x[b], params[b], w, r)
                fitted = (c[:, None, :] @ K)[:, 0]
                total += float(((clean[b] - fitted).norm(dim=1) / spread[b]).sum())
            losses.append(total)
    return losses[0] <= losses[1]


# =========================================================================== training
def new_network(
    params: Mapping[str, Any], dataset: ResponseDataset, config: TrainingConfig
) -> tuple[AdaptivePoleNetwork, tuple[NDArray[np.float64], NDArray[np.bool_]], int]:
    """A fresh network for ``dataset`` (what ``fit`` trains) and its warm-start labels.

    Checks the options, chooses the structure and its centre, builds the feature
    subspace (principal directions of unit-norm noise-free training responses) and the
    network, seeded by ``random_state``.

    Parameters
    ----------
    params : mapping
        The estimator's constructor parameters.
    dataset : ResponseDataset
        Training records with their noise-free responses and true poles.
    config : TrainingConfig
        The training configuration (its ``validation_fraction`` splits the records).

    Returns
    -------
    module : AdaptivePoleNetwork
        Untrained (it predicts the centre).
    warm_start : (ndarray, ndarray of bool)
        The records' true poles as block parameters, and which records fit the structure.
    seed : int
        The checked ``random_state``.

    Raises
    ------
    DataError
        If an option is invalid or a noise-free record is constant.
    """
    seed, hidden, n_features, n_stages, pole_range, step = check_options(params)
    t = np.asarray(dataset.t, dtype=float)
    kind = dataset.kind
    clean = np.asarray(dataset.clean, dtype=float)
    _spread(clean)
    kinds, centre = resolve_structure(
        params["structure"], dataset.basis_poles, t, clean, kind
    )
    centre = _omega_floor(kinds, centre)
    train_idx, val_idx = split_indices(len(dataset), config.validation_fraction, seed)
    labels, valid = _match_labels(kinds, centre, np.asarray(dataset.poles))
    in_train = np.zeros(len(dataset), dtype=bool)
    in_train[train_idx] = True
    relative_degree = resolve_relative_degree(
        params["relative_degree"], kinds, t, clean, kind, labels, valid & in_train
    )

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
            weights=response_weights(t, params["weights"]).numpy(),
            kind=kind,
            relative_degree=relative_degree,
        )
    return module, (labels, valid), seed


def train_stages(
    module: AdaptivePoleNetwork,
    dataset: ResponseDataset,
    config: TrainingConfig,
    seed: int,
    *,
    warm_start: tuple[NDArray[np.float64], NDArray[np.bool_]] | None,
    pretrain_epochs: int,
    progress: bool,
) -> tuple[list[TrainingHistory], list[TrainingHistory], int]:
    """Train ``module`` stage by stage on ``dataset``, in place.

    Stage ``k`` learns while the others are frozen: a warm start regressing the log block
    parameters on the labels (at most ``pretrain_epochs`` epochs), then the end-to-end
    loss ``1 - fit/100`` of the noise-free responses, both with
    :func:`~kautztwin.nn.fit_network`.  With ``warm_start`` (``fit``: the records'
    log-pole labels and their validity) each stage's input is standardised on the data
    and warm-started; with ``None`` (``fine_tune``: a trained module) its normalisation
    is kept and there is no warm start.

    Parameters
    ----------
    module : AdaptivePoleNetwork
    dataset : ResponseDataset
        Noisy records and their noise-free responses.
    config : TrainingConfig
        Options of the end-to-end runs.
    seed : int
        Seed of the split; stage ``k`` trains with ``seed + k``.
    warm_start : (ndarray, ndarray of bool) or None
        Labels and their validity, or ``None``.
    pretrain_epochs : int
        Most epochs of each warm start.
    progress : bool
        Show a progress bar while training.

    Returns
    -------
    histories : list of TrainingHistory
        End-to-end runs, one per stage.
    pretrain_histories : list of TrainingHistory
        Warm starts (empty without one).
    n_train : int
        Records in the training part of the split.
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
        warm = bool(pretrain_epochs) and tr_l.numel() > 0 and va_l.numel() > 0
    pre_config = TrainingConfig(
        learning_rate=1e-3,
        max_epochs=max(1, int(pretrain_epochs)),
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
                progress=bool(progress),
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
                    for i in torch.arange(X.shape[0]).split(RECORD_BATCH)
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
    return histories, pre_histories, int(train_idx.size)


def draw_training_data(
    params: Mapping[str, Any],
    system: ParametricSystem,
    uncertainty: float | Mapping[str, float],
    t: ArrayLike,
    *,
    noise: float,
    n_train: int,
    kind: str,
    noise_kind: str,
    color_pole: float,
) -> ResponseDataset:
    """Noisy records drawn from an uncertain system (what ``fit_distribution`` trains on).

    Parameters
    ----------
    params : mapping
        The estimator's constructor parameters (``random_state`` seeds the draws;
        pole locations in ``structure`` are the basis of the labels).
    system, uncertainty, t, noise, n_train, kind, noise_kind, color_pole
        As in :meth:`AdaptivePoleEstimator.fit_distribution
        <kautztwin.nn.AdaptivePoleEstimator.fit_distribution>`.

    Returns
    -------
    ResponseDataset

    Raises
    ------
    DataError
        On invalid options (see :func:`~kautztwin.datasets.make_dataset`).
    """
    if not isinstance(system, ParametricSystem):
        raise DataError(f"system must be a ParametricSystem, got {type(system).__name__}")
    check_int(n_train, "n_train", minimum=2)
    seed = check_options(params)[0]
    ss = np.random.SeedSequence([seed, 1])
    draw_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    P = draw_parameters(system, uncertainty, int(n_train), random_state=draw_rng)
    poles = system.poles()
    s = params["structure"]
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
    return data
