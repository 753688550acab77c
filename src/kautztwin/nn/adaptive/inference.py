"""Inference of the adaptive-pole estimator: network poles, VarPro refinement, least squares.

Also the Jacobian of the fitted responses that their uncertainty needs.

Functions of a trained :class:`~kautztwin.nn.AdaptivePoleNetwork` and checked records
(float64 arrays of shape ``(n_records, n_samples)``), batched by
:data:`~kautztwin.nn.adaptive.network.RECORD_BATCH` records without gradients.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from ...approx import optimize_poles
from ...basis._blocks import parse_poles
from ...exceptions import ConvergenceWarning, DataError, KautzTwinError
from ..estimator_base import checked_records
from ..kautz_torch import block_poles, response_weights
from .network import RECORD_BATCH, AdaptivePoleNetwork

__all__ = [
    "check_records",
    "least_squares_fit",
    "predict_params",
    "refine_constrained",
    "refine_params",
    "response_jacobian",
    "weights_tensor",
]


def check_records(
    est: Any, responses: Any, t: ArrayLike | None
) -> tuple[NDArray[np.float64], bool]:
    """Records checked against a fitted estimator (a writable copy), none all zeros.

    Parameters
    ----------
    est : AdaptivePoleEstimator
        A fitted estimator.
    responses : array-like or ResponseDataset
        One record (1-D), many (2-D), or a data set.
    t : array-like or None
        Sample times of the records, checked against the estimator's grid.

    Returns
    -------
    X : ndarray of shape (n_records, n_samples)
    single : bool
        Whether one 1-D record was given.

    Raises
    ------
    DataError
        As :func:`~kautztwin.nn.estimator_base.checked_records`, or on an all-zero record.
    """
    X, single = checked_records(est, responses, t, copy=True)  # a writable copy
    if np.any(np.all(X == 0, axis=1)):
        i = int(np.argmax(np.all(X == 0, axis=1)))
        raise DataError(f"record {i} is all zeros; there are no poles to estimate")
    return X, single


def predict_params(module: AdaptivePoleNetwork, X: NDArray) -> NDArray[np.float64]:
    """Block parameters the network predicts for every record (float64).

    Parameters
    ----------
    module : AdaptivePoleNetwork
    X : ndarray of shape (n_records, n_samples)

    Returns
    -------
    ndarray of shape (n_records, n_params)
    """
    out = np.empty((X.shape[0], module.n_functions))
    dtype = module.projector.dtype
    with torch.no_grad():
        for s in range(0, X.shape[0], RECORD_BATCH):
            xb = torch.as_tensor(X[s : s + RECORD_BATCH], dtype=dtype)
            out[s : s + xb.shape[0]] = module(xb).double().numpy()
    return out


def refine_params(
    t: NDArray,
    kinds: tuple[str, ...],
    kind: str,
    X: NDArray,
    params: NDArray,
    max_iter: int,
) -> NDArray[np.float64]:
    """Variable-projection refinement of every record's block parameters.

    :func:`kautztwin.optimize_poles` started from ``params``; a record whose refinement
    fails or changes the block structure keeps its start.

    Parameters
    ----------
    t : ndarray of shape (n_samples,)
    kinds : tuple of str
        Block structure.
    kind : {'impulse', 'step'}
        What the records are.
    X : ndarray of shape (n_records, n_samples)
    params : ndarray of shape (n_records, n_params)
        Start values.
    max_iter : int
        ``max_iter`` of the refinement.

    Returns
    -------
    ndarray of shape (n_records, n_params)
    """
    out = params.copy()
    for i in range(X.shape[0]):
        start = block_poles(kinds, torch.from_numpy(params[i])).numpy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            try:
                res = optimize_poles(t, X[i], start, kind=kind, max_iter=int(max_iter))
            except (KautzTwinError, np.linalg.LinAlgError):
                continue
        got_kinds, p = parse_poles(res.basis.poles, 0.0)
        if got_kinds == kinds and np.all(np.isfinite(p)):
            out[i] = p
    return out


def refine_constrained(
    module: AdaptivePoleNetwork,
    X: NDArray,
    params: NDArray,
    w: torch.Tensor | None,
    max_iter: int,
    relative_degree: int,
) -> NDArray[np.float64]:
    """Variable projection under a relative-degree constraint, record by record.

    :func:`refine_params` optimises the poles of the *unconstrained* least-squares fit;
    with ``relative_degree > 1`` the fit keeps the first Markov parameters at zero, so the
    poles are refined for that fit instead: ``scipy.optimize.least_squares`` (trust region,
    finite-difference Jacobian) over the log block parameters, the residual being the
    record minus its constrained least-squares fit (:meth:`AdaptivePoleNetwork.least_squares`,
    float64).  A record whose refinement fails or does not lower the residual keeps its start.

    Parameters
    ----------
    module : AdaptivePoleNetwork
    X : ndarray of shape (n_records, n_samples)
    params : ndarray of shape (n_records, n_params)
        Start values.
    w : torch.Tensor or None
        Least-squares weights (:func:`weights_tensor`).
    max_iter : int
        Most Jacobian evaluations per record.
    relative_degree : int
        Degree of the fit.

    Returns
    -------
    ndarray of shape (n_records, n_params)
    """
    import scipy.optimize

    sw = None if w is None else np.sqrt(w.double().numpy())
    out = params.copy()

    def residual(log_p: NDArray, x: torch.Tensor) -> NDArray:
        P = torch.from_numpy(np.exp(log_p))[None]
        K = module.design(P)
        c = module.least_squares(K, x, P, w, relative_degree)
        r = (x - (c[:, None, :] @ K)[:, 0])[0].numpy()
        return r if sw is None else r * sw

    with torch.no_grad():
        for i in range(X.shape[0]):
            x = torch.as_tensor(X[i : i + 1], dtype=torch.float64)
            start = np.log(params[i])
            try:
                res = scipy.optimize.least_squares(
                    residual, start, args=(x,), method="trf", x_scale=1.0,
                    max_nfev=int(max_iter) * (start.size + 1),
                )
            except (ValueError, np.linalg.LinAlgError, RuntimeError):
                continue
            if np.all(np.isfinite(res.x)) and res.cost <= 0.5 * float(
                np.sum(residual(start, x) ** 2)
            ):
                out[i] = np.exp(res.x)
    return out


def weights_tensor(t: NDArray, rule: str, dtype: torch.dtype) -> torch.Tensor | None:
    """Least-squares weights of the ``weights`` option; ``None`` for ordinary least squares."""
    if rule == "uniform":
        return None  # ordinary least squares: skip the multiplication
    return response_weights(t, rule, dtype=dtype)


def least_squares_fit(
    module: AdaptivePoleNetwork,
    X: NDArray,
    params: NDArray,
    w: torch.Tensor | None,
    dtype: torch.dtype,
    *,
    responses: bool = False,
    relative_degree: int | None = None,
) -> NDArray[np.float64]:
    """Least-squares fit of every record on the basis of its block parameters.

    Parameters
    ----------
    module : AdaptivePoleNetwork
        Supplies the basis signals (:meth:`~AdaptivePoleNetwork.design`).
    X : ndarray of shape (n_records, n_samples)
    params : ndarray of shape (n_records, n_params)
    w : torch.Tensor or None
        Least-squares weights (:func:`weights_tensor`).
    dtype : torch.dtype
        Dtype of the basis and the least squares.
    responses : bool, default=False
        Return the fitted responses instead of the coefficients.
    relative_degree : int, optional
        Degree of the fit (default: the module's own).

    Returns
    -------
    ndarray of shape (n_records, n_functions), or (n_records, n_samples) with ``responses``
    """
    out = np.empty_like(X if responses else params)
    with torch.no_grad():
        for s in range(0, X.shape[0], RECORD_BATCH):
            P = torch.as_tensor(params[s : s + RECORD_BATCH], dtype=dtype)
            h = torch.as_tensor(X[s : s + RECORD_BATCH], dtype=dtype)
            K = module.design(P)
            c = module.least_squares(K, h, P, w, relative_degree)
            fit = (c[:, None, :] @ K)[:, 0] if responses else c
            out[s : s + P.shape[0]] = fit.double().numpy()
    return out


def response_jacobian(
    module: AdaptivePoleNetwork,
    params: NDArray,
    coef: NDArray,
    relative_degree: int | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]:
    """Fitted responses and their Jacobian in ``(params, coefficients)`` (float64, batched).

    The coefficient columns are the basis signals themselves (under a relative-degree
    constraint, their combinations that keep it: ``K^T Q`` with ``Q`` an orthonormal
    basis of the constraints' null space, ``relative_degree - 1`` columns fewer); the
    parameter columns are central differences of ``coef @ design(params)`` with a
    relative step of 1e-5.

    Parameters
    ----------
    module : AdaptivePoleNetwork
        Supplies the basis signals (:meth:`~AdaptivePoleNetwork.design`).
    params : ndarray of shape (n_records, n_params)
    coef : ndarray of shape (n_records, n_functions)
    relative_degree : int, optional
        Degree of the fit (default: the module's own).

    Returns
    -------
    fitted : ndarray of shape (n_records, n_samples)
    jac : ndarray of shape (n_records, n_samples, n_params + n_functions - relative_degree + 1)
    lift : ndarray of shape (n_records, n_params + n_functions, n_params + n_free) or None
        ``blockdiag(I, Q)``: maps the Jacobian's coordinates (parameters, free coefficient
        directions) to (parameters, coefficients), so that a covariance ``S`` of the former
        is ``lift S lift^T`` in the latter; ``None`` without a constraint (the identity).
    """
    n_rec, n_par = params.shape
    n_samples = int(module._t.size)
    r = module.relative_degree if relative_degree is None else int(relative_degree)
    n_free = coef.shape[1] - (r - 1)
    fitted = np.empty((n_rec, n_samples))
    jac = np.empty((n_rec, n_samples, n_par + n_free))
    lift = None
    if n_free < coef.shape[1]:
        lift = np.zeros((n_rec, n_par + coef.shape[1], n_par + n_free))
        lift[:, :n_par, :n_par] = np.eye(n_par)
    with torch.no_grad():
        for s in range(0, n_rec, RECORD_BATCH):
            P = torch.as_tensor(params[s : s + RECORD_BATCH], dtype=torch.float64)
            c = torch.as_tensor(coef[s : s + RECORD_BATCH], dtype=torch.float64)
            K = module.design(P)
            b = slice(s, s + P.shape[0])
            fitted[b] = (c[:, None, :] @ K)[:, 0].numpy()
            M = module.constraints(P, r)
            if M is None:
                jac[b, :, n_par:] = K.transpose(1, 2).numpy()
            else:  # the null space of M^T: the last columns of a complete QR of M
                Q = torch.linalg.qr(M, mode="complete").Q[:, :, M.shape[-1] :]
                jac[b, :, n_par:] = (K.transpose(1, 2) @ Q).numpy()
                lift[b, n_par:, n_par:] = Q.numpy()
            for j in range(n_par):
                h = 1e-5 * torch.clamp(P[:, j].abs(), min=1e-3)
                up, down = P.clone(), P.clone()
                up[:, j] += h
                down[:, j] -= h
                diff = (c[:, None, :] @ (module.design(up) - module.design(down)))[:, 0]
                jac[b, :, j] = (diff / (2 * h[:, None])).numpy()
    return fitted, jac, lift
