r"""Static maps of the nonlinear Kautz models: polynomials and small MLPs, evaluated in numpy.

A fitted model never needs torch to simulate: the maps trained in torch are exported to
these immutable objects.  Both maps standardise their input first,
:math:`z = (x - m) / s`.

* :class:`PolynomialMap`: :math:`f(x) = \sum_i c_i \prod_j z_j^{e_{ij}}` (optionally on a
  projection :math:`z P`), one or several outputs; degree 1 is a linear map, the full
  monomial set of degree ``d`` on Kautz filter states is a Volterra series;
* :class:`MLPMap`: one hidden ``tanh`` layer, :math:`f(x) = W_2 \tanh(W_1 z + b_1) + b_2`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...exceptions import DataError

__all__ = ["MLPMap", "PolynomialMap", "map_from_dict", "monomial_exponents"]


def _ro(x: ArrayLike, dtype: Any = float) -> NDArray:
    a = np.array(x, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


def monomial_exponents(n_inputs: int, degree: int, *, min_degree: int = 0) -> NDArray[np.int64]:
    """Exponent rows of every monomial of ``n_inputs`` variables with degree in a range.

    Parameters
    ----------
    n_inputs : int
        Number of variables.
    degree : int
        Largest total degree.
    min_degree : int, default=0
        Smallest total degree (0 includes the constant).

    Returns
    -------
    ndarray of shape (n_monomials, n_inputs)
        Ordered by degree, then lexicographically.

    Examples
    --------
    >>> monomial_exponents(2, 2, min_degree=1).tolist()
    [[1, 0], [0, 1], [2, 0], [1, 1], [0, 2]]
    """
    rows = []
    for d in range(min_degree, degree + 1):
        for combo in itertools.combinations_with_replacement(range(n_inputs), d):
            e = np.zeros(n_inputs, dtype=np.int64)
            for j in combo:
                e[j] += 1
            rows.append(e)
    return np.asarray(rows, dtype=np.int64).reshape(-1, n_inputs)


def monomials(Z: NDArray, exponents: NDArray) -> NDArray[np.float64]:
    """Columns ``prod_j Z[:, j] ** e_ij`` for each exponent row ``e_i``."""
    out = np.ones((Z.shape[0], exponents.shape[0]))
    for j in range(Z.shape[1]):
        col = exponents[:, j]
        for p in np.unique(col[col > 0]):
            out[:, col == p] *= (Z[:, j] ** p)[:, None]
    return out


@dataclass(frozen=True, eq=False)
class PolynomialMap:
    r"""A polynomial static map :math:`f(x) = M(z) C`, ``z = ((x - m) / s) P``.

    Parameters
    ----------
    exponents : array-like of int, shape (n_terms, n_variables)
        Monomials of ``z``.
    coef : array-like of shape (n_terms,) or (n_terms, n_outputs)
        Coefficients.
    in_mean, in_scale : array-like of shape (n_inputs,)
        Standardisation of ``x``.
    projection : array-like of shape (n_inputs, n_variables), optional
        ``P``; identity when omitted.

    Examples
    --------
    >>> import numpy as np
    >>> f = PolynomialMap([[0], [1], [2]], [1.0, 2.0, 3.0], [0.0], [1.0])
    >>> f(np.array([[1.0], [2.0]]))
    array([ 6., 17.])
    """

    exponents: NDArray[np.int64]
    coef: NDArray[np.float64]
    in_mean: NDArray[np.float64]
    in_scale: NDArray[np.float64]
    projection: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        e = _ro(np.atleast_2d(self.exponents), np.int64)
        c = _ro(self.coef)
        if c.shape[0] != e.shape[0]:
            raise DataError(f"coef has {c.shape[0]} rows but there are {e.shape[0]} monomials")
        object.__setattr__(self, "exponents", e)
        object.__setattr__(self, "coef", c)
        object.__setattr__(self, "in_mean", _ro(np.atleast_1d(self.in_mean)))
        object.__setattr__(self, "in_scale", _ro(np.atleast_1d(self.in_scale)))
        if self.projection is not None:
            object.__setattr__(self, "projection", _ro(np.atleast_2d(self.projection)))

    @property
    def n_outputs(self) -> int:
        """Number of outputs."""
        return 1 if self.coef.ndim == 1 else int(self.coef.shape[1])

    def features(self, x: ArrayLike) -> NDArray[np.float64]:
        """The monomial columns ``M(z)`` of ``x`` (shape (n, n_terms)).

        Parameters
        ----------
        x : array-like of shape (n_samples, n_inputs)

        Returns
        -------
        ndarray of shape (n_samples, n_terms)
        """
        z = (np.asarray(x, dtype=float) - self.in_mean) / self.in_scale
        if self.projection is not None:
            z = z @ self.projection
        return monomials(z, self.exponents)

    def __call__(self, x: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the map on the rows of ``x``; 1-D result for one output."""
        return self.features(x) @ self.coef

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (inverse: :func:`map_from_dict`)."""
        d = {"kind": "polynomial", "exponents": self.exponents.tolist(),
             "coef": self.coef.tolist(), "in_mean": self.in_mean.tolist(),
             "in_scale": self.in_scale.tolist()}
        if self.projection is not None:
            d["projection"] = self.projection.tolist()
        return d


@dataclass(frozen=True, eq=False)
class MLPMap:
    r"""A one-hidden-layer ``tanh`` network :math:`f(x) = W_2 \tanh(W_1 z + b_1) + b_2`.

    Parameters
    ----------
    W1 : array-like of shape (n_hidden, n_inputs)
    b1 : array-like of shape (n_hidden,)
    W2 : array-like of shape (n_outputs, n_hidden)
    b2 : array-like of shape (n_outputs,)
    in_mean, in_scale : array-like of shape (n_inputs,)
        Standardisation of ``x``: ``z = (x - in_mean) / in_scale``.

    Examples
    --------
    >>> import numpy as np
    >>> f = MLPMap([[1.0]], [0.0], [[2.0]], [0.5], [0.0], [1.0])
    >>> np.round(f(np.array([[0.0], [1.0]])), 4)
    array([0.5   , 2.0232])
    """

    W1: NDArray[np.float64]
    b1: NDArray[np.float64]
    W2: NDArray[np.float64]
    b2: NDArray[np.float64]
    in_mean: NDArray[np.float64]
    in_scale: NDArray[np.float64]

    def __post_init__(self) -> None:
        for name in ("W1", "W2"):
            object.__setattr__(self, name, _ro(np.atleast_2d(getattr(self, name))))
        for name in ("b1", "b2", "in_mean", "in_scale"):
            object.__setattr__(self, name, _ro(np.atleast_1d(getattr(self, name))))
        if self.W1.shape[0] != self.b1.size or self.W2.shape != (self.b2.size, self.b1.size):
            raise DataError(
                f"MLP shapes do not chain: W1 {self.W1.shape}, b1 {self.b1.shape}, "
                f"W2 {self.W2.shape}, b2 {self.b2.shape}"
            )

    @property
    def n_outputs(self) -> int:
        """Number of outputs."""
        return int(self.b2.size)

    def __call__(self, x: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the map on the rows of ``x``; 1-D result for one output."""
        z = (np.asarray(x, dtype=float) - self.in_mean) / self.in_scale
        out = np.tanh(z @ self.W1.T + self.b1) @ self.W2.T + self.b2
        return out[:, 0] if self.n_outputs == 1 else out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (inverse: :func:`map_from_dict`)."""
        return {"kind": "mlp", **{k: getattr(self, k).tolist()
                                  for k in ("W1", "b1", "W2", "b2", "in_mean", "in_scale")}}


def map_from_dict(data: dict[str, Any] | None) -> PolynomialMap | MLPMap | None:
    """Rebuild a map written by ``to_dict`` (``None`` stays ``None``).

    Parameters
    ----------
    data : dict or None

    Returns
    -------
    PolynomialMap, MLPMap or None

    Raises
    ------
    DataError
        If the dictionary names no known map.
    """
    if data is None:
        return None
    kind = data.get("kind")
    fields = {k: v for k, v in data.items() if k != "kind"}
    if kind == "polynomial":
        return PolynomialMap(**fields)
    if kind == "mlp":
        return MLPMap(**fields)
    raise DataError(f"unknown static map kind {kind!r}; expected 'polynomial' or 'mlp'")
