r"""Exact simulation of continuous-time LTI models driven by sampled inputs.

A sampled input only defines the continuous input between the samples once an
*intersample behaviour* is chosen.  Two are supported, and for each the
simulation is exact (up to rounding) at the sample times, also on non-uniform
grids and with an input delay that is not a multiple of the sampling period:

* ``'zoh'`` (zero-order hold): the input is piecewise constant,
  :math:`u(t) = u_k` on :math:`[t_k, t_{k+1})`;
* ``'foh'`` (first-order hold): the input is piecewise linear between the
  samples, :math:`u(t) = u_k + (u_{k+1} - u_k)(t - t_k)/(t_{k+1} - t_k)`,
  and held at the last value after the last sample.

Over an interval of length :math:`h` on which the input is
:math:`u(t_i + r) = v + s\,r` the state moves exactly as

.. math::

    x(t_i + h) = e^{Ah} x(t_i) + \Gamma_0(h)\,v + \Gamma_1(h)\,s,\qquad
    \exp\!\left(\begin{bmatrix}A & B & 0\\ 0 & 0 & 1\\ 0 & 0 & 0\end{bmatrix} h\right)
    = \begin{bmatrix}e^{Ah} & \Gamma_0(h) & \Gamma_1(h)\\ 0 & 1 & h\\ 0 & 0 & 1\end{bmatrix},

so every step is one matrix exponential (computed once per distinct interval
length, in a batch) and no ODE solver is involved.  A delay :math:`\tau`
shifts the breakpoints of the input to :math:`t_k + \tau`; they are merged into
the grid, so the result stays exact.  Uniform grids use a blocked form of the
recursion that needs only about :math:`2\sqrt{n}` sequential steps.

Size: over 600 lines because the two hold rules, the delay breakpoints and the batched
matrix exponentials form one algorithm whose parts share their grid bookkeeping.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_choice, check_finite, check_nonnegative, check_time
from ..approx._system import as_state_space
from ..exceptions import DataError, DimensionError

__all__ = ["impulse_response", "simulate_lti", "step_response"]

INTERSAMPLE = ("zoh", "foh")
_UNIFORM_RTOL = 1e-12


# --------------------------------------------------------------------------- matrix exponentials
def expm_batch(M: NDArray) -> NDArray[np.float64]:
    """Matrix exponentials of a stack of square matrices (scaling and squaring, Taylor).

    Each matrix is scaled by its own power of two to 1-norm <= 1/4, where an
    order-14 Taylor polynomial is accurate to rounding (truncation below
    ``0.25**15 / 15! = 7e-22``), then squared back.  All operations are batched
    numpy calls, which is about a hundred times faster than calling
    ``scipy.linalg.expm`` per matrix for the small state dimensions used here.

    Parameters
    ----------
    M : ndarray of shape (m, d, d)

    Returns
    -------
    ndarray of shape (m, d, d)
    """
    M = np.asarray(M, dtype=float)
    m, d, _ = M.shape
    if m == 0:
        return M.copy()
    norms = np.abs(M).sum(axis=1).max(axis=1)  # 1-norm of each matrix
    with np.errstate(divide="ignore"):
        s = np.where(norms > 0.25, np.ceil(np.log2(np.maximum(norms, 1e-300) / 0.25)), 0.0)
    s = s.astype(int)
    X = M / (2.0 ** s)[:, None, None]
    eye = np.eye(d)
    E = eye + X / 14.0
    for k in range(13, 0, -1):
        E = eye + (X @ E) / k
    for j in range(int(s.max(initial=0))):
        sel = s > j
        E[sel] = E[sel] @ E[sel]
    return E


def hold_matrices(
    A: NDArray, B: NDArray, h: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    r"""``e^{Ah}``, :math:`\Gamma_0(h)` and :math:`\Gamma_1(h)` for every length in ``h``.

    Parameters
    ----------
    A : ndarray of shape (d, d)
    B : ndarray of shape (d,)
    h : ndarray of shape (m,)
        Interval lengths.

    Returns
    -------
    Phi : ndarray of shape (m, d, d)
        :math:`e^{Ah}`.
    G0, G1 : ndarray of shape (m, d)
        :math:`\int_0^h e^{A(h-r)}B\,dr` and :math:`\int_0^h e^{A(h-r)}B\,r\,dr`.
    """
    d = A.shape[0]
    h = np.asarray(h, dtype=float)
    M = np.zeros((h.size, d + 2, d + 2))
    M[:, :d, :d] = A[None] * h[:, None, None]
    M[:, :d, d] = B[None] * h[:, None]
    M[:, d, d + 1] = h
    E = expm_batch(M)
    return E[:, :d, :d], E[:, :d, d], E[:, :d, d + 1]


# --------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class PiecewiseInput:
    """A continuous input built from pieces: 0 before ``breakpoints[0]``.

    On ``[breakpoints[j], breakpoints[j+1])`` the input is
    ``values[j] + slopes[j] * (t - breakpoints[j])``; ``kicks`` are Dirac
    impulses ``(time, area)``.

    Parameters
    ----------
    breakpoints : ndarray of shape (n_pieces,)
        Non-decreasing times where a piece starts (a later duplicate wins).
    values : ndarray of shape (n_pieces,)
        Input at the start of each piece.
    slopes : ndarray of shape (n_pieces,)
        Slope of each piece (0 for a held input).
    kicks : tuple of (float, float), default=()
        Dirac impulses as ``(time, area)``.
    """

    breakpoints: NDArray[np.float64]
    values: NDArray[np.float64]
    slopes: NDArray[np.float64]
    kicks: tuple[tuple[float, float], ...] = field(default=())

    def value_at(self, t: NDArray) -> NDArray[np.float64]:
        """The (right-continuous) input at times ``t``.

        Parameters
        ----------
        t : ndarray of any shape

        Returns
        -------
        ndarray of the shape of ``t``
        """
        if self.breakpoints.size == 0:
            return np.zeros(np.shape(t))
        j = np.searchsorted(self.breakpoints, t, side="right") - 1
        jc = np.maximum(j, 0)
        v = self.values[jc] + self.slopes[jc] * (t - self.breakpoints[jc])
        return np.where(j >= 0, v, 0.0)


def sampled_input(
    t: NDArray,
    u: NDArray,
    *,
    delay: float = 0.0,
    intersample: str = "zoh",
    u_before: float | None = None,
) -> PiecewiseInput:
    """The continuous input that samples ``u`` at ``t`` define, delayed by ``delay``.

    Parameters
    ----------
    t, u : ndarray of shape (n_samples,)
        Sample times and values.
    delay : float, default=0.0
        Input delay in seconds.
    intersample : {'zoh', 'foh'}, default='zoh'
        Held or linearly interpolated between samples.
    u_before : float, optional
        Input from ``t[0]`` until the delayed samples start; 0 when omitted.

    Returns
    -------
    PiecewiseInput
    """
    u = np.asarray(u, dtype=float)
    slopes = np.zeros(u.size)
    if intersample == "foh" and u.size > 1:
        slopes[:-1] = np.diff(u) / np.diff(t)
    bp = t + delay
    if u_before is not None:
        # a duplicate breakpoint at t[0] (delay 0) is harmless: the later piece wins
        bp, u, slopes = (np.concatenate([[a], b]) for a, b in
                         ((t[0], bp), (u_before, u), (0.0, slopes)))
    return PiecewiseInput(bp, u, slopes)


def step_input(start: float, amplitude: float) -> PiecewiseInput:
    """An ideal step of height ``amplitude`` at ``start``.

    Parameters
    ----------
    start : float
    amplitude : float

    Returns
    -------
    PiecewiseInput
    """
    return PiecewiseInput(np.array([start]), np.array([amplitude]), np.zeros(1))


def impulse_input(start: float, area: float) -> PiecewiseInput:
    """A Dirac impulse of area ``area`` at ``start``.

    Parameters
    ----------
    start : float
    area : float

    Returns
    -------
    PiecewiseInput
    """
    return PiecewiseInput(np.zeros(0), np.zeros(0), np.zeros(0), ((float(start), float(area)),))


# --------------------------------------------------------------------------- the recursion
def _uniform(h: NDArray) -> bool:
    return h.size > 0 and bool(np.all(np.abs(h - h[0]) <= _UNIFORM_RTOL * max(h[0], 1e-300)))


def _blocked(Phi: NDArray, x0: NDArray, w: NDArray) -> NDArray[np.float64]:
    """``x[k+1] = Phi x[k] + w[k]`` for a constant ``Phi``; ``x0 (d, q)``, ``w (n-1, d, q)``.

    The recursion runs over blocks of ``m ~ sqrt(n)`` steps: the zero-start
    solutions inside all blocks advance together (``m`` batched steps), then the
    block starts are chained (``n / m`` steps) and added with the powers of
    ``Phi``.  Only small stacked products are used (no large BLAS calls).
    """
    n = w.shape[0] + 1
    d, q = x0.shape
    m = max(1, int(np.ceil(np.sqrt(n))))
    J = -(-(n - 1) // m)
    W = np.zeros((J * m, d, q))
    W[: n - 1] = w
    W = W.reshape(J, m, d, q)
    P = np.empty((J, m, d, q))  # P[j, i]: state after step i of block j from a zero start
    acc = np.zeros((J, d, q))
    for i in range(m):
        acc = np.matmul(Phi, acc) + W[:, i]
        P[:, i] = acc
    powers = np.empty((m + 1, d, d))
    powers[0] = np.eye(d)
    for r in range(1, m + 1):
        powers[r] = np.matmul(Phi, powers[r - 1])
    starts = np.empty((J + 1, d, q))
    starts[0] = x0
    for j in range(J):
        starts[j + 1] = np.matmul(powers[m], starts[j]) + P[j, m - 1]
    # x[j*m + i + 1] = Phi^(i+1) x[j*m] + P[j, i]
    inner = np.matmul(powers[None, 1:], starts[:J, None]) + P
    out = np.empty((n, d, q))
    out[0] = x0
    out[1:] = inner.reshape(J * m, d, q)[: n - 1]
    return out


def _loop(Phis: NDArray, x0: NDArray, w: NDArray) -> NDArray[np.float64]:
    """``x[k+1] = Phis[k] x[k] + w[k]`` with a different matrix per step."""
    n = w.shape[0] + 1
    out = np.empty((n,) + x0.shape)
    out[0] = x = x0
    for k in range(n - 1):
        x = Phis[k] @ x + w[k]
        out[k + 1] = x
    return out


def _as_steps(inp: PiecewiseInput, t0: float, t1: float) -> list[tuple[float, float]] | None:
    """The input as a few steps ``(time, jump)`` on ``[t0, t1]``, or ``None`` if it has ramps."""
    if inp.breakpoints.size and np.any(inp.slopes != 0):
        return None
    inside = (inp.breakpoints > t0) & (inp.breakpoints <= t1)
    if int(inside.sum()) > 4:
        return None
    steps = []
    first = float(inp.value_at(np.array([t0]))[0])
    if first != 0.0:
        steps.append((float(t0), first))
    for j in np.flatnonzero(inside):
        before = inp.values[j - 1] if j > 0 else 0.0
        if inp.values[j] != before:
            steps.append((float(inp.breakpoints[j]), float(inp.values[j] - before)))
    return steps


def _direct(
    A: NDArray,
    B: NDArray,
    t: NDArray,
    steps: list[tuple[float, float]],
    kicks: tuple[tuple[float, float], ...],
    X0: NDArray | None,
) -> NDArray[np.float64]:
    r"""States for step and impulse inputs by superposition, on any grid.

    .. math::

        x(t) = \sum_j \Delta_j \Gamma_0(t - b_j)^+ + \sum_c a_c e^{A(t - c)}B\,[t \ge c]
               + e^{A(t - t_0)} X_0 .

    Each term is computed on the nominal uniform grid ``t0 + k h`` (``h`` the
    median interval) by the exact recursion, then carried to the actual time
    stamp ``t0 + k h + delta`` with
    :math:`\Gamma_0(\theta + \delta) = e^{A\delta}\Gamma_0(\theta) + \Gamma_0(\delta)`,
    one small matrix exponential per distinct ``delta`` (jittered logs have few).
    """
    d = A.shape[0]
    q = 0 if X0 is None else X0.shape[1]
    n = t.size
    out = np.zeros((n, d, 1 + q))
    M = np.zeros((d + 1, d + 1))
    M[:d, :d] = A
    M[:d, d] = B
    h = float(np.median(np.diff(t)))
    k = np.rint((t - t[0]) / h).astype(np.int64)
    if k[-1] > 4 * n:  # long gaps: one exponential per sample instead
        def at(theta: NDArray) -> NDArray:
            return expm_batch(M[None] * theta[:, None, None])

        for time, jump in steps:
            sel = t > time
            out[sel, :, 0] += at(t[sel] - time)[:, :d, d] * jump
        for time, area in kicks:
            sel = t >= time
            out[sel, :, 0] += at(t[sel] - time)[:, :d, :d] @ B * area
        if q:
            out[:, :, 1:] = at(t - t[0])[:, :d, :d] @ X0
        return out
    delta = t - (t[0] + k * h)
    # stamps within 1e-10 periods of the nominal grid are on it (rounding of k * h)
    delta[np.abs(delta) <= 1e-10 * h] = 0.0
    du, dinv = np.unique(delta, return_inverse=True)
    Ed = expm_batch(M[None] * du[:, None, None])[dinv]  # (n, d+1, d+1)
    Phi_d, G_d = Ed[:, :d, :d], Ed[:, :d, d]
    Eh = expm_batch(M[None] * np.array([h])[:, None, None])[0]
    Phi_h, G_h = Eh[:d, :d], Eh[:d, d]
    K = int(k[-1]) + 1
    grid = t[0] + h * np.arange(K)
    slack = float(np.max(np.abs(delta))) + 1e-12 * max(1.0, abs(t[-1]))

    def nominal(first: NDArray, j0: int, forcing: NDArray | None) -> NDArray:
        """``x[j+1] = Phi_h x[j] (+ forcing)`` for ``j >= j0`` on the nominal grid."""
        count = K - j0
        w = np.zeros((count - 1, d, first.shape[1]))
        if forcing is not None:
            w[:, :, 0] = forcing
        seq = np.zeros((K, d, first.shape[1]))
        seq[j0:] = _blocked(Phi_h, first, w) if count > 1 else first[None]
        return seq

    for time, jump in steps:
        sel = t > time
        if not sel.any():
            continue
        j0 = int(np.searchsorted(grid, time - slack, side="right"))
        j0 = min(j0, int(k[sel][0]))
        first = expm_batch(M[None] * (grid[j0] - time))[0][:d, d]
        seq = nominal(first[:, None], j0, G_h)[:, :, 0]
        kk = k[sel]
        out[sel, :, 0] += (np.einsum("nab,nb->na", Phi_d[sel], seq[kk]) + G_d[sel]) * jump
    for time, area in kicks:
        sel = t >= time
        if not sel.any():
            continue
        j0 = int(np.searchsorted(grid, time - slack, side="right"))
        j0 = min(j0, int(k[sel][0]))
        first = expm_batch(M[None] * (grid[j0] - time))[0][:d, :d] @ B
        seq = nominal(first[:, None], j0, None)[:, :, 0]
        kk = k[sel]
        out[sel, :, 0] += np.einsum("nab,nb->na", Phi_d[sel], seq[kk]) * area
    if q:
        seq = nominal(np.asarray(X0, dtype=float), 0, None)
        out[:, :, 1:] = Phi_d @ seq[k]
    return out


def propagate(
    A: NDArray,
    B: NDArray,
    t: NDArray,
    inp: PiecewiseInput,
    *,
    X0: NDArray | None = None,
) -> NDArray[np.float64]:
    """States at the times ``t`` of ``dx/dt = A x + B u`` for a piecewise input, exactly.

    Parameters
    ----------
    A : ndarray of shape (d, d)
    B : ndarray of shape (d,)
    t : ndarray of shape (n,)
        Strictly increasing output times; the simulation starts at ``t[0]``.
    inp : PiecewiseInput
        The input (pieces before ``t[0]`` act only through their value at ``t[0]``).
    X0 : ndarray of shape (d, q), optional
        Initial states of ``q`` free responses propagated alongside.

    Returns
    -------
    ndarray of shape (n, d, 1 + q)
        Column 0 is the forced response from rest at ``t[0]``; columns ``1..q``
        the free responses from the columns of ``X0``.
    """
    d = A.shape[0]
    q = 0 if X0 is None else X0.shape[1]
    t0, t1 = t[0], t[-1]
    if t.size > 2:
        steps = _as_steps(inp, t0, t1)
        if steps is not None and len(steps) + len(inp.kicks) <= 4:
            return _direct(A, B, t, steps, inp.kicks, X0)
    inner = inp.breakpoints[(inp.breakpoints > t0) & (inp.breakpoints < t1)]
    grid = np.union1d(t, inner) if inner.size else t
    h_grid = np.diff(grid)
    v = inp.value_at(grid[:-1])
    j = np.searchsorted(inp.breakpoints, grid[:-1], side="right") - 1
    s = np.where(j >= 0, inp.slopes[np.maximum(j, 0)], 0.0) if inp.breakpoints.size else 0.0 * v
    hu, inv = np.unique(h_grid, return_inverse=True)
    Phi_u, G0_u, G1_u = hold_matrices(A, B, hu)
    g = G0_u[inv] * v[:, None] + G1_u[inv] * s[:, None]  # (n_grid - 1, d)

    h_out = np.diff(t)
    if inner.size:
        k = np.searchsorted(t, grid[:-1], side="right") - 1  # output interval of each piece
        rem = t[k + 1] - grid[1:]
        ru, rinv = np.unique(rem, return_inverse=True)
        Phi_r = expm_batch(A[None] * ru[:, None, None])
        contrib = np.einsum("mab,mb->ma", Phi_r[rinv], g)
        w_vec = np.zeros((t.size - 1, d))
        np.add.at(w_vec, k, contrib)
        ou, oinv = np.unique(h_out, return_inverse=True)
        Phi_out = expm_batch(A[None] * ou[:, None, None])
    else:
        w_vec = g
        ou, oinv, Phi_out = hu, inv, Phi_u

    x_init = np.zeros(d)
    for time, area in inp.kicks:
        if time < t0 or time > t1:
            continue
        kk = int(np.searchsorted(t, time, side="right") - 1)
        if time == t[kk]:
            if kk == 0:
                x_init = x_init + B * area
            else:
                w_vec[kk - 1] += B * area
        else:
            E = expm_batch(A[None] * (t[kk + 1] - time))[0]
            w_vec[kk] += E @ B * area

    x0 = np.zeros((d, 1 + q))
    x0[:, 0] = x_init
    if q:
        x0[:, 1:] = X0
    w = np.zeros((t.size - 1, d, 1 + q))
    w[:, :, 0] = w_vec
    if t.size == 1:
        return x0[None]
    if _uniform(h_out):
        return _blocked(Phi_out[oinv[0]], x0, w)
    return _loop(Phi_out[oinv], x0, w)


# --------------------------------------------------------------------------- public functions
def _continuous_system(system: Any) -> tuple[NDArray, NDArray, NDArray, float]:
    ss = as_state_space(system)
    if ss.dt != 0:
        raise DataError(f"system must be continuous-time (dt = 0); got dt = {ss.dt:g}")
    return ss.A, ss.B, ss.C, ss.D


def simulate_lti(
    system: Any,
    t: ArrayLike,
    u: ArrayLike,
    *,
    delay: float = 0.0,
    intersample: str = "zoh",
    x0: ArrayLike | None = None,
    u_before: float = 0.0,
) -> NDArray[np.float64]:
    r"""Output of a continuous-time LTI system for a sampled input, exactly at the samples.

    Parameters
    ----------
    system : scipy.signal.lti, python-control system, (num, den) or (A, B, C, D)
        A continuous-time SISO system (stable or not).
    t : array-like of shape (n_samples,)
        Strictly increasing sample times in seconds (uniform or not); the
        simulation starts at ``t[0]``.
    u : array-like of shape (n_samples,)
        Input samples.
    delay : float, default=0.0
        Input delay :math:`\tau \ge 0` in seconds (any value, not only
        multiples of the sampling period): the system sees :math:`u(t - \tau)`.
    intersample : {'zoh', 'foh'}, default='zoh'
        How the input behaves between samples: piecewise constant (zero-order
        hold) or piecewise linear (first-order hold, held after the last
        sample).  The result is exact for the chosen behaviour.
    x0 : array-like of shape (n_states,), optional
        State at ``t[0]`` in the realisation of ``system`` (zero by default).
    u_before : float, default=0.0
        Input before ``t[0]``; it reaches the output only through the delay,
        on :math:`[t_0, t_0 + \tau)`.

    Returns
    -------
    ndarray of shape (n_samples,)

    Raises
    ------
    DataError
        On NaN, a non-increasing ``t``, a negative delay, an unknown option or
        a discrete-time system.
    DimensionError
        If ``u`` and ``t`` differ in length or ``x0`` has the wrong size.

    See Also
    --------
    step_response : Exact response to an ideal step.
    impulse_response : Exact response to a Dirac impulse.

    Notes
    -----
    Each interval between the (merged) breakpoints of the delayed input and the
    sample times is propagated with the exact transition

    .. math:: x(t_i + h) = e^{Ah} x(t_i) + \Gamma_0(h) v_i + \Gamma_1(h) s_i

    (module docstring), and :math:`y = Cx + D\,u(t - \tau)`, with ``u``
    right-continuous at its breakpoints.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import simulate_lti
    >>> t = np.array([0.0, 0.5, 1.3, 2.0])            # non-uniform grid
    >>> y = simulate_lti(([1.0], [1.0, 1.0]), t, np.ones(4))
    >>> np.allclose(y, 1 - np.exp(-t))                  # exact: 1/(s+1), unit step
    True
    """
    check_choice(intersample, "intersample", INTERSAMPLE)
    A, B, C, D = _continuous_system(system)
    t = check_time(t, min_samples=1)
    u = np.asarray(u, dtype=float)
    if u.shape != t.shape:
        raise DimensionError(f"u has shape {u.shape} but t has shape {t.shape}")
    check_finite(u, "u")
    delay = check_nonnegative(delay, "delay")
    inp = sampled_input(t, u, delay=delay, intersample=intersample, u_before=float(u_before))
    d = A.shape[0]
    if d == 0:
        return D * inp.value_at(t)
    X0 = None
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float).reshape(-1)
        if x0.size != d:
            raise DimensionError(f"x0 has {x0.size} entries but the system has {d} states")
        check_finite(x0, "x0")
        X0 = x0[:, None]
    X = propagate(A, B, t, inp, X0=X0)
    x = X[:, :, 0] if X0 is None else X[:, :, 0] + X[:, :, 1]
    return x @ C + D * inp.value_at(t)


def _response(system: Any, t: ArrayLike, delay: float, kind: str) -> NDArray[np.float64]:
    A, B, C, D = _continuous_system(system)
    t = check_time(t, min_samples=1)
    delay = check_nonnegative(delay, "delay")
    if t[0] < 0:
        raise DataError(f"t must start at t >= 0 (the input acts at t = 0); got t[0] = {t[0]:g}")
    prepend = t[0] > 0
    tt = np.concatenate([[0.0], t]) if prepend else t
    inp = step_input(delay, 1.0) if kind == "step" else impulse_input(delay, 1.0)
    if kind == "impulse" and D != 0:
        raise DataError("the impulse response of a system with direct feedthrough holds a Dirac")
    d = A.shape[0]
    x = propagate(A, B, tt, inp)[:, :, 0] if d else np.zeros((tt.size, 0))
    y = x @ C if d else np.zeros(tt.size)
    if kind == "step":
        y = y + D * inp.value_at(tt)
    return y[1:] if prepend else y


def step_response(system: Any, t: ArrayLike, *, delay: float = 0.0) -> NDArray[np.float64]:
    r"""Exact unit-step response of a continuous-time system at the times ``t``.

    Parameters
    ----------
    system : scipy.signal.lti, python-control system, (num, den) or (A, B, C, D)
        Continuous-time SISO system.
    t : array-like of shape (n_samples,)
        Strictly increasing times ``>= 0``; the step acts at ``t = delay``.
    delay : float, default=0.0
        Dead time in seconds.

    Returns
    -------
    ndarray of shape (n_samples,)

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import step_response
    >>> y = step_response(([2.0], [1.0, 2.0]), [0.0, 1.0, 2.0], delay=1.0)
    >>> np.allclose(y, [0.0, 0.0, 1 - np.exp(-2.0)])
    True
    """
    return _response(system, t, delay, "step")


def impulse_response(system: Any, t: ArrayLike, *, delay: float = 0.0) -> NDArray[np.float64]:
    r"""Exact impulse response of a strictly proper continuous-time system.

    Parameters
    ----------
    system : scipy.signal.lti, python-control system, (num, den) or (A, B, C, D)
        Continuous-time SISO system without direct feedthrough.
    t : array-like of shape (n_samples,)
        Strictly increasing times ``>= 0``; the impulse acts at ``t = delay``
        (the response is right-continuous there).
    delay : float, default=0.0
        Dead time in seconds.

    Returns
    -------
    ndarray of shape (n_samples,)

    Raises
    ------
    DataError
        If the system has direct feedthrough.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import impulse_response
    >>> h = impulse_response(([1.0], [1.0, 1.0]), [0.0, 1.0])
    >>> np.allclose(h, [1.0, np.exp(-1.0)])
    True
    """
    return _response(system, t, delay, "impulse")
