"""Initial poles of the refinement, from orthonormal-basis (Kautz, Laguerre) regressions."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from ...exceptions import KautzTwinError
from ..records import Record
from ..simulate import propagate
from .problem import _Problem


def _unit_responses(records: list[Record]) -> tuple[NDArray, NDArray, str]:
    """Step or impulse records as unit responses on one uniform grid from the event."""
    kind = records[0].kind
    spans, steps, pieces = [], [], []
    for r in records:
        assert r.start is not None and r.amplitude is not None
        after = r.t >= r.start
        before = r.t <= r.start
        level = float(np.mean(r.y[before]))
        tt = r.t[after] - r.start
        pieces.append((tt, (r.y[after] - level) / r.amplitude))
        spans.append(tt[-1])
        steps.append(float(np.median(np.diff(r.t))))
    span = float(min(spans))
    dt = float(min(steps))
    n = int(min(max(round(span / dt) + 1, 8), 400))  # a start only: a coarse grid will do
    tg = np.linspace(0.0, span, n)
    H = np.array([np.interp(tg, tt, h) for tt, h in pieces])
    return tg, H, kind


def _reduced_poles(A: NDArray, B: NDArray, c: NDArray, n: int) -> NDArray[np.complex128] | None:
    """Poles of the balanced truncation to order ``n`` of ``(A, B, c)`` (orthonormal basis).

    For an orthonormal basis the controllability Gramian is the identity, so the
    balanced truncation keeps the dominant eigenvectors ``V_r`` of the
    observability Gramian, and its poles are those of ``V_r^T A V_r``.
    """
    try:
        Q = scipy.linalg.solve_continuous_lyapunov(A.T, -np.outer(c, c))
        P = scipy.linalg.solve_continuous_lyapunov(A, -np.outer(B, B))
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not np.allclose(P, np.eye(A.shape[0]), atol=1e-6):
        # general square-root balancing
        try:
            Lp = np.linalg.cholesky(P + 1e-14 * np.eye(P.shape[0]))
            Lq = np.linalg.cholesky(Q + 1e-14 * np.eye(Q.shape[0]))
        except np.linalg.LinAlgError:
            return None
        U, s, Vt = np.linalg.svd(Lq.T @ Lp)
        S = np.diag(s[:n] ** -0.5)
        T = Lp @ Vt[:n].T @ S
        Ti = S @ U[:, :n].T @ Lq.T
        return np.linalg.eigvals(Ti @ A @ T)
    w, V = np.linalg.eigh((Q + Q.T) / 2)
    Vr = V[:, np.argsort(w)[::-1][:n]]
    return np.linalg.eigvals(Vr.T @ A @ Vr)


def _obf_starts(records: list[Record], n: int, rate_lo: float, intersample: str
                ) -> list[NDArray[np.complex128]]:
    """Candidate initial poles from orthonormal-basis regressions."""
    from ...approx import optimize_poles
    from ...basis import LaguerreBasis

    starts: list[NDArray[np.complex128]] = []
    kinds = {r.kind for r in records}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kinds <= {"step", "impulse"} and len(kinds) == 1:
            tg, H, kind = _unit_responses(records)
            for N in (n, n + 2):
                if 2 * N >= tg.size:
                    continue
                try:
                    res = optimize_poles(tg, H, N, kind=kind, max_iter=20 if N == n else 12)
                except (KautzTwinError, np.linalg.LinAlgError, ValueError):
                    continue
                if N == n:
                    starts.append(res.basis.poles)
                else:
                    c = np.atleast_2d(res.coefficients).mean(axis=0)
                    red = _reduced_poles(res.basis.A, res.basis.B, c, n)
                    if red is not None:
                        starts.append(red)
            return starts
        # input/output records: Laguerre regression, then Kautz poles for its impulse response
        dt = float(min(np.median(np.diff(r.t)) for r in records))
        span = float(max(r.duration for r in records))
        n_lag = int(min(12, max(2 * n + 2, 8)))
        prob = _Problem(records, n_lag, n_lag - 1, intersample=intersample, offset=True,
                        initial_state="zero")
        best = None
        rate = 2.0 / dt
        while rate >= 2.0 / span:
            basis = LaguerreBasis(pole=-rate, n=n_lag)
            cols = []
            for r in records:
                X = propagate(basis.A, basis.B, r.t, prob.input(r, 0.0))[:, :, 0]
                cols.append((X, np.ones((r.t.size, 1))))
            c, _, resid = _Problem.solve(cols, prob.y, prob.sw)
            cost = float(resid @ resid)
            if best is None or cost < best[0]:
                best = (cost, basis, c)
            rate /= 2.0
        if best is None:
            return starts
        _, basis, c = best
        red = _reduced_poles(basis.A, basis.B, c, n)
        if red is not None:
            starts.append(red)
        th = min(span, 12.0 / (-basis.poles[0].real))
        tg = np.linspace(0.0, th, 400)
        h = c @ basis.evaluate(tg)
        if np.ptp(h) > 0:
            try:
                res = optimize_poles(tg, h, n, kind="impulse", max_iter=20)
                starts.append(res.basis.poles)
            except (KautzTwinError, np.linalg.LinAlgError, ValueError):
                pass
    return starts
