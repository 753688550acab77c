"""Fit metrics: fit percent (MATLAB ``compare``), NRMSE, MSE, R^2 and ISE.

Records run along axis 0 and time along the last axis: a 2-D array of shape
``(n_records, n_samples)`` gives one value per record.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._quadrature import quadrature_weights
from ._validation import check_finite, check_time
from .exceptions import DataError, DimensionError

__all__ = ["fit_percent", "ise", "mse", "nrmse", "r_squared"]


def _pair(y: ArrayLike, yhat: ArrayLike) -> tuple[NDArray, NDArray]:
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    if y.shape != yhat.shape:
        raise DimensionError(f"y has shape {y.shape} but yhat has shape {yhat.shape}")
    if y.ndim == 0 or y.shape[-1] == 0:
        raise DimensionError("y must hold at least one sample")
    check_finite(y, "y")
    check_finite(yhat, "yhat")
    return y, yhat


def nrmse(y: ArrayLike, yhat: ArrayLike) -> float | NDArray[np.float64]:
    r"""Normalised root-mean-square error :math:`\|y - \hat y\| / \|y - \bar y\|`.

    Parameters
    ----------
    y, yhat : array-like of shape (n_samples,) or (n_records, n_samples)
        Measured and model signals on the same grid.

    Returns
    -------
    float or ndarray of shape (n_records,)

    Raises
    ------
    DataError
        If a record of ``y`` is constant (the metric is undefined).
    """
    y, yhat = _pair(y, yhat)
    spread = np.linalg.norm(y - y.mean(axis=-1, keepdims=True), axis=-1)
    if np.any(spread == 0):
        raise DataError("fit is undefined for a constant measured signal y")
    out = np.linalg.norm(y - yhat, axis=-1) / spread
    return float(out) if out.ndim == 0 else out


def fit_percent(y: ArrayLike, yhat: ArrayLike) -> float | NDArray[np.float64]:
    r"""Fit percent as MATLAB ``compare`` defines it.

    .. math:: \mathrm{fit} = 100\Big(1 - \frac{\|y - \hat y\|_2}{\|y - \bar y\|_2}\Big)

    100 is a perfect fit, 0 is no better than the mean, and it can be negative.

    Parameters
    ----------
    y : array-like of shape (n_samples,) or (n_records, n_samples)
        Measured signal.
    yhat : array-like of the same shape
        Model signal.

    Returns
    -------
    float or ndarray of shape (n_records,)

    Raises
    ------
    DataError
        If ``y`` is constant or holds NaN/inf.

    Examples
    --------
    >>> import kautztwin as kt
    >>> kt.fit_percent([0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0])
    100.0
    >>> round(kt.fit_percent([0.0, 1.0, 2.0, 3.0], [1.5, 1.5, 1.5, 1.5]), 6)
    0.0
    """
    out = 100.0 * (1.0 - np.asarray(nrmse(y, yhat)))
    return float(out) if out.ndim == 0 else out


def r_squared(y: ArrayLike, yhat: ArrayLike) -> float | NDArray[np.float64]:
    """Coefficient of determination ``1 - NRMSE^2``.

    Parameters
    ----------
    y, yhat : array-like of shape (n_samples,) or (n_records, n_samples)

    Returns
    -------
    float or ndarray of shape (n_records,)
    """
    out = 1.0 - np.asarray(nrmse(y, yhat)) ** 2
    return float(out) if out.ndim == 0 else out


def mse(y: ArrayLike, yhat: ArrayLike) -> float | NDArray[np.float64]:
    """Mean squared error over the samples.

    Parameters
    ----------
    y, yhat : array-like of shape (n_samples,) or (n_records, n_samples)

    Returns
    -------
    float or ndarray of shape (n_records,)
    """
    y, yhat = _pair(y, yhat)
    out = np.mean((y - yhat) ** 2, axis=-1)
    return float(out) if out.ndim == 0 else out


def ise(t: ArrayLike, y: ArrayLike, yhat: ArrayLike, *, rule: str = "simpson") -> float | NDArray:
    r"""Integral of squared error :math:`\int (y - \hat y)^2 dt` over the record, by quadrature.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times.
    y, yhat : array-like of shape (n_samples,) or (n_records, n_samples)
    rule : {'simpson', 'trapezoid'}, default='simpson'
        Quadrature rule; Simpson is exact for piecewise quadratics.

    Returns
    -------
    float or ndarray of shape (n_records,)
        Clamped at 0 (Simpson weights on strongly non-uniform grids can be negative).

    See Also
    --------
    kautztwin.ise_from_system : Exact ISE of a known LTI system (no quadrature).
    """
    t = check_time(t)
    y, yhat = _pair(y, yhat)
    if y.shape[-1] != t.size:
        raise DimensionError(f"y has {y.shape[-1]} samples but t has {t.size}")
    out = np.maximum((y - yhat) ** 2 @ quadrature_weights(t, rule), 0.0)
    return float(out) if out.ndim == 0 else out


def fit_percent_or_nan(y: ArrayLike, yhat: ArrayLike) -> float:
    """Fit percent over the samples where both signals are finite; NaN where undefined.

    The tolerant form of :func:`fit_percent` for running monitors, whose windows may hold
    dropouts: it never raises, and returns NaN for fewer than two usable samples or a
    constant measured signal.

    Parameters
    ----------
    y, yhat : array-like of shape (n_samples,)
        Measured and model signals; NaN or inf marks a missing sample.

    Returns
    -------
    float

    Examples
    --------
    >>> from kautztwin.metrics import fit_percent_or_nan
    >>> fit_percent_or_nan([0.0, 1.0, float("nan"), 3.0], [0.0, 1.0, 5.0, 3.0])
    100.0
    """
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    ok = np.isfinite(y) & np.isfinite(yhat)
    if ok.sum() < 2:
        return float("nan")
    yy = y[ok]
    spread = float(np.linalg.norm(yy - yy.mean()))
    if spread == 0.0:
        return float("nan")
    return 100.0 * (1.0 - float(np.linalg.norm(yy - yhat[ok])) / spread)
