r"""Fitted nonlinear Kautz models: one block-structured model, and an average of several.

A :class:`NonlinearKautzModel` is, with standardised input :math:`u_s = (u - \bar u)/s_u`,

.. math::

    v(k) = [u_s(k),\ g(u_s(k))],\qquad x(k+1) = A x(k) + B v(k)\ \text{(each channel)},
    \qquad \hat y(k) = \bar y + s_y\, f(x(k)),

with an optional static input map ``g`` (Hammerstein, Wiener-Hammerstein), the discrete
Kautz bank ``(A, B)`` of :mod:`~kautztwin.ident.nonlinear.filters` and a static output map
``f`` (linear: Hammerstein; polynomial: Volterra / Wiener; MLP: Wiener).  The initial
state is the steady state of a constant input *level* held before the record.  Simulation
is numpy only.  :class:`NonlinearKautzEnsemble` averages the simulations of several such
models (the fold and seed models of a block cross-validation).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from ..._json import to_jsonable
from ..._validation import check_finite, check_int, check_number
from ...approx.model import KautzModel
from ...basis import KautzBasis
from ...exceptions import DataError, DimensionError
from ..kautz_oe import OutputErrorFit
from .filters import bank_matrices, filter_bank_states
from .maps import MLPMap, PolynomialMap, map_from_dict

__all__ = ["NonlinearKautzEnsemble", "NonlinearKautzModel", "load_nonlinear_model"]

STRUCTURES = ("wiener", "hammerstein", "wiener-hammerstein", "volterra")


def check_signal(u: ArrayLike, name: str = "u") -> NDArray[np.float64]:
    """A finite 1-D float signal, or a one-line error."""
    a = np.asarray(u, dtype=float)
    if a.ndim != 1:
        raise DimensionError(f"{name} must be 1-D (SISO), got shape {a.shape}")
    if a.size == 0:
        raise DimensionError(f"{name} is empty")
    check_finite(a, name)
    return a


@dataclass(frozen=True, eq=False)
class NonlinearKautzModel:
    r"""A block-structured nonlinear model on a discrete Kautz filter bank (immutable).

    Parameters
    ----------
    structure : {'wiener', 'hammerstein', 'wiener-hammerstein', 'volterra'}
        What the model is (for reports; the maps define the computation).
    poles : array-like of complex
        Discrete poles of the bank, ``|p| < 1``.
    output_map : PolynomialMap or MLPMap
        Static map of the bank's states to the standardised output.
    input_map : PolynomialMap, MLPMap or None, default=None
        Static map of the standardised input to extra bank channels.
    u_mean, u_scale, y_mean, y_scale : float, default 0, 1, 0, 1
        Standardisation of input and output.
    level : float, default=0.0
        Input level held before the estimation record (its initial state), input units.
    dt : float, default=1.0
        Sampling period.
    fit_percent : float or None, default=None
        Fit on the data it was estimated on (simulation), percent.

    Attributes
    ----------
    n_poles : int
        Number of poles of the bank.

    See Also
    --------
    NonlinearKautzEnsemble : The average of several models.
    identify_nonlinear : Fits these models with structure selection.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.nonlinear import NonlinearKautzModel, PolynomialMap
    >>> f = PolynomialMap([[1], [2]], [1.0, 0.5], [0.0], [1.0])  # y = x + 0.5 x^2
    >>> m = NonlinearKautzModel("wiener", [0.5], f)
    >>> np.round(m.simulate(np.ones(3)) / np.sqrt(0.75), 4)
    array([0.    , 1.433 , 2.4743])
    """

    structure: str
    poles: NDArray[np.complex128]
    output_map: PolynomialMap | MLPMap
    input_map: PolynomialMap | MLPMap | None = None
    u_mean: float = 0.0
    u_scale: float = 1.0
    y_mean: float = 0.0
    y_scale: float = 1.0
    level: float = 0.0
    dt: float = 1.0
    fit_percent: float | None = None

    def __post_init__(self) -> None:
        if self.structure not in STRUCTURES:
            raise DataError(f"structure must be one of {STRUCTURES}, got {self.structure!r}")
        p = np.array(self.poles, dtype=complex, copy=True).ravel()
        filter_bank_states(p, np.zeros(1))  # validates the poles
        p.setflags(write=False)
        object.__setattr__(self, "poles", p)
        for name in ("u_mean", "u_scale", "y_mean", "y_scale", "level", "dt"):
            object.__setattr__(self, name, check_number(getattr(self, name), name))
        if self.u_scale <= 0 or self.y_scale <= 0 or self.dt <= 0:
            raise DataError("u_scale, y_scale and dt must be positive")

    @property
    def n_poles(self) -> int:
        """Number of poles of the filter bank."""
        return int(self.poles.size)

    def _channels(self, us: NDArray) -> NDArray:
        if self.input_map is None:
            return us[:, None]
        g = self.input_map(us[:, None])
        return np.column_stack([us, g])

    def states(self, u: ArrayLike, level: float | None = None) -> NDArray[np.float64]:
        """The bank's states for an input record (rows: samples).

        Parameters
        ----------
        u : array-like of shape (n_samples,)
        level : float, optional
            Input level before the record; the model's ``level`` when omitted.

        Returns
        -------
        ndarray of shape (n_samples, n_channels * n_poles)
        """
        u = check_signal(u)
        lvl = self.level if level is None else check_number(level, "level")
        us = (u - self.u_mean) / self.u_scale
        v = self._channels(us)
        v_lvl = self._channels(np.array([(lvl - self.u_mean) / self.u_scale]))[0]
        return filter_bank_states(self.poles, v, v_lvl)

    def simulate(self, u: ArrayLike, level: float | None = None) -> NDArray[np.float64]:
        """Free-run simulation for an input record.

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Input, finite.
        level : float, optional
            Input level held before the record (sets the initial state); the level fitted
            on the estimation record when omitted.

        Returns
        -------
        ndarray of shape (n_samples,)

        Raises
        ------
        DimensionError, DataError
            If ``u`` is not a finite 1-D signal.
        """
        return self.y_mean + self.y_scale * self.output_map(self.states(u, level))

    def fit_level(self, u: ArrayLike, y: ArrayLike, n_samples: int = 5) -> float:
        """The input level whose steady state best explains the first outputs of a record.

        Only ``y[:n_samples]`` is used (the initial-state samples a protocol allows).

        Parameters
        ----------
        u, y : array-like of shape (n_samples_record,)
        n_samples : int, default=5

        Returns
        -------
        float
        """
        u, y, n = _level_data(u, y, n_samples)
        return _fit_level([self], u, y, n)[0]

    def linearize(self, u0: float) -> OutputErrorFit:
        r"""The linear Kautz model of small deviations around the steady state of ``u0``.

        With the bank driven by :math:`u - u_0`, :math:`\hat y = y_{ss} + c^T x_f`:
        :math:`y_{ss}` is the model's steady output for the constant input ``u0`` and ``c``
        the chain rule through the maps (``c_i = sum_ch df/dx_{ch,i} dv_ch/du``, central
        differences).  The result is what :func:`~kautztwin.ident.identify_output_error`
        returns, on the same delayed discrete basis: the form the twin's digital model and
        its MPC take.

        Parameters
        ----------
        u0 : float
            Operating point (input units).

        Returns
        -------
        OutputErrorFit
            ``model`` (a :class:`~kautztwin.KautzModel` on the bank's poles), ``offset``
            :math:`y_{ss}`, ``input_offset`` ``u0``; ``fit_percent`` is NaN.
        """
        u0 = check_number(u0, "u0")
        us0 = (u0 - self.u_mean) / self.u_scale
        h = 1e-5
        v0 = self._channels(np.array([us0]))[0]
        dv = (self._channels(np.array([us0 + h]))[0]
              - self._channels(np.array([us0 - h]))[0]) / (2 * h * self.u_scale)
        A, B = bank_matrices(self.poles)
        xss = np.linalg.solve(np.eye(B.size) - A, B)
        X0 = np.kron(v0, xss)
        step = h * np.maximum(1.0, np.abs(X0))
        E = np.diag(step)
        grad = (self.output_map(X0[None, :] + E) - self.output_map(X0[None, :] - E)) / (2 * step)
        c = self.y_scale * (grad.reshape(v0.size, B.size) * dv[:, None]).sum(axis=0)
        y_ss = float(self.y_mean + self.y_scale * np.atleast_1d(self.output_map(X0[None, :]))[0])
        basis = KautzBasis(self.poles, dt=self.dt, delayed=True)
        return OutputErrorFit(model=KautzModel(basis, c), offset=y_ss, input_offset=u0,
                              fit_percent=float("nan"), n_evaluations=0, success=True,
                              message=f"linearised {self.structure} model at u0 = {u0:g}")

    def with_level(self, level: float) -> NonlinearKautzModel:
        """A copy with another initial-state level."""
        return replace(self, level=check_number(level, "level"))

    def with_fitted_level(
        self, u: ArrayLike, y: ArrayLike, n_samples: int = 5
    ) -> NonlinearKautzModel:
        """A copy whose level best explains ``y[:n_samples]`` (see :meth:`fit_level`).

        Parameters
        ----------
        u, y : array-like of shape (n_samples_record,)
        n_samples : int, default=5

        Returns
        -------
        NonlinearKautzModel
        """
        return self.with_level(self.fit_level(u, y, n_samples))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (inverse: :meth:`from_dict`)."""
        return {
            "type": "NonlinearKautzModel", "structure": self.structure,
            "poles": [[p.real, p.imag] for p in self.poles],
            "output_map": self.output_map.to_dict(),
            "input_map": None if self.input_map is None else self.input_map.to_dict(),
            **{k: getattr(self, k) for k in ("u_mean", "u_scale", "y_mean", "y_scale",
                                              "level", "dt", "fit_percent")},
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NonlinearKautzModel:
        """Rebuild a model from :meth:`to_dict`'s dictionary.

        Parameters
        ----------
        data : dict

        Returns
        -------
        NonlinearKautzModel
        """
        try:
            poles = [complex(re, im) for re, im in data["poles"]]
            return cls(
                structure=data["structure"], poles=poles,
                output_map=map_from_dict(data["output_map"]),
                input_map=map_from_dict(data.get("input_map")),
                **{k: data[k] for k in ("u_mean", "u_scale", "y_mean", "y_scale", "level", "dt")},
                fit_percent=data.get("fit_percent"),
            )
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, DataError):
                raise
            raise DataError(f"not a nonlinear Kautz model dictionary: {exc}") from None

    def save(self, path: str | Path) -> None:
        """Write the model as JSON (:func:`load_nonlinear_model` reads it back)."""
        Path(path).write_text(json.dumps(to_jsonable(self.to_dict()), indent=1))

    def allclose(self, other: NonlinearKautzModel, rtol: float = 1e-10, atol: float = 0.0) -> bool:
        """Whether two models have the same structure and parameters to a tolerance."""
        a, b = _flat(self.to_dict()), _flat(other.to_dict())
        return a[0] == b[0] and a[1].shape == b[1].shape and np.allclose(a[1], b[1], rtol, atol)


@dataclass(frozen=True, eq=False)
class NonlinearKautzEnsemble:
    """The average of several nonlinear Kautz models (immutable).

    Parameters
    ----------
    members : sequence of NonlinearKautzModel
        The models; their simulations are averaged.
    fit_percent : float or None, default=None
        Fit on the estimation data (simulation of the average), percent.

    See Also
    --------
    NonlinearKautzModel : One member.
    """

    members: tuple[NonlinearKautzModel, ...]
    fit_percent: float | None = None

    def __post_init__(self) -> None:
        members = tuple(self.members)
        if not members or not all(isinstance(m, NonlinearKautzModel) for m in members):
            raise DataError("members must be a non-empty sequence of NonlinearKautzModel")
        object.__setattr__(self, "members", members)

    @property
    def structure(self) -> str:
        """Structure of the first member."""
        return self.members[0].structure

    @property
    def dt(self) -> float:
        """Sampling period."""
        return self.members[0].dt

    def simulate(self, u: ArrayLike, level: float | None = None) -> NDArray[np.float64]:
        """Average free-run simulation of the members (see :meth:`NonlinearKautzModel.simulate`).

        Parameters
        ----------
        u : array-like of shape (n_samples,)
        level : float, optional
            One level for every member; each member's own when omitted.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return np.mean([m.simulate(u, level) for m in self.members], axis=0)

    def linearize(self, u0: float) -> OutputErrorFit:
        r"""The linear Kautz model of small deviations of the average around ``u0``.

        The average of the members' linearisations (:meth:`NonlinearKautzModel.linearize`)
        is a linear model whose poles are all the members' poles; its impulse response is
        expanded, exactly up to the truncation of the slowest pole's tail (below
        :math:`10^{-13}`), on the delayed discrete Kautz basis of those poles (least squares
        on the orthonormal basis sequences).  The offset is the members' mean steady output.

        Parameters
        ----------
        u0 : float
            Operating point (input units).

        Returns
        -------
        OutputErrorFit
            As :meth:`NonlinearKautzModel.linearize`, on ``sum(m.n_poles)`` poles.
        """
        fits = [m.linearize(u0) for m in self.members]
        poles = np.concatenate([m.poles for m in self.members])
        basis = KautzBasis(poles, dt=self.dt, delayed=True)
        r = float(np.max(np.abs(poles)))
        n = int(min(max(np.ceil(np.log(1e-13) / np.log(max(r, 1e-3))) + 2, 50), 200_000))
        t = self.dt * np.arange(n)
        h = np.mean([f.model.impulse(t) for f in fits], axis=0)
        coef, *_ = np.linalg.lstsq(basis.evaluate(t).T, h, rcond=None)
        offset = float(np.mean([f.offset for f in fits]))
        return OutputErrorFit(model=KautzModel(basis, coef), offset=offset, input_offset=u0,
                              fit_percent=float("nan"), n_evaluations=0, success=True,
                              message=f"linearised average of {len(fits)} {self.structure} "
                              f"models at u0 = {u0:g}")

    def with_fitted_level(
        self, u: ArrayLike, y: ArrayLike, n_samples: int = 5
    ) -> NonlinearKautzEnsemble:
        """A copy whose members share the level that best explains ``y[:n_samples]``.

        Parameters
        ----------
        u, y : array-like of shape (n_samples_record,)
        n_samples : int, default=5

        Returns
        -------
        NonlinearKautzEnsemble
        """
        u, y, n = _level_data(u, y, n_samples)
        lvl = _fit_level(list(self.members), u, y, n)[0]
        return replace(self, members=tuple(m.with_level(lvl) for m in self.members))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (inverse: :meth:`from_dict`)."""
        return {"type": "NonlinearKautzEnsemble", "fit_percent": self.fit_percent,
                "members": [m.to_dict() for m in self.members]}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NonlinearKautzEnsemble:
        """Rebuild an ensemble from :meth:`to_dict`'s dictionary."""
        try:
            return cls(tuple(NonlinearKautzModel.from_dict(m) for m in data["members"]),
                       data.get("fit_percent"))
        except (KeyError, TypeError) as exc:
            raise DataError(f"not a nonlinear Kautz ensemble dictionary: {exc}") from None

    def save(self, path: str | Path) -> None:
        """Write the ensemble as JSON (:func:`load_nonlinear_model` reads it back)."""
        Path(path).write_text(json.dumps(to_jsonable(self.to_dict()), indent=1))


def load_nonlinear_model(path: str | Path) -> NonlinearKautzModel | NonlinearKautzEnsemble:
    """Read a model or ensemble written by ``save``.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    NonlinearKautzModel or NonlinearKautzEnsemble

    Raises
    ------
    DataError
        If the file holds no such model.
    """
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot read a nonlinear model from {path}: {exc}") from None
    kind = data.get("type") if isinstance(data, dict) else None
    if kind == "NonlinearKautzModel":
        return NonlinearKautzModel.from_dict(data)
    if kind == "NonlinearKautzEnsemble":
        return NonlinearKautzEnsemble.from_dict(data)
    raise DataError(f"{path} holds no nonlinear Kautz model (type {kind!r})")


# --------------------------------------------------------------------------- helpers
def _flat(d: dict[str, Any]) -> tuple[str, NDArray]:
    keys: list[str] = []
    vals: list[float] = []

    def walk(prefix: str, x: Any) -> None:
        if isinstance(x, dict):
            for k in sorted(x):
                walk(f"{prefix}.{k}", x[k])
        elif isinstance(x, list | tuple):
            for i, v in enumerate(x):
                walk(f"{prefix}[{i}]", v)
        elif isinstance(x, bool | str) or x is None:
            keys.append(f"{prefix}={x}")
        else:
            vals.append(float(x))
            keys.append(prefix)
    walk("", d)
    return "|".join(keys), np.asarray(vals)


def _level_data(u: ArrayLike, y: ArrayLike, n_samples: int) -> tuple[NDArray, NDArray, int]:
    u = check_signal(u, "u")
    y = np.asarray(y, dtype=float)
    n = check_int(n_samples, "n_samples", 1)
    if y.ndim != 1 or y.size < n:
        raise DimensionError(f"y must be 1-D with at least n_samples = {n} samples, "
                             f"got shape {y.shape}")
    check_finite(y[:n], "y")
    if u.size < n:
        raise DimensionError(f"u has {u.size} samples, fewer than n_samples = {n}")
    return u[:n], y[:n], n


def _fit_level(models: list[NonlinearKautzModel], u: NDArray, y: NDArray, n: int) -> list[float]:
    """One level for the average of ``models`` that best explains ``y[:n]`` (grid, then Brent)."""
    lo = min(m.u_mean - 3 * m.u_scale for m in models)
    hi = max(m.u_mean + 3 * m.u_scale for m in models)
    lo, hi = min(lo, float(u.min())), max(hi, float(u.max()))

    def cost(lvl: float) -> float:
        yh = np.mean([m.simulate(u, lvl) for m in models], axis=0)
        return float(np.sum((y - yh) ** 2))

    grid = np.linspace(lo, hi, 61)
    costs = [cost(g) for g in grid]
    i = int(np.argmin(costs))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = scipy.optimize.minimize_scalar(cost, bounds=(a, b), method="bounded",
                                         options={"xatol": 1e-9 * (hi - lo)})
    best = float(res.x) if res.fun <= costs[i] else float(grid[i])
    return [best]
