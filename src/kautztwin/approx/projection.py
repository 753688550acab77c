"""Coefficients of responses in an orthonormal basis: projection, least squares, Sylvester."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.integrate
import scipy.linalg
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from .._quadrature import least_squares_weights, quadrature_weights
from .._validation import check_choice, check_records, check_time
from ..basis import KautzBasis
from ..basis._propagate import sample_indices, uniform_step
from ..exceptions import DataError, DimensionError
from ..metrics import fit_percent, ise, mse
from ._system import as_state_space
from .model import KautzModel

__all__ = [
    "Approximation",
    "approximate",
    "coefficients_from_system",
    "impulse_to_step",
    "ise_from_system",
    "project",
    "step_to_impulse",
]

_KINDS = ("impulse", "step")
_METHODS = ("quadrature", "lstsq")


def _design(basis: KautzBasis, t: NDArray, kind: str) -> NDArray[np.float64]:
    """Basis signals that a response of this kind is a combination of, shape (N, n)."""
    return basis.evaluate(t) if kind == "impulse" else basis.step_functions(t)


def project(
    basis: KautzBasis,
    t: ArrayLike,
    h: ArrayLike,
    *,
    kind: str = "impulse",
    method: str = "quadrature",
    rule: str = "simpson",
) -> NDArray[np.float64]:
    r"""Coefficients of sampled impulse or step responses in an orthonormal basis.

    ``method='quadrature'`` is the orthogonal projection
    :math:`c_i = \int h K_i\,dt`, computed as one matrix product with
    quadrature weights (composite Simpson by default, also on non-uniform
    grids).  For a step response ``y`` it uses integration by parts instead of
    differentiating noisy data (kautz-math.md 4.3):

    .. math:: \int_{t_0}^{T} h K\,dt = y(T)K(T) - y(t_0)K(t_0) - A\int_{t_0}^{T} y K\,dt .

    ``method='lstsq'`` minimises the squared error (weighted by Simpson's rule) between
    the record and the model's impulse or step response on the grid; it is
    the better choice for short records, where the functions have not decayed.
    Discrete bases (``basis.dt > 0``) use plain sums, which are exact in
    :math:`\ell_2`; their records start at ``t = 0`` on the grid ``k * dt``.

    Parameters
    ----------
    basis : KautzBasis
        The orthonormal basis.
    t : array-like of shape (n_samples,)
        Strictly increasing sample times (uniform or not), in seconds.
    h : array-like of shape (n_samples,) or (n_records, n_samples)
        One record, or many records on the same grid (one per row).
    kind : {'impulse', 'step'}, default='impulse'
        What the records are.  Step responses are unit-step responses from
        rest: subtract the initial level and divide by the step height first.
    method : {'quadrature', 'lstsq'}, default='quadrature'
        Projection by quadrature, or weighted least squares on the grid.
    rule : {'simpson', 'trapezoid'}, default='simpson'
        Quadrature rule for ``method='quadrature'`` (continuous bases).

    Returns
    -------
    ndarray of shape (n_functions,) or (n_records, n_functions)

    Raises
    ------
    DataError
        On NaN/inf, a non-increasing ``t`` or an unknown option.
    DimensionError
        If ``h`` and ``t`` have different numbers of samples.

    See Also
    --------
    approximate : The same, returned as a model with its errors.
    coefficients_from_system : Exact coefficients of a known system (no quadrature).

    Notes
    -----
    The projection error is :math:`O(\Delta^4)` with Simpson's rule, and the
    record must be long enough for ``h`` and the basis to decay.  Projecting
    10,000 records is one ``(10000, n) @ (n, N)`` product.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> t = np.linspace(0, 20, 2001)
    >>> h = np.exp(-t)                      # impulse response of 1/(s+1)
    >>> c = kt.project(kt.LaguerreBasis(pole=-1, n=3), t, h)
    >>> np.round(c, 6)                      # 1/sqrt(2) on the first function
    array([0.707107, 0.      , 0.      ])
    """
    check_choice(kind, "kind", _KINDS)
    check_choice(method, "method", _METHODS)
    t = check_time(t)
    h = check_records(h, t.size)
    if basis.is_discrete:
        return _project_discrete(basis, t, h, kind, method)
    if method == "lstsq":
        return _weighted_lstsq(_design(basis, t, kind), least_squares_weights(t), h)
    K = basis.evaluate(t)
    w = quadrature_weights(t, rule)
    Kw = (K * w).T  # (n, N): weights folded into the small factor, not the records
    if kind == "impulse":
        return h @ Kw
    integral = h @ Kw  # int y K dt, per record
    y_end, y_start = h[..., -1:], h[..., :1]
    return y_end * K[:, -1] - y_start * K[:, 0] - integral @ basis.A.T


def _project_discrete(
    basis: KautzBasis, t: NDArray, h: NDArray, kind: str, method: str
) -> NDArray[np.float64]:
    F = basis.evaluate(t)  # also checks that t lies on the grid k*dt
    if method == "lstsq":
        return _weighted_lstsq(_design(basis, t, kind), np.ones(t.size), h)
    # plain sums are the l2 inner products only over the whole sequence from k = 0;
    # a record that starts later or skips samples would give wrong coefficients silently
    if not np.array_equal(sample_indices(t, basis.dt), np.arange(t.size)):
        raise DataError(
            f"a discrete {kind} record must hold consecutive samples k = 0, 1, 2, ... "
            "(t = k * dt); use method='lstsq' for other grids"
        )
    if kind == "step":
        h = np.diff(h, axis=-1, prepend=0.0)
    return h @ F.T


def _weighted_lstsq(Phi: NDArray, w: NDArray, h: NDArray) -> NDArray[np.float64]:
    """Solve ``min ||sqrt(w) (h - c^T Phi)||`` for every record at once."""
    sw = np.sqrt(w)
    M = (Phi * sw).T  # (n, N)
    rhs = (h * sw).T  # (n,) or (n, n_records)
    c, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return c.T


@dataclass(frozen=True, eq=False)
class Approximation:
    """Result of :func:`approximate`: the model and its errors on the data grid.

    Parameters
    ----------
    model : KautzModel
        The approximant.
    kind : {'impulse', 'step'}
        Which response the errors refer to.
    ise : float
        Integral of the squared error over the record (quadrature on the grid).
    mse : float
        Mean squared error over the samples.
    fit_percent : float
        Fit percent (MATLAB ``compare`` definition) of the same signal.
    """

    model: KautzModel
    kind: str
    ise: float
    mse: float
    fit_percent: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: coefficients, poles, ise, mse, fit_percent, kind."""
        return {
            "coefficients": self.model.coefficients.tolist(),
            "poles": [[float(p.real), float(p.imag)] for p in self.model.poles],
            "dt": self.model.dt,
            "kind": self.kind,
            "ise": self.ise,
            "mse": self.mse,
            "fit_percent": self.fit_percent,
            "dc_gain": self.model.dc_gain,
        }


def approximate(
    basis: KautzBasis,
    t: ArrayLike,
    h: ArrayLike,
    *,
    kind: str = "impulse",
    method: str = "quadrature",
) -> Approximation:
    """Approximate one sampled impulse or step response in a basis, with its errors.

    Parameters
    ----------
    basis : KautzBasis
        The orthonormal basis.
    t : array-like of shape (n_samples,)
        Strictly increasing sample times.
    h : array-like of shape (n_samples,)
        The record (impulse response, or unit-step response from rest).
    kind : {'impulse', 'step'}, default='impulse'
        What ``h`` is; the errors are reported on the same signal.
    method : {'quadrature', 'lstsq'}, default='quadrature'
        See :func:`project`.

    Returns
    -------
    Approximation

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> t = np.linspace(0, 20, 2001)
    >>> res = kt.approximate(kt.LaguerreBasis(pole=-1, n=3), t, np.exp(-t))
    >>> round(res.fit_percent, 4)
    100.0
    """
    t = check_time(t)
    h = check_records(h, t.size)
    if h.ndim != 1:
        raise DimensionError(f"approximate() takes one record; got shape {h.shape} (use project())")
    c = project(basis, t, h, kind=kind, method=method)
    model = KautzModel(basis, c)
    yhat = model.impulse(t) if kind == "impulse" else model.step(t)
    return Approximation(
        model=model,
        kind=kind,
        ise=float(ise(t, h, yhat)),
        mse=float(mse(h, yhat)),
        fit_percent=float(fit_percent(h, yhat)),
    )


def coefficients_from_system(basis: KautzBasis, system: Any) -> NDArray[np.float64]:
    r"""Exact coefficients of a known LTI system's impulse response (no integration).

    Continuous time solves the Sylvester equation
    :math:`AX + XA_h^T + BB_h^T = 0` and returns :math:`c = XC_h^T`
    (kautz-math.md 5); discrete time the Stein equation
    :math:`X = AXA_h^T + BB_h^T`.

    Parameters
    ----------
    basis : KautzBasis
        Continuous or discrete basis; the system must be of the same time domain
        (and the same ``dt``).
    system : scipy.signal.lti, dlti, control system, (num, den) or (A, B, C, D)
        A stable SISO system.  Tuples are continuous; append ``dt`` for discrete.
        A continuous direct feedthrough ``D`` (an impulse at ``t = 0``) is not in
        :math:`L_2` and is left out, with a warning.

    Returns
    -------
    ndarray of shape (n_functions,)

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> w = np.sqrt(15) / 2
    >>> basis = kt.KautzBasis([-1, -3, -0.5 + 1j * w, -0.5 - 1j * w])
    >>> den = np.poly([-1, -3, -0.5 + 1j * w, -0.5 - 1j * w]).real
    >>> c = kt.coefficients_from_system(basis, ([6.0], den))
    >>> np.round(c, 8)
    array([ 0.1767767 , -0.22963966,  0.22097087,  0.08838835])
    """
    ss = _matching_state_space(basis, system)
    A, B = basis.A, basis.B
    if basis.dt == 0:
        X = scipy.linalg.solve_sylvester(A, ss.A.T, -np.outer(B, ss.B))
        return X @ ss.C
    X = _solve_stein(A, ss.A, np.outer(B, ss.B))
    # pulse response h(0) = D, h(k) = C A^{k-1} B (k >= 1)
    if basis.delayed:
        return X @ ss.C  # sum_{k>=1} A^{k-1} B h(k); the k = 0 term meets F(0) = 0
    return A @ X @ ss.C + B * ss.D


def _solve_stein(A: NDArray, Ah: NDArray, Q: NDArray) -> NDArray[np.float64]:
    """Solve ``X = A X Ah^T + Q`` by its Kronecker form (small sizes)."""
    n, m = Q.shape
    M = np.eye(n * m) - np.kron(Ah, A)  # column-major vec: vec(A X Ah^T) = (Ah kron A) vec X
    x = np.linalg.solve(M, Q.reshape(-1, order="F"))
    return x.reshape((n, m), order="F")


def _matching_state_space(basis: KautzBasis, system: Any):
    ss = as_state_space(system)
    if ss.dt != basis.dt:
        raise DataError(
            f"the system has dt = {ss.dt:g} but the basis has dt = {basis.dt:g}; "
            "both must be continuous (0) or share the sampling period"
        )
    eig = np.linalg.eigvals(ss.A) if ss.A.size else np.zeros(0)
    if basis.dt == 0 and np.any(eig.real >= 0):
        raise DataError("the system is not stable: its impulse response is not square-integrable")
    if basis.dt > 0 and np.any(np.abs(eig) >= 1):
        raise DataError("the system is not stable: its pulse response is not square-summable")
    if basis.dt == 0 and ss.D != 0:
        warnings.warn(
            f"the system has direct feedthrough D = {ss.D:g}; only its strictly proper part "
            "is approximated",
            UserWarning,
            stacklevel=3,
        )
    return ss


def ise_from_system(basis: KautzBasis, system: Any) -> float:
    r"""Exact ISE of the best approximation of a known system in a basis.

    Eq. 7 of the paper via Parseval: :math:`\mathrm{ISE} = \|h\|^2 - \|c\|^2`,
    with :math:`\|h\|^2 = C_h W C_h^T` from a Lyapunov equation; clamped at 0
    against cancellation (kautz-math.md 8.7).

    Parameters
    ----------
    basis : KautzBasis
    system : see :func:`coefficients_from_system`

    Returns
    -------
    float
    """
    c = coefficients_from_system(basis, system)
    ss = as_state_space(system)
    BBt = np.outer(ss.B, ss.B)
    if basis.dt == 0:
        W = scipy.linalg.solve_continuous_lyapunov(ss.A, -BBt)
        energy = ss.C @ W @ ss.C
    else:
        W = scipy.linalg.solve_discrete_lyapunov(ss.A, BBt)
        energy = ss.C @ W @ ss.C + ss.D**2
    return float(max(energy - c @ c, 0.0))


def impulse_to_step(t: ArrayLike, h: ArrayLike) -> NDArray[np.float64]:
    """Step response from an impulse response by cumulative Simpson integration.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing times; the integral starts at ``t[0]`` with value 0.
    h : array-like of shape (n_samples,) or (n_records, n_samples)

    Returns
    -------
    ndarray of the shape of ``h``
    """
    t = check_time(t, min_samples=3)
    h = check_records(h, t.size)
    return scipy.integrate.cumulative_simpson(h, x=t, axis=-1, initial=0.0)


def step_to_impulse(
    t: ArrayLike, y: ArrayLike, *, window: int | None = None, polyorder: int = 3
) -> NDArray[np.float64]:
    """Impulse response from a step response by noise-robust differentiation.

    On a uniform grid this is the Savitzky-Golay derivative (a local least-squares
    polynomial of degree ``polyorder`` over ``window`` samples), which smooths
    white noise instead of amplifying it.  On a non-uniform grid it falls back
    to second-order finite differences (``numpy.gradient``), which amplify noise:
    resample first if the record is noisy.  Where possible avoid the conversion:
    :func:`project` takes step data directly.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing times.
    y : array-like of shape (n_samples,) or (n_records, n_samples)
        Unit-step response(s).
    window : int, optional
        Odd window length in samples; default about 2 % of the record, at least
        ``polyorder + 2``.
    polyorder : int, default=3
        Degree of the local polynomial.

    Returns
    -------
    ndarray of the shape of ``y``
    """
    t = check_time(t, min_samples=3)
    y = check_records(y, t.size, name="y")
    h = uniform_step(t)
    if h is None:
        return np.gradient(y, t, axis=-1)
    if window is None:
        window = max(polyorder + 2, int(0.02 * t.size))
    window = int(window) | 1  # make odd
    if window > t.size:
        raise DataError(f"window = {window} is longer than the record ({t.size} samples)")
    if polyorder >= window:
        raise DataError(f"polyorder = {polyorder} must be smaller than window = {window}")
    return scipy.signal.savgol_filter(
        y, window, polyorder, deriv=1, delta=h, axis=-1, mode="interp"
    )
