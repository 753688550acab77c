"""Exact evaluation of ``F(t) = e^{At} B`` (or ``A^k B``) on time grids, batched.

No ODE solver and no eigendecomposition (the Laguerre ``A`` is a single Jordan
block): uniform grids use the exact one-step recursion ``F(t + h) = e^{Ah} F(t)``
arranged in sqrt(n) blocks (so rounding accumulates over about ``2 sqrt(n)``
steps, not ``n``); discrete grids take all ``A^k B`` by doubling (``A^j`` times
the first ``j`` columns, ``j = 1, 2, 4, ...``: about ``2 log2(n)`` batched
products, and rounding accumulated over as many); other grids use one matrix
exponential per sample.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from ..exceptions import DataError

_UNIFORM_RTOL = 1e-12


def _power_columns(step: NDArray, first: NDArray, m: int) -> NDArray[np.float64]:
    """Columns ``step^k first`` for ``k < m`` by doubling: ``(b, N) -> (b, N, m)``.

    Columns ``[j, 2j)`` are ``step^j`` times columns ``[0, j)``, with ``step^j``
    from repeated squaring: about ``2 log2(m)`` batched products instead of ``m``
    one-column steps, and rounding accumulated over as many products.
    """
    batch, size = first.shape
    out = np.empty((batch, size, m))
    out[:, :, 0] = first
    power = step  # step^filled
    filled = 1
    while filled < m:
        take = min(filled, m - filled)
        out[:, :, filled: filled + take] = power @ out[:, :, :take]
        filled += take
        if filled < m:
            power = power @ power
    return out


def _blocked_recursion(
    step: NDArray, step_m: NDArray, first: NDArray, n: int, m: int
) -> NDArray[np.float64]:
    """Columns ``step^k first`` for ``k < n``; ``step_m`` must equal ``step^m``."""
    batch, size = first.shape
    out = np.empty((batch, size, n))
    block = np.empty((batch, size, m))
    cur = first
    for i in range(m):
        block[:, :, i] = cur
        cur = np.einsum("bij,bj->bi", step, cur)
    for start in range(0, n, m):
        stop = min(start + m, n)
        out[:, :, start:stop] = block[:, :, : stop - start]
        if stop < n:
            block = step_m @ block
    return out


def uniform_step(t: NDArray) -> float | None:
    """The grid spacing if ``t`` is uniform to rounding, else ``None``."""
    if t.size < 3:
        return None
    h = (t[-1] - t[0]) / (t.size - 1)
    if h <= 0:
        return None
    ideal = t[0] + h * np.arange(t.size)
    if np.max(np.abs(t - ideal)) <= _UNIFORM_RTOL * max(1.0, abs(t[-1]), abs(t[0])):
        return float(h)
    return None


def continuous_functions(A: NDArray, B: NDArray, t: NDArray) -> NDArray[np.float64]:
    """``e^{A t} B`` for every ``t`` (zero for ``t < 0``); shapes ``(b,N,N), (b,N) -> (b,N,n)``."""
    h = uniform_step(t)
    if h is not None and t[0] >= 0:
        m = max(1, int(np.ceil(np.sqrt(t.size))))
        first = np.einsum("bij,bj->bi", scipy.linalg.expm(A * t[0]), B)
        return _blocked_recursion(
            scipy.linalg.expm(A * h), scipy.linalg.expm(A * (h * m)), first, t.size, m
        )
    if t.size >= 3 and t[0] >= 0:
        jittered = _near_uniform(A, B, t)
        if jittered is not None:
            return jittered
    tc = np.clip(t, 0.0, None)
    E = scipy.linalg.expm(A[:, None, :, :] * tc[None, :, None, None])  # (b, n, N, N)
    out = np.einsum("bkij,bj->bik", E, B)
    out[:, :, t < 0] = 0.0
    return out


def _near_uniform(A: NDArray, B: NDArray, t: NDArray) -> NDArray[np.float64] | None:
    """``e^{At} B`` on a jittered uniform grid, or ``None`` if the jitter is too large.

    Each sample is the exact value at its nominal grid point (uniform recursion)
    carried over the small offset ``delta`` by the Taylor series of
    ``e^{A delta}``, used only where ``||A delta|| <= 1/2`` (then 14 terms reach
    rounding level).  Real logged time stamps (jitter, rounding) take this path
    at the cost of the uniform one instead of one matrix exponential per sample.
    """
    n = t.size
    step = (t[-1] - t[0]) / (n - 1)
    nominal = t[0] + step * np.arange(n)
    delta = t - nominal
    norm = float(np.max(np.abs(A).sum(axis=-1)))  # infinity norm, worst over the batch
    if np.max(np.abs(delta)) * norm > 0.5:
        return None
    term = continuous_functions(A, B, nominal)
    out = term.copy()
    for j in range(1, 30):
        term = (A @ term) * (delta / j)
        out += term
        if np.max(np.abs(term)) <= 1e-17 * max(np.max(np.abs(out)), 1e-300):
            break
    return out


def discrete_functions(A: NDArray, B: NDArray, k: NDArray) -> NDArray[np.float64]:
    """``A^k B`` for integer ``k >= 0``; shapes ``(b,N,N), (b,N) -> (b,N,len(k))``."""
    table = _power_columns(A, B, int(k.max()) + 1)
    return table[:, :, k]


def sample_indices(t: NDArray, dt: float, *, name: str = "t") -> NDArray[np.intp]:
    """Sample numbers ``k = t / dt`` of a discrete grid, checked to be integers ``>= 0``."""
    k = t / dt
    kr = np.rint(k)
    bad = np.abs(k - kr) > 1e-6 * np.maximum(1.0, np.abs(k))
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError(
            f"{name}[{i}] = {t[i]:g} is not a multiple of the sampling period dt = {dt:g}"
        )
    if (kr < 0).any():
        i = int(np.argmax(kr < 0))
        raise DataError(f"{name}[{i}] = {t[i]:g} is negative; discrete bases start at t = 0")
    return kr.astype(np.intp)
