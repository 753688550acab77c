r"""Calibrated uncertainty of an estimate: Laplace covariance, conformal scale, response bands.

Every estimate of :class:`~kautztwin.nn.AdaptivePoleEstimator` is a least-squares fit of
the record on a Kautz basis whose poles the network (or the VARPRO refinement) chose.
Its uncertainty is the **Laplace (linearised least-squares) covariance** of that fit,
with a noise model read from the record's own residual, and one **calibration scale**
fitted on fresh records of the training distribution.

Why this and not an ensemble or a heteroscedastic head:

- *cost at inference*: one Jacobian of the fitted response (``2 N`` columns, ``N``
  basis-function evaluations by central differences, batched) and a small SVD per record,
  about as much as the estimate itself; an ensemble of ``M`` networks costs ``M`` times the
  network and ``M`` trainings;
- *calibration*: the linearised covariance has the right *shape* (where in time the
  response is uncertain, how it grows with the noise of the record in hand), but not the
  right *level*, because the network's poles are not the least-squares poles and the noise
  may be coloured; one scalar fitted on fresh simulated records (split conformal
  calibration of the normalised error) fixes the level, and the family trainer has
  those records for free;
- *what the twin needs*: a band per estimate that widens when the record is noisy or
  unlike the training data (the residual-based noise level does that, a fixed-level
  band would not) and one number to accept or defer an update
  (:attr:`ResponseEstimate.relative_width`).

Math.  With :math:`\theta = (p, c)` (block parameters and coefficients),
:math:`\hat h = c^T K(p)` and :math:`J = \partial \hat h / \partial \theta`
(``n_samples x 2N``), an error :math:`e` of the record moves the least-squares fit by
:math:`\delta\hat h = P e`, :math:`P = U U^T` the projector onto the span of :math:`J`
(:math:`J = U S V^T`).  With AR(1) noise :math:`\Sigma = s^2 R`,
:math:`R_{kl} = \rho^{|k - l|}`, estimated from the residual :math:`r = y - \hat h`
(:math:`s^2 = \|r\|^2 / (n - \operatorname{rank} J)`, :math:`\rho` its lag-1
autocorrelation),

.. math:: \operatorname{var}\hat h_k = s^2\, u_k^T (U^T R U)\, u_k,\qquad
          \operatorname{cov}\theta = s^2\, V S^{-1} (U^T R U) S^{-1} V^T,

and :math:`U^T R U = Z^T Z` with :math:`Z = L^T U` (:math:`R = L L^T`, the AR(1)
colouring filter run backwards in time).  The band at level :math:`\alpha` is
:math:`\hat h \pm \kappa\, z_\alpha\, \operatorname{sd}\hat h`, :math:`z_\alpha` the
two-sided normal quantile and :math:`\kappa` the calibration scale (1 until
:func:`calibration_scale` sets it): the :math:`\alpha`-quantile of
:math:`|h - \hat h| / (z_\alpha \operatorname{sd}\hat h)` over all samples of fresh
records with known truth :math:`h`.  Step and frequency bands propagate
:math:`\kappa^2 \operatorname{cov}\theta` through their own Jacobians and use the
band containers of :mod:`kautztwin.ident.diagnostics`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.signal
import scipy.stats
from numpy.typing import ArrayLike, NDArray

from ..approx import KautzModel
from ..basis import KautzBasis
from ..exceptions import DataError
from ..ident.diagnostics import FrequencyResponseBand, StepResponseBand

__all__ = [
    "DEFAULT_LEVEL",
    "ImpulseResponseBand",
    "ResponseEstimate",
    "band_coverage",
    "calibrate_estimate",
    "calibration_scale",
    "fixed_basis_estimate",
    "laplace_response_covariance",
    "normal_quantile",
]

#: Level of the bands and of the calibration unless told otherwise.
DEFAULT_LEVEL = 0.9
_RANK_RTOL = 1e-10  # singular values below this share of the largest are dropped
_RHO_MAX = 0.995  # the residual's lag-1 correlation is clipped to [-_RHO_MAX, _RHO_MAX]
_FD_STEP = 1e-5  # relative step of the central differences in the block parameters


def normal_quantile(level: float) -> float:
    """Two-sided standard normal quantile of a confidence level in ``(0, 1)``.

    Parameters
    ----------
    level : float

    Returns
    -------
    float
        ``z`` with ``P(|N(0, 1)| <= z) = level``.

    Raises
    ------
    DataError
        If ``level`` is not in ``(0, 1)``.

    Examples
    --------
    >>> from kautztwin.nn.uncertainty import normal_quantile
    >>> round(normal_quantile(0.9), 4)
    1.6449
    """
    try:
        a = float(level)
    except (TypeError, ValueError):
        raise DataError(f"level must be a number in (0, 1), got {level!r}") from None
    if not 0.0 < a < 1.0:
        raise DataError(f"level must lie in (0, 1), got {level!r}")
    return float(scipy.stats.norm.ppf(0.5 + a / 2.0))


# =============================================================================== covariance
def _ar1_adjoint(U: NDArray, rho: float) -> NDArray:
    """``L^T U`` for the unit-variance stationary AR(1) colouring filter ``L`` (time on axis 0)."""
    if rho == 0.0:
        return U
    Z = scipy.signal.lfilter([1.0], [1.0, -rho], U[::-1], axis=0)[::-1]
    Z[1:] *= np.sqrt(1.0 - rho * rho)
    return Z


def laplace_response_covariance(
    J: ArrayLike, residual: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    r"""Linearised least-squares uncertainty of fitted responses under AR(1) residual noise.

    Parameters
    ----------
    J : array-like of shape (n_records, n_samples, n_theta)
        Jacobian of each fitted response with respect to the fitted parameters.
    residual : array-like of shape (n_records, n_samples)
        Record minus fitted response.

    Returns
    -------
    std : ndarray of shape (n_records, n_samples)
        Standard deviation of each fitted sample (the module's formula, no calibration).
    cov : ndarray of shape (n_records, n_theta, n_theta)
        Covariance of the parameters (pseudo-inverse in poorly determined directions).
    noise_std : ndarray of shape (n_records,)
        :math:`s`, the residual's standard deviation (degrees of freedom corrected).
    rho : ndarray of shape (n_records,)
        The residual's lag-1 autocorrelation (the AR(1) pole of the noise model).

    Raises
    ------
    DataError
        If the shapes disagree or there are no more samples than parameters.

    Examples
    --------
    A constant fitted to 4 samples whose residual has no lag-1 correlation: the
    standard deviation of the fit is :math:`s / \sqrt{4}` with
    :math:`s^2 = \|r\|^2 / (4 - 1) = 2/3`, i.e. :math:`\sqrt{1/6}`.

    >>> import numpy as np
    >>> from kautztwin.nn.uncertainty import laplace_response_covariance
    >>> std, cov, s, rho = laplace_response_covariance(np.ones((1, 4, 1)), [[1.0, 0, -1.0, 0]])
    >>> rho, std.round(6), bool(np.isclose(std[0, 0], np.sqrt(1 / 6)))
    (array([0.]), array([[0.408248, 0.408248, 0.408248, 0.408248]]), True)
    """
    J = np.asarray(J, dtype=float)
    r = np.asarray(residual, dtype=float)
    if J.ndim != 3 or r.shape != J.shape[:2]:
        raise DataError(
            f"J must have shape (n_records, n_samples, n_theta) and residual "
            f"(n_records, n_samples); got {J.shape} and {r.shape}"
        )
    n_rec, n, p = J.shape
    if n <= p:
        raise DataError(f"{n} samples cannot carry the uncertainty of {p} parameters")
    scale = np.linalg.norm(J, axis=1)  # (n_rec, p): column scaling before the SVD
    scale = np.where(scale > 0, scale, 1.0)
    U, S, Vt = np.linalg.svd(J / scale[:, None, :], full_matrices=False)
    keep = S > _RANK_RTOL * S[:, :1]
    U = U * keep[:, None, :]
    s_inv = np.where(keep, 1.0 / np.where(keep, S, 1.0), 0.0)
    rank = keep.sum(axis=1)
    ss = np.einsum("ij,ij->i", r, r)
    noise_var = ss / (n - rank)
    lag1 = np.einsum("ij,ij->i", r[:, 1:], r[:, :-1])
    rho = np.clip(np.where(ss > 0, lag1 / np.where(ss > 0, ss, 1.0), 0.0), -_RHO_MAX, _RHO_MAX)
    std = np.empty((n_rec, n))
    cov = np.empty((n_rec, p, p))
    for i in range(n_rec):
        Z = _ar1_adjoint(U[i], float(rho[i]))
        M = noise_var[i] * (Z.T @ Z)
        std[i] = np.sqrt(np.maximum(np.einsum("kj,jl,kl->k", U[i], M, U[i]), 0.0))
        W = Vt[i].T * s_inv[i]  # V S^-1
        cov[i] = (W @ M @ W.T) / np.outer(scale[i], scale[i])
    return std, cov, np.sqrt(noise_var), rho


# =============================================================================== calibration
def _normalised_error(
    truth: NDArray, estimate: NDArray, std: NDArray, level: float
) -> NDArray[np.float64]:
    err = np.abs(np.asarray(truth, dtype=float) - np.asarray(estimate, dtype=float))
    sd = normal_quantile(level) * np.asarray(std, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(sd > 0, err / np.where(sd > 0, sd, 1.0), np.where(err > 0, np.inf, 0.0))
    return q


def calibration_scale(
    truth: ArrayLike, estimate: ArrayLike, std: ArrayLike, level: float = DEFAULT_LEVEL
) -> float:
    r"""Scale :math:`\kappa` of the standard deviations that makes the bands cover ``level``.

    Split conformal calibration: the ``level``-quantile (``'higher'`` rule) of
    :math:`|h - \hat h| / (z\,\mathrm{sd})` over every sample of every record, so that
    :math:`\hat h \pm \kappa z\,\mathrm{sd}` contains at least a share ``level`` of the
    calibration samples.

    Parameters
    ----------
    truth, estimate, std : array-like of shape (n_records, n_samples)
        Noise-free responses, fitted responses and their uncalibrated standard deviations.
    level : float, default=0.9

    Returns
    -------
    float
        :math:`\kappa > 0`.

    Raises
    ------
    DataError
        On different shapes, a bad level, or bands of zero width where the error is not zero
        for more than ``1 - level`` of the samples.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.nn.uncertainty import calibration_scale
    >>> e = np.random.default_rng(0).standard_normal((200, 50))
    >>> round(calibration_scale(e, 0 * e, np.ones_like(e)), 1)   # N(0, 1) errors: kappa ~ 1
    1.0
    """
    truth = np.asarray(truth, dtype=float)
    if np.shape(estimate) != truth.shape or np.shape(std) != truth.shape:
        raise DataError(
            f"truth, estimate and std must have one shape; got {truth.shape}, "
            f"{np.shape(estimate)} and {np.shape(std)}"
        )
    q = _normalised_error(truth, np.asarray(estimate), np.asarray(std), level).ravel()
    kappa = float(np.quantile(q, level, method="higher"))
    if not np.isfinite(kappa):
        raise DataError(
            "the uncalibrated bands have zero width where the estimate is wrong on more than "
            f"{100 * (1 - level):g} % of the samples; cannot calibrate them"
        )
    return max(kappa, np.finfo(float).tiny)


def band_coverage(
    truth: ArrayLike, lower: ArrayLike, upper: ArrayLike
) -> float:
    """Share of samples whose true value lies in the band (per-sample coverage).

    Parameters
    ----------
    truth, lower, upper : array-like of one shape

    Returns
    -------
    float
        In ``[0, 1]``.

    Examples
    --------
    >>> from kautztwin.nn.uncertainty import band_coverage
    >>> band_coverage([0.0, 1.0, 5.0], [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    0.6666666666666666
    """
    h = np.asarray(truth, dtype=float)
    inside = (h >= np.asarray(lower, dtype=float)) & (h <= np.asarray(upper, dtype=float))
    return float(np.mean(inside))


# =============================================================================== bands
@dataclass(frozen=True, eq=False)
class ImpulseResponseBand(StepResponseBand):
    """Impulse response with a confidence band (the step band's container, another response).

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Times, s.
    y : ndarray of shape (n_samples,)
        Impulse response of the estimated model.
    std : ndarray of shape (n_samples,)
        Its (calibrated) standard deviation.
    confidence : float
        Level of the band.
    """


def _model(kinds: tuple[str, ...], params: NDArray, coef: NDArray) -> KautzModel:
    return KautzModel(KautzBasis._from_blocks(kinds, params), coef)


def _jacobian(
    kinds: tuple[str, ...], params: NDArray, coef: NDArray, response: Any
) -> tuple[NDArray, NDArray]:
    """``response(model)`` and its Jacobian in ``(params, coef)`` (central differences)."""
    base = _model(kinds, params, coef)
    y0 = np.asarray(response(base))
    cols = []
    for j in range(params.size):
        h = _FD_STEP * max(abs(float(params[j])), 1e-3)
        up, down = params.copy(), params.copy()
        up[j] += h
        down[j] -= h
        cols.append(
            (np.asarray(response(_model(kinds, up, coef)))
             - np.asarray(response(_model(kinds, down, coef)))) / (2 * h)
        )
    for i in range(coef.size):
        unit = np.zeros(coef.size)
        unit[i] = 1.0
        cols.append(np.asarray(response(base.with_coefficients(unit))))
    return y0, np.stack(cols, axis=-1)


@dataclass(frozen=True, eq=False)
class ResponseEstimate:
    r"""Estimated models of records with calibrated uncertainty (immutable).

    Returned by :meth:`AdaptivePoleEstimator.estimate
    <kautztwin.nn.AdaptivePoleEstimator.estimate>`; see :mod:`kautztwin.nn.uncertainty`
    for the method.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        The records' grid.
    kind : {'impulse', 'step'}
        What the records (and :attr:`response`) are.
    kinds : tuple of str
        Block structure of the bases.
    params : ndarray of shape (n_records, n_functions)
        Block parameters of each record's basis.
    coefficients : ndarray of shape (n_records, n_functions)
        Least-squares coefficients.
    response : ndarray of shape (n_records, n_samples)
        Fitted (noise-free) response on ``t``.
    std : ndarray of shape (n_records, n_samples)
        Calibrated standard deviation of ``response`` (``scale`` included).
    covariance : ndarray of shape (n_records, 2 n_functions, 2 n_functions)
        Calibrated covariance of ``(params, coefficients)``.
    noise_std : ndarray of shape (n_records,)
        Residual standard deviation of each record.
    noise_correlation : ndarray of shape (n_records,)
        Lag-1 autocorrelation of each residual.
    scale : float
        Calibration scale :math:`\kappa` (1.0: uncalibrated).
    calibrated : bool
        Whether ``scale`` was fitted on fresh records.
    level : float
        Level of :attr:`lower`, :attr:`upper` and :attr:`relative_width`.

    Attributes
    ----------
    lower, upper : ndarray of shape (n_records, n_samples)
        The band ``response -+ z * std``, ``z`` the normal quantile of ``level``.
    relative_width : ndarray of shape (n_records,)
        RMS half-width of the band over the RMS of the fitted response: one number per
        record for the twin's accept-or-defer decision.
    """

    t: NDArray[np.float64]
    kind: str
    kinds: tuple[str, ...]
    params: NDArray[np.float64]
    coefficients: NDArray[np.float64]
    response: NDArray[np.float64]
    std: NDArray[np.float64]
    covariance: NDArray[np.float64]
    noise_std: NDArray[np.float64]
    noise_correlation: NDArray[np.float64]
    scale: float
    calibrated: bool
    level: float = DEFAULT_LEVEL

    def __post_init__(self) -> None:
        normal_quantile(self.level)  # validates
        for name in ("t", "params", "coefficients", "response", "std", "covariance",
                     "noise_std", "noise_correlation"):
            a = np.array(getattr(self, name), dtype=float)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.response.shape[0])

    @property
    def z(self) -> float:
        """Normal quantile of ``level``."""
        return normal_quantile(self.level)

    @property
    def lower(self) -> NDArray[np.float64]:
        """Lower band on ``t``."""
        return self.response - self.z * self.std

    @property
    def upper(self) -> NDArray[np.float64]:
        """Upper band on ``t``."""
        return self.response + self.z * self.std

    @property
    def relative_width(self) -> NDArray[np.float64]:
        """RMS half-width of the band relative to the RMS fitted response, per record."""
        num = self.z * np.linalg.norm(self.std, axis=1)
        den = np.linalg.norm(self.response, axis=1)
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)

    def with_level(self, level: float) -> ResponseEstimate:
        """The same estimate with bands at another level (the calibration scale is kept)."""
        from dataclasses import replace

        return replace(self, level=float(level))

    def model(self, i: int = 0) -> KautzModel:
        """The estimated :class:`~kautztwin.KautzModel` of record ``i``."""
        return _model(self.kinds, self.params[i], self.coefficients[i])

    def models(self) -> list[KautzModel]:
        """All estimated models, one per record."""
        return [self.model(i) for i in range(len(self))]

    def _band(self, i: int, t: ArrayLike | None, which: str) -> StepResponseBand:
        if t is None and which == self.kind:
            cls = ImpulseResponseBand if which == "impulse" else StepResponseBand
            return cls(t=self.t, y=self.response[i].copy(), std=self.std[i].copy(),
                       confidence=self.level)
        tt = self.t if t is None else np.asarray(t, dtype=float)
        y, jac = _jacobian(self.kinds, self.params[i], self.coefficients[i],
                           (lambda m: m.impulse(tt)) if which == "impulse"
                           else (lambda m: m.step(tt)))
        std = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, self.covariance[i], jac), 0.0))
        cls = ImpulseResponseBand if which == "impulse" else StepResponseBand
        return cls(t=tt, y=y, std=std, confidence=self.level)

    def impulse_band(self, i: int = 0, t: ArrayLike | None = None) -> ImpulseResponseBand:
        """Impulse response of record ``i``'s model with its band (on ``t``, default the grid)."""
        return self._band(i, t, "impulse")  # type: ignore[return-value]

    def step_band(self, i: int = 0, t: ArrayLike | None = None) -> StepResponseBand:
        """Unit-step response of record ``i``'s model with its band (on ``t``, default the grid)."""
        return self._band(i, t, "step")

    def frequency_band(self, i: int = 0, w: ArrayLike | None = None) -> FrequencyResponseBand:
        """Bode magnitude and phase of record ``i``'s model with bands.

        Parameters
        ----------
        i : int, default=0
        w : array-like, optional
            Angular frequencies, rad/s; by default 200 points from a decade below the
            slowest pole to a decade above the fastest.

        Returns
        -------
        FrequencyResponseBand
        """
        if w is None:
            mags = np.abs(self.model(i).poles)
            w = np.logspace(np.floor(np.log10(mags.min())) - 1,
                            np.ceil(np.log10(mags.max())) + 1, 200)
        w = np.asarray(w, dtype=float)
        g, jac = _jacobian(self.kinds, self.params[i], self.coefficients[i],
                           lambda m: m.frequency_response(w))
        cov = self.covariance[i]
        mag = np.abs(g)
        safe = np.where(mag > 0, g, 1.0)
        gm = np.real(np.conj(safe)[:, None] * jac) / np.abs(safe)[:, None]
        gp = np.imag(jac / safe[:, None])

        def sd(a: NDArray) -> NDArray:
            return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", a, cov, a), 0.0))

        return FrequencyResponseBand(w=w, response=g, magnitude_std=sd(gm), phase_std=sd(gp),
                                     confidence=self.level)

    def summary(self) -> dict[str, Any]:
        """JSON-ready per-record summary: relative width, noise estimate, calibration."""
        return {
            "level": self.level,
            "calibrated": self.calibrated,
            "scale": self.scale,
            "relative_width": self.relative_width.tolist(),
            "noise_std": self.noise_std.tolist(),
            "noise_correlation": self.noise_correlation.tolist(),
        }


# =============================================================================== estimators
def calibrate_estimate(
    raw: ResponseEstimate, truth: ArrayLike, *, refine: bool = False
) -> tuple[float, dict[str, Any]]:
    """Calibration scale of an uncalibrated estimate against the truth, and what was measured.

    Parameters
    ----------
    raw : ResponseEstimate
        Estimate with scale 1 of fresh records, at the level to calibrate.
    truth : array-like of shape (n_records, n_samples)
        Their noise-free responses.
    refine : bool, default=False
        Whether the estimate was refined (recorded in the report).

    Returns
    -------
    scale : float
    report : dict
        ``method``, ``level``, ``scale``, ``n_records``, ``refine``,
        ``coverage_uncalibrated`` and ``coverage`` (on these records).
    """
    truth = np.asarray(truth, dtype=float)
    kappa = calibration_scale(truth, raw.response, raw.std, raw.level)
    half = kappa * raw.z * raw.std
    return kappa, {
        "method": "laplace-ar1+conformal-scale",
        "level": float(raw.level),
        "scale": float(kappa),
        "n_records": int(truth.shape[0]),
        "refine": bool(refine),
        "coverage_uncalibrated": band_coverage(truth, raw.lower, raw.upper),
        "coverage": band_coverage(truth, raw.response - half, raw.response + half),
    }


def fixed_basis_estimate(
    basis: KautzBasis,
    t: NDArray[np.float64],
    kind: str,
    records: NDArray[np.float64],
    coefficients: NDArray[np.float64],
    *,
    scale: float = 1.0,
    calibrated: bool = False,
    level: float = DEFAULT_LEVEL,
) -> ResponseEstimate:
    """Uncertainty of coefficient estimates on a fixed basis (the coefficient estimator's).

    The Jacobian of the response is the basis itself (the poles are fixed, so their
    block of the covariance is zero); the residual is the record minus the estimate.

    Parameters
    ----------
    basis : KautzBasis
        Continuous-time basis.
    t : ndarray of shape (n_samples,)
    kind : {'impulse', 'step'}
    records : ndarray of shape (n_records, n_samples)
    coefficients : ndarray of shape (n_records, n_functions)
        The estimates.
    scale : float, default=1.0
        Calibration scale.
    calibrated : bool, default=False
    level : float, default=0.9

    Returns
    -------
    ResponseEstimate
    """
    N = basis.n_functions
    if kind == "impulse":
        K = np.asarray(basis.evaluate(t), dtype=float)
    else:
        K = np.array([KautzModel(basis, np.eye(N)[i]).step(t) for i in range(N)])
    fitted = coefficients @ K
    J = np.broadcast_to(K.T, (records.shape[0], *K.T.shape))
    std, cov, noise_std, rho = laplace_response_covariance(J, records - fitted)
    full = np.zeros((records.shape[0], 2 * N, 2 * N))
    full[:, N:, N:] = scale * scale * cov
    params = np.broadcast_to(np.asarray(basis._params, dtype=float), (records.shape[0], N))
    return ResponseEstimate(
        t=np.asarray(t, dtype=float), kind=kind, kinds=tuple(basis.block_kinds), params=params,
        coefficients=coefficients, response=fitted, std=scale * std, covariance=full,
        noise_std=noise_std, noise_correlation=rho, scale=float(scale), calibrated=calibrated,
        level=float(level),
    )
