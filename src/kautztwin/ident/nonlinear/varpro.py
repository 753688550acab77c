r"""Variable projection for the nonlinear Kautz models that are linear in their map parameters.

Three structures have output maps linear in their coefficients :math:`\beta` once the poles
(and, for Wiener, the projection direction) are fixed:

* **Volterra**: :math:`\hat y = \sum_i \beta_i \prod_j z_j^{e_{ij}}`, all monomials of the
  standardised Kautz states :math:`z` up to a degree: a Volterra series whose kernels are
  expanded in products of Kautz functions (refs 24-26 of the seed paper);
* **Hammerstein (polynomial)**: the powers :math:`u, u^2, \dots, u^d` each drive the bank,
  :math:`\hat y = \beta_0 + \sum \beta_{ij} x_i[u^j]`;
* **Hammerstein (tanh basis)**: fixed sigmoids :math:`\tanh(w (u - c_j))` centred at
  quantiles of the training input drive the bank beside ``u``; unlike powers of ``u`` they
  level off outside the inputs seen, so a held-out operating point is not extrapolated by a
  polynomial (the map is an :class:`~.maps.MLPMap` with fixed first layer);
* **Wiener (polynomial)**: :math:`\hat y = \sum_k a_k (c^T z)^k`, one direction ``c`` with its
  largest entry fixed to 1 (the scale lives in ``a``).

For every candidate of the nonlinear parameters (pole parameters, the initial-state level,
``c``) the coefficients are the linear least-squares solution on the training samples, so
only those few parameters are searched (``scipy.optimize.least_squares``).  The level stays
inside the input's range (:func:`level_bounds`) and a faint pull towards its start decides it
where the outputs do not.  The residual
is the free-run simulation error: no past outputs enter the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
from numpy.typing import NDArray

from .filters import filter_bank_states, poles_from_raw
from .maps import MLPMap, PolynomialMap, monomial_exponents, monomials
from .model import NonlinearKautzModel

__all__ = ["LEVEL_PRIOR", "TANH_SLOPE", "VarproResult", "fit_varpro", "level_bounds",
           "tanh_centres"]

#: slope of the tanh basis functions, per standard deviation of the input
TANH_SLOPE = 2.0


def tanh_centres(us: NDArray, n_centres: int) -> NDArray[np.float64]:
    """Centres of the tanh input basis: equally spaced quantiles of the (training) input.

    Parameters
    ----------
    us : ndarray of shape (n_samples,)
        Standardised input samples.
    n_centres : int
        Number of basis functions.

    Returns
    -------
    ndarray of shape (n_centres,)
        The ``j / (n_centres + 1)`` quantiles, ``j = 1 .. n_centres``.
    """
    return np.quantile(us, np.arange(1, n_centres + 1) / (n_centres + 1))

#: weight of the residual ``level - level0`` that decides the level where the data do not
LEVEL_PRIOR = 1e-3


def level_bounds(us: NDArray) -> tuple[float, float]:
    """Range of the initial-state level: the input's range widened by 10 % on each side.

    A level outside the inputs seen is not a plausible operating point; where the outputs do
    not determine the level (a fold that holds out the start of the record), an unbounded
    level would run off and ruin the simulation of the held-out block.
    """
    a, b = float(np.min(us)), float(np.max(us))
    pad = 0.1 * (b - a)
    return a - pad, b + pad


@dataclass(frozen=True)
class VarproResult:
    """A variable-projection fit: the model, its search result and its held-out error."""

    model: NonlinearKautzModel
    val_mse: float
    train_mse: float
    n_evaluations: int


class _Problem:
    """Residual of one structure for given nonlinear parameters (poles, level, direction)."""

    def __init__(self, structure: str, degree: int, kinds: tuple[str, ...], us: NDArray,
                 ys: NDArray, train: NDArray, ridge: float,
                 centres: NDArray | None = None) -> None:
        self.structure, self.degree, self.kinds = structure, degree, kinds
        self.centres = None if centres is None else np.asarray(centres, dtype=float)
        self.us, self.ys, self.train, self.ridge = us, ys, train, ridge
        self.n_raw = sum(1 if k == "real" else 2 for k in kinds)
        self.n_eval = 0
        self.powers = (np.arange(2, degree + 1)[:, None]
                       if structure == "hammerstein" and self.centres is None
                       else np.zeros((0, 1), dtype=int))
        self.level0 = 0.0
        self.x_mean: NDArray | None = None
        self.x_scale: NDArray | None = None
        self.pivot = 0

    def _channels(self, us: NDArray) -> NDArray:
        if self.centres is not None:
            return np.column_stack([us, np.tanh(TANH_SLOPE * (us[:, None] - self.centres))])
        if self.powers.size:
            return np.column_stack([us, monomials(us[:, None], self.powers)])
        return us[:, None]

    def states(self, p: NDArray) -> NDArray:
        poles = poles_from_raw(self.kinds, p[: self.n_raw])
        lvl = p[self.n_raw]
        return filter_bank_states(poles, self._channels(self.us),
                                  self._channels(np.array([lvl]))[0])

    def standardise(self, p: NDArray) -> None:
        """Fix the state standardisation at the starting parameters (training samples)."""
        X = self.states(p)[self.train]
        self.x_mean = X.mean(axis=0)
        self.x_scale = np.where(X.std(axis=0) > 1e-12, X.std(axis=0), 1.0)

    def direction(self, p: NDArray) -> NDArray:
        n_f = self.n_raw
        c = np.insert(p[self.n_raw + 1 :], self.pivot, 1.0)
        return c[:n_f]

    def exponents(self, n_var: int) -> NDArray:
        if self.structure == "volterra":
            return monomial_exponents(n_var, self.degree)
        if self.structure == "wiener":
            return np.arange(self.degree + 1)[:, None]
        return monomial_exponents(n_var, 1)

    def design(self, p: NDArray) -> NDArray:
        self.n_eval += 1
        Z = (self.states(p) - self.x_mean) / self.x_scale
        if self.structure == "wiener":
            Z = Z @ self.direction(p)[:, None]
        return monomials(Z, self.exponents(Z.shape[1]))

    def solve(self, p: NDArray) -> tuple[NDArray, NDArray]:
        Phi = self.design(p)
        A = Phi[self.train]
        b = self.ys[self.train]
        if self.ridge > 0:
            k = A.shape[1]
            scale = np.sqrt(self.ridge * max(np.trace(A.T @ A) / k, 1e-300))
            A = np.vstack([A, scale * np.eye(k)])
            b = np.concatenate([b, np.zeros(k)])
        beta, *_ = np.linalg.lstsq(A, b, rcond=None)
        return beta, Phi @ beta

    def residual(self, p: NDArray) -> NDArray:
        _, yh = self.solve(p)
        r = (self.ys - yh)[self.train]
        if not np.all(np.isfinite(r)):
            r = np.full(r.shape, 1e6)
        # a faint pull of the level towards its start: decides it where the data do not
        return np.append(r, LEVEL_PRIOR * (p[self.n_raw] - self.level0))


def fit_varpro(
    structure: str, degree: int, kinds: tuple[str, ...], raw0: NDArray, us: NDArray,
    ys: NDArray, train: NDArray, val: NDArray, *, level0: float, stats: tuple[float, ...],
    dt: float, max_iter: int = 100, ridge: float = 1e-10, direction0: NDArray | None = None,
    n_centres: int = 0,
) -> VarproResult:
    """Fit one linear-in-the-map structure by variable projection (internal).

    Parameters
    ----------
    structure : {'volterra', 'hammerstein', 'wiener'}
    degree : int
        Polynomial degree.
    kinds, raw0 : block structure and starting unconstrained pole parameters.
    us, ys : ndarray of shape (n_samples,)
        Standardised input and output.
    train, val : ndarray of bool
        Samples whose error is minimised / held out.
    level0 : float
        Starting standardised level.
    stats : (u_mean, u_scale, y_mean, y_scale)
    dt : float
    max_iter : int, default=100
        Iterations (Jacobian evaluations) of the search.
    ridge : float, default=1e-10
        Relative ridge of the coefficient solve.
    direction0 : ndarray, optional
        Starting Wiener direction (the unit vector of the largest state when omitted).
    n_centres : int, default=0
        Hammerstein only: ``n_centres > 0`` replaces the powers of the input by that many
        tanh basis functions (:func:`tanh_centres` of the training input; ``degree`` is then
        unused).

    Returns
    -------
    VarproResult
    """
    centres = None
    if n_centres > 0:
        if structure != "hammerstein":
            raise ValueError("the tanh basis is an input map: structure must be 'hammerstein'")
        centres = tanh_centres(us[train], n_centres)
    prob = _Problem(structure, degree, kinds, us, ys, train, ridge, centres)
    prob.level0 = level0
    lo, hi = level_bounds(us)
    p0 = np.concatenate([raw0, [float(np.clip(level0, lo, hi))]])
    prob.standardise(p0)
    if structure == "wiener":
        c0 = np.zeros(prob.n_raw) if direction0 is None else np.asarray(direction0, float)
        if direction0 is None:
            # the direction of the best linear fit of the states
            Z = (prob.states(p0) - prob.x_mean) / prob.x_scale
            c0, *_ = np.linalg.lstsq(Z[train], ys[train], rcond=None)
        prob.pivot = int(np.argmax(np.abs(c0)))
        c0 = c0 / c0[prob.pivot]
        p0 = np.concatenate([p0, np.delete(c0, prob.pivot)])
    lower = np.full(p0.size, -np.inf)
    upper = np.full(p0.size, np.inf)
    lower[prob.n_raw], upper[prob.n_raw] = lo, hi
    sol = scipy.optimize.least_squares(
        prob.residual, p0, bounds=(lower, upper), method="trf", x_scale="jac",
        max_nfev=max_iter * (p0.size + 1),
        ftol=1e-12, xtol=1e-12, gtol=1e-12,
    )
    p = sol.x
    beta, yh = prob.solve(p)
    u_mean, u_scale, y_mean, y_scale = stats
    exps = prob.exponents(1 if structure == "wiener" else prob.x_mean.size)
    projection = prob.direction(p)[:, None] if structure == "wiener" else None
    out_map = PolynomialMap(exps, beta, prob.x_mean, prob.x_scale, projection)
    in_map: PolynomialMap | MLPMap | None = None
    if centres is not None:
        m = centres.size
        in_map = MLPMap(TANH_SLOPE * np.ones((m, 1)), -TANH_SLOPE * centres, np.eye(m),
                        np.zeros(m), [0.0], [1.0])
    elif prob.powers.size:
        m = prob.powers.shape[0]
        in_map = PolynomialMap(prob.powers, np.eye(m), [0.0], [1.0])
    model = NonlinearKautzModel(
        structure=structure, poles=poles_from_raw(kinds, p[: prob.n_raw]), output_map=out_map,
        input_map=in_map, u_mean=u_mean, u_scale=u_scale, y_mean=y_mean, y_scale=y_scale,
        level=u_mean + u_scale * p[prob.n_raw], dt=dt,
    )
    err = ys - yh
    val_mse = float(np.mean(err[val] ** 2)) if val.any() else float("nan")
    return VarproResult(model, val_mse, float(np.mean(err[train] ** 2)), prob.n_eval)
