r"""Parameter covariance carried to the Bode plot, the step response and the poles.

First-order (delta-method) propagation through the exact Jacobians of a
:class:`~kautztwin.ident.TransferFunctionModel`'s frequency and step responses with
respect to its parameters (``num``, ``den[1:]`` and the delay when it was estimated).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_finite, check_time
from ...exceptions import DataError, DimensionError
from ..simulate import impulse_response, step_response
from .correlation import _check_alpha, _z

if TYPE_CHECKING:
    from ..tfest import TransferFunctionModel

__all__ = [
    "FrequencyResponseBand",
    "PoleUncertainty",
    "StepResponseBand",
    "frequency_response_band",
    "frequency_response_jacobian",
    "pole_uncertainty",
    "step_response_band",
    "step_response_jacobian",
]


# =============================================================================== jacobians
def _parameters(model: TransferFunctionModel) -> tuple[NDArray, NDArray, bool]:
    """The parameter vector of ``model.covariance`` and the covariance; delay estimated?"""
    cov = model.covariance
    if cov is None:
        raise DataError("the model has no parameter covariance (it was not estimated from data)")
    has_delay = "delay" in model.parameter_names
    theta = np.concatenate([model.num, model.den[1:], [model.delay] if has_delay else []])
    if cov.shape != (theta.size, theta.size):
        raise DimensionError(
            f"the covariance has shape {cov.shape} but the model has {theta.size} parameters "
            "(num, den[1:], and delay when estimated)"
        )
    return theta, np.asarray(cov, dtype=float), has_delay


def frequency_response_jacobian(model: TransferFunctionModel, w: ArrayLike
                                ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    r"""Frequency response :math:`G(j\omega)e^{-j\omega\tau}` and its exact parameter Jacobian.

    .. math:: \frac{\partial G}{\partial b_k} = \frac{(j\omega)^{m-k}}{D}e^{-j\omega\tau},
              \quad
              \frac{\partial G}{\partial a_i} = -\frac{(j\omega)^{n-i}}{D}\,G,\quad
              \frac{\partial G}{\partial \tau} = -j\omega\,G

    for :math:`G = e^{-j\omega\tau}\sum_k b_k s^{m-k} / (s^n + \sum_i a_i s^{n-i})`; the
    columns follow ``model.parameter_names``.

    Parameters
    ----------
    model : TransferFunctionModel
        A model with a covariance.
    w : array-like of shape (n_freq,)
        Angular frequencies, rad/s.

    Returns
    -------
    g : ndarray of complex, shape (n_freq,)
    jac : ndarray of complex, shape (n_freq, n_params)
    """
    _, _, has_delay = _parameters(model)
    w = np.asarray(w, dtype=float)
    s = 1j * w
    den = np.polyval(model.den, s)
    lag = np.exp(-s * model.delay)
    g = np.polyval(model.num, s) / den * lag
    m, n = model.n_zeros, model.n_poles
    cols = [s ** (m - k) / den * lag for k in range(m + 1)]
    cols += [-(s ** (n - i)) / den * g for i in range(1, n + 1)]
    if has_delay:
        cols.append(-s * g)
    return g, np.column_stack(cols)


def step_response_jacobian(model: TransferFunctionModel, t: ArrayLike
                           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    r"""Exact unit-step response and its parameter Jacobian at the times ``t``.

    Each column is itself an exact step response: of :math:`s^{m-k}/D(s)` for a numerator
    coefficient, of :math:`-N(s)s^{n-i}/D(s)^2` for a denominator coefficient (both delayed
    by :math:`\tau`), and :math:`-g(t-\tau)` (the impulse response of the strictly proper
    part) for the delay.

    Parameters
    ----------
    model : TransferFunctionModel
        A model with a covariance.
    t : array-like of shape (n_samples,)
        Strictly increasing times ``>= 0``.

    Returns
    -------
    y : ndarray of shape (n_samples,)
    jac : ndarray of shape (n_samples, n_params)
    """
    _, _, has_delay = _parameters(model)
    t = check_time(t, min_samples=1)
    num, den, tau = model.num, model.den, model.delay
    m, n = model.n_zeros, model.n_poles
    y = step_response((num, den), t, delay=tau)
    cols = []
    for k in range(m + 1):
        unit = np.zeros(m - k + 1)
        unit[0] = 1.0
        cols.append(step_response((unit, den), t, delay=tau))
    den2 = np.polymul(den, den)
    for i in range(1, n + 1):
        shift = np.zeros(n - i + 1)
        shift[0] = -1.0
        cols.append(step_response((np.polymul(num, shift), den2), t, delay=tau))
    if has_delay:
        d = num[0] if m == n else 0.0
        strict = np.polysub(np.pad(num, (n + 1 - num.size, 0)), d * den)[1:]
        strict = strict if np.any(strict) else np.zeros(1)
        cols.append(-impulse_response((strict, den), t, delay=tau))
    return y, np.column_stack(cols)


def _std(jac: NDArray, cov: NDArray) -> NDArray[np.float64]:
    """Row-wise ``sqrt(J_i C J_i^T)``."""
    return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, cov, jac), 0.0))


def _default_frequencies(model: TransferFunctionModel, n: int = 200,
                         w_max: float | None = None) -> NDArray[np.float64]:
    """A decade below the slowest pole to a decade above the fastest (or to ``w_max``)."""
    mags = np.abs(model.poles)
    mags = mags[mags > 0]
    lo, hi = (mags.min(), mags.max()) if mags.size else (1.0, 1.0)
    top = np.ceil(np.log10(hi)) + 1 if w_max is None else np.log10(w_max)
    bottom = np.floor(np.log10(lo)) - 1
    return np.logspace(min(bottom, top - 1), top, n)


def _default_times(model: TransferFunctionModel, n: int = 300) -> NDArray[np.float64]:
    slowest = float(np.min(np.abs(model.poles.real)))
    return np.linspace(0.0, model.delay + 7.0 / max(slowest, 1e-12), n)


# =============================================================================== bands
@dataclass(frozen=True, eq=False)
class FrequencyResponseBand:
    r"""Bode magnitude and phase with first-order confidence bands (immutable).

    Parameters
    ----------
    w : ndarray of shape (n_freq,)
        Angular frequencies, rad/s.
    response : ndarray of complex, shape (n_freq,)
        :math:`G(j\omega)e^{-j\omega\tau}`.
    magnitude_std : ndarray of shape (n_freq,)
        Standard deviation of :math:`|G|`.
    phase_std : ndarray of shape (n_freq,)
        Standard deviation of the phase, rad.
    confidence : float
        Level of the bands.

    Attributes
    ----------
    magnitude : ndarray
        :math:`|G(j\omega)|`.
    phase : ndarray
        Unwrapped phase, rad.
    z : float
        Normal quantile of ``confidence``: the bands are ``value +- z * std``.
    magnitude_lower, magnitude_upper, phase_lower, phase_upper : ndarray
        The bands (the lower magnitude band is floored at 0).
    """

    w: NDArray[np.float64]
    response: NDArray[np.complex128]
    magnitude_std: NDArray[np.float64]
    phase_std: NDArray[np.float64]
    confidence: float

    @property
    def magnitude(self) -> NDArray[np.float64]:
        """:math:`|G(j\\omega)|`."""
        return np.abs(self.response)

    @property
    def phase(self) -> NDArray[np.float64]:
        """Unwrapped phase in radians."""
        return np.unwrap(np.angle(self.response))

    @property
    def z(self) -> float:
        """Normal quantile of the confidence level."""
        return _z(self.confidence)

    @property
    def magnitude_lower(self) -> NDArray[np.float64]:
        """Lower magnitude band (floored at 0)."""
        return np.maximum(self.magnitude - self.z * self.magnitude_std, 0.0)

    @property
    def magnitude_upper(self) -> NDArray[np.float64]:
        """Upper magnitude band."""
        return self.magnitude + self.z * self.magnitude_std

    @property
    def phase_lower(self) -> NDArray[np.float64]:
        """Lower phase band, rad."""
        return self.phase - self.z * self.phase_std

    @property
    def phase_upper(self) -> NDArray[np.float64]:
        """Upper phase band, rad."""
        return self.phase + self.z * self.phase_std


def frequency_response_band(model: TransferFunctionModel, w: ArrayLike | None = None, *,
                            confidence: float = 0.95) -> FrequencyResponseBand:
    r"""Bode magnitude and phase of a model with confidence bands from its covariance.

    First-order (delta-method) propagation of the parameter covariance :math:`\Sigma`
    through the exact Jacobian :math:`J = \partial G/\partial\theta`
    (:func:`frequency_response_jacobian`):

    .. math:: \operatorname{var}|G| \approx g_m^T\Sigma g_m,\quad
              g_m = \frac{\operatorname{Re}(\bar G J)}{|G|};\qquad
              \operatorname{var}\arg G \approx g_p^T\Sigma g_p,\quad
              g_p = \operatorname{Im}\frac{J}{G}.

    The bands are :math:`\pm z` standard deviations, :math:`z` the two-sided normal quantile
    of ``confidence`` (MATLAB ``showConfidence`` draws a chosen number of standard
    deviations the same way). They are accurate while the standard deviations are small
    against the values; check them with a Monte Carlo over the covariance otherwise.

    Parameters
    ----------
    model : TransferFunctionModel
        A model with a covariance (as estimated by ``TransferFunctionEstimator``).
    w : array-like of shape (n_freq,), optional
        Angular frequencies, rad/s; by default 200 points from a decade below the slowest
        pole to a decade above the fastest.
    confidence : float, default=0.95
        Level of the bands.

    Returns
    -------
    FrequencyResponseBand

    Raises
    ------
    DataError
        If the model has no covariance or ``confidence`` is outside (0, 1).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import TransferFunctionModel
    >>> from kautztwin.ident.diagnostics import frequency_response_band
    >>> m = TransferFunctionModel(num=[2.0], den=[1.0, 1.0], covariance=np.diag([0.01, 0.0]),
    ...                           parameter_names=("num[0]", "den[1]"))
    >>> band = frequency_response_band(m, [0.0, 1.0])
    >>> np.round(band.magnitude_std, 4), np.round(band.phase_std, 12)   # d|G|/db0 = |G|/b0
    (array([0.1   , 0.0707]), array([0., 0.]))
    """
    confidence = _check_alpha(confidence, "confidence")
    _, cov, _ = _parameters(model)
    w = _default_frequencies(model) if w is None else np.asarray(w, dtype=float)
    if w.ndim != 1 or w.size == 0:
        raise DimensionError(f"w must be a non-empty 1-D array; got shape {w.shape}")
    check_finite(w, "w")
    g, jac = frequency_response_jacobian(model, w)
    mag = np.abs(g)
    safe = np.where(mag > 0, g, 1.0)
    gm = np.real(np.conj(safe)[:, None] * jac) / np.abs(safe)[:, None]
    gp = np.imag(jac / safe[:, None])
    return FrequencyResponseBand(w=w, response=g, magnitude_std=_std(gm, cov),
                                 phase_std=_std(gp, cov), confidence=confidence)


@dataclass(frozen=True, eq=False)
class StepResponseBand:
    """Unit-step response with a first-order confidence band (immutable).

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Times, s.
    y : ndarray of shape (n_samples,)
        Step response of the estimated model.
    std : ndarray of shape (n_samples,)
        Its standard deviation.
    confidence : float
        Level of the band.

    Attributes
    ----------
    lower, upper : ndarray
        ``y -+ z * std``, ``z`` the two-sided normal quantile of ``confidence``.
    """

    t: NDArray[np.float64]
    y: NDArray[np.float64]
    std: NDArray[np.float64]
    confidence: float

    @property
    def lower(self) -> NDArray[np.float64]:
        """Lower band."""
        return self.y - _z(self.confidence) * self.std

    @property
    def upper(self) -> NDArray[np.float64]:
        """Upper band."""
        return self.y + _z(self.confidence) * self.std


def step_response_band(model: TransferFunctionModel, t: ArrayLike | None = None, *,
                       confidence: float = 0.95) -> StepResponseBand:
    r"""Unit-step response of a model with a confidence band from its covariance.

    :math:`\operatorname{var} y(t) \approx J(t)\,\Sigma\,J(t)^T` with the exact Jacobian of
    :func:`step_response_jacobian`.

    Parameters
    ----------
    model : TransferFunctionModel
        A model with a covariance.
    t : array-like of shape (n_samples,), optional
        Times ``>= 0``; by default 300 points up to the delay plus seven times the slowest
        time constant.
    confidence : float, default=0.95
        Level of the band.

    Returns
    -------
    StepResponseBand

    Raises
    ------
    DataError
        If the model has no covariance or ``confidence`` is outside (0, 1).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import TransferFunctionModel
    >>> from kautztwin.ident.diagnostics import step_response_band
    >>> m = TransferFunctionModel(num=[2.0], den=[1.0, 1.0], covariance=np.diag([0.04, 0.0]),
    ...                           parameter_names=("num[0]", "den[1]"))
    >>> band = step_response_band(m, [0.0, np.log(2.0)])      # y = 2 (1 - exp(-t))
    >>> np.round(band.y, 6), np.round(band.std, 6)
    (array([0., 1.]), array([0. , 0.1]))
    """
    confidence = _check_alpha(confidence, "confidence")
    _, cov, _ = _parameters(model)
    t = _default_times(model) if t is None else check_time(t, min_samples=1)
    y, jac = step_response_jacobian(model, t)
    return StepResponseBand(t=t, y=y, std=_std(jac, cov), confidence=confidence)


@dataclass(frozen=True, eq=False)
class PoleUncertainty:
    """Poles of a model with the standard deviations of their real and imaginary parts.

    Parameters
    ----------
    poles : ndarray of complex, shape (n_poles,)
    std_real, std_imag : ndarray of shape (n_poles,)
        First-order standard deviations (NaN for a repeated pole, where the roots are not
        differentiable in the coefficients).
    """

    poles: NDArray[np.complex128]
    std_real: NDArray[np.float64]
    std_imag: NDArray[np.float64]

    def to_list(self) -> list[dict[str, float]]:
        """One ``{re, im, std_re, std_im}`` dict per pole.

        Returns
        -------
        list of dict
        """
        return [{"re": float(p.real), "im": float(p.imag), "std_re": float(a),
                 "std_im": float(b)}
                for p, a, b in zip(self.poles, self.std_real, self.std_imag, strict=True)]


def pole_uncertainty(model: TransferFunctionModel) -> PoleUncertainty:
    r"""Poles and their first-order standard deviations from the denominator covariance.

    A simple root :math:`p` of :math:`D(s) = s^n + \sum_i a_i s^{n-i}` moves by
    :math:`\partial p/\partial a_i = -p^{n-i}/D'(p)`; the real and imaginary parts of this
    complex gradient carry the covariance of ``den[1:]`` to ``Re p`` and ``Im p``.

    Parameters
    ----------
    model : TransferFunctionModel
        A model with a covariance.

    Returns
    -------
    PoleUncertainty

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import TransferFunctionModel
    >>> from kautztwin.ident.diagnostics import pole_uncertainty
    >>> m = TransferFunctionModel(num=[1.0], den=[1.0, 2.0], covariance=np.diag([0.0, 0.01]),
    ...                           parameter_names=("num[0]", "den[1]"))
    >>> pu = pole_uncertainty(m)                                   # p = -a1
    >>> pu.poles.real, pu.std_real
    (array([-2.]), array([0.1]))
    """
    _, cov, _ = _parameters(model)
    m, n = model.n_zeros, model.n_poles
    cov_den = cov[m + 1 : m + 1 + n, m + 1 : m + 1 + n]
    poles = model.poles
    dden = np.polyder(model.den)
    sr, si = np.full(n, np.nan), np.full(n, np.nan)
    for j, p in enumerate(poles):
        slope = np.polyval(dden, p)
        if abs(slope) <= 1e-10 * max(1.0, float(np.max(np.abs(model.den)))):
            continue
        grad = -(p ** (n - np.arange(1, n + 1))) / slope
        sr[j] = np.sqrt(max(grad.real @ cov_den @ grad.real, 0.0))
        si[j] = np.sqrt(max(grad.imag @ cov_den @ grad.imag, 0.0))
    return PoleUncertainty(poles=poles, std_real=sr, std_imag=si)
