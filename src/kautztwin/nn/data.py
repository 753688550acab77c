"""Training-data preparation: the train/validation split and the per-feature standardisation."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_int
from ..exceptions import DataError, DimensionError
from .config import _check_validation_fraction

__all__ = ["Standardizer", "split_indices"]


def split_indices(
    n: int, validation_fraction: float = 0.15, random_state: int = 0
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Random disjoint training/validation indices (the paper's 85/15 split).

    Parameters
    ----------
    n : int
        Number of records, ``>= 2``.
    validation_fraction : float, default=0.15
        Share of validation records, in ``(0, 1)``; the validation set holds
        ``max(1, round(validation_fraction * n))`` records.
    random_state : int, default=0
        Seed of the shuffle.

    Returns
    -------
    train, val : ndarray of int
        Sorted indices; together a permutation of ``range(n)``.

    Raises
    ------
    DataError
        If ``n < 2``, the fraction is out of range, or the training part would be empty.

    Examples
    --------
    >>> from kautztwin.nn import split_indices
    >>> train, val = split_indices(20, 0.15, random_state=0)
    >>> len(train), len(val)
    (17, 3)
    """
    n = check_int(n, "n", minimum=2)
    f = _check_validation_fraction(validation_fraction)
    n_val = max(1, int(round(f * n)))
    if n_val >= n:
        raise DataError(f"validation_fraction = {f:g} of {n} records leaves no training records")
    seed = check_int(random_state, "random_state", minimum=0)
    perm = np.random.default_rng(seed).permutation(int(n))
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


@dataclass(frozen=True, eq=False)
class Standardizer:
    r"""Per-feature affine normalisation :math:`z = (x - \mu) / \sigma`.

    Build it with :meth:`fit`.  A feature with (nearly) zero spread gets
    :math:`\sigma = 1`, so constant features pass through shifted only.

    Parameters
    ----------
    mean : array-like of shape (n_features,)
        :math:`\mu`.
    scale : array-like of shape (n_features,)
        :math:`\sigma > 0`.

    Raises
    ------
    DataError
        If the values are not finite or a scale is not positive.
    DimensionError
        If the shapes differ or are not 1-D.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.nn import Standardizer
    >>> s = Standardizer.fit([[1.0, 5.0], [3.0, 5.0]])
    >>> s.mean, s.scale
    (array([2., 5.]), array([1., 1.]))
    >>> s.transform([[3.0, 6.0]])
    array([[1., 1.]])
    """

    mean: NDArray[np.float64]
    scale: NDArray[np.float64]

    def __post_init__(self) -> None:
        mean = np.array(self.mean, dtype=float, copy=True)
        scale = np.array(self.scale, dtype=float, copy=True)
        if mean.ndim != 1 or scale.shape != mean.shape:
            raise DimensionError(
                f"mean and scale must be 1-D of equal length; got shapes {mean.shape} "
                f"and {scale.shape}"
            )
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(scale))):
            raise DataError("standardizer mean and scale must be finite")
        if np.any(scale <= 0):
            raise DataError("standardizer scale must be positive")
        mean.setflags(write=False)
        scale.setflags(write=False)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "scale", scale)

    @property
    def n_features(self) -> int:
        """Number of features."""
        return int(self.mean.size)

    @classmethod
    def fit(
        cls, x: ArrayLike, *, rtol: float = 1e-12, constant_scale: float | None = 1.0
    ) -> Standardizer:
        """Mean and standard deviation (``ddof=0``) of every column.

        Parameters
        ----------
        x : array-like of shape (n_records, n_features)
            At least one row.
        rtol : float, default=1e-12
            A column whose standard deviation is at most ``rtol`` times the
            largest absolute value in ``x`` (or zero) gets ``constant_scale``.
        constant_scale : float or None, default=1.0
            Scale of constant columns.  ``None`` uses the detection threshold
            ``rtol * max|x|``: labels use it, so that a constant label is
            predicted as its value (to ``rtol``) whatever the network outputs.

        Returns
        -------
        Standardizer

        Raises
        ------
        DimensionError
            If ``x`` is not 2-D with at least one row.
        DataError
            If ``x`` holds NaN or inf.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[0] < 1:
            raise DimensionError(f"x must have shape (n_records, n_features); got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise DataError("x contains NaN or inf; cannot fit a standardizer")
        mean = x.mean(axis=0)
        std = x.std(axis=0)
        tiny = rtol * float(np.max(np.abs(x))) if x.size else 0.0
        if constant_scale is None:  # the detection threshold itself: rounding noise stays small
            constant_scale = tiny if tiny > 0 else 1.0
        std = np.where(std > tiny, std, constant_scale)
        return cls(mean, std)

    def _check(self, x: ArrayLike) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=float)
        if x.shape[-1:] != (self.n_features,):
            raise DimensionError(
                f"x has {x.shape[-1] if x.ndim else 0} features but the standardizer was fitted "
                f"with {self.n_features}"
            )
        return x

    def transform(self, x: ArrayLike) -> NDArray[np.float64]:
        """Normalise: ``(x - mean) / scale`` along the last axis."""
        return (self._check(x) - self.mean) / self.scale

    def inverse_transform(self, z: ArrayLike) -> NDArray[np.float64]:
        """Undo :meth:`transform`: ``z * scale + mean`` along the last axis."""
        return self._check(z) * self.scale + self.mean

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-ready dictionary ``{'mean': [...], 'scale': [...]}`` (exact float round trip)."""
        return {"mean": self.mean.tolist(), "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Standardizer:
        """Rebuild a standardizer written by :meth:`to_dict`.

        Raises
        ------
        DataError
            If a key is missing or the values are invalid.
        """
        try:
            mean, scale = data["mean"], data["scale"]
            return cls(np.asarray(mean, dtype=float), np.asarray(scale, dtype=float))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"invalid standardizer data: {exc}") from None

