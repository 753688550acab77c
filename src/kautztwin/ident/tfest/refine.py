"""Output-error refinement of one order: multi-start bounded least squares over the denominator."""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.optimize
from numpy.typing import NDArray

from ...exceptions import ConvergenceWarning, DataError
from ..records import Record
from .model import TransferFunctionModel
from .problem import _den_from_theta, _Problem, _theta_bounds, _theta_from_poles, _trend
from .starts import _obf_starts
from .statistics import finalize

if TYPE_CHECKING:
    from .estimator import TransferFunctionEstimator

def fit_order(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record], n: int,
              m: int, *, starts: list[tuple[NDArray, float]] | None = None
              ) -> TransferFunctionModel:
    """Fit order ``n`` with ``m`` zeros: multi-start output-error refinement, then statistics.

    ``starts`` (poles, delay) replace the orthonormal-basis starts: the one of
    lowest initial cost is refined to convergence (the structure search's warm start).
    """
    prob, den, tau, best = refine_order(tf, est, n, m, starts=starts)
    return finalize(tf, prob, recs, den, tau, tf.delay is True, best)


def check_samples(tf: TransferFunctionEstimator, est: list[Record], n: int, m: int) -> None:
    """Raise the one-line error when the estimation samples cannot carry order ``n``."""
    free = sum((1 if tf.offset else 0) + (
        n if (tf.initial_state == "estimate" or (tf.initial_state == "auto" and r.kind == "io"))
        else 0) for r in est)
    estimate_delay = tf.delay is True
    n_total = (m + 1) + free + n + (1 if estimate_delay else 0)
    n_samples = sum(r.n_samples for r in est)
    if n_samples < 2 * n_total:
        raise DataError(
            f"the records are too short: {n_samples} estimation samples for {n_total} "
            f"parameters (order {n}, {m} zeros{', delay' if estimate_delay else ''}, "
            "offsets and initial states; at least two samples per parameter are needed); "
            "give longer records or a lower order"
        )


def refine_order(tf: TransferFunctionEstimator, est: list[Record], n: int, m: int, *,
                 starts: list[tuple[NDArray, float]] | None = None, multistart: bool = False,
                 max_iter: int | None = None, min_rate: float | None = None,
                 stop_unresolved: bool = False) -> tuple[_Problem, NDArray, float, Any]:
    """Output-error refinement of order ``n``: the problem, denominator, delay and solution.

    Without ``starts`` the starts are the orthonormal-basis ones (:func:`fit_order`).
    With ``starts`` (poles, delay) and ``multistart=False`` the best of them is
    refined alone (``tf.max_iter`` iterations, or ``max_iter`` residual
    evaluations besides the Jacobians for a brief refinement); with
    ``multistart=True`` they join the orthonormal-basis starts.  ``min_rate``
    replaces the slowest allowed pole rate ``0.01 / record length``; with
    ``stop_unresolved`` a refinement from ``starts`` stops at the first iterate
    with a pole slower than ``min_rate`` (see :func:`_refine_from`).
    """
    prob = _Problem(est, n, m, intersample=tf.intersample, offset=bool(tf.offset),
                    initial_state=tf.initial_state, trend=_trend(tf))
    check_samples(tf, est, n, m)
    estimate_delay = tf.delay is True
    dt = float(min(np.median(np.diff(r.t)) for r in est))
    span = float(max(r.duration for r in est))
    rate_lo, rate_hi = 0.01 / span, 50.0 / dt
    if min_rate is not None:
        rate_lo = float(min_rate)
    lo, hi = _theta_bounds(n, rate_lo, rate_hi)
    fixed_delay = 0.0 if isinstance(tf.delay, bool) else float(tf.delay)
    tau_max = 0.25 * float(min(r.duration for r in est))
    if estimate_delay:
        lo = np.append(lo, 0.0)
        hi = np.append(hi, tau_max)

    def unpack(x: NDArray) -> tuple[NDArray, float]:
        return _den_from_theta(x[:n], n), (float(x[n]) if estimate_delay else fixed_delay)

    def fun(x: NDArray) -> NDArray:
        den, tau = unpack(x)
        return prob.residual(den, tau)

    def clip(x: NDArray) -> NDArray:
        span_ = hi - lo
        return np.clip(x, lo + 1e-9 * span_, hi - 1e-9 * span_)

    if starts is not None and not multistart:
        nfev = int(tf.max_iter) * (lo.size + 1) if max_iter is None else int(max_iter)
        den, tau, sol = _refine_from(tf, prob, starts, n, lo, hi, unpack, fun, clip, dt,
                                     estimate_delay, nfev,
                                     min_rate=min_rate if stop_unresolved else None)
        if not sol.success and max_iter is None and sol.status != -2:
            warnings.warn(f"the output-error refinement did not converge: {sol.message}",
                          ConvergenceWarning, stacklevel=4)
        _warn_slow_poles(den, rate_lo, "0.01 / record length" if min_rate is None
                         else f"{rate_lo:.3g} (the slowest rate allowed)")
        return prob, den, tau, sol
    # ---- starts
    thetas = []
    for poles in _obf_starts(est, n, rate_lo, tf.intersample):
        if poles is None or len(poles) != n or not np.all(np.isfinite(poles)):
            continue
        thetas.append(_theta_from_poles(poles, n))
    # a generic start from the record length scale
    p0 = 4.0 / span
    thetas.append(_theta_from_poles(-p0 * 2.0 ** np.arange(n), n))
    for poles, _ in starts or []:  # warm starts join the multi-start
        thetas.append(_theta_from_poles(poles, n))
    x_starts = []
    for th in thetas:
        th = np.clip(th, lo[:n] + 1e-6, hi[:n] - 1e-6)
        if estimate_delay:
            grid = np.unique(np.concatenate([dt * np.arange(11), np.linspace(0, tau_max, 17)]))
            grid = grid[grid <= tau_max]
            costs = [float(np.sum(fun(np.append(th, g)) ** 2)) for g in grid]
            th = np.append(th, grid[int(np.argmin(costs))])
        x_starts.append(clip(th))
    # rank the starts by their initial cost; a short refinement of the best few, then
    # (with any random restarts) the best one to convergence
    init_cost = [float(np.sum(fun(x) ** 2)) for x in x_starts]
    order = np.argsort(init_cost)[:3]
    x_scale = np.ones(lo.size)
    if estimate_delay:
        x_scale[-1] = dt

    def refine(x0: NDArray, iters: int) -> Any:
        return scipy.optimize.least_squares(
            fun, clip(x0), bounds=(lo, hi), method="trf", x_scale=x_scale,
            ftol=tf.tol, xtol=tf.tol, gtol=tf.tol, max_nfev=iters * (lo.size + 1),
        )

    short = min(15, int(tf.max_iter))
    trials = [refine(x_starts[i], short) for i in order]
    best = min(trials, key=lambda sol: sol.cost)
    rng = np.random.default_rng(tf.random_state)
    for _ in range(int(tf.n_restarts)):
        pert = best.x + rng.normal(0.0, 0.5, best.x.size) * (np.arange(best.x.size) < n)
        sol = refine(pert, short)
        if sol.cost < best.cost:
            best = sol
    if not best.success:
        sol = refine(best.x, int(tf.max_iter))
        if sol.cost <= best.cost:
            best = sol
    assert best is not None
    tf.n_evaluations_ += prob.n_eval
    if not best.success:
        warnings.warn(f"the output-error refinement did not converge: {best.message}",
                      ConvergenceWarning, stacklevel=4)
    den, tau = unpack(best.x)
    _warn_slow_poles(den, rate_lo, "0.01 / record length")
    return prob, den, tau, best


def _refine_from(tf: TransferFunctionEstimator, prob: _Problem,
                 starts: list[tuple[NDArray, float]], n: int, lo: NDArray, hi: NDArray,
                 unpack: Any, fun: Any, clip: Any, dt: float, estimate_delay: bool,
                 max_nfev: int, min_rate: float | None = None) -> tuple[NDArray, float, Any]:
    """Refine the best of given (poles, delay) starts to convergence (no multi-start).

    With ``min_rate`` (the structure search's refinement of its pick to
    convergence) the refinement stops at the first iterate with a pole slower
    than ``min_rate``: the search rejects such a model (a mode the records
    cannot resolve), and a refinement to convergence that reached one was not
    seen to leave it again; the iterate is returned as it is
    (``sol.status == -2``).  Brief refinements do return from there at times
    (a few iterations through the slow region, then back), so they are never
    stopped (``least_squares``' callback, SciPy >= 1.16).
    """
    # the residual of the chosen start is the refinement's first evaluation: kept, not redone
    seen: dict[bytes, NDArray] = {}

    def cost(x: NDArray) -> float:
        r = seen[x.tobytes()] = fun(x)
        return float(np.sum(r**2))

    def first(x: NDArray) -> NDArray:
        r = seen.pop(np.asarray(x, dtype=float).tobytes(), None) if seen else None
        return fun(x) if r is None else r.copy()

    xs = []
    for poles, tau in starts:
        th = np.clip(_theta_from_poles(poles, n), lo[:n] + 1e-6, hi[:n] - 1e-6)
        xs.append(clip(np.append(th, tau) if estimate_delay else th))
    x0 = xs[0] if len(xs) == 1 else xs[int(np.argmin([cost(x) for x in xs]))]
    if estimate_delay:  # the delay of the best start on a grid about it, as fit_order does
        grid = np.unique(np.concatenate([x0[-1] + dt * np.arange(-3, 4),
                                         np.linspace(lo[-1], hi[-1], 9)]))
        grid = grid[(grid >= lo[-1]) & (grid <= hi[-1])]
        cands = [clip(np.append(x0[:n], g)) for g in grid]
        x0 = cands[int(np.argmin([cost(x) for x in cands]))]
    x0 = np.asarray(x0, dtype=float)
    seen = {k: v for k, v in seen.items() if k == x0.tobytes()}
    x_scale = np.ones(lo.size)
    if estimate_delay:
        x_scale[-1] = dt
    kw: dict[str, Any] = {}
    if min_rate is not None:
        def unresolved(intermediate_result: Any) -> None:
            if np.min(-np.roots(unpack(intermediate_result.x)[0]).real) < min_rate:
                raise StopIteration

        kw["callback"] = unresolved
    best = scipy.optimize.least_squares(
        first, x0, bounds=(lo, hi), method="trf", x_scale=x_scale,
        ftol=tf.tol, xtol=tf.tol, gtol=tf.tol, max_nfev=max_nfev, **kw,
    )
    tf.n_evaluations_ += prob.n_eval
    prob.n_eval = 0
    den, tau = unpack(best.x)
    return den, tau, best


def _warn_slow_poles(den: NDArray, rate_lo: float, bound: str) -> None:
    for p in np.roots(den):
        if -p.real >= rate_lo:
            continue
        if abs(p.imag) > 1e-9 * abs(p):
            warnings.warn(
                f"the model has a nearly undamped pole pair at {complex(p):.3g} (it reached "
                "the stability limit); try fewer poles or zeros", ConvergenceWarning,
                stacklevel=4)
        else:
            warnings.warn(
                f"the model has a pole at {p.real:.3g}, slower than {bound}: "
                "the records cannot resolve it (it acts as a drift or offset); try fewer "
                "poles or zeros", ConvergenceWarning, stacklevel=4)
        break
