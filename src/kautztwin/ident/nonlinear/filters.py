r"""The discrete Kautz filter bank of the nonlinear models, in numpy and as a torch recursion.

Every nonlinear model of :mod:`kautztwin.ident.nonlinear` drives one orthonormal
discrete Kautz network (kautz-math.md 3.2, :func:`kautztwin.basis._blocks.discrete_matrices`)

.. math::

    x(k+1) = A x(k) + B v(k)

with each channel of a signal ``v`` (the input, or the outputs of a static input map).  The
state at sample ``k`` only depends on ``v`` before ``k`` (the delayed basis), so every model
is strictly proper.  The initial state is the steady state of a constant input *level*
:math:`\ell` held before the record (one parameter per record instead of ``n`` states):

.. math::

    x(k) = (I - A)^{-1} B\,\ell + \sum_{j=0}^{k-1} A^j B\,\bigl(v(k-1-j) - \ell\bigr).

Both implementations compute exactly this: the impulse sequence ``A^j B`` by repeated
doubling and the sum by an FFT convolution.  The torch one is differentiable in the pole
parameters, the level and ``v`` (gradients flow through the whole filter recursion).

Pole parameters are unconstrained reals mapped to stable poles, one or two per block:
a real block ``xi = R tanh(a)``, a pair ``r e^{\pm j\theta}`` with ``r = R sigmoid(a)``
and ``theta = pi sigmoid(b)``; ``R = 0.999``.  torch is imported inside the functions that
need it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ...basis._blocks import REAL, discrete_matrices, parse_poles

__all__ = [
    "MAX_RADIUS",
    "bank_matrices",
    "filter_bank_states",
    "poles_from_raw",
    "raw_from_poles",
    "require_torch",
    "torch_bank_matrices",
    "torch_bank_states",
    "torch_poles_params",
]

#: largest pole radius the unconstrained parametrisation reaches
MAX_RADIUS = 0.999


def require_torch() -> Any:
    """Import torch, or raise a one-line ``ImportError`` that names the extra to install.

    Returns
    -------
    module
        The ``torch`` module.

    Raises
    ------
    ImportError
        If PyTorch is not installed.
    """
    try:
        import torch
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "this nonlinear model is trained with PyTorch, which is not installed: "
            "pip install 'kautztwin[nn]'"
        ) from None
    return torch


# --------------------------------------------------------------------------- parametrisation
def _logit(p: float) -> float:
    p = min(max(p, 1e-9), 1 - 1e-9)
    return math.log(p / (1 - p))


def raw_from_poles(poles: ArrayLike) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    """Block kinds and unconstrained parameters of discrete poles.

    Parameters
    ----------
    poles : array-like of complex
        Discrete poles, ``|p| < 1``; each complex pole with its conjugate.  Radii beyond
        ``0.99 MAX_RADIUS`` are pulled in to it so that the parametrisation stays smooth.

    Returns
    -------
    kinds : tuple of {'real', 'pair'}
    raw : ndarray of shape (n_poles,)

    Raises
    ------
    PoleError
        If a pole is invalid (unstable, no conjugate partner).
    """
    kinds, params = parse_poles(poles, 1.0)
    raw, col, lim = [], 0, 0.99 * MAX_RADIUS
    for kind in kinds:
        if kind == REAL:
            xi = float(np.clip(params[col], -lim, lim))
            raw.append(math.atanh(xi / MAX_RADIUS))
            col += 1
        else:
            z = complex(params[col], params[col + 1])
            r = min(abs(z), lim)
            raw += [_logit(r / MAX_RADIUS), _logit(np.angle(z) / math.pi)]
            col += 2
    return kinds, np.asarray(raw, dtype=float)


def _sigmoid(x: float) -> float:
    """The logistic function, without overflow for any finite ``x``."""
    return 0.5 * (1.0 + math.tanh(0.5 * x))


def _block_params(kinds: tuple[str, ...], raw: NDArray) -> NDArray[np.float64]:
    """Discrete block parameters ``[xi]`` / ``[x, y]`` of unconstrained parameters (numpy)."""
    out = np.empty(len(raw))
    col = 0
    for kind in kinds:
        if kind == REAL:
            out[col] = MAX_RADIUS * math.tanh(raw[col])
            col += 1
        else:
            r = MAX_RADIUS * _sigmoid(raw[col])
            th = math.pi * _sigmoid(raw[col + 1])
            out[col], out[col + 1] = r * math.cos(th), r * math.sin(th)
            col += 2
    return out


def poles_from_raw(kinds: tuple[str, ...], raw: ArrayLike) -> NDArray[np.complex128]:
    """Discrete pole locations of unconstrained parameters (pairs as ``p, conj(p)``).

    Parameters
    ----------
    kinds : tuple of {'real', 'pair'}
        Block structure.
    raw : array-like of shape (n_poles,)
        Unconstrained parameters.

    Returns
    -------
    ndarray of complex, shape (n_poles,)
    """
    par = _block_params(kinds, np.asarray(raw, dtype=float))
    out, col = [], 0
    for kind in kinds:
        if kind == REAL:
            out.append(complex(par[col]))
            col += 1
        else:
            out += [complex(par[col], par[col + 1]), complex(par[col], -par[col + 1])]
            col += 2
    return np.asarray(out)


# --------------------------------------------------------------------------- numpy
def bank_matrices(poles: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Network matrices ``A`` (n x n) and ``B`` (n,) of the discrete Kautz bank of ``poles``.

    Parameters
    ----------
    poles : array-like of complex
        Discrete poles, ``|p| < 1``.

    Returns
    -------
    A : ndarray of shape (n_poles, n_poles)
    B : ndarray of shape (n_poles,)
        ``A A^T + B B^T = I``.
    """
    kinds, params = parse_poles(poles, 1.0)
    A, B = discrete_matrices(kinds, params)
    return A[0], B[0]


def _impulse(A: NDArray, B: NDArray, n: int) -> NDArray[np.float64]:
    """Rows ``A^j B``, ``j = 0..n-1``, by doubling."""
    F = B[None, :].copy()
    P = A.copy()
    while F.shape[0] < n:
        F = np.vstack([F, F @ P.T])
        P = P @ P
    return F[:n]


def filter_bank_states(
    poles: ArrayLike, v: ArrayLike, level: ArrayLike | float = 0.0
) -> NDArray[np.float64]:
    r"""States of the discrete Kautz bank driven by each channel of ``v`` (numpy).

    Parameters
    ----------
    poles : array-like of complex
        Discrete poles, ``|p| < 1``.
    v : array-like of shape (n_samples,) or (n_samples, n_channels)
        Driving signal(s).
    level : float or array-like of shape (n_channels,), default=0.0
        Constant value of each channel before the record: the initial state is its steady
        state.

    Returns
    -------
    ndarray of shape (n_samples, n_channels * n_poles)
        Row ``k`` is the state at sample ``k`` (driven by ``v`` before ``k``), channel by
        channel.

    Raises
    ------
    PoleError
        If a pole is invalid.

    Examples
    --------
    >>> import numpy as np
    >>> X = filter_bank_states([0.5], np.ones(3))       # one real pole: sqrt(0.75) / (z - 0.5)
    >>> np.round(X[:, 0] / np.sqrt(0.75), 4)
    array([0. , 1. , 1.5])
    """
    A, B = bank_matrices(poles)
    v = np.asarray(v, dtype=float)
    v2 = v[:, None] if v.ndim == 1 else v
    n, n_ch = v2.shape
    lvl = np.broadcast_to(np.asarray(level, dtype=float), (n_ch,))
    xss = np.linalg.solve(np.eye(A.shape[0]) - A, B)
    F = np.vstack([np.zeros((1, B.size)), _impulse(A, B, max(n - 1, 1))])[:n]
    w = v2 - lvl[None, :]
    X = scipy.signal.fftconvolve(F[:, None, :], w[:, :, None], axes=0)[:n]
    X = X + lvl[None, :, None] * xss[None, None, :]
    return X.reshape(n, n_ch * B.size)


# --------------------------------------------------------------------------- torch
def torch_poles_params(kinds: tuple[str, ...], raw: Any) -> Any:
    """Discrete block parameters (``[xi]`` / ``[x, y]`` per block) of a raw torch tensor.

    Parameters
    ----------
    kinds : tuple of {'real', 'pair'}
    raw : torch.Tensor of shape (n_poles,)

    Returns
    -------
    torch.Tensor of shape (n_poles,)
    """
    torch = require_torch()
    parts, col = [], 0
    for kind in kinds:
        if kind == REAL:
            parts.append(MAX_RADIUS * torch.tanh(raw[col : col + 1]))
            col += 1
        else:
            r = MAX_RADIUS * torch.sigmoid(raw[col])
            th = math.pi * torch.sigmoid(raw[col + 1])
            parts.append(torch.stack([r * torch.cos(th), r * torch.sin(th)]))
            col += 2
    return torch.cat(parts)


def _torch_sections(kind: str, x: Any, y: Any | None) -> tuple[Any, Any, Any, Any]:
    torch = require_torch()
    if kind == REAL:
        r = torch.sqrt(1.0 - x**2)
        return x.reshape(1, 1), r.reshape(1), r.reshape(1), -x
    mod2 = x**2 + y**2
    b = 2.0 * x / (1.0 + mod2)
    c = -mod2
    rb = torch.sqrt(1.0 - b**2)
    rc = torch.sqrt(1.0 - c**2)
    Aj = torch.stack([torch.stack([-b * c, c * rb]), torch.stack([rb, b])])
    Bj = torch.stack([rc, torch.zeros_like(rc)])
    Cj = torch.stack([-b * rc, rb * rc])
    return Aj, Bj, Cj, -c


def torch_bank_matrices(kinds: tuple[str, ...], params: Any) -> tuple[Any, Any]:
    """``A`` and ``B`` of the discrete Kautz bank from block parameters, differentiably.

    The same cascade as :func:`kautztwin.basis._blocks.discrete_matrices` (one parameter set).

    Parameters
    ----------
    kinds : tuple of {'real', 'pair'}
    params : torch.Tensor of shape (n_poles,)
        Block parameters ``[xi]`` / ``[x, y]`` (see :func:`torch_poles_params`).

    Returns
    -------
    A : torch.Tensor of shape (n_poles, n_poles)
    B : torch.Tensor of shape (n_poles,)
    """
    torch = require_torch()
    sections, col = [], 0
    for kind in kinds:
        if kind == REAL:
            sections.append(_torch_sections(kind, params[col], None))
            col += 1
        else:
            sections.append(_torch_sections(kind, params[col], params[col + 1]))
            col += 2
    rows_A, rows_B = [], []
    gain_before = params.new_ones(())
    for j, (Aj, Bj, _Cj, Dj) in enumerate(sections):
        blocks = []
        between = params.new_ones(())
        left = []
        for k in range(j - 1, -1, -1):
            Ck = sections[k][2]
            left.append(Bj[:, None] * (between * Ck[None, :]))
            between = between * sections[k][3]
        blocks = left[::-1] + [Aj]
        rest = sum(s[0].shape[0] for s in sections[j + 1 :])
        if rest:
            blocks.append(params.new_zeros((Aj.shape[0], rest)))
        rows_A.append(torch.cat(blocks, dim=1))
        rows_B.append(Bj * gain_before)
        gain_before = gain_before * Dj
    return torch.cat(rows_A, dim=0), torch.cat(rows_B)


def torch_bank_states(A: Any, B: Any, v: Any, level: Any) -> Any:
    """States of the bank for each channel of ``v`` (torch, differentiable).

    Parameters
    ----------
    A : torch.Tensor of shape (n_poles, n_poles)
    B : torch.Tensor of shape (n_poles,)
    v : torch.Tensor of shape (n_samples, n_channels)
    level : torch.Tensor of shape (n_channels,)
        Value of each channel before the record (steady-state initial state).

    Returns
    -------
    torch.Tensor of shape (n_samples, n_channels * n_poles)
    """
    torch = require_torch()
    n, n_ch = v.shape
    m = B.shape[0]
    F = B[None, :]
    P = A
    while F.shape[0] < n - 1:
        F = torch.cat([F, F @ P.T], dim=0)
        P = P @ P
    F = torch.cat([F.new_zeros((1, m)), F], dim=0)[:n]  # delayed: F[0] = 0
    xss = torch.linalg.solve(torch.eye(m, dtype=A.dtype) - A, B)
    w = v - level[None, :]
    size = 2 * n
    X = torch.fft.irfft(
        torch.fft.rfft(F, n=size, dim=0)[:, None, :] * torch.fft.rfft(w, n=size, dim=0)[:, :, None],
        n=size, dim=0,
    )[:n]
    X = X + level[None, :, None] * xss[None, None, :]
    return X.reshape(n, n_ch * m)

