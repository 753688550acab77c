r"""Update module of the digital twin: keeps the twin's model synchronised with the plant.

Three pieces:

* :class:`RecursiveKautzEstimator`, the **fast path**: recursive least squares
  with exponential forgetting on Kautz-filtered regressors.  The input drives
  the discrete orthonormal basis network
  :math:`x_f(k+1) = A x_f(k) + B u(k)` (kautz-math.md 3.2, delayed form), and
  the output is modelled as :math:`y(k) \approx c^T x_f(k) + d`.  One update
  costs :math:`O(N^2)` (a few microseconds for :math:`N \le 8`).
* :class:`SyncMonitor`: the rolling fit of the twin's predicted output
  against the measured one, with desynchronisation detection (fit below a
  threshold for ``n_consecutive`` windows) and re-identification triggers.
* :class:`Updater`: runs the two each sample, and the **accurate path** when
  the monitor triggers: output-error re-identification of poles and
  coefficients on the recent window by variable projection
  (:func:`identify_output_error`), accepted only when it predicts held-out
  recent data better than the current model.  A trained DNN estimator (any
  object with ``predict_models``) or :func:`kautztwin.optimize_poles` turns a
  step test into a model (:meth:`Updater.update_from_step_test`).

Every accepted model is a new :class:`~kautztwin.twin.DigitalModel` version.
The model of the twin is ``y(k) = c^T x_f(k) + offset``: the
:class:`~kautztwin.KautzModel` (a discrete, delayed basis on the sampling
period) carries ``c``; the operating-point ``offset`` is kept by the updater
(:attr:`Updater.offset`) and logged with every version.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..approx.model import KautzModel
from ..approx.poles import optimize_poles
from ..basis import KautzBasis
from ..basis._blocks import PAIR, REAL, parse_poles
from ..basis._propagate import discrete_functions
from ..exceptions import DataError, DimensionError, KautzTwinError, NotFittedError
from .digital_model import DigitalModel
from .signals import SampleFlag, SampleSanitizer

__all__ = [
    "FitHistory",
    "ModelUpdate",
    "OutputErrorFit",
    "RecursiveKautzEstimator",
    "SyncEvent",
    "SyncMonitor",
    "UpdateResult",
    "Updater",
    "discretize_model",
    "identify_output_error",
]


# --------------------------------------------------------------------------- helpers
def _as_float(value: Any) -> float:
    """``value`` as a float, NaN when it is not a finite real scalar; never raises."""
    if isinstance(value, bool | np.bool_):
        return math.nan
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError):
        return math.nan
    return out if math.isfinite(out) else math.nan


def _fit(y: NDArray, yhat: NDArray) -> float:
    """Fit percent on the samples where both are finite; NaN if undefined."""
    ok = np.isfinite(y) & np.isfinite(yhat)
    if ok.sum() < 2:
        return math.nan
    yy = y[ok]
    spread = float(np.linalg.norm(yy - yy.mean()))
    if spread == 0.0:
        return math.nan
    return 100.0 * (1.0 - float(np.linalg.norm(yy - yhat[ok])) / spread)


def _delayed_basis(poles: ArrayLike | KautzBasis, dt: float) -> KautzBasis:
    """A delayed discrete basis on ``dt`` from discrete poles or a (continuous) basis."""
    if isinstance(poles, KautzBasis):
        if not poles.is_discrete:
            poles = poles.discretize(dt)
        elif abs(poles.dt - dt) > 1e-12 * dt:
            raise DataError(f"the basis has dt = {poles.dt:g} but the twin samples at dt = {dt:g}")
        return KautzBasis._from_blocks(poles.block_kinds, poles._params, dt, True)
    return KautzBasis(poles, dt=dt, delayed=True)


def _states(basis: KautzBasis, u: NDArray, x0: NDArray | None = None) -> NDArray[np.float64]:
    """Filter states ``x(k)``, ``k = 0..n`` (``n + 1`` rows) of ``x(k+1) = A x(k) + B u(k)``.

    Exact convolution of the delayed basis sequences with ``u`` (FFT), plus the
    free response ``A^k x0``.
    """
    n = u.size
    k = np.arange(n + 1)
    F = basis.evaluate(k * basis.dt)  # delayed: F[:, 0] = 0, F[:, k] = A^{k-1} B
    X = scipy.signal.fftconvolve(F, u[None, :], axes=1)[:, : n + 1]
    if x0 is not None and np.any(x0):
        X += discrete_functions(np.asarray(basis.A)[None], np.asarray(x0)[None], k)[0]
    return X.T


def _stein_coefficients(A: NDArray, B: NDArray, Ah: NDArray, Bh: NDArray, Ch: NDArray) -> NDArray:
    """Coefficients ``X C_h^T`` with ``X - A X A_h^T = B B_h^T`` (kautz-math.md section 5)."""
    n, m = A.shape[0], Ah.shape[0]
    lhs = np.eye(n * m) - np.kron(Ah, A)
    rhs = np.outer(B, Bh).reshape(-1, order="F")
    X = np.linalg.solve(lhs, rhs).reshape((n, m), order="F")
    return X @ Ch


def discretize_model(model: KautzModel, dt: float) -> KautzModel:
    """Zero-order-hold discretisation of a continuous Kautz model on the matched delayed basis.

    The sampled pulse response of the zero-order-hold model lies exactly in
    the span of the delayed discrete basis with poles ``exp(p * dt)``
    (kautz-math.md 3.3), so the coefficients follow exactly from one Stein
    equation.

    Parameters
    ----------
    model : KautzModel
        A continuous-time model (``dt = 0``), or a discrete one on a delayed basis
        with the same ``dt`` (returned unchanged).
    dt : float
        Sampling period, s, ``> 0``.

    Returns
    -------
    KautzModel
        Discrete, delayed basis: ``y(k) = c^T x_f(k)``, ``x_f(k+1) = A x_f(k) + B u(k)``.

    Raises
    ------
    DataError
        If ``dt`` is not positive, or ``model`` is discrete with another period
        or an undelayed basis (which has a direct feedthrough).

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.twin.update import discretize_model
    >>> m = kt.KautzModel(kt.KautzBasis([-2.0]), [2.0])   # 4 / (s + 2)
    >>> md = discretize_model(m, 0.1)
    >>> md.basis.delayed, round(md.dc_gain, 10), round(m.dc_gain, 10)
    (True, 2.0, 2.0)
    """
    dt = float(dt)
    if not (math.isfinite(dt) and dt > 0):
        raise DataError(f"dt must be a positive sampling period, got {dt}")
    if model.dt > 0:
        if not model.basis.delayed:
            raise DataError(
                "the model is on an undelayed discrete basis (a direct feedthrough); the twin "
                "needs a delayed one"
            )
        if abs(model.dt - dt) > 1e-12 * dt:
            raise DataError(f"the model has dt = {model.dt:g}, not the twin's dt = {dt:g}")
        return model
    A, B, C, _ = model.state_space()
    Ah = scipy.linalg.expm(A * dt)
    Bh = np.linalg.solve(A, (Ah - np.eye(A.shape[0])) @ B)[:, 0]
    basis_d = _delayed_basis(model.basis, dt)
    c = _stein_coefficients(np.asarray(basis_d.A), np.asarray(basis_d.B), Ah, Bh, C[0])
    return KautzModel(basis_d, c)


def _continuous_poles(basis: KautzBasis) -> NDArray[np.complex128]:
    """Continuous-time equivalents ``log(xi) / dt`` of a discrete basis' poles."""
    if not basis.is_discrete:
        return np.array(basis.poles)
    out = []
    for p in basis.poles:
        mag = max(abs(p), 1e-12)
        if abs(p.imag) <= 1e-12 * max(1.0, abs(p)):
            out.append(complex(math.log(mag) / basis.dt))
        else:
            out.append(complex(math.log(mag), np.angle(p)) / basis.dt)
    return np.asarray(out)


# --------------------------------------------------------------------------- RLS
class RecursiveKautzEstimator:
    r"""Recursive least squares with forgetting on Kautz-filtered regressors.

    The input drives the delayed discrete Kautz network on the sampling
    period, :math:`x_f(k+1) = A x_f(k) + B u(k)`, whose states are the
    regressors; the output is modelled as :math:`y(k) \approx c^T x_f(k) + d`
    (``d`` only with ``fit_offset``).  Each :meth:`update` makes the a-priori
    prediction, corrects :math:`\theta = [c; d]` with the standard RLS gain and
    advances the filter:

    .. math::

        g = \frac{P\varphi}{\lambda + \varphi^T P \varphi},\quad
        \theta \leftarrow \theta + g\,(y - \varphi^T\theta),\quad
        P \leftarrow (P - g\,\varphi^T P)/\lambda .

    Anti-windup: with forgetting and poor excitation :math:`P` grows like
    :math:`\lambda^{-k}` in the unexcited directions; its trace is therefore
    clamped to ``max_trace`` (scaling :math:`P` down, counted in
    ``n_clamped_``), and :meth:`reset_covariance` restarts it.

    Parameters
    ----------
    poles : array-like of complex or KautzBasis
        Discrete pole locations (``|p| < 1``) on the period ``dt``, or a basis
        (a continuous one is discretised with poles ``exp(p dt)``).
    dt : float, default=1.0
        Sampling period, s.
    forgetting : float, default=0.99
        Forgetting factor :math:`\lambda \in (0, 1]`; the memory is about
        :math:`1/(1-\lambda)` samples.
    delta : float, default=100.0
        Initial covariance :math:`P = \delta I` (large: little trust in ``coef_init``).
    max_trace : float, default=1e4
        Anti-windup bound on :math:`\operatorname{tr} P`.
    fit_offset : bool, default=True
        Estimate the output offset ``d``.
    coef_init : array-like of shape (n_functions,), optional
        Initial coefficients ``c`` (zeros when omitted).
    offset_init : float, default=0.0
        Initial offset ``d``.
    input_offset : float, default=0.0
        Operating point :math:`u_0` of the input: the filter is driven by
        :math:`u - u_0`.  Centring the input keeps the regressors nearly
        orthogonal to the constant of the offset, which the recursion needs
        when the input varies little around a large mean.

    Attributes
    ----------
    basis_ : KautzBasis
        The delayed discrete basis.
    coef_ : ndarray of shape (n_functions,)
        Current coefficients ``c``.
    offset_ : float
        Current offset ``d`` (0 without ``fit_offset``).
    covariance_ : ndarray of shape (n_params, n_params)
        Current :math:`P` (a copy).
    state_ : ndarray of shape (n_functions,)
        Current filter state :math:`x_f(k)` (a copy).
    n_updates_ : int
        Measurements used since the last reset.
    n_clamped_ : int
        Times the covariance trace was clamped.

    Raises
    ------
    DataError
        On an invalid parameter (at the first use, as scikit-learn estimators do).

    See Also
    --------
    Updater : Runs this estimator as the twin's fast path.
    kautztwin.KautzBasis : The basis and its network realisation.

    Notes
    -----
    The regressors are orthonormal filters, so for a white input their
    covariance is the identity and the recursion is well conditioned.  A
    system whose pulse response lies in the span of the basis (its poles
    among the basis poles) is recovered exactly from noise-free data.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.update import RecursiveKautzEstimator
    >>> rng = np.random.default_rng(0)
    >>> u = rng.standard_normal(400)
    >>> true = RecursiveKautzEstimator([0.5, 0.8], dt=0.1, coef_init=[1.0, -0.5], offset_init=2.0)
    >>> y = true.simulate(u)
    >>> est = RecursiveKautzEstimator([0.5, 0.8], dt=0.1, forgetting=1.0, delta=1e6).fit(u, y)
    >>> np.round(est.coef_, 4), round(est.offset_, 4)
    (array([ 1. , -0.5]), 2.0)
    """

    def __init__(
        self,
        poles: ArrayLike | KautzBasis,
        *,
        dt: float = 1.0,
        forgetting: float = 0.99,
        delta: float = 100.0,
        max_trace: float = 1e4,
        fit_offset: bool = True,
        coef_init: ArrayLike | None = None,
        offset_init: float = 0.0,
        input_offset: float = 0.0,
    ) -> None:
        self.poles = poles
        self.dt = dt
        self.forgetting = forgetting
        self.delta = delta
        self.max_trace = max_trace
        self.fit_offset = fit_offset
        self.coef_init = coef_init
        self.offset_init = offset_init
        self.input_offset = input_offset

    # ------------------------------------------------------------------ setup
    def _check_params(self) -> None:
        dt = _as_float(self.dt)
        if not dt > 0:
            raise DataError(f"dt must be a positive sampling period, got {self.dt!r}")
        lam = _as_float(self.forgetting)
        if not 0 < lam <= 1:
            raise DataError(f"forgetting must lie in (0, 1], got {self.forgetting!r}")
        for name in ("delta", "max_trace"):
            if not _as_float(getattr(self, name)) > 0:
                raise DataError(f"{name} must be a positive number, got {getattr(self, name)!r}")
        for name in ("offset_init", "input_offset"):
            if math.isnan(_as_float(getattr(self, name))):
                raise DataError(f"{name} must be a finite number, got {getattr(self, name)!r}")

    def reset(self) -> RecursiveKautzEstimator:
        """(Re)initialise: basis, ``theta`` from the initial values, ``P = delta I``, zero state.

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.

        Raises
        ------
        DataError
            On an invalid parameter.
        DimensionError
            If ``coef_init`` does not have one entry per basis function.
        """
        self._check_params()
        basis = _delayed_basis(self.poles, float(self.dt))
        n = basis.n_functions
        coef = np.zeros(n) if self.coef_init is None else np.asarray(self.coef_init, float)
        if coef.shape != (n,):
            raise DimensionError(
                f"coef_init has shape {coef.shape} but the basis has {n} functions"
            )
        if not np.all(np.isfinite(coef)):
            raise DataError("coef_init contains NaN or inf")
        self._install(basis, coef, float(self.offset_init), np.zeros(n), float(self.delta))
        return self

    def _install(
        self, basis: KautzBasis, coef: NDArray, offset: float, state: NDArray, delta: float
    ) -> None:
        n = basis.n_functions
        self.basis_ = basis
        self._n = n
        self._A = np.array(basis.A)
        self._B = np.array(basis.B)
        self._lam = float(self.forgetting)
        self._max_trace = float(self.max_trace)
        self._u0 = float(self.input_offset)
        self._offset = bool(self.fit_offset)
        n_par = n + int(self._offset)
        self._theta = np.zeros(n_par)
        self._theta[:n] = coef
        self._d = offset  # the fixed offset when it is not estimated
        if self._offset:
            self._theta[n] = offset
        self._P = delta * np.eye(n_par)
        self._phi = np.zeros(n_par)
        self._phi[:n] = state
        if self._offset:
            self._phi[n] = 1.0
        self.n_updates_ = 0
        self.n_clamped_ = 0

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "_theta"):
            raise NotFittedError(
                "this RecursiveKautzEstimator is not initialised; call reset(), fit() or "
                "partial_fit() first"
            )

    def reseed(
        self,
        model: KautzModel,
        *,
        offset: float = 0.0,
        state: ArrayLike | None = None,
        delta: float | None = None,
    ) -> RecursiveKautzEstimator:
        """Continue from another model (new poles and coefficients) without losing the run.

        Parameters
        ----------
        model : KautzModel
            The new model: continuous (discretised on ``dt``) or on a delayed
            discrete basis with the same ``dt``.
        offset : float, default=0.0
            Its offset ``d``.
        state : array-like of shape (n_functions,), optional
            The new basis' filter state at the current sample (zeros when omitted).
        delta : float, optional
            New initial covariance scale; ``self.delta`` when omitted.

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.
        """
        self._check_params()
        md = discretize_model(model, float(self.dt))
        n = md.n_functions
        x = np.zeros(n) if state is None else np.asarray(state, dtype=float)
        if x.shape != (n,):
            raise DimensionError(f"state has shape {x.shape} but the model has {n} functions")
        d = float(self.delta) if delta is None else float(delta)
        self._install(md.basis, np.array(md.coefficients), float(offset), x, d)
        return self

    # ------------------------------------------------------------------ recursion
    def predict(self) -> float:
        """A-priori prediction of the current sample's output, :math:`\\theta^T\\varphi(k)`.

        Returns
        -------
        float
        """
        self._check_is_fitted()
        out = float(self._theta @ self._phi)
        return out if self._offset else out + self._d

    @property
    def parameters_(self) -> NDArray[np.float64]:
        """Current parameter vector :math:`\\theta = [c; d]` (a copy; no ``d`` without offset)."""
        self._check_is_fitted()
        return self._theta.copy()

    def predict_with(self, theta: NDArray[np.float64]) -> float:
        """Prediction of the current sample's output with other parameters (e.g. frozen ones).

        Parameters
        ----------
        theta : ndarray of shape (n_params,)
            A parameter vector like :attr:`parameters_`.

        Returns
        -------
        float
        """
        out = float(theta @ self._phi)
        return out if self._offset else out + self._d

    def update(self, u: float, y: float = math.nan) -> float:
        """One sample: predict ``y(k)``, correct with the measured ``y``, advance with ``u(k)``.

        Parameters
        ----------
        u : float
            Input applied at this sample (drives the filter to the next sample).
        y : float, default=nan
            Measured output of this sample; NaN (a dropout) only advances the filter.

        Returns
        -------
        float
            The a-priori prediction of ``y(k)`` (made before ``y`` was used).

        Raises
        ------
        DataError
            If ``u`` is not finite.
        """
        if not hasattr(self, "_theta"):
            self.reset()
        u = float(u)
        if not math.isfinite(u):
            raise DataError(f"u must be finite, got {u}")
        phi = self._phi
        theta = self._theta
        yhat = float(theta @ phi)
        if not self._offset:
            yhat += self._d
        if y == y:  # not NaN
            P = self._P
            Pphi = P @ phi
            denom = self._lam + float(phi @ Pphi)
            if denom > 0 and math.isfinite(denom):
                g = Pphi / denom
                theta += g * (float(y) - yhat)
                P -= np.outer(g, Pphi)
                if self._lam < 1.0:
                    P /= self._lam
                self.n_updates_ += 1
                if self.n_updates_ % 64 == 0:
                    P += P.T
                    P *= 0.5
                tr = float(P.trace())
                if tr > self._max_trace:
                    P *= self._max_trace / tr
                    self.n_clamped_ += 1
                elif not tr > 0:  # lost positive definiteness (rounding): restart
                    self.reset_covariance()
            else:
                self.reset_covariance()
        n = self._n
        phi[:n] = self._A @ phi[:n] + self._B * (u - self._u0)
        return yhat

    def advance(self, u: float, n_steps: int = 1) -> None:
        """Advance the filter with input ``u`` without using a measurement.

        Parameters
        ----------
        u : float
            Input held over the steps.
        n_steps : int, default=1
            Number of samples.
        """
        self._check_is_fitted()
        n = self._n
        v = float(u) - self._u0
        for _ in range(int(n_steps)):
            self._phi[:n] = self._A @ self._phi[:n] + self._B * v

    def reset_covariance(self, delta: float | None = None) -> None:
        """Restart the covariance at ``delta * I`` (``self.delta`` when omitted).

        Parameters
        ----------
        delta : float, optional
            New scale.
        """
        self._check_is_fitted()
        d = float(self.delta) if delta is None else float(delta)
        self._P = d * np.eye(self._theta.size)

    def partial_fit(self, u: ArrayLike, y: ArrayLike) -> RecursiveKautzEstimator:
        """Run :meth:`update` over a batch of samples (continuing the recursion).

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Inputs (finite).
        y : array-like of shape (n_samples,)
            Outputs; NaN samples only advance the filter.

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.

        Raises
        ------
        DimensionError
            If ``u`` and ``y`` are not 1-D of one length.
        DataError
            If ``u`` is not finite.
        """
        u = np.asarray(u, dtype=float)
        y = np.asarray(y, dtype=float)
        if u.ndim != 1 or u.shape != y.shape:
            raise DimensionError(
                f"u and y must be 1-D of one length, got shapes {u.shape} and {y.shape}"
            )
        if not np.all(np.isfinite(u)):
            raise DataError("u contains NaN or inf")
        if not hasattr(self, "_theta"):
            self.reset()
        for uk, yk in zip(u.tolist(), y.tolist(), strict=True):
            self.update(uk, yk)
        return self

    def fit(self, u: ArrayLike, y: ArrayLike) -> RecursiveKautzEstimator:
        """Reset, then run the recursion over ``u`` and ``y`` from a zero filter state.

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Inputs.
        y : array-like of shape (n_samples,)
            Outputs (NaN: dropout).

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.
        """
        return self.reset().partial_fit(u, y)

    def simulate(self, u: ArrayLike, x0: ArrayLike | None = None) -> NDArray[np.float64]:
        """Output of the current model for an input sequence (parameters frozen).

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Inputs.
        x0 : array-like of shape (n_functions,), optional
            Initial filter state (zeros when omitted: at rest at ``input_offset``;
            the estimator's own state is untouched).

        Returns
        -------
        ndarray of shape (n_samples,)
            ``y(k) = c^T x_f(k) + d`` for ``k = 0 .. n_samples - 1``, the filter
            driven by ``u - input_offset``.
        """
        if not hasattr(self, "_theta"):
            self.reset()
        u = np.asarray(u, dtype=float)
        if u.ndim != 1:
            raise DimensionError(f"u must be 1-D, got shape {u.shape}")
        x = None if x0 is None else np.asarray(x0, dtype=float)
        X = _states(self.basis_, u - float(self.input_offset), x)[:-1]
        return X @ self.coef_ + self.offset_

    # ------------------------------------------------------------------ results
    @property
    def coef_(self) -> NDArray[np.float64]:
        """Current coefficients ``c`` (a copy)."""
        self._check_is_fitted()
        return self._theta[: self._n].copy()

    @property
    def offset_(self) -> float:
        """Current offset ``d``."""
        self._check_is_fitted()
        return float(self._theta[self._n]) if self._offset else self._d

    @property
    def covariance_(self) -> NDArray[np.float64]:
        """Current covariance ``P`` (a copy)."""
        self._check_is_fitted()
        return self._P.copy()

    @property
    def state_(self) -> NDArray[np.float64]:
        """Current filter state ``x_f(k)`` (a copy)."""
        self._check_is_fitted()
        return self._phi[: self._n].copy()

    @property
    def model_(self) -> KautzModel:
        """The current model ``c`` on :attr:`basis_` (a new immutable object)."""
        return KautzModel(self.basis_, self.coef_)

    def __repr__(self) -> str:
        return (
            f"RecursiveKautzEstimator(n_functions={getattr(self, '_n', '?')}, dt={self.dt}, "
            f"forgetting={self.forgetting})"
        )


# --------------------------------------------------------------------------- sync monitor
@dataclass(frozen=True)
class SyncEvent:
    """A synchronisation event of :class:`SyncMonitor`.

    Parameters
    ----------
    kind : {'desync', 'resync'}
        ``'desync'``: the rolling fit stayed below the threshold for
        ``n_consecutive`` windows (a re-identification trigger; repeated every
        further ``n_consecutive`` bad windows).  ``'resync'``: the fit is back
        above the threshold.
    k : int or None
        Sample index that completed the window.
    t : float or None
        Its time.
    fit : float
        Rolling fit of that window, percent.
    n_bad : int
        Consecutive windows below the threshold (0 for ``'resync'``).
    message : str
        Human-readable text.
    """

    kind: str
    k: int | None
    t: float | None
    fit: float
    n_bad: int
    message: str

    def payload(self) -> dict[str, Any]:
        """JSON-ready dictionary of the event.

        Returns
        -------
        dict
        """
        return {"kind": self.kind, "k": self.k, "t": self.t, "fit": self.fit, "n_bad": self.n_bad}


@dataclass(frozen=True, eq=False)
class FitHistory:
    """Rolling fits computed by :class:`SyncMonitor`.

    Parameters
    ----------
    k : ndarray of int, shape (n_windows,)
        Sample index that completed each window (-1 when unknown).
    t : ndarray of shape (n_windows,)
        Its time (NaN when unknown).
    fit : ndarray of shape (n_windows,)
        Fit percent of each window.
    """

    k: NDArray[np.int64]
    t: NDArray[np.float64]
    fit: NDArray[np.float64]


class SyncMonitor:
    r"""Rolling fit of the twin's prediction and desynchronisation detection.

    Every ``stride`` valid samples, once ``window`` valid samples have been
    seen, the fit percent of the last ``window`` pairs is computed,

    .. math:: \mathrm{fit} = 100\Big(1 - \frac{\|y - \hat y\|}{\|y - \bar y\|}\Big),

    (a window with a constant ``y`` has no defined fit and is skipped).  A fit
    below ``threshold`` for ``n_consecutive`` windows in a row emits a
    ``'desync'`` :class:`SyncEvent` (the trigger for re-identification); it is
    emitted again after every further ``n_consecutive`` bad windows while the
    fit stays low, and a ``'resync'`` event follows the first good window.

    Parameters
    ----------
    window : int, default=100
        Samples per rolling window (``>= 3``).
    stride : int, optional
        Samples between evaluations; ``window // 4`` when omitted.
    threshold : float, default=95.0
        Fit percent below which a window is bad.
    n_consecutive : int, default=3
        Bad windows in a row that make a desynchronisation.

    Raises
    ------
    DataError
        If a parameter is out of range.

    Attributes
    ----------
    fit : float
        The latest window fit (NaN before the first).
    in_sync : bool
        False between a ``'desync'`` and the next ``'resync'``.
    n_bad : int
        Current run of consecutive bad windows.

    See Also
    --------
    Updater : Feeds the monitor and acts on its events.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.update import SyncMonitor
    >>> mon = SyncMonitor(window=20, stride=10, threshold=90.0, n_consecutive=2)
    >>> y = np.sin(np.arange(100) / 3.0)
    >>> y_pred = y + np.where(np.arange(100) > 50, 0.5, 0.0)  # the twin drifts off at k = 51
    >>> events = [e for k in range(100) for e in mon.update(y[k], y_pred[k], k=k)]
    >>> [(e.kind, e.k) for e in events]
    [('desync', 69), ('desync', 89)]
    """

    def __init__(
        self,
        *,
        window: int = 100,
        stride: int | None = None,
        threshold: float = 95.0,
        n_consecutive: int = 3,
    ) -> None:
        window = _int_param(window, "window", 3)
        stride = max(1, window // 4) if stride is None else _int_param(stride, "stride", 1)
        threshold = _as_float(threshold)
        if math.isnan(threshold):
            raise DataError(f"threshold must be a finite fit percent, got {threshold}")
        self.window = window
        self.stride = stride
        self.threshold = threshold
        self.n_consecutive = _int_param(n_consecutive, "n_consecutive", 1)
        self.reset()

    def clear_window(self) -> None:
        """Empty the rolling window (after a model change) but keep the fits and the state.

        The next fit is computed once ``window`` new samples have arrived, so it
        judges the new model only; the run of bad windows restarts at 0.
        """
        self._y.clear()
        self._yp.clear()
        self._since = 0
        self.n_bad = 0

    def reset(self) -> None:
        """Forget the window, the fits and the state (back in sync)."""
        self._y: deque[float] = deque(maxlen=self.window)
        self._yp: deque[float] = deque(maxlen=self.window)
        self._since = 0
        self._k: list[int] = []
        self._t: list[float] = []
        self._fits: list[float] = []
        self.fit = math.nan
        self.in_sync = True
        self.n_bad = 0

    def update(
        self, y: float, y_pred: float, *, k: int | None = None, t: float | None = None
    ) -> tuple[SyncEvent, ...]:
        """Add one measured/predicted pair; NaN pairs are ignored.

        Parameters
        ----------
        y : float
            Measured output.
        y_pred : float
            The twin's prediction of it.
        k : int, optional
            Sample index (reported in events).
        t : float, optional
            Sample time (reported in events).

        Returns
        -------
        tuple of SyncEvent
            Events raised by this sample (usually none).
        """
        yf, pf = _as_float(y), _as_float(y_pred)
        if math.isnan(yf) or math.isnan(pf):
            return ()
        self._y.append(yf)
        self._yp.append(pf)
        self._since += 1
        if len(self._y) < self.window or self._since < self.stride:
            return ()
        self._since = 0
        fit = _fit(np.asarray(self._y, dtype=float), np.asarray(self._yp, dtype=float))
        if math.isnan(fit):
            return ()
        self.fit = fit
        self._k.append(-1 if k is None else int(k))
        self._t.append(math.nan if t is None else float(t))
        self._fits.append(fit)
        if fit < self.threshold:
            self.n_bad += 1
            if self.n_bad % self.n_consecutive == 0:
                first = self.in_sync
                self.in_sync = False
                what = "desynchronised" if first else "still desynchronised"
                return (
                    SyncEvent(
                        "desync", k, t, fit, self.n_bad,
                        f"twin {what}: fit {fit:.2f} % < {self.threshold:g} % for "
                        f"{self.n_bad} windows",
                    ),
                )
            return ()
        self.n_bad = 0
        if not self.in_sync:
            self.in_sync = True
            return (
                SyncEvent("resync", k, t, fit, 0, f"twin resynchronised: fit {fit:.2f} %"),
            )
        return ()

    @property
    def history(self) -> FitHistory:
        """All window fits so far.

        Returns
        -------
        FitHistory
        """
        return FitHistory(
            np.asarray(self._k, dtype=np.int64), np.asarray(self._t, dtype=float),
            np.asarray(self._fits, dtype=float),
        )

    def __repr__(self) -> str:
        return (
            f"SyncMonitor(window={self.window}, stride={self.stride}, threshold={self.threshold:g},"
            f" n_consecutive={self.n_consecutive}, fit={self.fit:.2f})"
        )


def _int_param(value: Any, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise DataError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------- output error
@dataclass(frozen=True, eq=False)
class OutputErrorFit:
    r"""Result of :func:`identify_output_error`.

    Parameters
    ----------
    model : KautzModel
        Fitted model on a delayed discrete basis (``y = c^T x_f``).
    offset : float
        Fitted output offset ``d``.
    input_offset : float
        Input operating point :math:`u_0`: the model is
        :math:`\hat y = c^T x_f + d` with the filter driven by :math:`u - u_0`.
    fit_percent : float
        Simulation fit on the samples used (after the burn-in), percent.
    n_evaluations : int
        Residual evaluations over all starts.
    success : bool
        Whether the best start met its tolerance.
    message : str
        The solver's message for the best start.
    """

    model: KautzModel
    offset: float
    input_offset: float
    fit_percent: float
    n_evaluations: int
    success: bool
    message: str

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Simulated output for an input sequence from a zero filter state.

        Parameters
        ----------
        u : array-like of shape (n_samples,)

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        u = np.asarray(u, dtype=float) - self.input_offset
        return _states(self.model.basis, u)[:-1] @ self.model.coefficients + self.offset


class _OEProblem:
    """Variable projection for output error: poles searched, ``c`` and ``d`` by least squares."""

    def __init__(
        self, kinds: tuple[str, ...], u: NDArray, y: NDArray, dt: float, burn_in: int,
        fit_offset: bool,
    ) -> None:
        self.kinds = kinds
        self.u = u
        self.dt = dt
        use = np.isfinite(y)
        use[:burn_in] = False
        self.use = use
        self.y = y[use]
        self.fit_offset = fit_offset
        self.n_eval = 0

    def basis(self, x: NDArray) -> KautzBasis:
        params = np.empty_like(x)
        col = 0
        for kind in self.kinds:
            rate = math.exp(x[col]) * self.dt
            if kind == REAL:
                params[col] = math.exp(-rate)
                col += 1
            else:
                z = np.exp(complex(-rate, x[col + 1] * self.dt))
                params[col], params[col + 1] = z.real, abs(z.imag)
                col += 2
        return KautzBasis._from_blocks(self.kinds, params, self.dt, True)

    def solve(self, x: NDArray) -> tuple[KautzBasis, NDArray, NDArray]:
        self.n_eval += 1
        basis = self.basis(x)
        X = _states(basis, self.u)[:-1][self.use]
        if self.fit_offset:
            X = np.hstack([X, np.ones((X.shape[0], 1))])
        theta, *_ = np.linalg.lstsq(X, self.y, rcond=None)
        return basis, theta, self.y - X @ theta

    def residual(self, x: NDArray) -> NDArray:
        return self.solve(x)[2]


def _oe_x(kinds: tuple[str, ...], params: NDArray) -> NDArray:
    """Search coordinates (log-rates, angular frequencies) of continuous block parameters."""
    x = np.array(params, dtype=float)
    col = 0
    for kind in kinds:
        x[col] = math.log(params[col])
        col += 2 if kind == PAIR else 1
    return x


def _oe_bounds(
    kinds: tuple[str, ...], n: int, dt: float, min_rate: float
) -> tuple[NDArray, NDArray]:
    lo, hi = [], []
    for kind in kinds:
        lo.append(math.log(min_rate))
        hi.append(math.log(10.0 / dt))
        if kind == PAIR:
            lo.append(1e-3 / (n * dt))
            hi.append(math.pi / dt * (1 - 1e-6))
    return np.array(lo), np.array(hi)


def identify_output_error(
    u: ArrayLike,
    y: ArrayLike,
    init: int | ArrayLike | KautzBasis,
    *,
    dt: float,
    burn_in: int = 0,
    fit_offset: bool = True,
    input_offset: float | None = None,
    min_rate: float | None = None,
    max_iter: int = 50,
    tol: float = 1e-8,
) -> OutputErrorFit:
    r"""Output-error identification of a Kautz model from input/output data (variable projection).

    The model is :math:`\hat y(k) = c^T x_f(k) + d` with the delayed discrete
    Kautz network :math:`x_f(k+1) = A x_f(k) + B (u(k) - u_0)` started from
    rest at the first sample: exact when the plant starts at the equilibrium
    of the input ``u_0 = u[0]``.  For given poles :math:`c` and :math:`d` are the linear
    least-squares solution, so only the poles are searched
    (``scipy.optimize.least_squares`` over continuous-time log-rates and
    frequencies, so every iterate is stable).  The first ``burn_in`` samples
    are left out of the error while the unknown initial state dies out.

    Parameters
    ----------
    u : array-like of shape (n_samples,)
        Input, finite.
    y : array-like of shape (n_samples,)
        Output; NaN samples are left out.
    init : int, array-like of complex, or KautzBasis
        Starting poles: continuous-time locations (``Re < 0``; their
        real/pair structure is kept), a basis (continuous, or discrete on
        ``dt``), or the number of real poles (then several spreads are tried).
    dt : float
        Sampling period, s.
    burn_in : int, default=0
        Samples left out at the start.
    fit_offset : bool, default=True
        Estimate the offset ``d``.
    input_offset : float, optional
        Input operating point :math:`u_0`; ``u[0]`` when omitted.
    min_rate : float, optional
        Slowest allowed decay rate of a pole, 1/s; ``3 / T`` (``T`` the record
        length) when omitted.  A mode that does not decay within the record
        cannot be told apart from the offset: without this bound the fit
        tends to spend a pole on it, which predicts badly once the plant
        changes.  The fastest rate is ``10 / dt``.
    max_iter : int, default=50
        Iteration budget per start.
    tol : float, default=1e-8
        ``ftol``/``xtol``/``gtol`` of the solver.

    Returns
    -------
    OutputErrorFit

    Raises
    ------
    DimensionError
        If ``u`` and ``y`` are not 1-D of one length.
    DataError
        If ``u`` is not finite or too few usable samples remain.
    PoleError
        If ``init`` holds invalid poles.

    See Also
    --------
    kautztwin.optimize_poles : The same variable projection for impulse/step records.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.update import RecursiveKautzEstimator, identify_output_error
    >>> rng = np.random.default_rng(1)
    >>> u = np.repeat(rng.uniform(-1, 1, 40), 10)
    >>> true = RecursiveKautzEstimator(np.exp([-0.2, -0.9]), dt=0.1, coef_init=[1.0, 0.3])
    >>> res = identify_output_error(u, true.simulate(u), [-1.0, -5.0], dt=0.1, input_offset=0.0)
    >>> np.round(np.sort(res.model.poles.real), 4), bool(res.fit_percent > 99.99)
    (array([0.4066, 0.8187]), True)
    """
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.ndim != 1 or u.shape != y.shape:
        raise DimensionError(
            f"u and y must be 1-D of one length, got shapes {u.shape} and {y.shape}"
        )
    if not np.all(np.isfinite(u)):
        raise DataError("u contains NaN or inf")
    dt = _as_float(dt)
    if not dt > 0:
        raise DataError(f"dt must be a positive sampling period, got {dt}")
    burn_in = _int_param(burn_in, "burn_in", 0)
    n = u.size
    u0 = float(u[0]) if input_offset is None else _as_float(input_offset)
    if math.isnan(u0):
        raise DataError(f"input_offset must be a finite number, got {input_offset!r}")
    u = u - u0
    rate_lo = 3.0 / (n * dt) if min_rate is None else _as_float(min_rate)
    if not 0 < rate_lo < 10.0 / dt:
        raise DataError(f"min_rate must lie in (0, 10 / dt), got {min_rate!r}")
    if isinstance(init, KautzBasis):
        starts = [parse_poles(_continuous_poles(init), 0.0)]
    elif isinstance(init, int | np.integer) and not isinstance(init, bool):
        m = _int_param(init, "init", 1)
        lo, hi = max(rate_lo, 3.0 / (n * dt)), 0.3 / dt
        centre = math.sqrt(lo * hi)
        starts = []
        for spread in (hi / lo, (hi / lo) ** 0.5):
            rates = centre * spread ** (np.linspace(-0.5, 0.5, m) if m > 1 else np.zeros(1))
            starts.append(((REAL,) * m, np.sort(rates)))
    else:
        starts = [parse_poles(init, 0.0)]
    n_par = starts[0][1].size + int(bool(fit_offset))
    usable = int(np.isfinite(y[burn_in:]).sum())
    if usable < 2 * n_par + 2:
        raise DataError(
            f"{usable} usable samples after the burn-in are too few to fit {n_par} parameters"
        )
    best = None
    n_eval = 0
    for kinds, params in starts:
        prob = _OEProblem(kinds, u, y, dt, burn_in, bool(fit_offset))
        lo_b, hi_b = _oe_bounds(kinds, n, dt, rate_lo)
        x0 = np.clip(_oe_x(kinds, params), lo_b + 1e-6 * (hi_b - lo_b), hi_b - 1e-6 * (hi_b - lo_b))
        sol = scipy.optimize.least_squares(
            prob.residual, x0, bounds=(lo_b, hi_b), method="trf", x_scale="jac",
            ftol=tol, xtol=tol, gtol=tol, max_nfev=max_iter * (x0.size + 1),
        )
        n_eval += prob.n_eval
        if best is None or sol.cost < best[0].cost:
            best = (sol, prob)
    sol, prob = best
    basis, theta, _ = prob.solve(sol.x)
    n_f = basis.n_functions
    offset = float(theta[n_f]) if fit_offset else 0.0
    model = KautzModel(basis, theta[:n_f])
    yhat = (_states(basis, u)[:-1] @ theta[:n_f] + offset)[prob.use]
    return OutputErrorFit(
        model=model, offset=offset, input_offset=u0, fit_percent=_fit(prob.y, yhat),
        n_evaluations=n_eval,
        success=bool(sol.success), message=str(sol.message),
    )


# --------------------------------------------------------------------------- accurate-path job
@dataclass(frozen=True, eq=False)
class _ReidJob:
    """Frozen inputs of one re-identification attempt (copied when it is prepared).

    ``u`` and ``y`` are the window with its burn-in history (read-only
    copies); ``u[:n_est]`` is fitted (from sample ``w0`` on), the last
    ``n_val`` samples are held out for the validation.  ``k`` is the
    updater's sample counter when the window ended.
    """

    u: NDArray[np.float64]
    y: NDArray[np.float64]
    w0: int
    n_est: int
    n_val: int
    poles: NDArray[np.complex128]
    dt: float
    input_offset: float
    min_rate: float | None
    max_iter: int
    k: int


@dataclass(frozen=True, eq=False)
class _ReidOutcome:
    """What a fit returns: the best start (``None`` when cancelled) and its compute time."""

    fit: OutputErrorFit | None
    elapsed: float


def _fit_window(job: _ReidJob, cancel: threading.Event | None = None) -> _ReidOutcome:
    """The accurate path's computation: output error from the current poles and two scalings.

    A pure function of ``job`` (it runs in the worker thread in background
    mode).  ``cancel`` is checked between the starts.
    """
    start = time.perf_counter()
    best: OutputErrorFit | None = None
    for scale in (1.0, 0.75, 1.33):
        if cancel is not None and cancel.is_set():
            return _ReidOutcome(None, time.perf_counter() - start)
        fit = identify_output_error(
            job.u[: job.n_est], job.y[: job.n_est], _scaled_poles(job.poles, scale), dt=job.dt,
            burn_in=job.w0, input_offset=job.input_offset, min_rate=job.min_rate,
            max_iter=job.max_iter,
        )
        if best is None or fit.fit_percent > best.fit_percent:
            best = fit
    return _ReidOutcome(best, time.perf_counter() - start)


@dataclass
class _Pending:
    """A background attempt in flight."""

    job: _ReidJob
    future: Future[_ReidOutcome]
    cancel: threading.Event
    stale: str = ""  # why its result will be discarded ("" while it is current)


# --------------------------------------------------------------------------- updater
@dataclass(frozen=True, eq=False)
class ModelUpdate:
    """Outcome of one accurate-path or step-test update attempt of :class:`Updater`.

    Parameters
    ----------
    kind : {'reidentification', 'dnn-update', 'step-test'}
        What produced the candidate.
    k : int
        Sample index (the updater's next sample) at which it was decided.
    accepted : bool
        Whether the candidate replaced the current model.
    reason : str
        Why it was accepted or rejected.
    candidate : KautzModel or None
        The candidate model (delayed discrete basis), ``None`` if none was built.
    offset : float
        The candidate's output offset.
    fit_candidate : float
        Fit percent of the candidate on the held-out validation samples.
    fit_current : float
        Fit percent of the current model on the same samples.
    digital_model : DigitalModel or None
        The new version when accepted.
    elapsed : float
        Seconds of computation the attempt took (in a background attempt:
        the worker's fit plus the validation in :meth:`Updater.step`).
    k_submitted : int or None, default=None
        Sample index at which the attempt's data window ended; ``k`` for a
        synchronous attempt, earlier for a background one (which is judged
        at ``k``, when its result was ready).  ``None`` means ``k``.
    """

    kind: str
    k: int
    accepted: bool
    reason: str
    candidate: KautzModel | None
    offset: float
    fit_candidate: float
    fit_current: float
    digital_model: DigitalModel | None
    elapsed: float
    k_submitted: int | None = None

    def __post_init__(self) -> None:
        if self.k_submitted is None:
            object.__setattr__(self, "k_submitted", self.k)

    def payload(self) -> dict[str, Any]:
        """JSON-ready summary (for the history store).

        Returns
        -------
        dict
        """
        return {
            "kind": self.kind, "k": self.k, "k_submitted": self.k_submitted,
            "accepted": self.accepted, "reason": self.reason,
            "offset": self.offset, "fit_candidate": _json_float(self.fit_candidate),
            "fit_current": _json_float(self.fit_current), "elapsed": self.elapsed,
            "version": None if self.digital_model is None else self.digital_model.version,
            "model": None if self.candidate is None else self.candidate.to_dict(),
        }


def _json_float(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """What :meth:`Updater.step` did with one sample.

    Parameters
    ----------
    k : int
        Sample index.
    t : float or None
        Sample time, if given.
    y_pred : float
        A-priori prediction of this sample with the current parameters.
    y_pred_frozen : float
        Prediction with the parameters frozen at the start of the current
        prediction horizon (what the monitor judges).
    y : float
        The measured value used, NaN when the sample was skipped.
    flags : int
        :class:`~kautztwin.twin.SampleFlag` bits of the output sample.
    input_held : bool
        Whether the input was missing and the last one was held.
    fit : float
        Latest rolling fit of the monitor, percent (NaN before the first window).
    events : tuple of SyncEvent
        Monitor events raised by this sample.
    model_update : ModelUpdate or None
        An accurate-path attempt decided at this sample (in background mode:
        one submitted earlier whose result was judged now).
    version : int
        Version of the digital model after this sample.
    elapsed : float
        Wall-clock seconds spent in :meth:`Updater.step`.
    """

    k: int
    t: float | None
    y_pred: float
    y_pred_frozen: float
    y: float
    flags: int
    input_held: bool
    fit: float
    events: tuple[SyncEvent, ...]
    model_update: ModelUpdate | None
    version: int
    elapsed: float


class Updater:
    r"""Keeps the twin's model synchronised with the plant: fast path, monitor, accurate path.

    Each :meth:`step` takes one sample ``(u(k), y(k))`` and

    1. checks the timestamp: a sample that is not later than the previous one
       (late, out of order, duplicated) is ignored; a gap of missing samples
       advances the filter with the last input;
    2. predicts ``y(k)`` (a priori, before using it) and sanitises the
       measured value with a :class:`~kautztwin.twin.SampleSanitizer`:
       dropouts (NaN, garbage) and outliers are not used (neither by the
       estimator nor by the monitor), a missing input holds the last one;
    3. **fast path**: one :class:`RecursiveKautzEstimator` update
       (:math:`O(N^2)`, tens of microseconds including the bookkeeping);
    4. feeds the :class:`SyncMonitor` with the measured output and the
       prediction made with parameters frozen over ``horizon`` samples
       (a ``horizon``-step-ahead simulation, no output feedback inside);
    5. **accurate path**: the first ``'desync'`` event starts a recovery.
       The change is dated half a window before the end of the first bad
       window; once ``min_reid_samples`` samples have arrived since then, and
       every ``reid_every`` samples after that until the monitor reports
       ``'resync'``, poles and coefficients are re-identified by output error
       (:func:`identify_output_error`, from the current poles and two scaled
       copies) on the samples since the change (at most ``reid_samples``,
       the filters settled on ``burn_in`` samples of input history before
       them) except the final ``validation_fraction``.  A candidate replaces
       the current model only if it predicts those held-out samples better
       (fit percent higher by more than ``min_improvement``) *and* well
       enough in absolute terms (fit percent at least ``min_candidate_fit``).
       An accepted model is a new :class:`~kautztwin.twin.DigitalModel`
       version, the estimator continues from it and the monitor's window
       restarts.  With ``background=True`` the fit runs in a worker thread
       and a later :meth:`step` judges it (see Notes).

    :meth:`update_from_step_test` is the other fast path: a trained DNN
    estimator (any object with ``predict_models(responses, t=...)`` returning
    :class:`~kautztwin.KautzModel` objects, e.g. ``kautztwin.nn``'s) or, without
    one, :func:`kautztwin.optimize_poles` turns a recent step test into a
    candidate, validated the same way.

    Parameters
    ----------
    model : DigitalModel or KautzModel
        Initial model: continuous (discretised with a zero-order hold on
        ``dt``, stored as the next version) or on a delayed discrete basis
        with period ``dt``.
    dt : float
        Sampling period, s.
    offset : float, default=0.0
        Output offset ``d`` of the initial model: ``y = c^T x_f + d``.
    input_offset : float, default=0.0
        Input operating point :math:`u_0`: the filter is driven by
        :math:`u - u_0` (see :class:`RecursiveKautzEstimator`).  The twin
        starts from a zero filter state, i.e. the plant at rest at ``u_0``.
    forgetting : float, default=0.995
        Forgetting factor of the fast path (memory about ``1 / (1 - forgetting)`` samples).
    delta : float, default=1.0
        Covariance scale ``P = delta I`` at the start and after every model change.
    max_trace : float, default=1e4
        Anti-windup bound of the covariance trace.
    extra_poles : array-like of complex, optional
        Continuous-time poles (``Re < 0``) appended to the model's basis in
        the fast path only.  Their coefficients start at zero; they widen the
        span of the recursive estimator so that it can follow pole drifts
        (a slower extra pole for plants that slow down) without waiting for a
        re-identification.  Appended blocks leave the model's own basis
        functions unchanged.
    monitor : SyncMonitor, optional
        The synchronisation monitor; ``SyncMonitor()`` when omitted.
    sanitizer : SampleSanitizer, optional
        Sanitiser of the measured output; ``SampleSanitizer(threshold=8.0,
        window=100)`` when omitted (a generous threshold: it is meant for
        gross sensor errors, not for the fast transients of the plant).
        Set ``min_scale`` to the sensor resolution for quantised sensors.
    horizon : int, optional
        Samples over which the monitored prediction keeps its parameters
        frozen; ``monitor.stride`` when omitted.
    fast_update : bool, default=True
        Run the recursive update (``False``: coefficients fixed).
    reidentify : bool, default=True
        Run the accurate path on ``'desync'`` events.  With both flags off the
        updater is a static twin that only predicts and monitors.
    estimator : object, optional
        DNN estimator with ``predict_models`` for :meth:`update_from_step_test`.
    buffer_size : int, default=2000
        Recent samples kept for re-identification and validation.
    reid_samples : int, default=300
        Most samples in a re-identification window (estimation plus validation).
    min_reid_samples : int, default=150
        Samples after the dated change before the first attempt.
    reid_every : int, default=50
        Samples between attempts while the twin is desynchronised.
    max_attempts : int, default=20
        Attempts per recovery; afterwards a new ``'desync'`` event starts a new one.
    burn_in : int, default=250
        Samples of input history before a window that settle the filters
        (the plant's own history, so the window is fitted from its first sample).
    validation_fraction : float, default=0.3
        Held-out fraction at the end of a window.
    min_improvement : float, default=0.0
        Fit percent by which a candidate must beat the current model.
    min_candidate_fit : float or None, default=50.0
        Absolute floor: a candidate whose held-out fit percent is below it is
        rejected even when it beats the current model (which can be poor
        right after a change, so beating it proves little).  Applies to
        re-identified and step-test candidates alike; ``None`` disables the
        floor.  The default of 50 % (prediction error at most half the
        output's spread) rejects candidates that would only replace one bad
        model by another, and each accepted version costs a controller
        retune, a covariance restart and a new monitor window; it stays below
        the held-out fits of the useful intermediate candidates seen while a
        window still straddles an abrupt change (54 % and more in
        ``tests/test_twin_update.py``), which a floor near the monitor's
        threshold would refuse.
    background : bool, default=False
        Run the accurate path's fit in a single worker thread, off the
        sampling path: :meth:`step` submits an attempt with a frozen copy of
        its data window and returns at once, and a later :meth:`step` judges
        the result on the held-out samples fixed at submission (see Notes).
        Off by default because the sample at which a candidate is accepted
        then depends on wall-clock time: keep it off wherever runs must be
        reproducible.  Call :meth:`close` (or use the updater as a context
        manager) to stop the worker.
    min_rate : float, optional
        Slowest pole rate the re-identification may choose, 1/s (see
        :func:`identify_output_error`).
    max_iter : int, default=30
        Iteration budget of each re-identification start.
    history : HistoryStore, optional
        Where events and model versions are logged.
    run_id : int, optional
        The run in ``history`` (required with it).

    Raises
    ------
    DataError
        On an invalid parameter, or ``history`` without ``run_id``.

    Attributes
    ----------
    digital_model : DigitalModel
        The current (last accepted) model version.
    estimator_ : RecursiveKautzEstimator
        The fast-path estimator (its live parameters may differ from
        :attr:`digital_model` between versions; see :meth:`snapshot`).
    monitor : SyncMonitor
        The monitor.
    events : list of SyncEvent
        Every monitor event so far.
    model_updates : list of ModelUpdate
        Every accurate-path and step-test attempt so far.
    background : bool
        Whether attempts are submitted to the worker (may be switched
        between steps; an attempt in flight is still judged).

    See Also
    --------
    RecursiveKautzEstimator : The fast path.
    SyncMonitor : Rolling fit and triggers.
    identify_output_error : The accurate path.

    Notes
    -----
    **Recovery window.**  After the plant changes, the twin needs time before
    its rolling fit is back above the threshold: the change must become
    visible and settle (``T_ramp``, the duration of the change itself), a
    re-identified model must be built from data of the new behaviour
    (``min_reid_samples`` after the dated change, then one attempt every
    ``reid_every`` samples until a candidate wins), and the rolling window
    (``W = monitor.window`` samples) must slide past the samples that the old
    model predicted.  The recovery window after the start of a change is
    therefore about

    .. math::

        T_{rec} \approx T_{ramp} + \big(m + W\big)\,\Delta t,
        \qquad m \ge \mathrm{min\_reid\_samples},

    where ``m`` counts the samples until the winning attempt (or until the
    fast path has re-converged, about ``3 / (1 - forgetting)`` samples, when
    the drift stays inside the widened span of ``extra_poles``).

    Acceptance scenario (``tests/test_twin_update.py``): the hydraulic drive
    sampled at ``dt = 0.02`` s, a three-pole twin identified at 20 °C, the
    dominant pole slowed by 20 % at 30 s and by another 20 % at 60 s (40 % in
    all, 2 s oil-temperature ramps), ``forgetting=0.98``, one extra pole at
    half the slowest identified rate, ``W = 150``, stride 25,
    ``n_consecutive = 2``.  The documented recovery window is **15 s from
    the start of each drift event**; the measured recoveries are about 8 s
    and 10.5 s, and outside the windows the rolling fit of the twin's
    25-step-ahead prediction stays at or above 97 % (the static twin falls
    to a mean of about -200 %).  The fast path alone (fixed poles) recovers
    small drifts; a drift that moves the poles out of the basis' span needs
    the accurate path or ``extra_poles``.

    **Synchronous and background accurate path.**  By default an attempt
    runs inside :meth:`step` (tens of milliseconds to about two seconds,
    depending on the window and the convergence), so in a real-time loop the
    samples during an attempt wait in the caller's queue.  With
    ``background=True`` the step that starts an attempt only copies the
    window (the estimation part, the ``validation_fraction`` held out at its
    end and the current poles) and submits the fit to a single worker
    thread; the following steps run the fast path and the monitor as usual
    and poll the job.  The first :meth:`step` that finds it finished judges
    the candidate exactly as the synchronous path does - the same held-out
    samples, against the live model, with the same ``min_improvement`` and
    ``min_candidate_fit`` - and, when it wins, starts it from its filter
    state at the current sample (recomputed over the samples that arrived
    meanwhile).  The candidate is therefore the same model the synchronous
    path would have built; only the sample at which it takes over is later
    (:attr:`ModelUpdate.k` versus :attr:`ModelUpdate.k_submitted`).  At most
    one attempt is in flight: a due attempt waits until the previous one has
    been judged.  A ``'resync'`` event, another accepted model (e.g.
    :meth:`update_from_step_test`) or :meth:`cancel_pending` makes the
    attempt in flight stale: it is cancelled (the worker stops between the
    fit's starts) and reported as a rejected :class:`ModelUpdate` whose
    reason says why.  A thread is enough: a real-time loop sleeps most of
    each period and gets the GIL back within about the interpreter's switch
    interval (5 ms) when it wakes; measured on a 20 ms loop with the worker
    busy all the time, no sample was late (docs/twin.md, section 4).

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.twin.update import Updater, SyncMonitor
    >>> model = kt.KautzModel(kt.KautzBasis([-2.0]), [2.0])
    >>> upd = Updater(model, dt=0.05, monitor=SyncMonitor(window=20))
    >>> upd.digital_model.version, upd.digital_model.provenance  # continuous model: ZOH version 2
    (2, 'discretized')
    >>> res = upd.step(0.0, 0.0)
    >>> res.k, res.y_pred
    (0, 0.0)
    >>> upd.step(float("nan"), float("nan")).flags != 0   # a dropout does not crash
    True

    In background mode the updater owns a worker thread; close it when done:

    >>> with Updater(model, dt=0.05, background=True) as upd:
    ...     _ = [upd.step(1.0, 0.0) for _ in range(10)]
    ...     upd.pending            # nothing to re-identify yet
    False
    """

    def __init__(
        self,
        model: DigitalModel | KautzModel,
        *,
        dt: float,
        offset: float = 0.0,
        input_offset: float = 0.0,
        forgetting: float = 0.995,
        delta: float = 1.0,
        max_trace: float = 1e4,
        extra_poles: ArrayLike | None = None,
        monitor: SyncMonitor | None = None,
        sanitizer: SampleSanitizer | None = None,
        horizon: int | None = None,
        fast_update: bool = True,
        reidentify: bool = True,
        estimator: Any = None,
        buffer_size: int = 2000,
        reid_samples: int = 300,
        min_reid_samples: int = 150,
        reid_every: int = 50,
        max_attempts: int = 20,
        burn_in: int = 250,
        validation_fraction: float = 0.3,
        min_improvement: float = 0.0,
        min_candidate_fit: float | None = 50.0,
        min_rate: float | None = None,
        max_iter: int = 30,
        background: bool = False,
        history: Any = None,
        run_id: int | None = None,
    ) -> None:
        dt = _as_float(dt)
        if not dt > 0:
            raise DataError(f"dt must be a positive sampling period, got {dt}")
        self.dt = dt
        if isinstance(model, DigitalModel):
            dm = model
        elif isinstance(model, KautzModel):
            dm = DigitalModel.initial(model)
        else:
            raise DataError(
                f"model must be a DigitalModel or a KautzModel, got {type(model).__name__}"
            )
        md = discretize_model(dm.model, dt)
        if md is not dm.model:
            dm = dm.with_update(md, "discretized", dm.fit_percent)
        self.digital_model = dm
        for name, value in (("offset", offset), ("input_offset", input_offset)):
            if math.isnan(_as_float(value)):
                raise DataError(f"{name} must be a finite number, got {value!r}")
        self.input_offset = float(input_offset)
        self.delta = float(delta)
        if extra_poles is None:
            self.extra_poles = np.zeros(0, dtype=complex)
        else:
            self.extra_poles = np.atleast_1d(np.asarray(extra_poles, dtype=complex))
            parse_poles(self.extra_poles, 0.0)  # validates: stable, pairs complete
        self._core_n = md.n_functions
        wide = self._widen(md)
        self.estimator_ = RecursiveKautzEstimator(
            wide.basis, dt=dt, forgetting=forgetting, delta=delta, max_trace=max_trace,
            coef_init=wide.coefficients, offset_init=float(offset), input_offset=self.input_offset,
        ).reset()
        self.monitor = monitor if monitor is not None else SyncMonitor()
        if not isinstance(self.monitor, SyncMonitor):
            raise DataError(f"monitor must be a SyncMonitor, got {type(monitor).__name__}")
        self.sanitizer = (
            sanitizer if sanitizer is not None else SampleSanitizer(threshold=8.0, window=100)
        )
        self.horizon = (
            self.monitor.stride if horizon is None else _int_param(horizon, "horizon", 1)
        )
        self.fast_update = bool(fast_update)
        self.reidentify_enabled = bool(reidentify)
        if estimator is not None and not callable(getattr(estimator, "predict_models", None)):
            raise DataError("estimator must have a predict_models(responses, t=...) method")
        self.dnn = estimator
        self.reid_samples = _int_param(reid_samples, "reid_samples", 10)
        self.min_reid_samples = _int_param(min_reid_samples, "min_reid_samples", 10)
        self.reid_every = _int_param(reid_every, "reid_every", 1)
        self.max_attempts = _int_param(max_attempts, "max_attempts", 1)
        self.burn_in = _int_param(burn_in, "burn_in", 0)
        self.buffer_size = _int_param(buffer_size, "buffer_size", 10)
        if self.buffer_size < self.reid_samples + self.burn_in:
            raise DataError(
                f"buffer_size must hold reid_samples + burn_in = "
                f"{self.reid_samples + self.burn_in} samples, got {self.buffer_size}"
            )
        vf = _as_float(validation_fraction)
        if not 0 < vf < 1:
            raise DataError(f"validation_fraction must lie in (0, 1), got {validation_fraction!r}")
        self.validation_fraction = vf
        mi = _as_float(min_improvement)
        if math.isnan(mi):
            raise DataError(f"min_improvement must be a number, got {min_improvement!r}")
        self.min_improvement = mi
        if min_candidate_fit is None:
            self.min_candidate_fit: float | None = None
        else:
            floor = _as_float(min_candidate_fit)
            if not floor <= 100.0:  # also NaN
                raise DataError(
                    f"min_candidate_fit must be a fit percent <= 100 or None, got "
                    f"{min_candidate_fit!r}"
                )
            self.min_candidate_fit = floor
        self.min_rate = None if min_rate is None else _as_float(min_rate)
        self.max_iter = _int_param(max_iter, "max_iter", 1)
        if not isinstance(background, bool | np.bool_):
            raise DataError(f"background must be True or False, got {background!r}")
        self.background = bool(background)
        self._executor: ThreadPoolExecutor | None = None
        self._job: _Pending | None = None
        self._closed = False
        if history is not None and run_id is None:
            raise DataError("run_id is required with history")
        self.history = history
        self.run_id = run_id
        self._u: deque[float] = deque(maxlen=self.buffer_size)
        self._y: deque[float] = deque(maxlen=self.buffer_size)
        self._k = 0
        self._t_last: float | None = None
        self._u_last = self.input_offset
        self._theta_frozen = self.estimator_.parameters_
        self._recovery: dict[str, int] | None = None
        self._model_k = 0  # sample at which the current model was adopted
        self.events: list[SyncEvent] = []
        self.model_updates: list[ModelUpdate] = []
        self._counts = dict.fromkeys(
            ("samples", "used", "skipped", "late", "gap", "input_held", "attempts", "accepted"), 0
        )
        if self.history is not None and not self.history.model_versions(self.run_id):
            self.history.add_model_version(self.run_id, dm, k=0)

    @classmethod
    def from_fit(cls, fit: OutputErrorFit, *, dt: float, **kwargs: Any) -> Updater:
        """An updater that starts from an :func:`identify_output_error` result.

        Parameters
        ----------
        fit : OutputErrorFit
            The identification (its offset and input offset are used).
        dt : float
            Sampling period, s.
        **kwargs
            Further arguments of :class:`Updater`.

        Returns
        -------
        Updater
        """
        model = DigitalModel.initial(
            fit.model, provenance="identification", fit_percent=fit.fit_percent
        )
        return cls(model, dt=dt, offset=fit.offset, input_offset=fit.input_offset, **kwargs)

    def _widen(self, model: KautzModel) -> KautzModel:
        """``model`` on its basis plus the extra poles (zero coefficients for them)."""
        if self.extra_poles.size == 0:
            return model
        poles = np.concatenate([model.basis.poles, np.exp(self.extra_poles * self.dt)])
        basis = KautzBasis(poles, dt=self.dt, delayed=True)
        coef = np.concatenate([model.coefficients, np.zeros(self.extra_poles.size)])
        return KautzModel(basis, coef)

    # ------------------------------------------------------------------ state
    @property
    def k(self) -> int:
        """Index of the next sample."""
        return self._k

    @property
    def offset(self) -> float:
        """Current output offset ``d`` of the twin."""
        return self.estimator_.offset_

    @property
    def model(self) -> KautzModel:
        """The live model of the fast path (coefficients as of now)."""
        return self.estimator_.model_

    @property
    def recovering(self) -> bool:
        """Whether a recovery (re-identification attempts) is under way."""
        return self._recovery is not None

    @property
    def pending(self) -> bool:
        """Whether a background attempt is in flight (submitted, not judged yet)."""
        return self._job is not None

    @property
    def counts(self) -> dict[str, int]:
        """Counters: samples, used, skipped, late, gap, input_held, attempts, accepted (a copy)."""
        return dict(self._counts)

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Predict the output for future inputs from the current state (parameters as of now).

        Parameters
        ----------
        u : array-like of shape (horizon,)
            Inputs of the next samples.

        Returns
        -------
        ndarray of shape (horizon,)
            Predicted outputs of the same samples (``y(k)`` depends on inputs before ``k``).
        """
        est = self.estimator_
        return est.simulate(np.asarray(u, dtype=float), x0=est.state_)

    # ------------------------------------------------------------------ the loop
    def step(self, u: Any, y: Any, t: Any = None) -> UpdateResult:
        """Process one sample: predict, sanitise, update, monitor, maybe re-identify.

        Never raises on bad samples (NaN, garbage, outliers, late or missing
        timestamps); their flags tell what happened.  In background mode it
        never waits for the worker either: it judges an attempt whose fit has
        finished, and submits a due attempt when none is in flight.

        Parameters
        ----------
        u : float
            Input applied at this sample.
        y : float
            Measured output of this sample.
        t : float, optional
            Timestamp, s.  Without timestamps every call is one sample period.

        Returns
        -------
        UpdateResult
        """
        start = time.perf_counter()
        est = self.estimator_
        flags = SampleFlag.NONE
        self._counts["samples"] += 1
        tf: float | None = None
        if t is not None:
            tf = _as_float(t)
            if math.isnan(tf) or (self._t_last is not None and tf <= self._t_last):
                self._counts["late"] += 1
                return UpdateResult(
                    self._k, tf, math.nan, math.nan, math.nan,
                    int(SampleFlag.LATE | SampleFlag.HELD), False, self.monitor.fit, (), None,
                    self.digital_model.version, time.perf_counter() - start,
                )
            if self._t_last is not None:
                missing = min(int(round((tf - self._t_last) / self.dt)) - 1, self.buffer_size)
                if missing > 0:
                    flags |= SampleFlag.LATE | SampleFlag.GAP
                    self._counts["gap"] += missing
                    est.advance(self._u_last, missing)
                    self._u.extend([self._u_last] * missing)
                    self._y.extend([math.nan] * missing)
                    self._advance_k(missing)
            self._t_last = tf
        uf = _as_float(u)
        held = math.isnan(uf)
        if held:
            uf = self._u_last
            self._counts["input_held"] += 1
        k = self._k
        y_pred = est.predict()
        y_frozen = est.predict_with(self._theta_frozen)
        yf = _as_float(y)
        s = self.sanitizer.process(yf)
        flags |= s.flags
        events: tuple[SyncEvent, ...] = ()
        if not s.flags & (SampleFlag.HELD | SampleFlag.OUTLIER):
            self._counts["used"] += 1
            if self.fast_update:
                est.update(uf, yf)
            else:
                est.advance(uf)
            events = self.monitor.update(yf, y_frozen, k=k, t=tf)
        else:
            self._counts["skipped"] += 1
            est.advance(uf)
            yf = math.nan
        self._u.append(uf)
        self._y.append(yf)
        self._u_last = uf
        self._advance_k(1)
        for ev in events:
            self._on_event(ev)
        update = self._poll() if self._job is not None else None
        rec = self._recovery
        if rec is not None and self._k >= rec["next"] and self._job is None and update is None:
            if self.background and not self._closed:
                update = self._submit()
            else:
                update = self.reidentify()
            rec["attempts"] += 1
            rec["next"] = self._k + self.reid_every
            if rec["attempts"] >= self.max_attempts:
                self._recovery = None
        return UpdateResult(
            k, tf, y_pred, y_frozen, yf, int(flags), held, self.monitor.fit, events, update,
            self.digital_model.version, time.perf_counter() - start,
        )

    def _advance_k(self, n: int) -> None:
        before = self._k
        self._k += n
        if self._k // self.horizon != before // self.horizon:
            self._theta_frozen = self.estimator_.parameters_

    def _on_event(self, ev: SyncEvent) -> None:
        self.events.append(ev)
        self._log(ev.kind, ev.message, ev.k, ev.t, ev.payload())
        if ev.kind == "resync":
            self._recovery = None
            self._make_stale("the twin resynchronised while it ran")
        elif ev.kind == "desync" and self.reidentify_enabled and self._recovery is None:
            mon = self.monitor
            first_bad_end = self._k - (mon.n_consecutive - 1) * mon.stride
            change = max(first_bad_end - mon.window // 2, self._model_k, 0)
            self._recovery = {
                "change": change, "next": change + self.min_reid_samples, "attempts": 0,
            }

    # ------------------------------------------------------------------ accurate path
    def _buffer(self) -> tuple[NDArray, NDArray]:
        return (np.asarray(self._u, dtype=float), np.asarray(self._y, dtype=float))

    def _validate(
        self, model: KautzModel, offset: float, u: NDArray, y: NDArray, n_val: int
    ) -> tuple[float, float, NDArray]:
        """Fits of a candidate and of the live model on the last ``n_val`` samples of ``u, y``."""
        v = u - self.input_offset
        Xc = _states(model.basis, v)
        yc = Xc[:-1] @ model.coefficients + offset
        est = self.estimator_
        ym = _states(est.basis_, v)[:-1] @ est.coef_ + est.offset_
        sl = slice(u.size - n_val, u.size)
        return _fit(y[sl], yc[sl]), _fit(y[sl], ym[sl]), Xc[-1]

    def _prepare(self, n_samples: int | None) -> _ReidJob | ModelUpdate:
        """Freeze the window of an attempt (counted), or reject it for too few samples."""
        start = time.perf_counter()
        self._counts["attempts"] += 1
        u_all, y_all = self._buffer()
        if n_samples is None:
            n_samples = self.reid_samples
            if self._recovery is not None:
                n_samples = min(n_samples, self._k - self._recovery["change"])
        n_w = min(int(n_samples), u_all.size)
        h0 = max(0, u_all.size - n_w - self.burn_in)
        u, y = u_all[h0:], y_all[h0:]  # fresh arrays: the buffer is a deque
        w0 = u.size - n_w  # first sample of the window inside (u, y)
        n_val = int(self.validation_fraction * n_w)
        n_est = u.size - n_val
        n_par = self._core_n + 1
        usable = int(np.isfinite(y[w0:n_est]).sum())
        if n_val < 10 or usable < 4 * n_par or np.isfinite(y[n_est:]).sum() < 10:
            return self._finish(
                "reidentification", start, False,
                f"too few samples: {usable} usable for estimation, {n_val} for validation",
                None, math.nan, math.nan, math.nan, None,
            )
        u.setflags(write=False)
        y.setflags(write=False)
        poles = _continuous_poles(self.estimator_.basis_)[: self._core_n]
        return _ReidJob(
            u=u, y=y, w0=w0, n_est=n_est, n_val=n_val, poles=poles, dt=self.dt,
            input_offset=self.input_offset, min_rate=self.min_rate, max_iter=self.max_iter,
            k=self._k,
        )

    def reidentify(self, n_samples: int | None = None) -> ModelUpdate:
        """Accurate path now, synchronously: output-error re-identification on the recent window.

        Always runs in the caller's thread, also in background mode; an
        accepted candidate makes a background attempt in flight stale.

        Parameters
        ----------
        n_samples : int, optional
            Window length; since the dated change of the current recovery
            (at most ``reid_samples``), or ``reid_samples`` outside a recovery.

        Returns
        -------
        ModelUpdate
            Accepted or not, with both validation fits.
        """
        job = self._prepare(n_samples)
        if isinstance(job, ModelUpdate):
            return job
        out = _fit_window(job)
        assert out.fit is not None  # only a cancelled fit has none
        return self._judge(
            "reidentification", time.perf_counter() - out.elapsed, out.fit.model, out.fit.offset,
            job.u, job.y, job.n_val,
        )

    # ------------------------------------------------------------------ background
    def _submit(self) -> ModelUpdate | None:
        """Submit an attempt to the worker; ``None``, or the rejection when it cannot start."""
        job = self._prepare(None)
        if isinstance(job, ModelUpdate):
            return job
        if self._executor is None:
            self._executor = ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="kautztwin-reidentify"
            )
        cancel = threading.Event()
        # looked up at call time, so that tests can slow the fit down
        future = self._executor.submit(_fit_window, job, cancel)
        self._job = _Pending(job, future, cancel)
        return None

    def _make_stale(self, reason: str) -> None:
        """Mark the attempt in flight (if any) stale and ask the worker to stop early."""
        p = self._job
        if p is not None and not p.stale:
            p.stale = reason
            p.cancel.set()
            p.future.cancel()  # succeeds only if it has not started

    def _poll(self) -> ModelUpdate | None:
        """Judge the attempt in flight if its result is ready (the caller checked one exists)."""
        p = self._job
        assert p is not None
        if not p.future.done():
            return None
        self._job = None
        job = p.job
        if p.stale:
            return self._finish(
                "reidentification", time.perf_counter(), False,
                f"discarded the attempt submitted at sample {job.k}: {p.stale}",
                None, math.nan, math.nan, math.nan, None, k_submitted=job.k,
            )
        try:
            out = p.future.result()
        except (KautzTwinError, ValueError, ArithmeticError) as exc:
            return self._finish(
                "reidentification", time.perf_counter(), False,
                f"the fit submitted at sample {job.k} failed: {exc}",
                None, math.nan, math.nan, math.nan, None, k_submitted=job.k,
            )
        assert out.fit is not None  # not cancelled: it would be stale
        u_now = None
        if self._k > job.k:  # the input from the window's first sample up to now
            n_now = min(job.u.size + (self._k - job.k), len(self._u))
            u_now = np.asarray(self._u, dtype=float)[len(self._u) - n_now:]
        return self._judge(
            "reidentification", time.perf_counter() - out.elapsed, out.fit.model, out.fit.offset,
            job.u, job.y, job.n_val, u_now=u_now, k_submitted=job.k,
        )

    def cancel_pending(self, reason: str = "cancelled") -> bool:
        """Make the background attempt in flight stale (after a reset of your own, say).

        Its result is discarded when the worker stops (reported by a later
        :meth:`step` as a rejected :class:`ModelUpdate` with ``reason``).

        Parameters
        ----------
        reason : str, default='cancelled'
            Why, for the rejection's reason.

        Returns
        -------
        bool
            Whether an attempt was in flight.
        """
        was = self._job is not None and not self._job.stale
        self._make_stale(reason)
        return was

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the background attempt in flight has finished computing.

        The next :meth:`step` judges it; nothing is judged here.

        Parameters
        ----------
        timeout : float, optional
            Most seconds to wait (no limit when omitted).

        Returns
        -------
        bool
            Whether no computation is outstanding any more.
        """
        p = self._job
        if p is None:
            return True
        try:
            p.future.exception(timeout=timeout)
        except TimeoutError:
            return False
        except CancelledError:
            pass
        return True

    def close(self) -> None:
        """Stop the background worker: cancel the attempt in flight and join the thread.

        A running fit stops at its next start (one ``identify_output_error``
        run at most).  Idempotent; afterwards attempts run synchronously.
        """
        self._closed = True
        if self._job is not None:
            self._make_stale("the updater was closed")
            self._job = None
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> Updater:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _judge(
        self, kind: str, start: float, model: KautzModel, offset: float, u: NDArray,
        y: NDArray, n_val: int, *, u_now: NDArray | None = None, k_submitted: int | None = None,
    ) -> ModelUpdate:
        """Validate a candidate on the last ``n_val`` samples of ``u, y`` and maybe adopt it.

        ``u_now``: the input from the first sample of ``u`` (or a later one,
        when the buffer no longer holds it) up to now, when samples arrived
        after the window (a background attempt); an accepted candidate
        starts from its filter state at the end of ``u_now``.
        """
        fit_c, fit_m, state = self._validate(model, offset, u, y, n_val)
        better = math.isfinite(fit_c) and (
            not math.isfinite(fit_m) or fit_c > fit_m + self.min_improvement
        )
        if not better:
            return self._finish(
                kind, start, False,
                f"candidate fit {fit_c:.2f} % does not beat the current {fit_m:.2f} % "
                f"on {n_val} held-out samples",
                model, offset, fit_c, fit_m, None, k_submitted=k_submitted,
            )
        floor = self.min_candidate_fit
        if floor is not None and not fit_c >= floor:
            return self._finish(
                kind, start, False,
                f"candidate fit {fit_c:.2f} % on {n_val} held-out samples is below "
                f"min_candidate_fit = {floor:g} % (the current model has {fit_m:.2f} %)",
                model, offset, fit_c, fit_m, None, k_submitted=k_submitted,
            )
        dm = self.digital_model.with_update(model, kind, fit_c)
        self.digital_model = dm
        self._core_n = model.n_functions
        if u_now is None:
            u_now = u
        else:
            state = _states(model.basis, u_now - self.input_offset)[-1]
        wide = self._widen(model)
        if wide is not model:
            state = _states(wide.basis, u_now - self.input_offset)[-1]
        self.estimator_.reseed(wide, offset=offset, state=state, delta=self.delta)
        self._theta_frozen = self.estimator_.parameters_
        self.monitor.clear_window()
        self._model_k = self._k
        self._counts["accepted"] += 1
        self._make_stale("another model was accepted while it ran")
        if self.history is not None:
            self.history.add_model_version(self.run_id, dm, k=self._k)
        return self._finish(
            kind, start, True,
            f"candidate fit {fit_c:.2f} % beats the current {fit_m:.2f} % on {n_val} held-out "
            "samples",
            model, offset, fit_c, fit_m, dm, k_submitted=k_submitted,
        )

    def _finish(
        self, kind: str, start: float, accepted: bool, reason: str, model: KautzModel | None,
        offset: float, fit_c: float, fit_m: float, dm: DigitalModel | None,
        *, k_submitted: int | None = None,
    ) -> ModelUpdate:
        mu = ModelUpdate(
            kind, self._k, accepted, reason, model, offset, fit_c, fit_m, dm,
            time.perf_counter() - start, k_submitted,
        )
        self.model_updates.append(mu)
        self._log(
            "model-update" if accepted else "model-rejected", reason, self._k, None, mu.payload()
        )
        return mu

    def update_from_step_test(
        self,
        y: ArrayLike,
        *,
        t: ArrayLike | None = None,
        amplitude: float = 1.0,
        u0: float | None = None,
        y0: float | None = None,
    ) -> ModelUpdate:
        """Fast path from a step test: a DNN (or pole optimisation) estimate, validated.

        Parameters
        ----------
        y : array-like of shape (n_samples,)
            Measured output of a step test from an equilibrium, the step
            applied at the first sample.
        t : array-like of shape (n_samples,), optional
            Its sample times from the step (``k * dt`` when omitted; a DNN may
            need its own training grid).
        amplitude : float, default=1.0
            Step height of the input.
        u0 : float, optional
            Input before the step; the updater's ``input_offset`` when omitted.
        y0 : float, optional
            Output before the step; ``y[0]`` when omitted.

        Returns
        -------
        ModelUpdate
            ``kind='dnn-update'`` with an estimator, else ``'step-test'``.
            The candidate is validated on the last ``reid_samples`` buffered
            samples (their final ``validation_fraction``) when the buffer holds
            enough, else on the step test itself (on the twin's grid only; an
            accepted model then continues from the state at the end of the
            step test).

        Raises
        ------
        DataError
            If the record is not finite or ``amplitude`` is zero.
        """
        start = time.perf_counter()
        self._counts["attempts"] += 1
        yy = np.asarray(y, dtype=float).reshape(-1)
        if yy.size < 3 or not np.all(np.isfinite(yy)):
            raise DataError("y must hold at least 3 finite samples of a step test")
        amp = _as_float(amplitude)
        if math.isnan(amp) or amp == 0:
            raise DataError(f"amplitude must be a nonzero number, got {amplitude!r}")
        base_u = self.input_offset if u0 is None else _as_float(u0)
        base_y = float(yy[0]) if y0 is None else _as_float(y0)
        if math.isnan(base_u) or math.isnan(base_y):
            raise DataError("u0 and y0 must be finite numbers")
        record = (yy - base_y) / amp
        tt = None if t is None else np.asarray(t, dtype=float)
        if self.dnn is not None:
            kind = "dnn-update"
            model = self.dnn.predict_models(record, t=tt)[0]
        else:
            kind = "step-test"
            grid = np.arange(yy.size) * self.dt if tt is None else tt
            init = KautzBasis(_continuous_poles(self.estimator_.basis_)[: self._core_n])
            model = optimize_poles(grid, record, init, kind="step").model
        md = discretize_model(model, self.dt)
        offset = base_y - md.dc_gain * (base_u - self.input_offset)
        u_all, y_all = self._buffer()
        n_w = min(self.reid_samples, u_all.size)
        n_val = int(self.validation_fraction * n_w)
        if n_val >= 10 and np.isfinite(y_all[-n_val:]).sum() >= 10:
            h0 = max(0, u_all.size - n_w - self.burn_in)
            return self._judge(kind, start, md, offset, u_all[h0:], y_all[h0:], n_val)
        if tt is not None and (
            tt.size != yy.size or not np.allclose(np.diff(tt), self.dt, rtol=1e-6, atol=0)
        ):
            return self._finish(
                kind, start, False, "no buffered data to validate on, and the step test is "
                "not on the twin's sampling grid", md, offset, math.nan, math.nan, None,
            )
        # validate on the step test itself: the twin at rest at u0, the step at the first sample
        n_pre = max(self.burn_in, 1)
        u_rec = np.concatenate([np.full(n_pre, base_u), np.full(yy.size, base_u + amp)])
        y_rec = np.concatenate([np.full(n_pre, base_y), yy])
        return self._judge(kind, start, md, offset, u_rec, y_rec, yy.size)

    def snapshot(self, provenance: str = "rls-update") -> DigitalModel:
        """Publish the fast path's live coefficients as a new model version.

        Parameters
        ----------
        provenance : str, default='rls-update'
            Provenance of the version.

        Returns
        -------
        DigitalModel
        """
        dm = self.digital_model.with_update(self.estimator_.model_, provenance)
        self.digital_model = dm
        if self.history is not None:
            self.history.add_model_version(self.run_id, dm, k=self._k)
            self._log(
                "model-update", f"{provenance}: version {dm.version}", self._k, None,
                {"version": dm.version, "offset": self.offset},
            )
        return dm

    def _log(self, kind: str, message: str, k: int | None, t: float | None, payload: Any) -> None:
        if self.history is not None:
            self.history.log_event(self.run_id, kind, message, k=k, t=t, payload=payload)

    def __repr__(self) -> str:
        return (
            f"Updater(dt={self.dt:g}, version={self.digital_model.version}, k={self._k}, "
            f"fit={self.monitor.fit:.2f})"
        )


def _scaled_poles(poles: NDArray[np.complex128], scale: float) -> NDArray[np.complex128]:
    """Continuous poles with their decay rates (real parts) scaled."""
    return np.asarray([complex(p.real * scale, p.imag) for p in poles])
