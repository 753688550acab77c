r"""Discrete-time ARX models by linear least squares: the classical identification baseline.

The ARX(:math:`n_a, n_b, n_k`) model is

.. math::

    y(k) + a_1 y(k-1) + \dots + a_{n_a} y(k-n_a)
    = b_1 u(k-n_k) + \dots + b_{n_b} u(k-n_k-n_b+1) + e(k),

with signals measured from their offsets (by default the means of the
estimation data, as MATLAB's ``detrend`` does before ``arx``).  Its
coefficients minimise the one-step prediction error, a linear least-squares
problem; the model is then judged by free-run *simulation*, like any other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_finite
from ..exceptions import DataError, DimensionError, NotFittedError
from ..metrics import fit_percent

__all__ = ["ARXEstimator", "ARXModel"]


def _signal(x: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(x, dtype=float)
    if a.ndim != 1:
        raise DimensionError(f"{name} must be 1-D (SISO), got shape {a.shape}")
    check_finite(a, name)
    return a


@dataclass(frozen=True, eq=False)
class ARXModel:
    r"""An ARX model (immutable): coefficients, offsets and sampling period.

    Parameters
    ----------
    a : array-like of shape (na,)
        :math:`a_1, \dots, a_{n_a}`.
    b : array-like of shape (nb,)
        :math:`b_1, \dots, b_{n_b}`.
    nk : int, default=1
        Input delay in samples (``>= 0``).
    dt : float, default=1.0
        Sampling period in seconds.
    u_offset, y_offset : float, default=0.0
        Levels the signals are measured from.
    noise_variance : float, default=nan
        Variance of the one-step prediction error on the estimation data.

    Attributes
    ----------
    poles : ndarray of complex
        Roots of :math:`z^{n_a} + a_1 z^{n_a-1} + \dots + a_{n_a}`.
    gain : float
        Static gain :math:`\sum b / (1 + \sum a)`.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import ARXModel
    >>> m = ARXModel(a=[-0.5], b=[1.0])           # y(k) = 0.5 y(k-1) + u(k-1)
    >>> m.simulate(np.ones(4))
    array([0.  , 1.  , 1.5 , 1.75])
    >>> m.gain
    2.0
    """

    a: NDArray[np.float64]
    b: NDArray[np.float64]
    nk: int = 1
    dt: float = 1.0
    u_offset: float = 0.0
    y_offset: float = 0.0
    noise_variance: float = field(default=float("nan"))

    def __post_init__(self) -> None:
        a = np.atleast_1d(np.asarray(self.a, dtype=float))
        b = np.atleast_1d(np.asarray(self.b, dtype=float))
        if a.ndim != 1 or b.ndim != 1 or b.size == 0:
            raise DimensionError("a and b must be 1-D; b needs at least one coefficient")
        for name, x in (("a", a), ("b", b)):
            check_finite(x, name)
        if int(self.nk) != self.nk or self.nk < 0:
            raise DataError(f"nk must be an integer >= 0; got {self.nk}")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise DataError(f"dt must be a positive sampling period; got {self.dt}")
        for name, x in (("a", a), ("b", b)):
            x.setflags(write=False)
            object.__setattr__(self, name, x)
        object.__setattr__(self, "nk", int(self.nk))
        object.__setattr__(self, "dt", float(self.dt))

    @property
    def na(self) -> int:
        """Number of output lags."""
        return int(self.a.size)

    @property
    def nb(self) -> int:
        """Number of input lags."""
        return int(self.b.size)

    @property
    def poles(self) -> NDArray[np.complex128]:
        """Poles in the z-plane."""
        return np.roots(np.concatenate([[1.0], self.a])).astype(complex)

    @property
    def gain(self) -> float:
        """Static gain ``sum(b) / (1 + sum(a))``."""
        return float(np.sum(self.b) / (1.0 + np.sum(self.a)))

    def simulate(self, u: ArrayLike, *, y0: ArrayLike | None = None) -> NDArray[np.float64]:
        """Free-run simulation: the model's own past outputs, never the measured ones.

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Input.  Inputs before the first sample are taken at ``u_offset``.
        y0 : array-like of shape (na,), optional
            The first ``na`` outputs (e.g. measured); the simulation runs from
            sample ``na`` on.  By default the model starts at rest
            (``y_offset``), with outputs before the first sample at ``y_offset``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        u = _signal(u, "u") - self.u_offset
        n = u.size
        y = np.zeros(n)
        first = 0
        if y0 is not None:
            y0 = _signal(y0, "y0") - self.y_offset
            if y0.size != self.na:
                raise DimensionError(f"y0 has {y0.size} values but the model has na = {self.na}")
            first = min(self.na, n)
            y[:first] = y0[:first]
        na, nb, nk = self.na, self.nb, self.nk
        lag_u = nk + np.arange(nb)
        for k in range(first, n):
            acc = 0.0
            for i in range(1, na + 1):
                if k - i >= 0:
                    acc -= self.a[i - 1] * y[k - i]
            idx = k - lag_u
            ok = idx >= 0
            acc += float(self.b[ok] @ u[idx[ok]])
            y[k] = acc
        return y + self.y_offset

    def predict(self, u: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """One-step-ahead prediction from measured past outputs and inputs.

        Parameters
        ----------
        u, y : array-like of shape (n_samples,)

        Returns
        -------
        ndarray of shape (n_samples,)
            The first ``max(na, nk + nb - 1)`` entries use the offsets for missing past values.
        """
        u = _signal(u, "u") - self.u_offset
        y = _signal(y, "y") - self.y_offset
        if u.size != y.size:
            raise DimensionError(f"u has {u.size} samples but y has {y.size}")
        Phi = _regressors(u, y, self.na, self.nb, self.nk)
        return Phi @ np.concatenate([self.a, self.b]) + self.y_offset

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description.

        Returns
        -------
        dict
            ``a``, ``b``, ``nk``, ``dt``, the offsets and the noise variance.
        """
        return {"a": self.a.tolist(), "b": self.b.tolist(), "nk": self.nk, "dt": self.dt,
                "u_offset": self.u_offset, "y_offset": self.y_offset,
                "noise_variance": self.noise_variance}


def _regressors(u: NDArray, y: NDArray, na: int, nb: int, nk: int) -> NDArray[np.float64]:
    """Rows ``[-y(k-1) .. -y(k-na), u(k-nk) .. u(k-nk-nb+1)]`` (zeros before the start)."""
    n = u.size
    Phi = np.zeros((n, na + nb))
    for i in range(1, na + 1):
        Phi[i:, i - 1] = -y[: n - i]
    for j in range(nb):
        lag = nk + j
        if lag < n:
            Phi[lag:, na + j] = u[: n - lag]
    return Phi


class ARXEstimator:
    r"""Least-squares ARX(na, nb, nk) estimator (scikit-learn style).

    Parameters
    ----------
    na : int, default=2
        Number of past outputs.
    nb : int, default=2
        Number of past inputs.
    nk : int, default=1
        Input delay in samples.
    detrend : bool, default=True
        Measure ``u`` and ``y`` from the means of the estimation data (else from 0).

    Attributes
    ----------
    model_ : ARXModel
        The fitted model.
    fit_percent_ : float
        Simulation fit on the estimation data (started from the measured first
        ``na`` outputs).

    See Also
    --------
    TransferFunctionEstimator : Continuous-time output-error estimation.

    Notes
    -----
    Only rows whose regressors lie inside the record are used (``k >=
    max(na, nk + nb - 1)``); the normal equations are solved by ``lstsq``.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import ARXEstimator, ARXModel
    >>> rng = np.random.default_rng(0)
    >>> u = rng.standard_normal(200)
    >>> y = ARXModel(a=[-0.7, 0.1], b=[1.0, 0.5]).simulate(u)
    >>> est = ARXEstimator(na=2, nb=2, nk=1, detrend=False).fit(u, y)
    >>> np.round(est.model_.a, 6), np.round(est.model_.b, 6)
    (array([-0.7,  0.1]), array([1. , 0.5]))
    """

    def __init__(self, na: int = 2, nb: int = 2, nk: int = 1, *, detrend: bool = True) -> None:
        self.na = na
        self.nb = nb
        self.nk = nk
        self.detrend = detrend

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Constructor parameters (scikit-learn protocol).

        Parameters
        ----------
        deep : bool, default=True
            Unused (no nested estimators).

        Returns
        -------
        dict
        """
        return {"na": self.na, "nb": self.nb, "nk": self.nk, "detrend": self.detrend}

    def set_params(self, **params: Any) -> ARXEstimator:
        """Set constructor parameters (scikit-learn protocol).

        Parameters
        ----------
        **params
            New values of constructor parameters.

        Returns
        -------
        self
        """
        for k, v in params.items():
            if k not in self.get_params():
                raise ValueError(f"unknown parameter {k!r}")
            setattr(self, k, v)
        return self

    def fit(self, u: ArrayLike, y: ArrayLike, *, dt: float = 1.0) -> ARXEstimator:
        """Estimate the coefficients by least squares.

        Parameters
        ----------
        u, y : array-like of shape (n_samples,)
            Input and output, uniformly sampled.
        dt : float, default=1.0
            Sampling period (recorded in the model).

        Returns
        -------
        self

        Raises
        ------
        DataError
            On bad orders, NaN, a constant input, or too few samples.
        DimensionError
            If ``u`` and ``y`` differ in length.
        """
        for name in ("na", "nb", "nk"):
            v = getattr(self, name)
            low = 1 if name == "nb" else 0
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low:
                raise DataError(f"{name} must be an integer >= {low}; got {v!r}")
        u = _signal(u, "u")
        y = _signal(y, "y")
        if u.size != y.size:
            raise DimensionError(f"u has {u.size} samples but y has {y.size}")
        if np.ptp(u) == 0:
            raise DataError(f"u is constant ({u[0]:g}); an ARX model needs an exciting input")
        start = max(self.na, self.nk + self.nb - 1)
        if u.size - start <= self.na + self.nb:
            raise DataError(f"{u.size} samples are too few for ARX({self.na}, {self.nb}, "
                            f"{self.nk})")
        uo = float(u.mean()) if self.detrend else 0.0
        yo = float(y.mean()) if self.detrend else 0.0
        Phi = _regressors(u - uo, y - yo, self.na, self.nb, self.nk)[start:]
        target = (y - yo)[start:]
        theta, *_ = np.linalg.lstsq(Phi, target, rcond=None)
        resid = target - Phi @ theta
        var = float(resid @ resid) / max(resid.size - theta.size, 1)
        self.model_ = ARXModel(a=theta[: self.na], b=theta[self.na:], nk=self.nk, dt=dt,
                               u_offset=uo, y_offset=yo, noise_variance=var)
        self.fit_percent_ = self.score(u, y)
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise NotFittedError("this ARXEstimator is not fitted yet; call fit(u, y) first")

    def simulate(self, u: ArrayLike, *, y0: ArrayLike | None = None) -> NDArray[np.float64]:
        """Free-run simulation of the fitted model (see :meth:`ARXModel.simulate`).

        Parameters
        ----------
        u : array-like of shape (n_samples,)
        y0 : array-like of shape (na,), optional
            The first ``na`` outputs.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        self._check_fitted()
        return self.model_.simulate(u, y0=y0)

    def predict(self, u: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """One-step-ahead prediction (see :meth:`ARXModel.predict`).

        Parameters
        ----------
        u, y : array-like of shape (n_samples,)

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        self._check_fitted()
        return self.model_.predict(u, y)

    def score(self, u: ArrayLike, y: ArrayLike) -> float:
        """Simulation fit percent, started from the measured first ``na`` outputs.

        Parameters
        ----------
        u, y : array-like of shape (n_samples,)

        Returns
        -------
        float
        """
        self._check_fitted()
        y = _signal(y, "y")
        y0 = y[: self.model_.na] if self.model_.na else None
        return float(fit_percent(y, self.model_.simulate(u, y0=y0)))
