"""The result of transfer-function estimation: :class:`TransferFunctionModel` (immutable)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...exceptions import DataError
from ..records import _readonly
from ..simulate import INTERSAMPLE, impulse_response, simulate_lti, step_response

__all__ = ["TransferFunctionModel"]


@dataclass(frozen=True, eq=False)
class TransferFunctionModel:
    r"""An estimated continuous-time transfer function with its fit statistics (immutable).

    .. math:: G(s) = e^{-\tau s}\,\frac{\mathrm{num}(s)}{\mathrm{den}(s)}

    Parameters
    ----------
    num : array-like of shape (n_zeros + 1,)
        Numerator coefficients, highest power first.
    den : array-like of shape (n_poles + 1,)
        Monic denominator coefficients, highest power first.
    delay : float, default=0.0
        Input delay :math:`\tau` in seconds.
    intersample : {'zoh', 'foh'}, default='zoh'
        Intersample behaviour the model was fitted (and simulates) with.
    covariance : array-like of shape (n_params, n_params), optional
        Covariance of the parameters named in ``parameter_names``:
        ``num`` (highest power first), ``den[1:]``, then ``delay`` if it was estimated.
    parameter_names : tuple of str, default=()
        Names of the rows of ``covariance``.
    noise_variance : float, default=nan
        :math:`\hat\sigma^2 = \mathrm{RSS}/(N - p)` of the output error.
    fit_percent : float, default=nan
        Simulation fit over all estimation records (MATLAB ``compare``
        definition, each record about its own mean, pooled).
    fit_percent_per_record : array-like of shape (n_records,), default=()
        Fit of every estimation record.
    validation_fit_percent : float or None, default=None
        Pooled fit on the validation samples (``t >= validate_from``), if any.
    validation_fit_percent_per_record : array-like or None, default=None
        Validation fit of every record that has validation samples.
    aic : float, default=nan
        Akaike's criterion :math:`N\ln(\mathrm{RSS}/N) + 2p + N(\ln 2\pi + 1)`
        (MATLAB's raw AIC), with ``p`` counting every estimated parameter.
    n_samples : int, default=0
        Number of estimation samples ``N``.
    n_parameters : int, default=0
        Number of estimated parameters ``p`` (offsets and initial states included).
    offsets : array-like of shape (n_records,), default=()
        Estimated output offset of every estimation record.
    record_names : tuple of str, default=()
        Names of the estimation records.
    order_selection : tuple of dict, default=()
        With automatic order selection: one row per candidate order
        (``n_poles``, ``n_zeros``, ``aic``, ``fit_percent``, ``validation_fit_percent``).
    success : bool, default=True
        Whether the refinement met its tolerance.
    message : str, default=''
        The solver's message.
    input_level : float, optional
        For an integrating model (a pole at :math:`s = 0`, chosen by the
        structure search): the input level the model acts from, the level at
        which the integrator balances (the mean estimation input).  The model's
        input is ``u - input_level``; :meth:`TransferFunctionEstimator.predict`
        uses it in place of each record's ``u_before``.  ``None`` for the usual
        models, which act from each record's ``u_before``.

    Attributes
    ----------
    poles, zeros : ndarray of complex
        Roots of ``den`` and ``num``.
    gain : float
        Static (DC) gain ``num(0) / den(0)``.
    std : ndarray
        Standard deviations of the parameters in ``parameter_names``.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import TransferFunctionModel
    >>> m = TransferFunctionModel(num=[2.0], den=[1.0, 3.0, 2.0])
    >>> m.gain, np.sort(m.poles.real)
    (1.0, array([-2., -1.]))
    """

    num: NDArray[np.float64]
    den: NDArray[np.float64]
    delay: float = 0.0
    intersample: str = "zoh"
    covariance: NDArray[np.float64] | None = None
    parameter_names: tuple[str, ...] = ()
    noise_variance: float = float("nan")
    fit_percent: float = float("nan")
    fit_percent_per_record: NDArray[np.float64] = field(default=())  # type: ignore[assignment]
    validation_fit_percent: float | None = None
    validation_fit_percent_per_record: NDArray[np.float64] | None = None
    aic: float = float("nan")
    n_samples: int = 0
    n_parameters: int = 0
    offsets: NDArray[np.float64] = field(default=())  # type: ignore[assignment]
    record_names: tuple[str, ...] = ()
    order_selection: tuple[dict[str, Any], ...] = ()
    success: bool = True
    message: str = ""
    input_level: float | None = None

    def __post_init__(self) -> None:
        num = np.atleast_1d(np.asarray(self.num, dtype=float))
        den = np.atleast_1d(np.asarray(self.den, dtype=float))
        if num.ndim != 1 or den.ndim != 1 or den.size < 2:
            raise DataError("num and den must be 1-D coefficient lists; den of degree >= 1")
        if not (np.all(np.isfinite(num)) and np.all(np.isfinite(den))):
            raise DataError("num and den must be finite")
        if den[0] == 0:
            raise DataError("the leading denominator coefficient must be nonzero")
        if num.size > den.size:
            raise DataError(f"the model is improper: {num.size - 1} zeros > {den.size - 1} poles")
        num, den = num / den[0], den / den[0]
        if self.intersample not in INTERSAMPLE:
            raise DataError(f"intersample must be 'zoh' or 'foh'; got {self.intersample!r}")
        if not (np.isfinite(self.delay) and self.delay >= 0):
            raise DataError(f"delay must be finite and >= 0; got {self.delay}")
        object.__setattr__(self, "num", _readonly(num))
        object.__setattr__(self, "den", _readonly(den))
        object.__setattr__(self, "delay", float(self.delay))
        if self.covariance is not None:
            object.__setattr__(self, "covariance", _readonly(self.covariance))
        object.__setattr__(self, "fit_percent_per_record", _readonly(self.fit_percent_per_record))
        object.__setattr__(self, "offsets", _readonly(self.offsets))
        if self.validation_fit_percent_per_record is not None:
            object.__setattr__(self, "validation_fit_percent_per_record",
                               _readonly(self.validation_fit_percent_per_record))
        object.__setattr__(self, "parameter_names", tuple(self.parameter_names))
        object.__setattr__(self, "record_names", tuple(self.record_names))
        object.__setattr__(self, "order_selection", tuple(dict(r) for r in self.order_selection))

    # ------------------------------------------------------------------ properties
    @property
    def n_poles(self) -> int:
        """Number of poles (denominator degree)."""
        return int(self.den.size - 1)

    @property
    def n_zeros(self) -> int:
        """Number of zeros (numerator degree)."""
        return int(self.num.size - 1)

    @property
    def poles(self) -> NDArray[np.complex128]:
        """Roots of the denominator."""
        return np.roots(self.den).astype(complex)

    @property
    def zeros(self) -> NDArray[np.complex128]:
        """Roots of the numerator (leading zero coefficients are dropped)."""
        nz = np.trim_zeros(self.num, "f")
        return np.roots(nz).astype(complex) if nz.size > 1 else np.zeros(0, dtype=complex)

    @property
    def integrating(self) -> bool:
        """Whether the model has a pole at :math:`s = 0` (``den(0) = 0``)."""
        return bool(self.den[-1] == 0.0)

    @property
    def gain(self) -> float:
        """Static (DC) gain ``num(0) / den(0)`` (signed infinity for an integrating model)."""
        if self.integrating:
            return math.copysign(math.inf, float(self.num[-1])) if self.num[-1] else math.nan
        return float(self.num[-1] / self.den[-1])

    @property
    def std(self) -> NDArray[np.float64]:
        """One-sigma uncertainty of each parameter in ``parameter_names``."""
        if self.covariance is None:
            return np.zeros(0)
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def gain_std(self) -> float:
        """One-sigma uncertainty of :attr:`gain` (first-order propagation of ``covariance``)."""
        if self.covariance is None or self.integrating:
            return float("nan")
        grad = np.zeros(len(self.parameter_names))
        grad[self.n_zeros] = 1.0 / self.den[-1]  # d gain / d num[-1]
        grad[self.n_zeros + self.n_poles] = -self.num[-1] / self.den[-1] ** 2  # d / d den[-1]
        return float(np.sqrt(max(grad @ self.covariance @ grad, 0.0)))

    # ------------------------------------------------------------------ responses
    def simulate(
        self, t: ArrayLike, u: ArrayLike, *, u_before: float = 0.0
    ) -> NDArray[np.float64]:
        """Model output (no offset) for a sampled input, exactly at the samples.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Strictly increasing times; the model is at rest at ``t[0]``.
        u : array-like of shape (n_samples,)
            Input samples, held as ``intersample`` says.
        u_before : float, default=0.0
            Input before ``t[0]`` (it matters through the delay only).

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return simulate_lti((self.num, self.den), t, u, delay=self.delay,
                        intersample=self.intersample, u_before=u_before)

    def step(self, t: ArrayLike) -> NDArray[np.float64]:
        """Exact unit-step response (step at ``t = 0``, delay included).

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Strictly increasing times ``>= 0``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return step_response((self.num, self.den), t, delay=self.delay)

    def impulse(self, t: ArrayLike) -> NDArray[np.float64]:
        """Exact impulse response (strictly proper models; delay included).

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Strictly increasing times ``>= 0``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return impulse_response((self.num, self.den), t, delay=self.delay)

    def to_scipy(self) -> Any:
        """The model as ``scipy.signal.lti(num, den)``.

        Returns
        -------
        scipy.signal.lti
            Without the delay, which scipy cannot represent.
        """
        import scipy.signal

        return scipy.signal.lti(self.num, self.den)

    def allclose(self, other: TransferFunctionModel, rtol: float = 1e-8,
                 atol: float = 1e-12) -> bool:
        """Whether ``other`` has (nearly) the same numerator, denominator and delay.

        Parameters
        ----------
        other : TransferFunctionModel
        rtol, atol : float
            Tolerances of ``numpy.allclose``.

        Returns
        -------
        bool
        """
        return (
            isinstance(other, TransferFunctionModel)
            and self.num.shape == other.num.shape
            and self.den.shape == other.den.shape
            and bool(np.allclose(self.num, other.num, rtol=rtol, atol=atol))
            and bool(np.allclose(self.den, other.den, rtol=rtol, atol=atol))
            and bool(np.isclose(self.delay, other.delay, rtol=rtol, atol=atol))
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (complex numbers as ``[re, im]``).

        Returns
        -------
        dict
            ``num``, ``den``, ``poles``, ``zeros``, ``gain``, ``gain_std``, ``delay``,
            ``fit_percent``, ``fit_percent_per_record``, ``validation_fit_percent``
            (when validated), ``aic``, ``covariance``, ``parameter_std`` and the rest
            of the statistics.
        """

        def cplx(z: NDArray) -> list[list[float]]:
            return [[float(p.real), float(p.imag)] for p in z]

        out: dict[str, Any] = {
            "num": self.num.tolist(),
            "den": self.den.tolist(),
            "poles": cplx(self.poles),
            "zeros": cplx(self.zeros),
            "gain": self.gain,
            "gain_std": self.gain_std,
            "delay": self.delay,
            "n_poles": self.n_poles,
            "n_zeros": self.n_zeros,
            "intersample": self.intersample,
            "fit_percent": self.fit_percent,
            "fit_percent_per_record": self.fit_percent_per_record.tolist(),
        }
        if self.validation_fit_percent is not None:
            out["validation_fit_percent"] = self.validation_fit_percent
            per = self.validation_fit_percent_per_record
            out["validation_fit_percent_per_record"] = [] if per is None else per.tolist()
        if self.input_level is not None:
            out["input_level"] = self.input_level
        out.update(
            aic=self.aic,
            noise_variance=self.noise_variance,
            parameter_names=list(self.parameter_names),
            parameter_std=self.std.tolist(),
            covariance=None if self.covariance is None else self.covariance.tolist(),
            offsets=self.offsets.tolist(),
            records=list(self.record_names),
            n_samples=self.n_samples,
            n_parameters=self.n_parameters,
            success=self.success,
            message=self.message,
        )
        if self.order_selection:
            out["order_selection"] = [dict(r) for r in self.order_selection]
        return out
