r"""Refinement of the network's poles: variable projection with the network as a prior.

Plain variable projection (:func:`kautztwin.optimize_poles`) minimises the residual of
the record alone.  On a short record with strong coloured noise a ``max_order``-function
basis has more freedom than the plant (five poles and five coefficients for a
seven-parameter plant), and the residual's minimum often sits at poles that fit the
noise: a lightly damped pair tracing a slow noise swing.  The refinement here is the
maximum a-posteriori version of the same search: the coefficients are still the exact
least-squares solution for given poles (variable projection), and the poles minimise

.. math:: \frac{\|W (y - K(\theta)^T c(\theta))\|^2}{\hat\sigma^2}
          + \frac{\|\log\theta - \log\theta_{\mathrm{net}}\|^2}{s^2},

with :math:`W` the AR(1) whitening filter of the noise (its pole :math:`\hat a` and the
innovation scale :math:`\hat\sigma` estimated from the residual of the network's fit),
:math:`\theta` the second-order-block parameters :math:`(b, \sqrt c)` and real rates (so
a block crosses freely between two real poles and a complex pair), and :math:`s` the
prior scale of the network's log-parameter error (``prior_scale``).  ``prior_scale =
inf`` is whitened variable projection without a prior.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.optimize
import torch
from numpy.typing import NDArray

from ..kautz_torch import propagate
from .network import HIGH, LOW, QUAD, block_matrices, block_roots

__all__ = ["noise_model", "refine_map", "theta_from_poles"]

_MAX_AR = 0.98  # largest AR(1) pole of the estimated noise


def theta_from_poles(kinds: Sequence[str], poles: NDArray[np.complex128]) -> NDArray[np.float64]:
    """Block parameters ``(b, sqrt(c))`` / ``p`` that hold given pole locations.

    Complex pairs fill the second-order blocks first, then real poles in pairs of
    neighbouring rates; the real block (odd orders) takes the slowest real pole left.

    Parameters
    ----------
    kinds : sequence of {'quad', 'real'}
    poles : ndarray of complex, shape (n_functions,)
        Conjugate pairs complete; as many poles as the blocks hold.

    Returns
    -------
    ndarray of shape (n_params,)

    Examples
    --------
    >>> theta_from_poles(("quad", "real"), np.array([-1.0, -2.0, -5.0])).round(6).tolist()
    [7.0, 3.162278, 1.0]
    """
    poles = np.asarray(poles, dtype=complex)
    pairs = sorted((p for p in poles if p.imag > 0), key=abs)
    reals = sorted(-p.real for p in poles if p.imag == 0)
    n_quad = sum(1 for k in kinds if k == QUAD)
    single = [reals.pop(0)] if len(kinds) > n_quad else []
    quads = [(2.0 * -p.real, abs(p)) for p in pairs]
    while len(quads) < n_quad:
        r1, r2 = reals.pop(0), reals.pop(0)
        quads.append((r1 + r2, float(np.sqrt(r1 * r2))))
    out: list[float] = []
    for kind in kinds:
        out += list(quads.pop(0)) if kind == QUAD else [single.pop(0)]
    return np.array(out, dtype=float)


def _whiten(x: NDArray, a: float) -> NDArray:
    """Innovations of AR(1) noise with pole ``a`` along the last axis (unit-variance scale)."""
    w = np.empty_like(x)
    w[..., 0] = x[..., 0]
    w[..., 1:] = (x[..., 1:] - a * x[..., :-1]) / np.sqrt(1.0 - a * a)
    return w


def noise_model(residual: NDArray[np.float64]) -> tuple[float, float]:
    """AR(1) pole and innovation scale of a residual (lag-1 autocorrelation, clipped).

    Parameters
    ----------
    residual : ndarray of shape (n_samples,)

    Returns
    -------
    a : float
        In ``[0, 0.98]``.
    sigma : float
        Standard deviation of the whitened residual (``> 0``).
    """
    e = residual - residual.mean()
    den = float(e @ e)
    a = float(np.clip((e[1:] @ e[:-1]) / den, 0.0, _MAX_AR)) if den > 0 else 0.0
    sigma = float(np.std(_whiten(residual, a)))
    return a, max(sigma, 1e-12 * max(float(np.abs(residual).max()), 1e-300))


def _design(kinds: Sequence[str], theta: NDArray, t: NDArray) -> NDArray[np.float64]:
    A, B = block_matrices(kinds, torch.as_tensor(theta[None], dtype=torch.float64))
    return propagate(A, B, t)[0].numpy()


def refine_map(
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    kinds: Sequence[str],
    theta0: NDArray[np.float64],
    fitted0: NDArray[np.float64],
    *,
    prior_scale: float,
    max_iter: int,
    tol: float,
    rounds: int = 1,
) -> NDArray[np.complex128]:
    """Maximum a-posteriori poles of one record, started and centred at the network's.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
    y : ndarray of shape (n_samples,)
        The record.
    kinds : sequence of {'quad', 'real'}
    theta0 : ndarray of shape (n_params,)
        The network's block parameters (plant units): the start and the prior's centre.
    fitted0 : ndarray of shape (n_samples,)
        The least-squares fit on the network's basis (its residual sets the noise model).
    prior_scale : float
        Prior standard deviation of each log block parameter (``inf``: no prior).
    max_iter : int
        Residual evaluations per parameter.
    tol : float
        ``ftol``, ``xtol`` and ``gtol`` of the solver.
    rounds : int, default=1
        Searches; the noise model of each is re-estimated from the residual of the
        previous one (the first from the network's fit, whose residual also holds the
        network's approximation error and so overstates the noise of a clean record).

    Returns
    -------
    ndarray of complex, shape (n_functions,)
        Pole locations of the refined blocks.
    """
    span = float(t[-1])
    lo = np.full(theta0.size, np.log(LOW / span))
    hi = np.full(theta0.size, np.log(HIGH / span))
    phi0 = np.clip(np.log(theta0), lo + 1e-9, hi - 1e-9)
    inv_s = 0.0 if not np.isfinite(prior_scale) else 1.0 / float(prior_scale)
    x = phi0
    fitted = fitted0
    for _ in range(max(int(rounds), 1)):
        a, sigma = noise_model(y - fitted)
        yw = _whiten(y, a) / sigma

        def residual(phi: NDArray, a: float = a, sigma: float = sigma,
                     yw: NDArray = yw) -> NDArray:
            Kw = _whiten(_design(kinds, np.exp(phi), t), a).T / sigma  # (n, N)
            c, *_ = np.linalg.lstsq(Kw, yw, rcond=None)
            r = yw - Kw @ c
            return np.concatenate([r, inv_s * (phi - phi0)]) if inv_s else r

        sol = scipy.optimize.least_squares(residual, x, bounds=(lo, hi), method="trf",
                                           ftol=tol, xtol=tol, gtol=tol,
                                           max_nfev=int(max_iter) * (phi0.size + 1))
        x = sol.x
        K = _design(kinds, np.exp(x), t)
        fitted = np.linalg.lstsq(K.T, y, rcond=None)[0] @ K
    return block_roots(kinds, np.exp(x)[None])[0]
