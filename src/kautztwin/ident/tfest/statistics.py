"""Statistics of a fitted transfer function: covariance, fits, AIC and the validation fit."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..records import MIN_SAMPLES, Record
from .model import TransferFunctionModel
from .problem import _pooled_fit, _Problem, _record_fit, _weighted_lstsq

if TYPE_CHECKING:
    from .estimator import TransferFunctionEstimator

_LOG2PI1 = float(np.log(2 * np.pi) + 1)


def finalize(tf: TransferFunctionEstimator, prob: _Problem, recs: list[Record], den: NDArray,
             tau: float, estimate_delay: bool, sol: Any) -> TransferFunctionModel:
    """The model of a refined denominator with its covariance, fits, AIC and validation fit."""
    n, m = prob.n, prob.m
    cols = prob.all_columns(den, tau)
    b, nuis, resid = _Problem.solve(cols, prob.y, prob.sw)
    yhat = [R @ b + N @ c for (R, N), c in zip(cols, nuis, strict=True)]
    sw_all = np.concatenate(prob.sw)
    resid = sw_all * np.concatenate([y - yh for y, yh in zip(prob.y, yhat, strict=True)])
    rss = float(resid @ resid)
    N_s = float(np.sum(sw_all**2))  # rows as logged (merged rows count with their weight)
    # Jacobian of the (weighted) model output: numerator, denominator, delay, nuisance
    jac_cols = [np.concatenate([R[:, j] for R, _ in cols]) for j in range(m, -1, -1)]
    names = [f"num[{i}]" for i in range(m + 1)] + [f"den[{i}]" for i in range(1, n + 1)]

    def model_out(d: NDArray, t_: float) -> NDArray:
        cc = prob.all_columns(d, t_)
        return np.concatenate([R @ b + N @ c for (R, N), c in zip(cc, nuis, strict=True)])


    for i in range(1, n + 1):
        h = 1e-6 * max(abs(den[i]), 1e-12)
        dp, dm = den.copy(), den.copy()
        dp[i] += h
        dm[i] -= h
        jac_cols.append((model_out(dp, tau) - model_out(dm, tau)) / (2 * h))
    if estimate_delay:
        dt = float(min(np.median(np.diff(r.t)) for r in prob.records))
        h = 1e-6 * max(dt, tau)
        if tau > h:
            jac_cols.append((model_out(den, tau + h) - model_out(den, tau - h)) / (2 * h))
        else:
            jac_cols.append((model_out(den, tau + h) - model_out(den, tau)) / h)
        names.append("delay")
    n_model = len(jac_cols)
    offs = []
    start = 0
    for (R, N), c in zip(cols, nuis, strict=True):
        for j in range(N.shape[1]):
            col = np.zeros(sw_all.size)
            col[start : start + R.shape[0]] = N[:, j]
            jac_cols.append(col)
        offs.append(float(c[0]) if tf.offset and c.size else 0.0)
        start += R.shape[0]
    J = np.column_stack(jac_cols) * sw_all[:, None]
    p = J.shape[1]
    dof = max(N_s - p, 1.0)
    sigma2 = rss / dof
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    _, s, Vt = np.linalg.svd(J / scale, full_matrices=False)
    keep = s > 1e-12 * s[0]
    inv = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
    cov = sigma2 * inv / np.outer(scale, scale)
    cov = cov[:n_model, :n_model]
    # fits on the estimation data
    fit_rec = np.array([_record_fit(y, yh, w)
                        for y, yh, w in zip(prob.y, yhat, prob.w, strict=True)])
    fit_all = _pooled_fit(prob.y, yhat, prob.w)
    aic = N_s * np.log(max(rss, 1e-300) / N_s) + 2 * p + N_s * _LOG2PI1
    # validation
    val_fit, val_rec = None, None
    if tf.validate_from is not None:
        val_fit, val_rec = validation(tf, prob, recs, den, tau, b)
    return TransferFunctionModel(
        num=b[::-1].copy(), den=den, delay=tau, intersample=tf.intersample,
        covariance=cov, parameter_names=tuple(names), noise_variance=sigma2,
        fit_percent=float(fit_all), fit_percent_per_record=fit_rec,
        validation_fit_percent=val_fit, validation_fit_percent_per_record=val_rec,
        aic=float(aic), n_samples=int(round(N_s)), n_parameters=int(p),
        offsets=np.array(offs),
        record_names=tuple(r.name for r in prob.records), success=bool(sol.success),
        message=str(sol.message),
    )

def nuisance(prob: _Problem, rec: Record, free: bool, den: NDArray, tau: float,
             b: NDArray, mask: NDArray) -> tuple[NDArray, NDArray]:
    """Model output over the whole record, nuisance fitted on the samples in ``mask``."""
    R, N = prob.columns(den, tau, rec, free)
    y = np.asarray(rec.y)
    sw = np.sqrt(np.asarray(rec.weights))
    c = _weighted_lstsq(N[mask], y[mask] - R[mask] @ b, sw[mask])
    return R @ b + N @ c, c

def validation(tf: TransferFunctionEstimator, prob: _Problem, recs: list[Record], den: NDArray,
               tau: float, b: NDArray) -> tuple[float | None, NDArray | None]:
    """Pooled and per-record fits on the samples at ``t >= validate_from``."""
    T = float(tf.validate_from)  # type: ignore[arg-type]
    ys, yhs, ws, per = [], [], [], []
    for r in recs:
        vmask = r.t >= T
        if vmask.sum() < 2:
            continue
        emask = ~vmask
        free = tf.initial_state == "estimate" or (
            tf.initial_state == "auto" and r.kind == "io")
        use = emask if emask.sum() >= MIN_SAMPLES else vmask
        yh, _ = nuisance(prob, r, free, den, tau, b, use)
        ys.append(np.asarray(r.y)[vmask])
        yhs.append(yh[vmask])
        ws.append(np.asarray(r.weights)[vmask])
        per.append(_record_fit(ys[-1], yhs[-1], ws[-1]))
    if not ys:
        return None, None
    return float(_pooled_fit(ys, yhs, ws)), np.array(per)
