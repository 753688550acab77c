"""What both neural estimators share: parameters, data and record checks, the time-grid test."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..datasets import ResponseDataset
from ..exceptions import DataError, DimensionError

__all__ = [
    "EstimatorMixin",
    "check_dataset",
    "check_fine_tune_data",
    "checked_records",
    "grid_difference",
]

_GRID_RTOL = 1e-9  # relative to the grid span: two grids closer than this are the same grid


class EstimatorMixin:
    """``set_params`` and ``__repr__`` on top of a class's ``get_params`` (scikit-learn style).

    Also the one-line description of a fitted estimator's grid (``t_``, ``n_samples_``)
    used in its messages.
    """

    def get_params(self, deep: bool = True) -> dict[str, Any]:  # pragma: no cover - overridden
        raise NotImplementedError

    def set_params(self, **params: Any) -> Any:
        """Set constructor parameters (scikit-learn convention); returns ``self``."""
        valid = self.get_params()
        for key, value in params.items():
            if key not in valid:
                raise DataError(
                    f"invalid parameter {key!r} for {type(self).__name__}; "
                    f"valid: {', '.join(sorted(valid))}"
                )
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items() if v is not None)
        return f"{type(self).__name__}({args})"

    t_: NDArray[np.float64]
    n_samples_: int

    def _grid_text(self) -> str:
        return f"{self.n_samples_} samples on [{self.t_[0]:g}, {self.t_[-1]:g}] s"


def check_dataset(dataset: Any) -> None:
    """Raise :class:`DataError` unless ``dataset`` is a :class:`ResponseDataset`."""
    if not isinstance(dataset, ResponseDataset):
        raise DataError(
            f"dataset must be a kautztwin.datasets.ResponseDataset, got {type(dataset).__name__}"
        )


def check_fine_tune_data(est: Any, dataset: Any) -> None:
    """Fitted ``est``, and ``dataset`` a data set of its kind on its grid (both estimators)."""
    est._check_is_fitted()
    check_dataset(dataset)
    if dataset.kind != est.kind_:
        raise DataError(
            f"the data set holds {dataset.kind} responses but the estimator was trained on "
            f"{est.kind_} responses"
        )
    est.check_grid(dataset.t)


def grid_difference(t: NDArray[np.float64], t_: NDArray[np.float64]) -> int | None:
    """Index of the first sample where ``t`` leaves the training grid ``t_``, or ``None``.

    Both grids have the same length; two samples differ by more than ``1e-9`` of the span
    of ``t_`` (or ``t`` is not finite there) to count as another grid.
    """
    span = float(t_[-1] - t_[0]) or 1.0
    diff = np.abs(t - t_)
    if not np.all(np.isfinite(t)) or np.max(diff) > _GRID_RTOL * span:
        return int(np.argmax(np.where(np.isfinite(diff), diff, np.inf)))
    return None


def checked_records(
    est: Any, responses: Any, t: ArrayLike | None, *, copy: bool = False
) -> tuple[NDArray[np.float64], bool]:
    """Records to estimate, checked against a fitted estimator's grid and kind (both estimators).

    ``responses`` is a :class:`ResponseDataset` or an array of one record (1-D)
    or many (2-D); returns the 2-D float array (a copy with ``copy=True``) and
    whether a single record was given.
    """
    est._check_is_fitted()
    if isinstance(responses, ResponseDataset):
        if responses.kind != est.kind_:
            raise DataError(
                f"the data set holds {responses.kind} responses but the estimator was "
                f"trained on {est.kind_} responses"
            )
        t = responses.t if t is None else t
        responses = responses.responses
    if t is not None:
        est.check_grid(t)
    try:
        X = np.array(responses, dtype=float) if copy else np.asarray(responses, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DataError(f"responses must be an array of numbers: {exc}") from None
    if X.ndim not in (1, 2):
        raise DimensionError(
            f"responses must be 1-D (one record) or 2-D (n_records, n_samples), got shape {X.shape}"
        )
    single = X.ndim == 1
    X = np.atleast_2d(X)
    if X.shape[1] != est.n_samples_:
        raise DimensionError(
            f"responses has {X.shape[1]} samples per record but the estimator was trained "
            f"on {est._grid_text()}; resample the records onto the training grid"
        )
    bad = ~np.isfinite(X)
    if bad.any():
        i, k = (int(v) for v in np.argwhere(bad)[0])
        where = f"sample {k}" if single else f"record {i}, sample {k}"
        raise DataError(f"responses contains a non-finite value ({X[i, k]}) at {where}")
    return X, single
