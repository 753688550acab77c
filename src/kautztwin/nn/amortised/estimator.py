"""The amortised estimator: one network for every stable system up to an order, VARPRO on top.

Size: the module passes 600 lines (and the class 400) only through the numpydoc of the
public methods; the estimator's work is in the sibling modules (``network``, ``training``,
``systems``, ``refine``, ``pretrained``) and in :func:`kautztwin.optimize_poles`.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from ..._quadrature import least_squares_weights
from ..._validation import check_choice, check_int, check_records, check_time
from ...approx import KautzModel, optimize_poles
from ...basis import KautzBasis
from ...exceptions import ConvergenceWarning, DataError, KautzTwinError, NotFittedError
from ...metrics import fit_percent
from ..config import TrainingHistory
from ..estimator_base import EstimatorMixin
from ..model_files import check_network, load_verified, load_weights, save_verified
from .network import AmortisedPoleNetwork, bin_features, block_roots
from .pretrained import pretrained_folder
from .refine import refine_map, theta_from_poles
from .systems import random_systems
from .training import train_network

__all__ = ["AmortisedEstimate", "AmortisedEstimator"]

_FORMAT, _VERSION = "kautztwin.AmortisedEstimator", 1
_KIND_FILE = "estimator.json"  # read by ``kautztwin estimate`` to pick the estimator
_WEIGHTS = ("uniform", "simpson")
_REFINE = ("map", "varpro")
_AMBIGUOUS = 4.0  # a real pair within this rate ratio is also refined as a complex pair


@dataclass(frozen=True, eq=False)
class AmortisedEstimate:
    """Kautz models of records: poles, least-squares coefficients, fitted responses.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Sample times of the records.
    poles : ndarray of complex, shape (n_records, n_functions)
        Basis poles of each record (conjugates adjacent).
    coefficients : ndarray of shape (n_records, n_functions)
        Least-squares coefficients of each record in :class:`~kautztwin.KautzBasis` of
        its poles.
    response : ndarray of shape (n_records, n_samples)
        Fitted impulse responses.
    fit_percent : ndarray of shape (n_records,)
        Fit percent of each fitted response to its (noisy) record.
    refined : bool
        Whether the poles were refined by variable projection.
    seconds_per_record : float
        Wall-clock time of the estimate per record.
    """

    t: NDArray[np.float64]
    poles: NDArray[np.complex128]
    coefficients: NDArray[np.float64]
    response: NDArray[np.float64]
    fit_percent: NDArray[np.float64]
    refined: bool
    seconds_per_record: float

    def __len__(self) -> int:
        return int(self.poles.shape[0])

    def model(self, index: int = 0) -> KautzModel:
        """The Kautz model of record ``index``."""
        return KautzModel(KautzBasis(self.poles[index]), self.coefficients[index])

    def models(self) -> list[KautzModel]:
        """One Kautz model per record."""
        return [self.model(i) for i in range(len(self))]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: poles as ``[re, im]``, coefficients and fit of every record."""
        return {
            "refined": self.refined,
            "seconds_per_record": self.seconds_per_record,
            "poles": [[[float(p.real), float(p.imag)] for p in row] for row in self.poles],
            "coefficients": self.coefficients.tolist(),
            "fit_percent": self.fit_percent.tolist(),
        }


def _lstsq(t: NDArray, y: NDArray, poles: NDArray, sw: NDArray | None) -> tuple[NDArray, NDArray]:
    """Coefficients in ``KautzBasis(poles)`` and fitted response of one record."""
    K = KautzBasis(poles).evaluate(t)
    M = K.T if sw is None else K.T * sw[:, None]
    c, *_ = np.linalg.lstsq(M, y if sw is None else y * sw, rcond=None)
    return c, c @ K


def _flipped(poles: NDArray, n_quad: int) -> NDArray | None:
    """The start with every ambiguous second-order block read the other way, or None.

    A block of two real poles within ``_AMBIGUOUS`` of each other becomes the complex
    pair of the same mean rate (imaginary part a quarter of it); a complex pair with
    ``|Im| < |Re|`` becomes two real poles at half and one and a half times its rate.
    Variable projection keeps a start's real/complex structure, so this second start
    lets it cross the boundary that the network's output may sit on the wrong side of.
    """
    out = poles.copy()
    changed = False
    for j in range(n_quad):
        a, b = poles[2 * j], poles[2 * j + 1]
        if a.imag == 0 and b.imag == 0:
            lo, hi = sorted((-a.real, -b.real))
            if hi < _AMBIGUOUS * lo:
                s = 0.5 * (lo + hi)
                out[2 * j], out[2 * j + 1] = complex(-s, 0.25 * s), complex(-s, -0.25 * s)
                changed = True
        elif abs(a.imag) < abs(a.real):
            s = -a.real
            out[2 * j], out[2 * j + 1] = complex(-0.5 * s, 0), complex(-1.5 * s, 0)
            changed = True
    return out if changed else None


class AmortisedEstimator(EstimatorMixin):
    r"""One pole network for every stable system up to an order; VARPRO refinement on top.

    The network is trained once on random stable systems
    (:func:`~kautztwin.nn.amortised.random_systems`: orders ``1 .. max_order``, real
    and complex poles over a decade and a half of rates, zeros on either side, delays,
    white and coloured noise), with time measured in record lengths, so it applies to a
    plant no one trained it for, on any grid: it maps a record's normalised shape to the
    poles of a ``max_order``-function Kautz basis, and the coefficients are the exact
    least-squares projection of the record on that basis (linear-exact given the
    poles).  ``refine=True`` then runs variable projection
    (:func:`kautztwin.optimize_poles`) from the network's poles: the accurate path.
    :meth:`load_default` returns the model shipped with kautztwin (trained with the
    defaults below).

    Parameters
    ----------
    max_order : int, default=5
        Basis functions (and the largest system order of the training draws).  Every
        stable real pole set of this order is representable: ``max_order // 2``
        second-order blocks :math:`s^2 + bs + c` (a complex pair or two real poles)
        and one real block if odd.
    hidden : sequence of int, default=(256, 256, 256)
        Hidden widths of the perceptron.
    n_bins : int, default=128
        Features: bin averages of the record over this many equal bins.
    n_records : int, default=40000
        Random systems drawn for training.
    n_samples : int, default=512
        Samples of each training record.
    max_epochs : int, default=40
        Epochs of training.
    batch_size : int, default=256
        Records per step.
    learning_rate : float, default=2e-3
        Peak learning rate (one-cycle schedule).
    validation_fraction : float, default=0.1
        Share of the records held out; the best validation epoch is kept.
    weights : {'uniform', 'simpson'}, default='uniform'
        Least-squares weights of the samples: ordinary least squares (the norm of the
        fit percent), or Simpson's rule (as :func:`kautztwin.project` with
        ``method='lstsq'``).
    refine_method : {'map', 'varpro'}, default='map'
        ``'map'``: variable projection of the AR(1)-whitened record with the network's
        poles as a Gaussian prior on the log block parameters
        (:func:`~kautztwin.nn.amortised.refine.refine_map`); ``'varpro'``: plain
        :func:`kautztwin.optimize_poles` from the network's poles.
    prior_scale : float, default=0.3
        Prior standard deviation of the network's log block parameters (``'map'``;
        ``inf``: no prior).
    refine_rounds : int, default=1
        Searches of ``'map'``, the noise model of each re-estimated from the previous
        residual (the first comes from the network's fit, whose residual also holds the
        network's approximation error and so overstates the noise when the network is
        far off).
    refine_max_iter : int, default=50
        ``max_iter`` of each variable-projection refinement.
    refine_tol : float, default=1e-8
        ``tol`` of each refinement (relative change of the residual and of the poles; the
        fit percent it gives is settled to far better than 0.01 points).
    random_state : int, default=0
        Seed of the training draws, the split, the weights and the shuffles.
    progress : bool, default=False
        A progress bar while training.

    Attributes
    ----------
    network_ : AmortisedPoleNetwork
        The trained module (``eval`` mode).
    history_ : TrainingHistory
        Loss curves (``1 - fit/100`` of the noise-free responses).
    kinds_ : tuple of str
        Block structure of the network.
    tau_ : ndarray of shape (n_samples,)
        Normalised training grid.
    training_seconds_ : float
        Drawing the records and training.

    See Also
    --------
    kautztwin.nn.AdaptivePoleEstimator : Trained for one plant family (more accurate there).
    kautztwin.optimize_poles : The refinement.

    Notes
    -----
    With record length :math:`T` the network sees :math:`y(\tau T)`, :math:`\tau \in [0, 1]`,
    as unit-RMS bin averages, and returns normalised block parameters
    :math:`\tilde b, \sqrt{\tilde c}, \tilde p`; the plant's are
    :math:`b = \tilde b / T`, :math:`\sqrt c = \sqrt{\tilde c} / T`, :math:`p = \tilde p / T`.

    Examples
    --------
    >>> import numpy as np
    >>> import torch
    >>> from kautztwin.nn.amortised import AmortisedEstimator
    >>> _ = torch.set_num_threads(1)
    >>> est = AmortisedEstimator(max_order=3, hidden=(32,), n_records=300, n_samples=128,
    ...                          max_epochs=2).fit()
    >>> t = np.linspace(0.0, 10.0, 200)
    >>> h = np.exp(-t) - np.exp(-3.0 * t)          # 2 / ((s + 1)(s + 3))
    >>> raw = est.estimate(t, h)                     # network poles, least squares
    >>> exact = est.set_params(refine_method="varpro").refine(t, h, raw)
    >>> bool(exact.fit_percent[0] > 99.99 >= raw.fit_percent[0])  # noise-free: exact
    True
    """

    def __init__(
        self,
        max_order: int = 5,
        *,
        hidden: Sequence[int] = (256, 256, 256),
        n_bins: int = 128,
        n_records: int = 40000,
        n_samples: int = 512,
        max_epochs: int = 40,
        batch_size: int = 256,
        learning_rate: float = 2e-3,
        validation_fraction: float = 0.1,
        weights: str = "uniform",
        refine_method: str = "map",
        prior_scale: float = 0.3,
        refine_rounds: int = 1,
        refine_max_iter: int = 50,
        refine_tol: float = 1e-8,
        random_state: int = 0,
        progress: bool = False,
    ) -> None:
        self.max_order = max_order
        self.hidden = hidden
        self.n_bins = n_bins
        self.n_records = n_records
        self.n_samples = n_samples
        self.max_epochs = max_epochs
        self.batch_size = batch_size
        self.learning_rate = learning_rate
        self.validation_fraction = validation_fraction
        self.weights = weights
        self.refine_method = refine_method
        self.prior_scale = prior_scale
        self.refine_rounds = refine_rounds
        self.refine_max_iter = refine_max_iter
        self.refine_tol = refine_tol
        self.random_state = random_state
        self.progress = progress

    _PARAMS = ("max_order", "hidden", "n_bins", "n_records", "n_samples", "max_epochs",
               "batch_size", "learning_rate", "validation_fraction", "weights",
               "refine_method", "prior_scale", "refine_rounds", "refine_max_iter",
               "refine_tol", "random_state", "progress")

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Constructor parameters (scikit-learn convention)."""
        return {k: getattr(self, k) for k in self._PARAMS}

    # ------------------------------------------------------------------ training
    def _check_params(self) -> None:
        check_int(self.max_order, "max_order", minimum=1)
        check_int(self.n_bins, "n_bins", minimum=4)
        check_int(self.n_records, "n_records", minimum=10)
        check_int(self.n_samples, "n_samples", minimum=16)
        check_int(self.max_epochs, "max_epochs", minimum=1)
        check_int(self.batch_size, "batch_size", minimum=1)
        check_choice(self.weights, "weights", _WEIGHTS)
        check_choice(self.refine_method, "refine_method", _REFINE)
        if not 0.0 < float(self.validation_fraction) < 1.0:
            raise DataError(
                f"validation_fraction must lie in (0, 1), got {self.validation_fraction!r}")
        if not float(self.learning_rate) > 0:
            raise DataError(f"learning_rate must be > 0, got {self.learning_rate!r}")
        if any(int(h) < 1 for h in self.hidden):
            raise DataError(f"hidden widths must be >= 1, got {tuple(self.hidden)}")

    def fit(self) -> AmortisedEstimator:
        """Draw random stable systems and train the network on them.

        Returns
        -------
        AmortisedEstimator
            ``self``, fitted.

        Raises
        ------
        DataError
            On a bad constructor parameter.
        """
        self._check_params()
        t0 = time.perf_counter()
        rng = np.random.default_rng(int(self.random_state))
        torch.manual_seed(int(self.random_state))
        draws = random_systems(int(self.n_records), int(self.n_samples), rng,
                               max_order=int(self.max_order))
        net = AmortisedPoleNetwork(int(self.max_order), int(self.n_bins), self.hidden)
        history = train_network(
            net, draws.tau, draws.responses, draws.clean, max_epochs=int(self.max_epochs),
            batch_size=int(self.batch_size), learning_rate=float(self.learning_rate),
            validation_fraction=float(self.validation_fraction), rng=rng,
            progress=bool(self.progress))
        self._set_fitted(net, draws.tau, history, time.perf_counter() - t0)
        return self

    def _set_fitted(self, net: AmortisedPoleNetwork, tau: NDArray, history: TrainingHistory,
                    seconds: float) -> None:
        self.network_ = net.eval()
        self.kinds_ = net.kinds
        self.tau_ = np.asarray(tau, dtype=float)
        self.history_ = history
        self.training_seconds_ = float(seconds)

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "network_"):
            raise NotFittedError(
                "this AmortisedEstimator is not fitted yet; call fit() or load() first")

    # ------------------------------------------------------------------ inference
    def _records(self, t: ArrayLike, y: ArrayLike) -> tuple[NDArray, NDArray, bool]:
        self._check_is_fitted()
        t = check_time(t, min_samples=2 * self.network_.max_order + 2)
        if t[0] < 0:
            raise DataError(f"t must start at or after the impulse (t[0] >= 0), got {t[0]:g}")
        y = check_records(y, t.size, "y")
        Y = np.atleast_2d(y)
        flat = np.ptp(Y, axis=1) == 0
        if flat.any():
            raise DataError(f"record {int(np.argmax(flat))} is constant; there are no poles "
                            "to estimate")
        return t, Y, y.ndim == 1

    def _sw(self, t: NDArray) -> NDArray | None:
        return None if self.weights == "uniform" else np.sqrt(least_squares_weights(t))

    def predict_poles(self, t: ArrayLike, y: ArrayLike) -> NDArray[np.complex128]:
        """Basis poles the network gives each record (no refinement).

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Sample times, ``t[0] >= 0`` (the impulse at ``t = 0``), any increasing grid.
        y : array-like of shape (n_samples,) or (n_records, n_samples)
            Impulse-response records.

        Returns
        -------
        ndarray of complex, shape (n_functions,) or (n_records, n_functions)

        Raises
        ------
        NotFittedError
            Before :meth:`fit` or :meth:`load`.
        DataError, DimensionError
            Bad records (non-finite, constant, wrong length, too few samples).
        """
        t, Y, single = self._records(t, y)
        poles = self._poles(t, Y)
        return poles[0] if single else poles

    def _poles(self, t: NDArray, Y: NDArray) -> NDArray[np.complex128]:
        Z = torch.as_tensor(bin_features(t, Y, self.network_.n_bins), dtype=torch.float32)
        with torch.no_grad():
            theta = torch.cat([self.network_(z) for z in Z.split(1024)]).double().numpy()
        return block_roots(self.kinds_, theta) / float(t[-1])

    def project(self, t: ArrayLike, y: ArrayLike, poles: ArrayLike) -> NDArray[np.float64]:
        """Least-squares coefficients of records in the Kautz bases of given poles.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
        y : array-like of shape (n_samples,) or (n_records, n_samples)
        poles : array-like of complex, shape (n_functions,) or (n_records, n_functions)
            One pole set for all records, or one per record.

        Returns
        -------
        ndarray of shape (n_functions,) or (n_records, n_functions)
        """
        t, Y, single = self._records(t, y)
        P = np.atleast_2d(np.asarray(poles, dtype=complex))
        if P.shape[0] == 1:
            P = np.repeat(P, Y.shape[0], axis=0)
        if P.shape[0] != Y.shape[0]:
            raise DataError(f"poles has {P.shape[0]} rows but y has {Y.shape[0]} records")
        sw = self._sw(t)
        C = np.array([_lstsq(t, Y[i], P[i], sw)[0] for i in range(Y.shape[0])])
        return C[0] if single else C

    def estimate(self, t: ArrayLike, y: ArrayLike, *, refine: bool = False) -> AmortisedEstimate:
        """Kautz models of records: network poles (refined on request), least squares.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Sample times, ``t[0] >= 0`` (the impulse at ``t = 0``).
        y : array-like of shape (n_samples,) or (n_records, n_samples)
            Impulse-response records (any units and length; one record per row).
        refine : bool, default=False
            Refine every record's poles by variable projection from the network's
            (:meth:`refine`).

        Returns
        -------
        AmortisedEstimate
            Always two-dimensional (one row per record).

        Raises
        ------
        NotFittedError
            Before :meth:`fit` or :meth:`load`.
        DataError, DimensionError
            Bad records.
        """
        t, Y, _ = self._records(t, y)
        t0 = time.perf_counter()
        poles = self._poles(t, Y)
        est = self._assemble(t, Y, poles, refined=False, t0=t0)
        return self._refine(t, Y, est) if refine else est

    def _assemble(self, t: NDArray, Y: NDArray, poles: NDArray, *, refined: bool,
                  t0: float) -> AmortisedEstimate:
        sw = self._sw(t)
        C = np.empty(poles.shape)
        R = np.empty(Y.shape)
        for i in range(Y.shape[0]):
            C[i], R[i] = _lstsq(t, Y[i], poles[i], sw)
        return AmortisedEstimate(
            t=t, poles=poles, coefficients=C, response=R,
            fit_percent=np.atleast_1d(fit_percent(Y, R)), refined=refined,
            seconds_per_record=(time.perf_counter() - t0) / Y.shape[0])

    def refine(self, t: ArrayLike, y: ArrayLike, estimate: AmortisedEstimate) -> AmortisedEstimate:
        """Refine an estimate's poles by variable projection, record by record.

        Every record is refined by :func:`kautztwin.optimize_poles` (``max_iter =
        refine_max_iter``, collapsed pairs restarted as real poles) from its poles, and
        also from the other reading of each second-order block near the boundary
        between two real poles and a complex pair; the candidate (the start included)
        with the smallest least-squares residual on the record is kept, so the
        residual never grows.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
        y : array-like of shape (n_samples,) or (n_records, n_samples)
            The records of ``estimate``.
        estimate : AmortisedEstimate
            From :meth:`estimate`.

        Returns
        -------
        AmortisedEstimate
            With ``refined=True``; its time per record includes the network's.
        """
        t, Y, _ = self._records(t, y)
        if len(estimate) != Y.shape[0]:
            raise DataError(f"the estimate has {len(estimate)} records but y has {Y.shape[0]}")
        return self._refine(t, Y, estimate)

    def _refine(self, t: NDArray, Y: NDArray, est: AmortisedEstimate) -> AmortisedEstimate:
        check_choice(self.refine_method, "refine_method", _REFINE)
        t0 = time.perf_counter() - est.seconds_per_record * Y.shape[0]
        poles = est.poles.copy()
        for i in range(Y.shape[0]):
            if self.refine_method == "map":
                try:
                    poles[i] = refine_map(
                        t, Y[i], self.kinds_, theta_from_poles(self.kinds_, est.poles[i]),
                        est.response[i], prior_scale=float(self.prior_scale),
                        max_iter=int(self.refine_max_iter), tol=float(self.refine_tol),
                        rounds=int(self.refine_rounds))
                except (KautzTwinError, np.linalg.LinAlgError, ValueError):
                    continue
            else:
                poles[i] = self._varpro(t, Y[i], est.poles[i], est.response[i])
        return self._assemble(t, Y, poles, refined=True, t0=t0)

    def _varpro(self, t: NDArray, y: NDArray, start: NDArray, fitted: NDArray) -> NDArray:
        """Plain variable projection from ``start`` (and its flipped reading); the best."""
        sw = self._sw(t)
        best_poles = start
        best = np.sum(((y - fitted) if sw is None else (y - fitted) * sw) ** 2)
        starts = [start]
        other = _flipped(start, sum(1 for k in self.kinds_ if k == "quad"))
        if other is not None:
            starts.append(other)
        for s in starts:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                try:
                    res = optimize_poles(t, y, s, max_iter=int(self.refine_max_iter),
                                         tol=float(self.refine_tol), restart_collapsed=True)
                except (KautzTwinError, np.linalg.LinAlgError):
                    continue
            p = np.asarray(res.basis.poles)
            _, fit = _lstsq(t, y, p, sw)
            r = (y - fit) if sw is None else (y - fit) * sw
            if np.sum(r * r) < best:
                best, best_poles = float(np.sum(r * r)), p
        return best_poles

    # ------------------------------------------------------------------ files
    def save(self, directory: str | Path) -> Path:
        """Write ``weights.pt``, ``metadata.json`` (checksums) and ``estimator.json``.

        Parameters
        ----------
        directory : str or Path
            Folder (created).

        Returns
        -------
        Path
        """
        self._check_is_fitted()
        net = self.network_
        h = self.history_
        fields = {
            "architecture": {"network": type(net).__name__, "max_order": net.max_order,
                             "n_bins": net.n_bins, "hidden": list(net.hidden)},
            "params": {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in self.get_params().items()},
            "history": {"train_loss": list(h.train_loss), "val_loss": list(h.val_loss),
                        "best_epoch": h.best_epoch, "seconds": h.seconds},
            "training_seconds": self.training_seconds_,
        }
        path = save_verified(directory, _FORMAT, _VERSION, net.state_dict(), self.tau_, fields)
        (path / _KIND_FILE).write_text(json.dumps({"estimator": "amortised"}))
        return path

    @classmethod
    def load(cls, directory: str | Path) -> AmortisedEstimator:
        """Read a folder written by :meth:`save` (checksums verified).

        Raises
        ------
        DataError
            Missing, modified or malformed files.
        """

        def build(meta: dict[str, Any], weights: Path) -> AmortisedEstimator:
            arch = meta["architecture"]
            check_network(arch, AmortisedPoleNetwork)
            net = AmortisedPoleNetwork(int(arch["max_order"]), int(arch["n_bins"]),
                                       [int(v) for v in arch["hidden"]])
            net.load_state_dict(load_weights(weights))
            params = dict(meta["params"])
            params["hidden"] = tuple(params["hidden"])
            est = cls(**params)
            h = meta["history"]
            hist = TrainingHistory(train_loss=h["train_loss"], val_loss=h["val_loss"],
                                   best_epoch=h["best_epoch"], seconds=h["seconds"],
                                   stopped_early=False)
            grid = meta["time_grid"]
            tau = np.linspace(grid["t0"], grid["t_end"], int(grid["n_samples"]))
            est._set_fitted(net, tau, hist, float(meta["training_seconds"]))
            return est

        return load_verified(directory, _FORMAT, _VERSION, "amortised estimator", build)

    @classmethod
    def load_default(cls) -> AmortisedEstimator:
        """The amortised model shipped with kautztwin, ready to estimate any impulse record.

        Trained with the defaults (``max_order=5``, 40 000 random stable systems, 40
        epochs) by ``python examples/amortised_estimator.py --train``; its files are
        package data (``kautztwin/nn/amortised/shipped_model/``), read with
        :mod:`importlib.resources`, so this works from an installed wheel as from a source
        checkout, and their checksums are verified as by :meth:`load`.  ``kautztwin
        estimate`` uses this model when no ``--model`` is given.

        Returns
        -------
        AmortisedEstimator
            Fitted; a new object on every call.

        Raises
        ------
        DataError
            If the package's model files are missing or were modified.

        See Also
        --------
        load : A model folder of your own (``fit`` then ``save``, or ``kautztwin train
            --amortised``).
        kautztwin.nn.amortised.pretrained.pretrained_folder : The shipped folder on disk.

        Examples
        --------
        >>> import numpy as np
        >>> from kautztwin.nn.amortised import AmortisedEstimator
        >>> est = AmortisedEstimator.load_default()
        >>> est.max_order, est.n_records
        (5, 40000)
        >>> t = np.linspace(0.0, 10.0, 200)
        >>> h = np.exp(-t) - np.exp(-3.0 * t)            # 2 / ((s + 1)(s + 3))
        >>> e = est.estimate(t, h, refine=True)
        >>> e.poles.shape, bool(e.fit_percent[0] > 99.0)
        ((1, 5), True)
        """
        with pretrained_folder() as folder:
            return cls.load(folder)
