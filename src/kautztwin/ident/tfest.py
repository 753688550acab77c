r"""Continuous-time transfer-function estimation from sampled records (MATLAB ``tfest``'s job).

The model of record :math:`r` is

.. math::

    y_r(t) = o_r + \big[G(s)\,e^{-\tau s}\big]\big(u_r - u_{r,\mathrm{before}}\big)(t)
             + \text{free response}_r(t) + e_r(t),\qquad
    G(s) = \frac{b_m s^m + \dots + b_0}{s^n + a_{n-1}s^{n-1} + \dots + a_0},

with one offset :math:`o_r` per record, an optional initial state (for
input/output records) and a shared :math:`G` and delay :math:`\tau`.  The
parameters minimise the *simulation* (output) error over all records.

Method (see ``docs/identification.md``):

1. **Initialisation** from an orthonormal-basis regression.  Step and impulse
   records are normalised to unit responses and given to
   :func:`kautztwin.optimize_poles` (variable projection on a Kautz basis) with
   ``N = n`` functions, and with ``N = n + 2`` followed by balanced truncation
   to order ``n``.  Input/output records are first regressed on a Laguerre
   basis (best pole from a grid); that model's impulse response goes to
   :func:`~kautztwin.optimize_poles`, and the model itself is reduced by
   balanced truncation.  Each candidate set of poles is one start.
2. **Output-error refinement** by variable projection: the output is linear in
   the numerator, the offsets and the initial states, which are solved by
   linear least squares for every denominator (and delay); only the
   denominator and the delay are searched, by bounded nonlinear least squares.
   The denominator is a product of factors :math:`s^2 + e^{\theta_1}s + e^{\theta_2}`
   (and :math:`s + e^{\theta}` for odd orders), so every iterate is stable,
   real poles and complex pairs alike, without fixing which is which.
3. **Uncertainty**: :math:`\operatorname{cov} = \hat\sigma^2 (J^TJ)^{-1}`, with
   :math:`J` the Jacobian of the residual with respect to all parameters
   (numerator, denominator, delay, offsets, initial states) at the optimum and
   :math:`\hat\sigma^2 = \mathrm{RSS}/(N - p)`.

Simulation is exact for the chosen intersample behaviour (``'zoh'`` or
``'foh'``), on any grid, with any delay; step and impulse records use ideal
steps and impulses (:mod:`kautztwin.ident.simulate`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from ..exceptions import ConvergenceWarning, DataError, KautzTwinError, NotFittedError
from .records import MIN_SAMPLES, Record
from .simulate import (
    INTERSAMPLE,
    PiecewiseInput,
    impulse_input,
    impulse_response,
    propagate,
    sampled_input,
    simulate_lti,
    step_input,
    step_response,
)

__all__ = ["TransferFunctionEstimator", "TransferFunctionModel"]

_INITIAL_STATE = ("auto", "zero", "estimate")
_LOG2PI1 = float(np.log(2 * np.pi) + 1)


# =========================================================================== the result
def _readonly(x: ArrayLike, dtype: Any = float) -> NDArray:
    a = np.array(x, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


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
    def gain(self) -> float:
        """Static (DC) gain ``num(0) / den(0)``."""
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
        if self.covariance is None:
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


# =========================================================================== parameterisation
def _den_from_theta(theta: NDArray, n: int) -> NDArray[np.float64]:
    """Monic denominator from log-coefficients of its quadratic (and linear) factors."""
    den = np.ones(1)
    for k in range(n // 2):
        den = np.polymul(den, [1.0, np.exp(theta[2 * k]), np.exp(theta[2 * k + 1])])
    if n % 2:
        den = np.polymul(den, [1.0, np.exp(theta[-1])])
    return den


def _theta_from_poles(poles: NDArray, n: int) -> NDArray[np.float64]:
    """Log-coefficients of the factors holding ``poles`` (stable; pairs and real poles)."""
    p = np.asarray(poles, dtype=complex)
    rate = np.maximum(-p.real, 1e-12)
    p = -rate + 1j * p.imag
    cplx = p[p.imag > 1e-9 * np.abs(p)]
    reals = np.sort(p[np.abs(p.imag) <= 1e-9 * np.abs(p)].real)
    quads: list[tuple[float, float]] = [(-2 * z.real, abs(z) ** 2) for z in cplx]
    lin: list[float] = []
    if reals.size % 2:
        lin.append(-reals[0])
        reals = reals[1:]
    for a, b in zip(reals[::2], reals[1::2], strict=True):
        quads.append((-(a + b), a * b))
    if len(quads) != n // 2 or len(lin) != n % 2:  # pragma: no cover - poles come in pairs
        raise DataError(f"cannot arrange {p.size} poles into an order-{n} denominator")
    theta = [np.log(v) for q in quads for v in q] + [np.log(v) for v in lin]
    return np.asarray(theta, dtype=float)


def _theta_bounds(n: int, rate_lo: float, rate_hi: float) -> tuple[NDArray, NDArray]:
    lo: list[float] = []
    hi: list[float] = []
    for _ in range(n // 2):
        lo += [np.log(2e-3 * rate_lo), 2 * np.log(rate_lo)]
        hi += [np.log(2 * rate_hi), 2 * np.log(rate_hi)]
    if n % 2:
        lo.append(np.log(rate_lo))
        hi.append(np.log(rate_hi))
    return np.array(lo), np.array(hi)


def _companion(den: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Controller form of ``1/den``: states ``w, w', ..., w^(n-1)``."""
    n = den.size - 1
    A = np.zeros((n, n))
    A[np.arange(n - 1), np.arange(1, n)] = 1.0
    A[-1] = -den[::-1][:n]
    B = np.zeros(n)
    B[-1] = 1.0
    return A, B


def _weighted_lstsq(N: NDArray, y: NDArray, sw: NDArray) -> NDArray[np.float64]:
    """``argmin_c || sw * (y - N c) ||`` with column scaling (empty ``N``: no parameters)."""
    if N.shape[1] == 0:
        return np.zeros(0)
    Nw = N * sw[:, None]
    sc = np.linalg.norm(Nw, axis=0)
    sc[sc == 0] = 1.0
    return np.linalg.lstsq(Nw / sc, y * sw, rcond=None)[0] / sc


def _orth(M: NDArray) -> NDArray[np.float64]:
    """Orthonormal basis of the column space of ``M`` (rank by a relative tolerance)."""
    if M.shape[1] == 0:
        return M
    scale = np.linalg.norm(M, axis=0)
    scale[scale == 0] = 1.0
    U, s, _ = np.linalg.svd(M / scale, full_matrices=False)
    keep = s > 1e-10 * s[0] if s.size and s[0] > 0 else np.zeros(s.size, dtype=bool)
    return U[:, keep]


def _sums(y: NDArray, yh: NDArray, w: NDArray) -> tuple[float, float]:
    """Weighted squared error and weighted spread about the weighted mean."""
    mean = float(np.sum(w * y) / np.sum(w))
    return float(np.sum(w * (y - yh) ** 2)), float(np.sum(w * (y - mean) ** 2))


def _pooled_fit(ys: list[NDArray], yhats: list[NDArray], ws: list[NDArray]) -> float:
    """Fit percent of several records pooled: each record about its own mean."""
    err = spread = 0.0
    for y, yh, w in zip(ys, yhats, ws, strict=True):
        e, s = _sums(y, yh, w)
        err += e
        spread += s
    if spread == 0:
        raise DataError("fit is undefined: every measured output is constant")
    return 100.0 * (1.0 - np.sqrt(err / spread))


def _record_fit(y: NDArray, yh: NDArray, w: NDArray) -> float:
    err, spread = _sums(y, yh, w)
    if spread == 0:
        return float("nan")
    return 100.0 * (1.0 - np.sqrt(err / spread))


# =========================================================================== the problem
class _Problem:
    """Output-error problem for a fixed order: regressors, projection, model output."""

    def __init__(
        self,
        records: list[Record],
        n_poles: int,
        n_zeros: int,
        *,
        intersample: str,
        offset: bool,
        initial_state: str,
    ) -> None:
        self.records = records
        self.n = n_poles
        self.m = n_zeros
        self.intersample = intersample
        self.offset = offset
        self.free = [
            initial_state == "estimate" or (initial_state == "auto" and r.kind == "io")
            for r in records
        ]
        self.y = [np.asarray(r.y) for r in records]
        self.w = [np.asarray(r.weights) for r in records]
        self.sw = [np.sqrt(w) for w in self.w]
        self.n_eval = 0

    # ------------------------------------------------------------------ pieces
    def input(self, rec: Record, delay: float) -> PiecewiseInput:
        if rec.kind == "io":
            return sampled_input(rec.t, rec.u - rec.u_before, delay=delay,
                                 intersample=self.intersample)
        assert rec.start is not None and rec.amplitude is not None  # set by Record
        if rec.kind == "step":
            return step_input(rec.start + delay, rec.amplitude)
        return impulse_input(rec.start + delay, rec.amplitude)

    def columns(
        self, den: NDArray, delay: float, rec: Record, free: bool
    ) -> tuple[NDArray, NDArray]:
        """Numerator regressors ``(n_t, m + 1)`` and nuisance columns ``(n_t, q)``."""
        A, B = _companion(den)
        inp = self.input(rec, delay)
        X = propagate(A, B, rec.t, inp, X0=np.eye(self.n) if free else None)
        states = X[:, :, 0]
        if self.m < self.n:
            R = states[:, : self.m + 1]
        else:
            top = inp.value_at(rec.t) - states @ den[::-1][: self.n]
            R = np.column_stack([states, top])
        nuis = []
        if self.offset:
            nuis.append(np.ones((rec.t.size, 1)))
        if free:
            nuis.append(X[:, 0, 1:])
        N = np.hstack(nuis) if nuis else np.zeros((rec.t.size, 0))
        return R, N

    def all_columns(self, den: NDArray, delay: float) -> list[tuple[NDArray, NDArray]]:
        return [self.columns(den, delay, r, f) for r, f in zip(self.records, self.free,
                                                                strict=True)]

    @staticmethod
    def solve(cols: list[tuple[NDArray, NDArray]], ys: list[NDArray], sws: list[NDArray]
              ) -> tuple[NDArray, list[NDArray], NDArray]:
        """Numerator by projected weighted least squares, then each record's nuisance.

        Returns the numerator (coefficient of ``s^i`` at index ``i``), the
        nuisance parameters of every record, and the weighted residual.
        """
        Rt, yt = [], []
        for (R, N), y, sw in zip(cols, ys, sws, strict=True):
            Q = _orth(N * sw[:, None])
            Rw, yw = R * sw[:, None], y * sw
            Rt.append(Rw - Q @ (Q.T @ Rw))
            yt.append(yw - Q @ (Q.T @ yw))
        Rs, ys_ = np.vstack(Rt), np.concatenate(yt)
        scale = np.linalg.norm(Rs, axis=0)
        scale[scale == 0] = 1.0
        b = np.linalg.lstsq(Rs / scale, ys_, rcond=None)[0] / scale
        resid = ys_ - Rs @ b
        nuis = []
        for (R, N), y, sw in zip(cols, ys, sws, strict=True):
            nuis.append(_weighted_lstsq(N, y - R @ b, sw))
        return b, nuis, resid

    def residual(self, den: NDArray, delay: float) -> NDArray[np.float64]:
        self.n_eval += 1
        return self.solve(self.all_columns(den, delay), self.y, self.sw)[2]

    def outputs(self, den: NDArray, delay: float, b: NDArray, nuis: list[NDArray]
                ) -> list[NDArray]:
        cols = self.all_columns(den, delay)
        return [R @ b + N @ c for (R, N), c in zip(cols, nuis, strict=True)]


# =========================================================================== initialisation
def _unit_responses(records: list[Record]) -> tuple[NDArray, NDArray, str]:
    """Step or impulse records as unit responses on one uniform grid from the event."""
    kind = records[0].kind
    spans, steps, pieces = [], [], []
    for r in records:
        assert r.start is not None and r.amplitude is not None
        after = r.t >= r.start
        before = r.t <= r.start
        level = float(np.mean(r.y[before]))
        tt = r.t[after] - r.start
        pieces.append((tt, (r.y[after] - level) / r.amplitude))
        spans.append(tt[-1])
        steps.append(float(np.median(np.diff(r.t))))
    span = float(min(spans))
    dt = float(min(steps))
    n = int(min(max(round(span / dt) + 1, 8), 400))  # a start only: a coarse grid will do
    tg = np.linspace(0.0, span, n)
    H = np.array([np.interp(tg, tt, h) for tt, h in pieces])
    return tg, H, kind


def _reduced_poles(A: NDArray, B: NDArray, c: NDArray, n: int) -> NDArray[np.complex128] | None:
    """Poles of the balanced truncation to order ``n`` of ``(A, B, c)`` (orthonormal basis).

    For an orthonormal basis the controllability Gramian is the identity, so the
    balanced truncation keeps the dominant eigenvectors ``V_r`` of the
    observability Gramian, and its poles are those of ``V_r^T A V_r``.
    """
    try:
        Q = scipy.linalg.solve_continuous_lyapunov(A.T, -np.outer(c, c))
        P = scipy.linalg.solve_continuous_lyapunov(A, -np.outer(B, B))
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not np.allclose(P, np.eye(A.shape[0]), atol=1e-6):
        # general square-root balancing
        try:
            Lp = np.linalg.cholesky(P + 1e-14 * np.eye(P.shape[0]))
            Lq = np.linalg.cholesky(Q + 1e-14 * np.eye(Q.shape[0]))
        except np.linalg.LinAlgError:
            return None
        U, s, Vt = np.linalg.svd(Lq.T @ Lp)
        S = np.diag(s[:n] ** -0.5)
        T = Lp @ Vt[:n].T @ S
        Ti = S @ U[:, :n].T @ Lq.T
        return np.linalg.eigvals(Ti @ A @ T)
    w, V = np.linalg.eigh((Q + Q.T) / 2)
    Vr = V[:, np.argsort(w)[::-1][:n]]
    return np.linalg.eigvals(Vr.T @ A @ Vr)


def _obf_starts(records: list[Record], n: int, rate_lo: float, intersample: str
                ) -> list[NDArray[np.complex128]]:
    """Candidate initial poles from orthonormal-basis regressions."""
    from ..approx import optimize_poles
    from ..basis import LaguerreBasis

    starts: list[NDArray[np.complex128]] = []
    kinds = {r.kind for r in records}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kinds <= {"step", "impulse"} and len(kinds) == 1:
            tg, H, kind = _unit_responses(records)
            for N in (n, n + 2):
                if 2 * N >= tg.size:
                    continue
                try:
                    res = optimize_poles(tg, H, N, kind=kind, max_iter=20 if N == n else 12)
                except (KautzTwinError, np.linalg.LinAlgError, ValueError):
                    continue
                if N == n:
                    starts.append(res.basis.poles)
                else:
                    c = np.atleast_2d(res.coefficients).mean(axis=0)
                    red = _reduced_poles(res.basis.A, res.basis.B, c, n)
                    if red is not None:
                        starts.append(red)
            return starts
        # input/output records: Laguerre regression, then Kautz poles for its impulse response
        dt = float(min(np.median(np.diff(r.t)) for r in records))
        span = float(max(r.duration for r in records))
        n_lag = int(min(12, max(2 * n + 2, 8)))
        prob = _Problem(records, n_lag, n_lag - 1, intersample=intersample, offset=True,
                        initial_state="zero")
        best = None
        rate = 2.0 / dt
        while rate >= 2.0 / span:
            basis = LaguerreBasis(pole=-rate, n=n_lag)
            cols = []
            for r in records:
                X = propagate(basis.A, basis.B, r.t, prob.input(r, 0.0))[:, :, 0]
                cols.append((X, np.ones((r.t.size, 1))))
            c, _, resid = _Problem.solve(cols, prob.y, prob.sw)
            cost = float(resid @ resid)
            if best is None or cost < best[0]:
                best = (cost, basis, c)
            rate /= 2.0
        if best is None:
            return starts
        _, basis, c = best
        red = _reduced_poles(basis.A, basis.B, c, n)
        if red is not None:
            starts.append(red)
        th = min(span, 12.0 / (-basis.poles[0].real))
        tg = np.linspace(0.0, th, 400)
        h = c @ basis.evaluate(tg)
        if np.ptp(h) > 0:
            try:
                res = optimize_poles(tg, h, n, kind="impulse", max_iter=20)
                starts.append(res.basis.poles)
            except (KautzTwinError, np.linalg.LinAlgError, ValueError):
                pass
    return starts


# =========================================================================== the estimator
class TransferFunctionEstimator:
    r"""Estimate a continuous-time transfer function from step, impulse or input/output records.

    The continuous-time counterpart of MATLAB's ``tfest``: chosen numbers of
    poles and zeros (or automatic order selection), an optional input delay,
    several records fitted together (each with its own offset and, for
    input/output records, initial state), exact simulation of sampled inputs,
    stability guaranteed, and parameter covariances.  The method is described
    in the module docstring and ``docs/identification.md``.

    Parameters
    ----------
    n_poles : int or 'auto', default=2
        Number of poles, or ``'auto'`` to choose it from 1 to ``max_order``:
        by the best validation fit when ``validate_from`` leaves validation
        data, else by the smallest AIC.
    n_zeros : int, optional
        Number of zeros (at most ``n_poles``); ``n_poles - 1`` when omitted,
        as in ``tfest``.  With ``n_poles='auto'`` it is capped at ``n - 1``.
    delay : bool or float, default=False
        ``False``: no delay.  ``True``: estimate the input delay.  A number:
        a fixed delay in seconds.
    kind : {'io', 'step', 'impulse'}, optional
        What ``(t, u, y)`` tuples passed to :meth:`fit` are.  When given,
        :class:`Record` objects must be of this kind.
    intersample : {'zoh', 'foh'}, default='zoh'
        Input between samples of ``'io'`` records: held (zero-order hold) or
        linearly interpolated (first-order hold).  Step and impulse records are
        ideal steps and impulses either way.
    initial_state : {'auto', 'zero', 'estimate'}, default='auto'
        Whether to estimate each record's initial state (``'auto'``: for
        ``'io'`` records; step and impulse records start at rest).
    offset : bool, default=True
        Estimate one output offset per record.
    validate_from : float, optional
        Samples at ``t >= validate_from`` are held out of the estimation; the
        model is simulated over the whole record and scored on them.
    max_order : int, default=4
        Largest order tried by ``n_poles='auto'``.
    max_iter : int, default=100
        Iteration budget of each refinement (residual evaluations are about
        ``max_iter * (n_params + 1)``).
    tol : float, default=1e-10
        ``ftol``, ``xtol`` and ``gtol`` of the refinement.
    n_restarts : int, default=0
        Extra refinements from randomly perturbed copies of the best start.
    random_state : int or numpy.random.Generator, optional
        Seed of those perturbations (the only randomness).

    Attributes
    ----------
    model_ : TransferFunctionModel
        The estimated model and its statistics.
    n_poles_, n_zeros_ : int
        The order fitted (chosen, with ``'auto'``).
    records_ : list of Record
        The records the model was fitted to.
    n_evaluations_ : int
        Residual evaluations spent (all starts and orders).

    See Also
    --------
    kautztwin.optimize_poles : The Kautz-basis pole optimisation used to initialise.
    kautztwin.ident.ARXEstimator : Discrete-time least-squares baseline.
    kautztwin.ident.simulate_lti : Exact simulation of continuous models with sampled inputs.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import Record, TransferFunctionEstimator, step_response
    >>> t = np.linspace(0, 10, 201)
    >>> y = 3.0 + 2.0 * step_response(([2.0], [1.0, 3.0, 2.0]), t)   # offset 3, step 2
    >>> est = TransferFunctionEstimator(n_poles=2, n_zeros=0)
    >>> model = est.fit(Record.step_response(t, y, amplitude=2.0)).model_
    >>> np.round(model.den, 6), round(model.gain, 6), round(model.fit_percent, 3)
    (array([1., 3., 2.]), 1.0, 100.0)
    """

    def __init__(
        self,
        n_poles: int | str = 2,
        n_zeros: int | None = None,
        *,
        delay: bool | float = False,
        kind: str | None = None,
        intersample: str = "zoh",
        initial_state: str = "auto",
        offset: bool = True,
        validate_from: float | None = None,
        max_order: int = 4,
        max_iter: int = 100,
        tol: float = 1e-10,
        n_restarts: int = 0,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.n_poles = n_poles
        self.n_zeros = n_zeros
        self.delay = delay
        self.kind = kind
        self.intersample = intersample
        self.initial_state = initial_state
        self.offset = offset
        self.validate_from = validate_from
        self.max_order = max_order
        self.max_iter = max_iter
        self.tol = tol
        self.n_restarts = n_restarts
        self.random_state = random_state

    # ------------------------------------------------------------------ sklearn plumbing
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
        names = ("n_poles", "n_zeros", "delay", "kind", "intersample", "initial_state", "offset",
                 "validate_from", "max_order", "max_iter", "tol", "n_restarts", "random_state")
        return {k: getattr(self, k) for k in names}

    def set_params(self, **params: Any) -> TransferFunctionEstimator:
        """Set constructor parameters (scikit-learn protocol).

        Parameters
        ----------
        **params
            New values of constructor parameters.

        Returns
        -------
        self
        """
        valid = self.get_params()
        for k, v in params.items():
            if k not in valid:
                raise ValueError(f"unknown parameter {k!r}; valid: {', '.join(valid)}")
            setattr(self, k, v)
        return self

    def __repr__(self) -> str:
        return f"TransferFunctionEstimator(n_poles={self.n_poles!r}, n_zeros={self.n_zeros!r})"

    # ------------------------------------------------------------------ validation
    def _records(self, records: Any) -> list[Record]:
        if isinstance(records, Record):
            records = [records]
        elif isinstance(records, tuple) and len(records) == 3 and not isinstance(records[0],
                                                                                  Record):
            records = [records]
        if not isinstance(records, Sequence) or len(records) == 0:
            raise DataError("records must be a Record, a (t, u, y) tuple, or a non-empty list "
                            "of them")
        out = []
        for i, r in enumerate(records):
            if isinstance(r, Record):
                if self.kind is not None and r.kind != self.kind:
                    raise DataError(f"records[{i}] is a {r.kind!r} record but kind={self.kind!r}")
                out.append(r)
            elif isinstance(r, (tuple, list)) and len(r) == 3:
                out.append(Record.from_data(*r, kind=self.kind or "io", name=f"record {i}"))
            else:
                raise DataError(f"records[{i}] must be a Record or a (t, u, y) tuple; got "
                                f"{type(r).__name__}")
        return out

    def _check_params(self) -> None:
        if self.intersample not in INTERSAMPLE:
            raise DataError(f"intersample must be 'zoh' or 'foh'; got {self.intersample!r}")
        if self.initial_state not in _INITIAL_STATE:
            raise DataError(
                f"initial_state must be one of {', '.join(map(repr, _INITIAL_STATE))}; "
                f"got {self.initial_state!r}"
            )
        if isinstance(self.n_poles, str):
            if self.n_poles != "auto":
                raise DataError(f"n_poles must be a positive integer or 'auto'; got "
                                f"{self.n_poles!r}")
            if not isinstance(self.max_order, (int, np.integer)) or self.max_order < 1:
                raise DataError(f"max_order must be an integer >= 1; got {self.max_order!r}")
        elif (not isinstance(self.n_poles, (int, np.integer)) or isinstance(self.n_poles, bool)
              or self.n_poles < 1):
            raise DataError(f"n_poles must be a positive integer or 'auto'; got {self.n_poles!r}")
        if self.n_zeros is not None:
            if (not isinstance(self.n_zeros, (int, np.integer)) or isinstance(self.n_zeros, bool)
                    or self.n_zeros < 0):
                raise DataError(f"n_zeros must be an integer >= 0; got {self.n_zeros!r}")
            if not isinstance(self.n_poles, str) and self.n_zeros > self.n_poles:
                raise DataError(f"n_zeros = {self.n_zeros} exceeds n_poles = {self.n_poles}: "
                                "the model would be improper")
        if not isinstance(self.delay, bool):
            try:
                d = float(self.delay)
            except (TypeError, ValueError):
                raise DataError(f"delay must be True, False or a number >= 0; got "
                                f"{self.delay!r}") from None
            if not (np.isfinite(d) and d >= 0):
                raise DataError(f"delay must be True, False or a number >= 0; got {self.delay!r}")
        if self.validate_from is not None and not np.isfinite(float(self.validate_from)):
            raise DataError(f"validate_from must be a finite time; got {self.validate_from!r}")
        if not isinstance(self.max_iter, (int, np.integer)) or self.max_iter < 1:
            raise DataError(f"max_iter must be an integer >= 1; got {self.max_iter!r}")
        if not (np.isfinite(self.tol) and self.tol > 0):
            raise DataError(f"tol must be > 0; got {self.tol!r}")

    def _split(self, records: list[Record]) -> tuple[list[Record], list[int]]:
        """Estimation parts of the records (``t < validate_from``) and their indices."""
        if self.validate_from is None:
            return records, list(range(len(records)))
        T = float(self.validate_from)
        est, idx = [], []
        for i, r in enumerate(records):
            mask = r.t < T
            if mask.sum() < MIN_SAMPLES:
                continue
            if r.kind != "io" and not r.start < T:
                continue
            try:
                est.append(r.select(mask))
            except KautzTwinError:
                continue
            idx.append(i)
        if not est:
            raise DataError(
                f"validate_from = {T:g} leaves no record with at least {MIN_SAMPLES} estimation "
                "samples (and its step or impulse) before it"
            )
        return est, idx

    # ------------------------------------------------------------------ fitting
    def fit(self, records: Any) -> TransferFunctionEstimator:
        """Estimate the transfer function from one or many records.

        Parameters
        ----------
        records : Record, (t, u, y) tuple, or list of them
            The experiments, fitted together.  Tuples are read with
            :meth:`Record.from_data` and this estimator's ``kind``.

        Returns
        -------
        self

        Raises
        ------
        DataError
            On invalid parameters, unusable records (NaN, constant input, ...),
            or fewer samples than parameters.
        DimensionError
            On records that are too short.
        """
        self._check_params()
        recs = self._records(records)
        if len({r.kind for r in recs}) > 1 and any(r.kind == "impulse" for r in recs):
            raise DataError("impulse records cannot be mixed with other kinds in one fit")
        if self.initial_state == "estimate":
            for r in recs:
                if r.kind != "io" and r.start is not None and r.start <= r.t[0]:
                    raise DataError(
                        f"record {r.name!r} starts at its {r.kind}: with initial_state="
                        "'estimate' its initial state, offset and gain cannot be told apart "
                        "(the response lies in the span of the free responses); use "
                        "initial_state='zero', or a record that starts before the "
                        f"{r.kind}"
                    )
        est, _ = self._split(recs)
        if self.n_poles == "auto":
            orders = range(1, int(self.max_order) + 1)
        else:
            orders = range(int(self.n_poles), int(self.n_poles) + 1)
        rows, fits = [], []
        self.n_evaluations_ = 0
        for n in orders:
            if self.n_zeros is None:
                m = n - 1
            else:
                m = int(self.n_zeros) if self.n_poles != "auto" else min(int(self.n_zeros), n - 1)
            if any(r.kind == "impulse" for r in recs) and m >= n:
                raise DataError(f"impulse records need fewer zeros than poles; got n_zeros = {m}, "
                                f"n_poles = {n}")
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                model = self._fit_order(recs, est, n, m)
            fits.append((model, caught))
            rows.append({"n_poles": n, "n_zeros": m, "aic": model.aic,
                         "fit_percent": model.fit_percent,
                         "validation_fit_percent": model.validation_fit_percent})
        best = 0
        if self.n_poles == "auto":
            if all(r["validation_fit_percent"] is not None for r in rows):
                best = int(np.argmax([r["validation_fit_percent"] for r in rows]))
            else:
                best = int(np.argmin([r["aic"] for r in rows]))
        chosen, caught = fits[best]
        for w in caught:  # only the chosen order's warnings matter
            warnings.warn(w.message, w.category, stacklevel=2)
        if self.n_poles == "auto":
            chosen = dataclasses.replace(chosen, order_selection=tuple(rows))
        self.model_ = chosen
        self.n_poles_ = chosen.n_poles
        self.n_zeros_ = chosen.n_zeros
        self.records_ = recs
        return self

    def _fit_order(self, recs: list[Record], est: list[Record], n: int, m: int
                   ) -> TransferFunctionModel:
        prob = _Problem(est, n, m, intersample=self.intersample, offset=bool(self.offset),
                        initial_state=self.initial_state)
        n_lin = (m + 1) + sum((1 if self.offset else 0) + (n if f else 0) for f in prob.free)
        estimate_delay = self.delay is True
        n_total = n_lin + n + (1 if estimate_delay else 0)
        n_samples = sum(r.n_samples for r in est)
        if n_samples <= n_total:
            raise DataError(
                f"the records are too short: {n_samples} estimation samples for {n_total} "
                f"parameters (order {n}, {m} zeros{', delay' if estimate_delay else ''}, "
                "offsets and initial states); give longer records or a lower order"
            )
        dt = float(min(np.median(np.diff(r.t)) for r in est))
        span = float(max(r.duration for r in est))
        rate_lo, rate_hi = 0.01 / span, 50.0 / dt
        lo, hi = _theta_bounds(n, rate_lo, rate_hi)
        fixed_delay = 0.0 if isinstance(self.delay, bool) else float(self.delay)
        tau_max = 0.25 * float(min(r.duration for r in est))
        if estimate_delay:
            lo = np.append(lo, 0.0)
            hi = np.append(hi, tau_max)

        def unpack(x: NDArray) -> tuple[NDArray, float]:
            return _den_from_theta(x[:n], n), (float(x[n]) if estimate_delay else fixed_delay)

        def fun(x: NDArray) -> NDArray:
            den, tau = unpack(x)
            return prob.residual(den, tau)

        def clip(x: NDArray) -> NDArray:
            span_ = hi - lo
            return np.clip(x, lo + 1e-9 * span_, hi - 1e-9 * span_)

        # ---- starts
        starts = []
        for poles in _obf_starts(est, n, rate_lo, self.intersample):
            if poles is None or len(poles) != n or not np.all(np.isfinite(poles)):
                continue
            starts.append(_theta_from_poles(poles, n))
        # a generic start from the record length scale
        p0 = 4.0 / span
        starts.append(_theta_from_poles(-p0 * 2.0 ** np.arange(n), n))
        x_starts = []
        for th in starts:
            th = np.clip(th, lo[:n] + 1e-6, hi[:n] - 1e-6)
            if estimate_delay:
                grid = np.unique(np.concatenate([dt * np.arange(11), np.linspace(0, tau_max, 17)]))
                grid = grid[grid <= tau_max]
                costs = [float(np.sum(fun(np.append(th, g)) ** 2)) for g in grid]
                th = np.append(th, grid[int(np.argmin(costs))])
            x_starts.append(clip(th))
        # rank the starts by their initial cost; a short refinement of the best few, then
        # (with any random restarts) the best one to convergence
        init_cost = [float(np.sum(fun(x) ** 2)) for x in x_starts]
        order = np.argsort(init_cost)[:3]
        x_scale = np.ones(lo.size)
        if estimate_delay:
            x_scale[-1] = dt

        def refine(x0: NDArray, iters: int) -> Any:
            return scipy.optimize.least_squares(
                fun, clip(x0), bounds=(lo, hi), method="trf", x_scale=x_scale,
                ftol=self.tol, xtol=self.tol, gtol=self.tol, max_nfev=iters * (lo.size + 1),
            )

        short = min(15, int(self.max_iter))
        trials = [refine(x_starts[i], short) for i in order]
        best = min(trials, key=lambda sol: sol.cost)
        rng = np.random.default_rng(self.random_state)
        for _ in range(int(self.n_restarts)):
            pert = best.x + rng.normal(0.0, 0.5, best.x.size) * (np.arange(best.x.size) < n)
            sol = refine(pert, short)
            if sol.cost < best.cost:
                best = sol
        if not best.success:
            sol = refine(best.x, int(self.max_iter))
            if sol.cost <= best.cost:
                best = sol
        assert best is not None
        self.n_evaluations_ += prob.n_eval
        if not best.success:
            warnings.warn(f"the output-error refinement did not converge: {best.message}",
                          ConvergenceWarning, stacklevel=3)
        den, tau = unpack(best.x)
        for p in np.roots(den):
            if -p.real >= rate_lo:
                continue
            if abs(p.imag) > 1e-9 * abs(p):
                warnings.warn(
                    f"the model has a nearly undamped pole pair at {complex(p):.3g} (it reached "
                    "the stability limit); try fewer poles or zeros", ConvergenceWarning,
                    stacklevel=3)
            else:
                warnings.warn(
                    f"the model has a pole at {p.real:.3g}, slower than 0.01 / record length: "
                    "the records cannot resolve it (it acts as a drift or offset); try fewer "
                    "poles or zeros", ConvergenceWarning, stacklevel=3)
            break
        return self._finalize(prob, recs, den, tau, estimate_delay, best)

    # ------------------------------------------------------------------ statistics
    def _finalize(self, prob: _Problem, recs: list[Record], den: NDArray, tau: float,
                  estimate_delay: bool, sol: Any) -> TransferFunctionModel:
        n, m = prob.n, prob.m
        cols = prob.all_columns(den, tau)
        b, nuis, resid = _Problem.solve(cols, prob.y, prob.sw)
        yhat = [R @ b + N @ c for (R, N), c in zip(cols, nuis, strict=True)]
        sw_all = np.concatenate(prob.sw)
        resid = sw_all * np.concatenate([y - yh for y, yh in zip(prob.y, yhat, strict=True)])
        rss = float(resid @ resid)
        N_s = float(np.sum(sw_all**2))  # rows as logged (merged rows count with their weight)
        # Jacobian of the (weighted) model output: numerator, denominator, delay, nuisance
        jac_cols = [np.concatenate([R[:, j] for R, _ in cols]) for j in range(m, -1, -1)]
        names = [f"num[{i}]" for i in range(m + 1)] + [f"den[{i}]" for i in range(1, n + 1)]

        def model_out(d: NDArray, t_: float) -> NDArray:
            cc = prob.all_columns(d, t_)
            return np.concatenate([R @ b + N @ c for (R, N), c in zip(cc, nuis, strict=True)])


        for i in range(1, n + 1):
            h = 1e-6 * max(abs(den[i]), 1e-12)
            dp, dm = den.copy(), den.copy()
            dp[i] += h
            dm[i] -= h
            jac_cols.append((model_out(dp, tau) - model_out(dm, tau)) / (2 * h))
        if estimate_delay:
            dt = float(min(np.median(np.diff(r.t)) for r in prob.records))
            h = 1e-6 * max(dt, tau)
            if tau > h:
                jac_cols.append((model_out(den, tau + h) - model_out(den, tau - h)) / (2 * h))
            else:
                jac_cols.append((model_out(den, tau + h) - model_out(den, tau)) / h)
            names.append("delay")
        n_model = len(jac_cols)
        offs = []
        start = 0
        for (R, N), c in zip(cols, nuis, strict=True):
            for j in range(N.shape[1]):
                col = np.zeros(sw_all.size)
                col[start : start + R.shape[0]] = N[:, j]
                jac_cols.append(col)
            offs.append(float(c[0]) if self.offset and c.size else 0.0)
            start += R.shape[0]
        J = np.column_stack(jac_cols) * sw_all[:, None]
        p = J.shape[1]
        dof = max(N_s - p, 1.0)
        sigma2 = rss / dof
        scale = np.linalg.norm(J, axis=0)
        scale[scale == 0] = 1.0
        _, s, Vt = np.linalg.svd(J / scale, full_matrices=False)
        keep = s > 1e-12 * s[0]
        inv = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
        cov = sigma2 * inv / np.outer(scale, scale)
        cov = cov[:n_model, :n_model]
        # fits on the estimation data
        fit_rec = np.array([_record_fit(y, yh, w)
                            for y, yh, w in zip(prob.y, yhat, prob.w, strict=True)])
        fit_all = _pooled_fit(prob.y, yhat, prob.w)
        aic = N_s * np.log(max(rss, 1e-300) / N_s) + 2 * p + N_s * _LOG2PI1
        # validation
        val_fit, val_rec = None, None
        if self.validate_from is not None:
            val_fit, val_rec = self._validation(prob, recs, den, tau, b)
        return TransferFunctionModel(
            num=b[::-1].copy(), den=den, delay=tau, intersample=self.intersample,
            covariance=cov, parameter_names=tuple(names), noise_variance=sigma2,
            fit_percent=float(fit_all), fit_percent_per_record=fit_rec,
            validation_fit_percent=val_fit, validation_fit_percent_per_record=val_rec,
            aic=float(aic), n_samples=int(round(N_s)), n_parameters=int(p),
            offsets=np.array(offs),
            record_names=tuple(r.name for r in prob.records), success=bool(sol.success),
            message=str(sol.message),
        )

    def _nuisance(self, prob: _Problem, rec: Record, free: bool, den: NDArray, tau: float,
                  b: NDArray, mask: NDArray) -> tuple[NDArray, NDArray]:
        """Model output over the whole record, nuisance fitted on the samples in ``mask``."""
        R, N = prob.columns(den, tau, rec, free)
        y = np.asarray(rec.y)
        sw = np.sqrt(np.asarray(rec.weights))
        c = _weighted_lstsq(N[mask], y[mask] - R[mask] @ b, sw[mask])
        return R @ b + N @ c, c

    def _validation(self, prob: _Problem, recs: list[Record], den: NDArray, tau: float,
                    b: NDArray) -> tuple[float | None, NDArray | None]:
        T = float(self.validate_from)  # type: ignore[arg-type]
        ys, yhs, ws, per = [], [], [], []
        for r in recs:
            vmask = r.t >= T
            if vmask.sum() < 2:
                continue
            emask = ~vmask
            free = self.initial_state == "estimate" or (
                self.initial_state == "auto" and r.kind == "io")
            use = emask if emask.sum() >= MIN_SAMPLES else vmask
            yh, _ = self._nuisance(prob, r, free, den, tau, b, use)
            ys.append(np.asarray(r.y)[vmask])
            yhs.append(yh[vmask])
            ws.append(np.asarray(r.weights)[vmask])
            per.append(_record_fit(ys[-1], yhs[-1], ws[-1]))
        if not ys:
            return None, None
        return float(_pooled_fit(ys, yhs, ws)), np.array(per)

    # ------------------------------------------------------------------ use
    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise NotFittedError(
                "this TransferFunctionEstimator is not fitted yet; call fit(records) first"
            )

    def predict(self, records: Any) -> list[NDArray[np.float64]]:
        """Simulated output of every record, as MATLAB ``compare`` computes it.

        The model is simulated over each whole record; the record's offset (and
        initial state, where estimated) is fitted to its samples before
        ``validate_from`` when there are enough of them, else to all samples.

        Parameters
        ----------
        records : Record, (t, u, y) tuple, or list of them

        Returns
        -------
        list of ndarray
            One simulated output per record, on the record's (merged) time grid.
        """
        self._check_fitted()
        recs = self._records(records)
        model = self.model_
        prob = _Problem(recs, model.n_poles, model.n_zeros, intersample=model.intersample,
                        offset=bool(self.offset), initial_state=self.initial_state)
        b = model.num[::-1].copy()
        out = []
        for r, free in zip(recs, prob.free, strict=True):
            mask = np.ones(r.n_samples, dtype=bool)
            if self.validate_from is not None:
                emask = r.t < float(self.validate_from)
                if emask.sum() >= MIN_SAMPLES:
                    mask = emask
            yh, _ = self._nuisance(prob, r, free, model.den, model.delay, b, mask)
            out.append(yh)
        return out

    def score(self, records: Any) -> float:
        """Pooled simulation fit percent of :meth:`predict` on ``records`` (all samples).

        Parameters
        ----------
        records : Record, (t, u, y) tuple, or list of them

        Returns
        -------
        float
        """
        recs = self._records(records)
        return float(_pooled_fit([np.asarray(r.y) for r in recs], self.predict(recs),
                                 [np.asarray(r.weights) for r in recs]))

    def simulate(self, t: ArrayLike, u: ArrayLike, *, u_before: float = 0.0
                 ) -> NDArray[np.float64]:
        """Output of the fitted model (no offset) for a sampled input.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
        u : array-like of shape (n_samples,)
        u_before : float, default=0.0
            Input before ``t[0]``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        self._check_fitted()
        return self.model_.simulate(t, u, u_before=u_before)
