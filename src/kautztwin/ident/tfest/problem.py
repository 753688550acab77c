"""The output-error problem of one order: stable denominator parameterisation and projection.

The denominator is a product of factors :math:`s^2 + e^{\theta_1}s + e^{\theta_2}`
(and :math:`s + e^{\theta}` for odd orders); :class:`_Problem` builds the
regressors of the numerator and the nuisance parameters (offsets, initial
states) for a denominator and delay and projects them out by weighted linear
least squares.  The pooled fit percent of several weighted records lives here too.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...exceptions import DataError
from ..records import Record
from ..simulate import PiecewiseInput, impulse_input, propagate, sampled_input, step_input


def _den_from_theta(theta: NDArray, n: int) -> NDArray[np.float64]:
    """Monic denominator from log-coefficients of its quadratic (and linear) factors."""
    den = np.ones(1)
    for k in range(n // 2):
        den = np.polymul(den, [1.0, np.exp(theta[2 * k]), np.exp(theta[2 * k + 1])])
    if n % 2:
        den = np.polymul(den, [1.0, np.exp(theta[-1])])
    return den


def _theta_from_poles(poles: NDArray, n: int) -> NDArray[np.float64]:
    """Log-coefficients of the factors holding ``poles`` (stable; pairs and real poles)."""
    p = np.asarray(poles, dtype=complex)
    rate = np.maximum(-p.real, 1e-12)
    p = -rate + 1j * p.imag
    cplx = p[p.imag > 1e-9 * np.abs(p)]
    reals = np.sort(p[np.abs(p.imag) <= 1e-9 * np.abs(p)].real)
    quads: list[tuple[float, float]] = [(-2 * z.real, abs(z) ** 2) for z in cplx]
    lin: list[float] = []
    if reals.size % 2:
        lin.append(-reals[0])
        reals = reals[1:]
    for a, b in zip(reals[::2], reals[1::2], strict=True):
        quads.append((-(a + b), a * b))
    if len(quads) != n // 2 or len(lin) != n % 2:  # pragma: no cover - poles come in pairs
        raise DataError(f"cannot arrange {p.size} poles into an order-{n} denominator")
    theta = [np.log(v) for q in quads for v in q] + [np.log(v) for v in lin]
    return np.asarray(theta, dtype=float)


def _theta_bounds(n: int, rate_lo: float, rate_hi: float) -> tuple[NDArray, NDArray]:
    lo: list[float] = []
    hi: list[float] = []
    for _ in range(n // 2):
        lo += [np.log(2e-3 * rate_lo), 2 * np.log(rate_lo)]
        hi += [np.log(2 * rate_hi), 2 * np.log(rate_hi)]
    if n % 2:
        lo.append(np.log(rate_lo))
        hi.append(np.log(rate_hi))
    return np.array(lo), np.array(hi)


def _companion(den: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Controller form of ``1/den``: states ``w, w', ..., w^(n-1)``."""
    n = den.size - 1
    A = np.zeros((n, n))
    A[np.arange(n - 1), np.arange(1, n)] = 1.0
    A[-1] = -den[::-1][:n]
    B = np.zeros(n)
    B[-1] = 1.0
    return A, B


def _weighted_lstsq(N: NDArray, y: NDArray, sw: NDArray) -> NDArray[np.float64]:
    """``argmin_c || sw * (y - N c) ||`` with column scaling (empty ``N``: no parameters).

    ``y`` may have several columns (one solution column each).
    """
    if N.shape[1] == 0:
        return np.zeros((0,) + y.shape[1:])
    Nw = N * sw[:, None]
    sc = np.linalg.norm(Nw, axis=0)
    sc[sc == 0] = 1.0
    yw = y * (sw if y.ndim == 1 else sw[:, None])
    c = np.linalg.lstsq(Nw / sc, yw, rcond=None)[0]
    return c / (sc if y.ndim == 1 else sc[:, None])


def _orth(M: NDArray) -> NDArray[np.float64]:
    """Orthonormal basis of the column space of ``M`` (rank by a relative tolerance)."""
    if M.shape[1] == 0:
        return M
    scale = np.linalg.norm(M, axis=0)
    scale[scale == 0] = 1.0
    U, s, _ = np.linalg.svd(M / scale, full_matrices=False)
    keep = s > 1e-10 * s[0] if s.size and s[0] > 0 else np.zeros(s.size, dtype=bool)
    return U[:, keep]


def _sums(y: NDArray, yh: NDArray, w: NDArray) -> tuple[float, float]:
    """Weighted squared error and weighted spread about the weighted mean."""
    mean = float(np.sum(w * y) / np.sum(w))
    return float(np.sum(w * (y - yh) ** 2)), float(np.sum(w * (y - mean) ** 2))


def _pooled_fit(ys: list[NDArray], yhats: list[NDArray], ws: list[NDArray]) -> float:
    """Fit percent of several records pooled: each record about its own mean."""
    err = spread = 0.0
    for y, yh, w in zip(ys, yhats, ws, strict=True):
        e, s = _sums(y, yh, w)
        err += e
        spread += s
    if spread == 0:
        raise DataError("fit is undefined: every measured output is constant")
    return 100.0 * (1.0 - np.sqrt(err / spread))


def _record_fit(y: NDArray, yh: NDArray, w: NDArray) -> float:
    err, spread = _sums(y, yh, w)
    if spread == 0:
        return float("nan")
    return 100.0 * (1.0 - np.sqrt(err / spread))


# =========================================================================== the problem
def _trend(tf: object) -> bool:
    """Whether ``tf`` fits a linear trend per record (the search for an integrating model)."""
    return bool(getattr(tf, "_trend", False))


class _Problem:
    """Output-error problem for a fixed order: regressors, projection, model output.

    Nuisance columns per record: the offset, the free responses of the
    initial state (when free) and, with ``trend``, a linear trend.
    """

    def __init__(
        self,
        records: list[Record],
        n_poles: int,
        n_zeros: int,
        *,
        intersample: str,
        offset: bool,
        initial_state: str,
        trend: bool = False,
    ) -> None:
        self.records = records
        self.trend = trend
        self.n = n_poles
        self.m = n_zeros
        self.intersample = intersample
        self.offset = offset
        self.free = [
            initial_state == "estimate" or (initial_state == "auto" and r.kind == "io")
            for r in records
        ]
        self.y = [np.asarray(r.y) for r in records]
        self.w = [np.asarray(r.weights) for r in records]
        self.sw = [np.sqrt(w) for w in self.w]
        self.n_eval = 0

    # ------------------------------------------------------------------ pieces
    def input(self, rec: Record, delay: float) -> PiecewiseInput:
        if rec.kind == "io":
            return sampled_input(rec.t, rec.u - rec.u_before, delay=delay,
                                 intersample=self.intersample)
        assert rec.start is not None and rec.amplitude is not None  # set by Record
        if rec.kind == "step":
            return step_input(rec.start + delay, rec.amplitude)
        return impulse_input(rec.start + delay, rec.amplitude)

    def columns(
        self, den: NDArray, delay: float, rec: Record, free: bool
    ) -> tuple[NDArray, NDArray]:
        """Numerator regressors ``(n_t, m + 1)`` and nuisance columns ``(n_t, q)``."""
        A, B = _companion(den)
        inp = self.input(rec, delay)
        X = propagate(A, B, rec.t, inp, X0=np.eye(self.n) if free else None)
        states = X[:, :, 0]
        if self.m < self.n:
            R = states[:, : self.m + 1]
        else:
            top = inp.value_at(rec.t) - states @ den[::-1][: self.n]
            R = np.column_stack([states, top])
        nuis = []
        if self.offset:
            nuis.append(np.ones((rec.t.size, 1)))
        if free:
            nuis.append(X[:, 0, 1:])
        if self.trend:  # the integrated input's level error (see structure._integrated)
            nuis.append(((rec.t - rec.t[0]) / max(rec.duration, 1e-300))[:, None])
        N = np.hstack(nuis) if nuis else np.zeros((rec.t.size, 0))
        return R, N

    def all_columns(self, den: NDArray, delay: float) -> list[tuple[NDArray, NDArray]]:
        return [self.columns(den, delay, r, f) for r, f in zip(self.records, self.free,
                                                                strict=True)]

    @staticmethod
    def solve(cols: list[tuple[NDArray, NDArray]], ys: list[NDArray], sws: list[NDArray]
              ) -> tuple[NDArray, list[NDArray], NDArray]:
        """Numerator by projected weighted least squares, then each record's nuisance.

        Returns the numerator (coefficient of ``s^i`` at index ``i``), the
        nuisance parameters of every record, and the weighted residual.
        """
        Rt, yt = [], []
        for (R, N), y, sw in zip(cols, ys, sws, strict=True):
            Q = _orth(N * sw[:, None])
            Rw, yw = R * sw[:, None], y * sw
            Rt.append(Rw - Q @ (Q.T @ Rw))
            yt.append(yw - Q @ (Q.T @ yw))
        Rs, ys_ = np.vstack(Rt), np.concatenate(yt)
        scale = np.linalg.norm(Rs, axis=0)
        scale[scale == 0] = 1.0
        b = np.linalg.lstsq(Rs / scale, ys_, rcond=None)[0] / scale
        resid = ys_ - Rs @ b
        nuis = []
        for (R, N), y, sw in zip(cols, ys, sws, strict=True):
            nuis.append(_weighted_lstsq(N, y - R @ b, sw))
        return b, nuis, resid

    def residual(self, den: NDArray, delay: float) -> NDArray[np.float64]:
        self.n_eval += 1
        return self.solve(self.all_columns(den, delay), self.y, self.sw)[2]

    def outputs(self, den: NDArray, delay: float, b: NDArray, nuis: list[NDArray]
                ) -> list[NDArray]:
        cols = self.all_columns(den, delay)
        return [R @ b + N @ c for (R, N), c in zip(cols, nuis, strict=True)]
