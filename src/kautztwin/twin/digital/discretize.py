"""Zero-order-hold discretisation of a Kautz model onto the twin's delayed discrete basis."""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_positive
from ...approx.model import KautzModel
from ...basis import KautzBasis
from ...exceptions import DataError

__all__ = ["discretize_model"]


def _delayed_basis(poles: ArrayLike | KautzBasis, dt: float) -> KautzBasis:
    """A delayed discrete basis on ``dt`` from discrete poles or a (continuous) basis."""
    if isinstance(poles, KautzBasis):
        if not poles.is_discrete:
            poles = poles.discretize(dt)
        elif abs(poles.dt - dt) > 1e-12 * dt:
            raise DataError(f"the basis has dt = {poles.dt:g} but the twin samples at dt = {dt:g}")
        return KautzBasis._from_blocks(poles.block_kinds, poles._params, dt, True)
    return KautzBasis(poles, dt=dt, delayed=True)


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
    >>> from kautztwin.twin.digital import discretize_model
    >>> m = kt.KautzModel(kt.KautzBasis([-2.0]), [2.0])   # 4 / (s + 2)
    >>> md = discretize_model(m, 0.1)
    >>> md.basis.delayed, round(md.dc_gain, 10), round(m.dc_gain, 10)
    (True, 2.0, 2.0)
    """
    dt = check_positive(dt, "dt")
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

