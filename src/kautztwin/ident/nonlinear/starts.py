"""Starting poles of the nonlinear models: a least-squares ARX fit, its poles clipped stable.

The study behind this package found that the Kautz poles of a resonant plant must start
near its resonance (the lightly damped ARX poles of the hydraulic actuator), after which the
gradient or variable-projection search refines them; a start far away settles in a poor
local minimum.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .filters import filter_bank_states

__all__ = ["arx_poles", "start_poles"]

#: radius range the starting poles are clipped to
_R_MIN, _R_MAX = 0.05, 0.99


def arx_poles(
    u: NDArray, y: NDArray, n_poles: int, use: NDArray | None = None
) -> NDArray[np.complex128]:
    """Poles of an ARX(``n_poles``, ``n_poles``, 1) least-squares fit, clipped into the disc.

    Parameters
    ----------
    u, y : ndarray of shape (n_samples,)
        Standardised input and output.
    n_poles : int
        Number of poles.
    use : ndarray of bool, optional
        Outputs that may be used (held-out samples excluded); a regression row needs its
        output and its lagged outputs in ``use``.

    Returns
    -------
    ndarray of complex, shape (n_poles,)
        Radii clipped to ``[0.05, 0.99]``; complex poles come with their conjugates.
    """
    n = u.size
    na = n_poles
    rows = n - na
    Phi = np.empty((rows, 2 * na + 1))
    for i in range(1, na + 1):
        Phi[:, i - 1] = -y[na - i : n - i]
        Phi[:, na + i - 1] = u[na - i : n - i]
    Phi[:, -1] = 1.0
    ok = np.ones(rows, dtype=bool)
    if use is not None:
        for i in range(na + 1):
            ok &= use[na - i : n - i]
    theta, *_ = np.linalg.lstsq(Phi[ok], y[na:][ok], rcond=None)
    roots = np.roots(np.concatenate([[1.0], theta[:na]]))
    out = []
    for r in roots:
        mag = abs(r)
        if mag < 1e-12:
            r, mag = complex(_R_MIN), _R_MIN
        scale = min(max(mag, _R_MIN), _R_MAX) / mag
        if abs(r.imag) < 1e-9:
            out.append(complex(r.real * scale))
        elif r.imag > 0:
            z = r * scale
            out += [z, z.conjugate()]
    return np.asarray(out, dtype=complex)


def _grid(n_poles: int) -> list[NDArray[np.complex128]]:
    """Repeated pairs ``r e^{+-j theta}`` (a real pole ``r`` for an odd count)."""
    out = []
    for r in (0.8, 0.9, 0.95, 0.98):
        for th in (0.05, 0.2, 0.5):
            z = r * np.exp(1j * th)
            p = [z, z.conjugate()] * (n_poles // 2) + [complex(r)] * (n_poles % 2)
            out.append(np.asarray(p))
    return out


def start_poles(u: NDArray, y: NDArray, n_poles: int, use: NDArray) -> NDArray[np.complex128]:
    """The best of the ARX poles and a small grid, judged by a linear Kautz output-error fit.

    Each candidate's bank states (started at the steady state of ``u[0]``) are fitted to
    ``y`` by linear least squares on the samples in ``use``; the candidate with the smallest
    residual is returned.

    Parameters
    ----------
    u, y : ndarray of shape (n_samples,)
        Standardised input and output.
    n_poles : int
    use : ndarray of bool
        Samples the fit may use.

    Returns
    -------
    ndarray of complex, shape (n_poles,)
    """
    best, best_cost = None, np.inf
    for poles in [arx_poles(u, y, n_poles, use), *_grid(n_poles)]:
        X = filter_bank_states(poles, u, u[0])[use]
        Phi = np.column_stack([np.ones(X.shape[0]), X])
        theta, *_ = np.linalg.lstsq(Phi, y[use], rcond=None)
        cost = float(np.sum((y[use] - Phi @ theta) ** 2))
        if cost < best_cost:
            best, best_cost = poles, cost
    return best
