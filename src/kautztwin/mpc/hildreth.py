r"""Hildreth's dual quadratic programming iteration (Wang 2009), dependency-free.

A fallback for :class:`~kautztwin.mpc.MPCProblem` when DAQP is not wanted, and
a reference implementation of the method in kautz-math.md 6.3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError, DimensionError

__all__ = ["HildrethResult", "hildreth"]


@dataclass(frozen=True, eq=False)
class HildrethResult:
    """Result of :func:`hildreth`.

    Parameters
    ----------
    x : ndarray of shape (n,)
        Primal solution (a compromise when ``converged`` is False).
    lam : ndarray of shape (m,)
        Lagrange multipliers of the rows of ``M`` (zero for rows dropped
        because their bound is ``+inf``).
    iterations : int
        Gauss-Seidel sweeps performed (0 if the unconstrained optimum is feasible).
    converged : bool
        Whether the multipliers met the tolerance within ``max_iter`` sweeps.
        Non-convergence usually means that the constraints are infeasible.
    message : str
        Short explanation.

    See Also
    --------
    hildreth : The solver.
    """

    x: NDArray[np.float64]
    lam: NDArray[np.float64]
    iterations: int
    converged: bool
    message: str

    def __post_init__(self) -> None:
        for name in ("x", "lam"):
            a = np.array(getattr(self, name), dtype=float, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)


def hildreth(
    E: ArrayLike,
    F: ArrayLike,
    M: ArrayLike,
    gamma: ArrayLike,
    *,
    max_iter: int = 5000,
    tol: float = 1e-12,
    lam0: ArrayLike | None = None,
) -> HildrethResult:
    r"""Solve :math:`\min_x \tfrac12 x^TEx + x^TF` subject to :math:`Mx \le \gamma`.

    Parameters
    ----------
    E : array-like of shape (n, n)
        Symmetric positive definite Hessian.
    F : array-like of shape (n,)
        Linear term.
    M : array-like of shape (m, n)
        Constraint matrix.
    gamma : array-like of shape (m,)
        Upper bounds; rows with ``+inf`` are ignored.
    max_iter : int, default=5000
        Maximum number of Gauss-Seidel sweeps over the multipliers.
    tol : float, default=1e-12
        Stop when :math:`\|\lambda - \lambda_{prev}\| \le tol\,\max(1, \|\lambda\|)`.
    lam0 : array-like of shape (m,), optional
        Initial multipliers (warm start); default zeros.

    Returns
    -------
    HildrethResult

    Raises
    ------
    DimensionError
        If the shapes do not fit.
    DataError
        If ``E`` is not positive definite, a bound is NaN or ``-inf``, or ``max_iter < 1``.

    See Also
    --------
    kautztwin.mpc.MPCProblem : Uses this with ``solver='hildreth'``.

    Notes
    -----
    The dual of the QP is :math:`\min_{\lambda\ge0}\tfrac12\lambda^TH\lambda + \lambda^TK`
    with :math:`H = ME^{-1}M^T`, :math:`K = \gamma + ME^{-1}F`.  Each sweep
    updates, in place,

    .. math::

        \lambda_i \leftarrow \max\Big(0,\ -\frac{K_i + \sum_{l\ne i}H_{il}\lambda_l}{H_{ii}}\Big),

    and finally :math:`x = -E^{-1}(F + M^T\lambda)`.  The iteration converges
    linearly for feasible problems; if the constraints conflict the multipliers
    grow without bound and the last iterate is returned as a compromise with
    ``converged=False``.

    References
    ----------
    L. Wang, *Model Predictive Control System Design and Implementation Using
    MATLAB*, Springer, 2009, section 2.4.

    Examples
    --------
    >>> from kautztwin.mpc import hildreth
    >>> res = hildreth([[2.0, 0.0], [0.0, 2.0]], [-2.0, -2.0], [[1.0, 1.0]], [1.0])
    >>> res.x.round(6), res.converged
    (array([0.5, 0.5]), True)
    """
    E = np.atleast_2d(np.asarray(E, dtype=float))
    n = E.shape[0]
    if E.shape != (n, n):
        raise DimensionError(f"E must be square, got shape {E.shape}")
    F = np.asarray(F, dtype=float).reshape(-1)
    if F.size != n:
        raise DimensionError(f"F has {F.size} entries but E is {n} x {n}")
    M = np.asarray(M, dtype=float).reshape(-1, n)
    gamma = np.asarray(gamma, dtype=float).reshape(-1)
    if gamma.size != M.shape[0]:
        raise DimensionError(f"gamma has {gamma.size} entries but M has {M.shape[0]} rows")
    if np.any(np.isnan(gamma)) or np.any(gamma == -np.inf):
        raise DataError("gamma must not contain NaN or -inf")
    if isinstance(max_iter, bool) or int(max_iter) < 1:
        raise DataError(f"max_iter must be a positive integer, got {max_iter!r}")
    try:
        cho = scipy.linalg.cho_factor(E)
    except np.linalg.LinAlgError as exc:
        raise DataError("E must be symmetric positive definite") from exc
    x_unc = -scipy.linalg.cho_solve(cho, F)
    m_all = M.shape[0]
    lam_all = np.zeros(m_all)
    rows = np.flatnonzero(np.isfinite(gamma))
    Mr, g = M[rows], gamma[rows]
    if rows.size == 0 or np.all(Mr @ x_unc <= g):
        return HildrethResult(x_unc, lam_all, 0, True, "unconstrained optimum is feasible")
    EinvMt = scipy.linalg.cho_solve(cho, Mr.T)
    H = Mr @ EinvMt
    K = g - Mr @ x_unc  # gamma + M E^{-1} F
    lam = np.zeros(rows.size) if lam0 is None else np.maximum(np.asarray(lam0, float)[rows], 0.0)
    diag = np.diag(H).copy()
    active = diag > 1e-14 * max(1.0, float(np.max(np.abs(diag))))
    idx = np.flatnonzero(active)
    Hrows = [H[i] for i in range(rows.size)]
    converged = False
    it = 0
    while it < int(max_iter):
        it += 1
        lam_prev = lam.copy()
        for i in idx:
            w = -(K[i] + Hrows[i] @ lam - diag[i] * lam[i]) / diag[i]
            lam[i] = w if w > 0.0 else 0.0
        step = float(np.linalg.norm(lam - lam_prev))
        if step <= tol * max(1.0, float(np.linalg.norm(lam))):
            converged = True
            break
    lam_all[rows] = lam
    x = x_unc - EinvMt @ lam
    msg = (
        f"converged in {it} sweeps"
        if converged
        else f"no convergence in {max_iter} sweeps (the constraints may be infeasible)"
    )
    return HildrethResult(x, lam_all, it, converged, msg)
