r"""Integrating models :math:`G(s)/s`: fitted as :math:`G` on the integrated input.

A plant with a pole at :math:`s = 0` (a level fed by a flow, a position driven
by a velocity) cannot be fitted by the stable denominators of
:mod:`.problem`.  With a held (zero-order hold) input, the integrated input

.. math::

    v(t) = \int_{t_0}^{t} \big(u(\tau) - \bar u\big)\,d\tau

is exactly piecewise linear between the samples, so :math:`G(s)/s` driven by
:math:`u - \bar u` is :math:`G(s)` driven by :math:`v` with a first-order
hold, and :math:`G` is a stable model that the usual machinery fits
(:func:`integrated`).  The level :math:`\bar u` at which the integrator
balances is not known: a level :math:`\bar u + d` integrates to
:math:`v - d\,(t - t_0)`, which :math:`G` turns into the trend
:math:`-d\,G(0)\,(t - t_0)` plus terms the offset and the initial state
absorb.  So :math:`G` is fitted with one linear trend per record (a nuisance
column, :class:`~.problem._Problem` ``trend``), starting from the mean
estimation input, and the level is corrected from the trend
(:func:`input_level`).  :func:`integrating_model` turns :math:`G` into the
model :math:`G(s)/s` acting from that level, its statistics computed on the
records as they are (what :meth:`TransferFunctionEstimator.predict` simulates).
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from ...exceptions import DataError
from ..records import Record
from .model import TransferFunctionModel
from .problem import _Problem, _weighted_lstsq
from .refine import fit_order
from .statistics import finalize

if TYPE_CHECKING:
    from .estimator import TransferFunctionEstimator

__all__: list[str] = []


def check_integrable(tf: TransferFunctionEstimator, recs: list[Record]) -> str | None:
    """Why ``G(s)/s`` cannot be fitted exactly to ``recs`` (``None`` when it can)."""
    if tf.intersample != "zoh":
        return "an integrator needs a held input (intersample='zoh')"
    if any(r.kind != "io" for r in recs):
        return "an integrator needs input/output records (not step or impulse records)"
    return None


def mean_level(est: list[Record]) -> float:
    """Weighted mean input of the estimation records (the first guess of the level)."""
    w = np.concatenate([np.asarray(r.weights) for r in est])
    return float(np.sum(w * np.concatenate([r.u for r in est])) / np.sum(w))


def integrated(r: Record, level: float) -> Record:
    """The record with its input integrated from ``level``: ``v(t) = int (u - level) dt``."""
    v = np.concatenate([[0.0], np.cumsum((r.u[:-1] - level) * np.diff(r.t))])
    return Record(r.t, v, r.y, kind="io", u_before=0.0, name=r.name, weights=r.weights)


def inner_estimator(tf: TransferFunctionEstimator) -> TransferFunctionEstimator:
    """A copy of ``tf`` that fits ``G`` to integrated records (first-order hold, trends)."""
    inner = type(tf)(**{**tf.get_params(), "intersample": "foh", "integrator": False})
    inner._trend = True  # type: ignore[attr-defined]
    inner.n_evaluations_ = 0
    return inner


def input_level(tf: TransferFunctionEstimator, g: TransferFunctionModel, est_v: list[Record],
                mean: float) -> float:
    """Level of ``G(s)/s`` from the trends of ``G``'s fit to the integrated records.

    ``d = -slope / G(0)`` (the slopes of several records averaged by their
    weights); ``mean`` when ``G(0)`` vanishes.
    """
    prob = _Problem(est_v, g.n_poles, g.n_zeros, intersample=g.intersample,
                    offset=bool(tf.offset), initial_state=tf.initial_state, trend=True)
    b = g.num[::-1]
    slopes, weights = [], []
    for r, free in zip(est_v, prob.free, strict=True):
        R, N = prob.columns(g.den, g.delay, r, free)
        sw = np.sqrt(np.asarray(r.weights))
        c = _weighted_lstsq(N, np.asarray(r.y) - R @ b, sw)
        slopes.append(float(c[-1]) / max(r.duration, 1e-300))
        weights.append(float(np.sum(sw**2)))
    gain = float(g.num[-1] / g.den[-1])
    if not math.isfinite(gain) or abs(gain) < 1e-12:
        return mean
    return mean - float(np.average(slopes, weights=weights)) / gain


def integrating_model(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record],
                      g: TransferFunctionModel, level: float,
                      rows: tuple[dict[str, Any], ...] = ()) -> TransferFunctionModel:
    """``G(s)/s`` acting from ``level``, its statistics from the records as they are.

    The numerator, offsets, initial states and fits are those of the held
    input from ``level`` (what :meth:`TransferFunctionEstimator.predict`
    simulates); the covariance is that of ``G``'s parameters (the integrator
    is fixed); the parameter count includes the input level.
    """
    def at_level(rs: list[Record]) -> list[Record]:
        return [dataclasses.replace(r, u_before=level) for r in rs]

    den = np.append(g.den, 0.0)
    prob = _Problem(at_level(est), g.n_poles + 1, g.n_zeros, intersample="zoh",
                    offset=bool(tf.offset), initial_state=tf.initial_state)
    sol = SimpleNamespace(success=g.success, message=g.message)
    m = finalize(tf, prob, at_level(recs), den, g.delay, tf.delay is True, sol)
    return dataclasses.replace(m, covariance=g.covariance, parameter_names=g.parameter_names,
                               input_level=level, order_selection=rows)


def fit_integrating(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record],
                    n: int, m: int) -> TransferFunctionModel:
    """Fit ``G(s)/s`` with ``n`` poles in all (the integrator included) and ``m`` zeros."""
    why = check_integrable(tf, recs)
    if why is not None:
        raise DataError(why)
    if n < 2 or m > n - 1:
        raise DataError(f"an integrating model needs n_poles >= 2 and n_zeros <= n_poles - 1 "
                        f"(a pole at 0 and a proper G); got n_poles = {n}, n_zeros = {m}")
    mean = mean_level(est)
    inner = inner_estimator(tf)
    g = fit_order(inner, [integrated(r, mean) for r in recs],
                  [integrated(r, mean) for r in est], n - 1, m)
    tf.n_evaluations_ += inner.n_evaluations_
    level = input_level(inner, g, [integrated(r, mean) for r in est], mean)
    return integrating_model(tf, recs, est, g, level)
