"""Pole parsing and the batched construction of the basis matrices.

A basis is an ordered list of *blocks*: a real pole (one function) or a
complex-conjugate pair (two functions).  The block *kinds* fix the structure;
the block *parameters* fix the numbers.  Keeping the two apart lets the pole
studies build thousands of bases of the same structure in one vectorised call.

Parameters per block (``params`` columns, in block order):

* continuous real pole ``s = -p``: ``[p]`` (rate ``p > 0``);
* continuous pair ``s = -sigma +- j omega``: ``[sigma, omega]``;
* discrete real pole ``z = xi``: ``[xi]``;
* discrete pair ``z = x +- j y``: ``[x, y]``.

The formulas are those of ``kautz-math.md`` sections 2.1 (continuous) and 3.2
(discrete).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import PoleError, UnstableModelError

REAL = "real"
PAIR = "pair"
_IMAG_TOL = 1e-12  # |Im| below this (relative) counts as a real pole
_PAIR_TOL = 1e-8  # relative tolerance when matching a complex pole with its conjugate
#: largest |p| of a continuous-time pole: a pair's block squares it (|p|^2 overflows past 1e154)
MAX_POLE_MAGNITUDE = 1e100


def parse_poles(poles: ArrayLike, dt: float) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    """Split pole locations into block kinds and block parameters.

    Parameters
    ----------
    poles : array-like of complex
        Pole locations; each complex pole appears together with its conjugate.
    dt : float
        ``0`` for s-plane poles (``Re < 0``), ``> 0`` for z-plane poles (``|z| < 1``).

    Returns
    -------
    kinds : tuple of {'real', 'pair'}
    params : ndarray of shape (n_params,)
    """
    try:
        p = np.atleast_1d(np.asarray(poles, dtype=complex))
    except (TypeError, ValueError) as exc:
        raise PoleError(f"poles must be numbers, got {poles!r}") from exc
    if p.ndim != 1 or p.size == 0:
        raise PoleError(f"poles must be a non-empty 1-D list, got shape {p.shape}")
    for i, pi in enumerate(p):
        if not np.isfinite(pi):
            raise PoleError(f"poles[{i}] = {pi} is not finite")
        if dt == 0 and abs(pi) > MAX_POLE_MAGNITUDE:
            raise PoleError(
                f"poles[{i}] = {_fmt(pi)} is too large to represent (|p| > "
                f"{MAX_POLE_MAGNITUDE:g}); rescale time so that the poles are moderate numbers"
            )
        if dt == 0 and pi.real >= 0:
            raise UnstableModelError(
                f"poles[{i}] = {_fmt(pi)} has Re >= 0; continuous-time poles must satisfy Re(p) < 0"
            )
        if dt > 0 and abs(pi) >= 1:
            raise UnstableModelError(
                f"poles[{i}] = {_fmt(pi)} has |p| = {abs(pi):.6g}; discrete-time poles must lie "
                "inside the unit circle"
            )
    kinds: list[str] = []
    params: list[float] = []
    used = np.zeros(p.size, dtype=bool)
    for i, pi in enumerate(p):
        if used[i]:
            continue
        used[i] = True
        scale = max(1.0, abs(pi))
        if abs(pi.imag) <= _IMAG_TOL * scale:
            kinds.append(REAL)
            params.append(-pi.real if dt == 0 else pi.real)
            continue
        partner = [
            j
            for j in range(i + 1, p.size)
            if not used[j] and abs(p[j] - np.conj(pi)) <= _PAIR_TOL * scale
        ]
        if not partner:
            raise PoleError(
                f"poles[{i}] = {_fmt(pi)} has no conjugate partner; list each complex pole "
                "together with its conjugate"
            )
        used[partner[0]] = True
        kinds.append(PAIR)
        if dt == 0:
            params += [-pi.real, abs(pi.imag)]
        else:
            params += [pi.real, abs(pi.imag)]
    return tuple(kinds), np.asarray(params, dtype=float)


def block_poles(kinds: tuple[str, ...], params: NDArray, dt: float) -> NDArray[np.complex128]:
    """Pole locations (pairs as ``(p, conj(p))`` with ``Im p > 0``) in block order."""
    out: list[complex] = []
    col = 0
    for kind in kinds:
        if kind == REAL:
            out.append(complex(-params[col] if dt == 0 else params[col]))
            col += 1
        else:
            re = -params[col] if dt == 0 else params[col]
            out += [complex(re, params[col + 1]), complex(re, -params[col + 1])]
            col += 2
    return np.asarray(out, dtype=complex)


def block_sizes(kinds: tuple[str, ...]) -> list[int]:
    """Number of functions in each block (1 for a real pole, 2 for a pair)."""
    return [1 if k == REAL else 2 for k in kinds]


def block_index(kinds: tuple[str, ...]) -> NDArray[np.intp]:
    """Block number of each basis function."""
    return np.repeat(np.arange(len(kinds)), block_sizes(kinds))


def continuous_matrices(
    kinds: tuple[str, ...], params: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Network realisation ``dF/dt = A F, F(0) = B`` for a batch of pole sets.

    ``params`` has shape ``(batch, n_params)``; returns ``A (batch, N, N)`` and
    ``B (batch, N)`` with ``A = blkdiag(A_j) - L(B B^T)`` (kautz-math.md 2.1).
    """
    params = np.atleast_2d(np.asarray(params, dtype=float))
    batch = params.shape[0]
    n = sum(block_sizes(kinds))
    A = np.zeros((batch, n, n))
    beta = np.zeros((batch, n))
    i = col = 0
    for kind in kinds:
        if kind == REAL:
            rate = params[:, col]
            A[:, i, i] = -rate
            beta[:, i] = np.sqrt(2.0 * rate)
            i += 1
            col += 1
        else:
            sigma, omega = params[:, col], params[:, col + 1]
            b = 2.0 * sigma
            root_c = np.sqrt(sigma**2 + omega**2)
            A[:, i, i] = -b
            A[:, i, i + 1] = -root_c
            A[:, i + 1, i] = root_c
            beta[:, i] = np.sqrt(2.0 * b)
            i += 2
            col += 2
    blk = block_index(kinds)
    lower = blk[:, None] > blk[None, :]
    A -= lower * (beta[:, :, None] * beta[:, None, :])
    return A, beta


def _discrete_sections(kind: str, x: NDArray, y: NDArray | None):
    """Lossless section ``(A_j, B_j, C_j, D_j)`` of one block, batched (kautz-math.md 3.2)."""
    if kind == REAL:
        r = np.sqrt(1.0 - x**2)
        return x[:, None, None], r[:, None], r[:, None], -x
    mod2 = x**2 + y**2
    b = 2.0 * x / (1.0 + mod2)
    c = -mod2
    rb = np.sqrt(1.0 - b**2)
    rc = np.sqrt(1.0 - c**2)
    Aj = np.stack([np.stack([-b * c, c * rb], -1), np.stack([rb, b], -1)], -2)
    Bj = np.stack([rc, np.zeros_like(rc)], -1)
    Cj = np.stack([-b * rc, rb * rc], -1)
    return Aj, Bj, Cj, -c


def discrete_matrices(
    kinds: tuple[str, ...], params: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Cascade realisation ``F(k+1) = A F(k), F(0) = B`` for a batch of z-plane pole sets.

    ``A A^T + B B^T = I`` holds exactly, which makes the sequences orthonormal in l2.
    """
    params = np.atleast_2d(np.asarray(params, dtype=float))
    batch = params.shape[0]
    sizes = block_sizes(kinds)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    n = int(starts[-1])
    A = np.zeros((batch, n, n))
    B = np.zeros((batch, n))
    sections = []
    col = 0
    for kind in kinds:
        if kind == REAL:
            sections.append(_discrete_sections(kind, params[:, col], None))
            col += 1
        else:
            sections.append(_discrete_sections(kind, params[:, col], params[:, col + 1]))
            col += 2
    gain_before = np.ones(batch)  # prod_{m<j} D_m
    for j, (Aj, Bj, _Cj, Dj) in enumerate(sections):
        rj = slice(starts[j], starts[j + 1])
        A[:, rj, rj] = Aj
        B[:, rj] = Bj * gain_before[:, None]
        between = np.ones(batch)  # prod_{k<m<j} D_m, built from k = j-1 downwards
        for k in range(j - 1, -1, -1):
            Ck = sections[k][2]
            rk = slice(starts[k], starts[k + 1])
            A[:, rj, rk] = Bj[:, :, None] * (between[:, None, None] * Ck[:, None, :])
            between = between * sections[k][3]
        gain_before = gain_before * Dj
    return A, B


def transfer_polynomials(
    kinds: tuple[str, ...], params: NDArray, dt: float
) -> tuple[list[NDArray[np.float64]], list[NDArray[np.float64]], list[NDArray[np.float64]]]:
    """Product-formula transfer functions of every basis function (independent of A, B).

    Returns ``nums, dens, tails`` with function ``i`` equal to ``nums[i] / dens[i]``
    (highest power first) and ``dens[i] * tails[i]`` equal to the common
    denominator ``d_pi``.  Continuous: ``K_i(s)`` (kautz-math.md 1.3).  Discrete:
    the undelayed sequences ``z phi_i(z)`` (kautz-math.md 3.1), i.e. the z-transform
    of ``F(k) = A^k B``.
    """
    block_num: list[list[NDArray]] = []
    block_den: list[NDArray] = []
    allpass: list[NDArray] = []
    col = 0
    for kind in kinds:
        if kind == REAL:
            v = params[col]
            col += 1
            if dt == 0:
                block_num.append([np.array([np.sqrt(2 * v)])])
                block_den.append(np.array([1.0, v]))
                allpass.append(np.array([1.0, -v]))
            else:
                block_num.append([np.array([np.sqrt(1 - v**2), 0.0])])
                block_den.append(np.array([1.0, -v]))
                allpass.append(np.array([-v, 1.0]))
        else:
            u, w = params[col], params[col + 1]
            col += 2
            if dt == 0:
                b, c = 2 * u, u**2 + w**2
                block_num.append([np.array([np.sqrt(2 * b), 0.0]), np.array([np.sqrt(2 * b * c)])])
                block_den.append(np.array([1.0, b, c]))
                allpass.append(np.array([1.0, -b, c]))
            else:
                mod2 = u**2 + w**2
                b, c = 2 * u / (1 + mod2), -mod2
                g = np.sqrt(1 - c**2)
                block_num.append(
                    [g * np.array([1.0, -b, 0.0]), g * np.sqrt(1 - b**2) * np.array([1.0, 0.0])]
                )
                block_den.append(np.array([1.0, b * (c - 1), -c]))
                allpass.append(np.array([-c, b * (c - 1), 1.0]))
    nums, dens, tails = [], [], []
    prefix_num = np.array([1.0])
    prefix_den = np.array([1.0])
    for j in range(len(kinds)):
        den = np.polymul(prefix_den, block_den[j])
        tail = np.array([1.0])
        for m in range(j + 1, len(kinds)):
            tail = np.polymul(tail, block_den[m])
        for local in block_num[j]:
            nums.append(np.polymul(prefix_num, local))
            dens.append(den)
            tails.append(tail)
        prefix_num = np.polymul(prefix_num, allpass[j])
        prefix_den = den
    return nums, dens, tails


def _fmt(p: complex) -> str:
    return f"{p.real:g}" if p.imag == 0 else f"{p.real:g}{p.imag:+g}j"
