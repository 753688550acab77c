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
from .problem import _den_from_theta, _Problem, _theta_bounds, _theta_from_poles
from .starts import _obf_starts
from .statistics import finalize

if TYPE_CHECKING:
    from .estimator import TransferFunctionEstimator


def fit_order(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record], n: int,
              m: int) -> TransferFunctionModel:
    """Fit order ``n`` with ``m`` zeros: multi-start output-error refinement, then statistics."""
    prob = _Problem(est, n, m, intersample=tf.intersample, offset=bool(tf.offset),
                    initial_state=tf.initial_state)
    n_lin = (m + 1) + sum((1 if tf.offset else 0) + (n if f else 0) for f in prob.free)
    estimate_delay = tf.delay is True
    n_total = n_lin + n + (1 if estimate_delay else 0)
    n_samples = sum(r.n_samples for r in est)
    if n_samples <= n_total:
        raise DataError(
            f"the records are too short: {n_samples} estimation samples for {n_total} "
            f"parameters (order {n}, {m} zeros{', delay' if estimate_delay else ''}, "
            "offsets and initial states); give longer records or a lower order"
        )
    dt = float(min(np.median(np.diff(r.t)) for r in est))
    span = float(max(r.duration for r in est))
    rate_lo, rate_hi = 0.01 / span, 50.0 / dt
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

    # ---- starts
    starts = []
    for poles in _obf_starts(est, n, rate_lo, tf.intersample):
        if poles is None or len(poles) != n or not np.all(np.isfinite(poles)):
            continue
        starts.append(_theta_from_poles(poles, n))
    # a generic start from the record length scale
    p0 = 4.0 / span
    starts.append(_theta_from_poles(-p0 * 2.0 ** np.arange(n), n))
    x_starts = []
    for th in starts:
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
                      ConvergenceWarning, stacklevel=3)
    den, tau = unpack(best.x)
    for p in np.roots(den):
        if -p.real >= rate_lo:
            continue
        if abs(p.imag) > 1e-9 * abs(p):
            warnings.warn(
                f"the model has a nearly undamped pole pair at {complex(p):.3g} (it reached "
                "the stability limit); try fewer poles or zeros", ConvergenceWarning,
                stacklevel=3)
        else:
            warnings.warn(
                f"the model has a pole at {p.real:.3g}, slower than 0.01 / record length: "
                "the records cannot resolve it (it acts as a drift or offset); try fewer "
                "poles or zeros", ConvergenceWarning, stacklevel=3)
        break
    return finalize(tf, prob, recs, den, tau, estimate_delay, best)
