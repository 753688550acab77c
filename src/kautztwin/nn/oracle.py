"""The statistical-limit reference: nonlinear least squares in the true model structure.

No estimator that sees only a noisy record can do systematically better than
fitting the *true* parametric model to it by least squares (the maximum
likelihood estimate under white Gaussian noise), started at the true
parameters so that it cannot get lost in a local minimum.  :func:`oracle_fit`
does exactly that; it needs the true parameters, so it is a benchmark
reference (the "oracle"), not an estimator for real data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from .._validation import check_records, check_time
from ..basis._propagate import continuous_functions, uniform_step
from ..datasets import ParametricSystem
from ..exceptions import DataError, DimensionError

__all__ = ["OracleFit", "oracle_fit", "simulate_parametric"]

_KINDS = ("impulse", "step")


@dataclass(frozen=True, eq=False)
class OracleFit:
    """Result of :func:`oracle_fit`.

    Parameters
    ----------
    parameters : ndarray of shape (n_parameters,)
        Fitted parameter vector, in the order of ``system.parameter_names``.
    response : ndarray of shape (n_samples,)
        Noise-free response of the fitted model on the record's grid.
    cost : float
        Half the sum of squared residuals at the solution.
    n_evaluations : int
        Model simulations (residual evaluations, the finite-difference
        Jacobian included).
    success : bool
        Whether the solver met its tolerance.
    """

    parameters: NDArray[np.float64]
    response: NDArray[np.float64]
    cost: float
    n_evaluations: int
    success: bool


def _state_space(num: NDArray, den: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Controllable canonical form of a strictly proper ``num / den`` (monic ``den``)."""
    n = den.size - 1
    A = np.zeros((n, n))
    A[0, :] = -den[1:]
    if n > 1:
        A[1:, :-1] = np.eye(n - 1)
    B = np.zeros(n)
    B[0] = 1.0
    C = np.zeros(n)
    C[n - num.size :] = num
    return A, B, C


def _propagate(A: NDArray, B: NDArray, t: NDArray) -> NDArray[np.float64]:
    """``e^{At} B`` on the grid: doubling with squared one-step exponentials if uniform."""
    h = uniform_step(t)
    if h is None:
        return continuous_functions(A[None], B[None], t)[0]
    first = B if t[0] == 0 else scipy.linalg.expm(A * t[0]) @ B
    F = np.empty((B.size, t.size))
    F[:, 0] = first
    E = scipy.linalg.expm(A * h)  # e^{A h m} for m = 1, 2, 4, ... by squaring
    m = 1
    while m < t.size:
        take = min(m, t.size - m)
        F[:, m : m + take] = E @ F[:, :take]
        m += take
        E = E @ E
    return F


def _simulate(system: ParametricSystem, p: NDArray, t: NDArray, kind: str) -> NDArray[np.float64]:
    num, den = system._build(p, system.order)  # no stability check: iterates may leave the region
    if num.size >= den.size:
        raise DataError(
            f"{system.name!r} is biproper at these parameters; its impulse response has a "
            "Dirac at t = 0"
        )
    A, B, C = _state_space(num, den)
    F = _propagate(A, B, t)
    if kind == "step":
        F = np.linalg.solve(A, F - B[:, None])
    return C @ F


def simulate_parametric(
    system: ParametricSystem, parameters: ArrayLike, t: ArrayLike, *, kind: str = "impulse"
) -> NDArray[np.float64]:
    r"""Exact impulse or unit-step response of a parametric system at one parameter vector.

    The transfer function is realised in controllable canonical form
    ``(A, B, C)`` and :math:`h(t) = C e^{At} B` (or
    :math:`y(t) = C A^{-1}(e^{At} - I) B`) is evaluated with exact
    matrix-exponential stepping on the grid (no ODE solver).  No stability
    check is made, so optimisers may pass through unstable parameters.

    Parameters
    ----------
    system : ParametricSystem
        The parametric model.
    parameters : array-like of shape (n_parameters,)
        Parameter values.
    t : array-like of shape (n_samples,)
        Strictly increasing sample times, ``t[0] >= 0``.
    kind : {'impulse', 'step'}, default='impulse'
        Which response.

    Returns
    -------
    ndarray of shape (n_samples,)

    Raises
    ------
    DataError
        On a bad grid, an unknown kind, or a biproper system.
    DimensionError
        If ``parameters`` has the wrong length.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.datasets import paper_system
    >>> from kautztwin.nn.oracle import simulate_parametric
    >>> t = np.linspace(0.0, 20.0, 900)
    >>> h = simulate_parametric(paper_system(), [6.0, 1.0, 3.0, 2.0, 0.25], t)
    >>> round(float(h[0]), 12), h.shape
    (0.0, (900,))
    """
    if kind not in _KINDS:
        raise DataError(f"kind must be 'impulse' or 'step', got {kind!r}")
    t = check_time(t)
    if t[0] < 0:
        raise DataError(f"t must start at t[0] >= 0, got t[0] = {t[0]:g}")
    return _simulate(system, system._vector(parameters), t, kind)


def oracle_fit(
    t: ArrayLike,
    record: ArrayLike,
    system: ParametricSystem,
    true_parameters: ArrayLike,
    kind: str = "impulse",
    *,
    tol: float = 1e-10,
    max_iter: int = 100,
) -> OracleFit:
    r"""Least-squares fit of the true model structure, started at the true parameters.

    Minimises :math:`\sum_k (y_k - \hat y(t_k; \theta))^2` over the parameters
    :math:`\theta` of ``system`` with ``scipy.optimize.least_squares``
    (Levenberg-Marquardt, finite-difference Jacobian), simulating the model
    exactly (:func:`simulate_parametric`).  Under white Gaussian noise this is
    the maximum-likelihood estimate; started at the truth it finds the
    minimum next to it, so its fit to the noise-free response is the
    statistical limit that any estimator of this record can reach.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times, ``t[0] >= 0``.
    record : array-like of shape (n_samples,)
        One measured (noisy) impulse or unit-step response.
    system : ParametricSystem
        The true model structure.
    true_parameters : array-like of shape (n_parameters,)
        The parameters that generated the record (the starting point).
    kind : {'impulse', 'step'}, default='impulse'
        What the record is.
    tol : float, default=1e-10
        ``ftol``, ``xtol`` and ``gtol`` of the solver.
    max_iter : int, default=100
        Budget of residual evaluations per parameter.

    Returns
    -------
    OracleFit
        Fitted parameters and the noise-free response of the fitted model.

    Raises
    ------
    DataError
        On NaN/inf, a bad grid, an unknown kind, or a biproper system.
    DimensionError
        If ``record`` is not one record on the grid ``t``, or
        ``true_parameters`` has the wrong length.

    See Also
    --------
    kautztwin.optimize_poles : The structure-free counterpart (variable projection on Kautz poles).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.datasets import paper_system
    >>> from kautztwin.nn.oracle import oracle_fit, simulate_parametric
    >>> system = paper_system()
    >>> t = np.linspace(0.0, 20.0, 900)
    >>> truth = [5.0, 1.2, 2.5, 1.8, 0.3]
    >>> clean = simulate_parametric(system, truth, t)
    >>> noisy = clean + 0.01 * np.random.default_rng(0).standard_normal(t.size)
    >>> res = oracle_fit(t, noisy, system, truth)
    >>> bool(np.linalg.norm(res.response - clean) < np.linalg.norm(noisy - clean))
    True
    """
    if kind not in _KINDS:
        raise DataError(f"kind must be 'impulse' or 'step', got {kind!r}")
    if not isinstance(system, ParametricSystem):
        raise DataError(f"system must be a ParametricSystem, got {type(system).__name__}")
    t = check_time(t, min_samples=3)
    if t[0] < 0:
        raise DataError(f"t must start at t[0] >= 0, got t[0] = {t[0]:g}")
    y = check_records(record, t.size, name="record")
    if y.ndim != 1:
        raise DimensionError(f"record must be one 1-D record; got shape {y.shape}")
    x0 = system._vector(true_parameters)
    count = [0]
    big = 1e6 * (1.0 + float(np.max(np.abs(y))))

    def residual(p: NDArray) -> NDArray:
        count[0] += 1
        with np.errstate(all="ignore"):
            yhat = _simulate(system, p, t, kind)
        r = yhat - y
        if not np.all(np.isfinite(r)):
            return np.full(t.size, big)
        return r

    sol: Any = scipy.optimize.least_squares(
        residual,
        x0,
        method="lm",
        x_scale="jac",
        ftol=tol,
        xtol=tol,
        gtol=tol,
        max_nfev=max_iter * (x0.size + 1),
    )
    p = np.asarray(sol.x, dtype=float)
    return OracleFit(
        parameters=p,
        response=_simulate(system, p, t, kind),
        cost=float(sol.cost),
        n_evaluations=count[0],
        success=bool(sol.success),
    )
