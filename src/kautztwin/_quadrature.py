"""Quadrature weights on arbitrary (also non-uniform) sample grids.

``integral f dt ~= weights @ f``.  Having the weights as a vector turns the
projection of many records onto a basis into one matrix product.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .exceptions import DataError

__all__ = ["least_squares_weights", "quadrature_weights"]


def _trapezoid(t: NDArray) -> NDArray[np.float64]:
    h = np.diff(t)
    w = np.zeros_like(t)
    w[:-1] += h / 2
    w[1:] += h / 2
    return w


def _simpson(t: NDArray) -> NDArray[np.float64]:
    """Composite Simpson weights for a non-uniform grid.

    Pairs of intervals get the parabola through their three points; with an
    odd number of intervals the last interval is integrated with the parabola
    through the last three points (the same rule as ``scipy.integrate.simpson``).
    """
    n = t.size
    if n < 3:
        return _trapezoid(t)
    h = np.diff(t)
    w = np.zeros_like(t)
    n_pairs = (n - 1) // 2
    h0 = h[0 : 2 * n_pairs : 2]
    h1 = h[1 : 2 * n_pairs : 2]
    s = h0 + h1
    idx = 2 * np.arange(n_pairs)
    np.add.at(w, idx, s / 6 * (2 - h1 / h0))
    np.add.at(w, idx + 1, s**3 / (6 * h0 * h1))
    np.add.at(w, idx + 2, s / 6 * (2 - h0 / h1))
    if (n - 1) % 2 == 1:  # one interval left over at the end
        h0, h1 = h[-2], h[-1]
        w[-1] += (2 * h1**2 + 3 * h0 * h1) / (6 * (h0 + h1))
        w[-2] += (h1**2 + 3 * h0 * h1) / (6 * h0)
        w[-3] -= h1**3 / (6 * h0 * (h0 + h1))
    return w


def quadrature_weights(t: NDArray, rule: str = "simpson") -> NDArray[np.float64]:
    """Weights ``w`` with ``integral_{t[0]}^{t[-1]} f dt ~= w @ f(t)``.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
        Strictly increasing sample times (uniform or not).
    rule : {'simpson', 'trapezoid'}, default='simpson'
        Composite Simpson (error O(h^4)) or trapezoid (O(h^2), always positive weights).

    Returns
    -------
    ndarray of shape (n_samples,)
    """
    if rule == "simpson":
        return _simpson(t)
    if rule == "trapezoid":
        return _trapezoid(t)
    # DataError (a ValueError) so that project(rule=...) and ise(rule=...) report it
    # like every other bad option, as a KautzTwinError
    raise DataError(f"rule must be 'simpson' or 'trapezoid', got {rule!r}")


def least_squares_weights(t: NDArray) -> NDArray[np.float64]:
    """Positive quadrature weights for weighted least squares on the grid ``t``.

    Simpson's weights where they are all positive (always on uniform grids),
    else the trapezoid rule's, so the weighted residual norm is a quadrature of
    the squared error of order 4 where possible and 2 otherwise.
    """
    w = _simpson(t)
    return w if np.all(w > 0) else _trapezoid(t)
