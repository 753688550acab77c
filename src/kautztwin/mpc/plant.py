"""The plant model of the MPC: a strictly proper discrete state-space system.

:func:`plant_model` converts what the rest of the package calls a model (a
``(A, B, C)`` tuple, a ``scipy.signal`` system, a :class:`~kautztwin.KautzModel`)
into a :class:`PlantModel`, discretising continuous ones with a zero-order hold.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError, DimensionError

__all__ = ["PlantModel", "plant_model"]

# |D| above this (relative to the largest |C B|-like entry) counts as direct feedthrough
_FEEDTHROUGH_TOL = 1e-12


def _readonly(x: ArrayLike) -> NDArray[np.float64]:
    a = np.array(x, dtype=float, copy=True)
    a.setflags(write=False)
    return a


# ----------------------------------------------------------------------------- plant
@dataclass(frozen=True, eq=False)
class PlantModel:
    r"""Strictly proper LTI plant :math:`x(k+1) = A x(k) + B u(k),\ y = C x` (or its ODE).

    Parameters
    ----------
    A : array-like of shape (n_states, n_states)
        State matrix.
    B : array-like of shape (n_states, n_inputs)
        Input matrix (a 1-D array is one input column).
    C : array-like of shape (n_outputs, n_states)
        Output matrix (a 1-D array is one output row).
    dt : float
        Sampling period (``> 0``); ``0`` means continuous time.

    Raises
    ------
    DimensionError
        If the matrix shapes do not fit together.
    DataError
        If a matrix holds NaN or inf, or ``dt < 0``.

    See Also
    --------
    plant_model : Build one from a tuple, a ``scipy.signal`` system or a KautzModel.

    Examples
    --------
    >>> from kautztwin.mpc import PlantModel
    >>> plant = PlantModel([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0], dt=1.0)
    >>> plant.n_states, plant.n_inputs, plant.n_outputs
    (2, 1, 1)
    """

    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    dt: float

    def __post_init__(self) -> None:
        A = np.atleast_2d(np.asarray(self.A, dtype=float))
        B = np.asarray(self.B, dtype=float)
        C = np.asarray(self.C, dtype=float)
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise DimensionError(f"A must be a square matrix, got shape {A.shape}")
        n = A.shape[0]
        if B.ndim < 2:
            B = B.reshape(n, -1) if B.size == n else B.reshape(-1, 1)
        if C.ndim < 2:
            C = C.reshape(1, -1)
        if B.ndim != 2 or B.shape[0] != n:
            raise DimensionError(f"B has shape {B.shape} but A has {n} states")
        if C.ndim != 2 or C.shape[1] != n:
            raise DimensionError(f"C has shape {C.shape} but A has {n} states")
        for name, M in (("A", A), ("B", B), ("C", C)):
            if not np.all(np.isfinite(M)):
                raise DataError(f"{name} contains NaN or inf")
        dt = float(self.dt)
        if not np.isfinite(dt) or dt < 0:
            raise DataError(f"dt must be 0 (continuous) or a positive sampling period, got {dt}")
        object.__setattr__(self, "A", _readonly(A))
        object.__setattr__(self, "B", _readonly(B))
        object.__setattr__(self, "C", _readonly(C))
        object.__setattr__(self, "dt", dt)

    @property
    def n_states(self) -> int:
        """Number of plant states."""
        return int(self.A.shape[0])

    @property
    def n_inputs(self) -> int:
        """Number of inputs."""
        return int(self.B.shape[1])

    @property
    def n_outputs(self) -> int:
        """Number of outputs."""
        return int(self.C.shape[0])

    @property
    def is_discrete(self) -> bool:
        """Whether the model is a discrete-time one (``dt > 0``)."""
        return self.dt > 0

    def to_scipy(self) -> scipy.signal.StateSpace:
        """The plant as ``scipy.signal.StateSpace`` (``dlti`` when discrete).

        Returns
        -------
        scipy.signal.StateSpace
        """
        D = np.zeros((self.n_outputs, self.n_inputs))
        if self.dt > 0:
            return scipy.signal.StateSpace(self.A, self.B, self.C, D, dt=self.dt)
        return scipy.signal.StateSpace(self.A, self.B, self.C, D)

    def allclose(self, other: PlantModel, rtol: float = 1e-10, atol: float = 1e-12) -> bool:
        """Whether ``other`` has the same ``dt`` and (nearly) the same matrices."""
        return (
            isinstance(other, PlantModel)
            and self.dt == other.dt
            and all(
                a.shape == b.shape and bool(np.allclose(a, b, rtol=rtol, atol=atol))
                for a, b in ((self.A, other.A), (self.B, other.B), (self.C, other.C))
            )
        )


def _plant_arrays(plant: Any) -> tuple[NDArray, NDArray, NDArray, NDArray, float | None]:
    """``(A, B, C, D, dt)`` of a supported plant; ``dt`` is ``None`` for bare matrices."""
    # local import: approx -> mpc is the allowed direction, keep the module import light
    from ..approx.model import KautzModel

    if isinstance(plant, PlantModel):
        D = np.zeros((plant.n_outputs, plant.n_inputs))
        return np.array(plant.A), np.array(plant.B), np.array(plant.C), D, plant.dt
    if isinstance(plant, KautzModel):
        A, B, C, D = plant.state_space()
        return A, B, C, D, plant.dt
    if isinstance(plant, (scipy.signal.lti, scipy.signal.dlti)):
        ss = plant if isinstance(plant, scipy.signal.StateSpace) else plant.to_ss()
        dt = float(plant.dt) if isinstance(plant, scipy.signal.dlti) else 0.0
        return (
            np.atleast_2d(ss.A).astype(float),
            np.atleast_2d(ss.B).astype(float),
            np.atleast_2d(ss.C).astype(float),
            np.atleast_2d(ss.D).astype(float),
            dt,
        )
    if isinstance(plant, (tuple, list)) and len(plant) in (3, 4):
        A = np.atleast_2d(np.asarray(plant[0], dtype=float))
        n = A.shape[0]
        B = np.asarray(plant[1], dtype=float)
        B = B.reshape(n, -1) if B.ndim < 2 else B
        C = np.asarray(plant[2], dtype=float)
        C = C.reshape(1, -1) if C.ndim < 2 else C
        D = np.zeros((C.shape[0], B.shape[1]))
        if len(plant) == 4:
            D = np.asarray(plant[3], dtype=float).reshape(C.shape[0], B.shape[1])
        return A, B, C, D, None
    raise DataError(
        "plant must be a tuple (A, B, C[, D]), a scipy.signal lti/dlti, a KautzModel or a "
        f"PlantModel, got {type(plant).__name__}"
    )


def _check_strictly_proper(C: NDArray, B: NDArray, D: NDArray) -> None:
    scale = max(1.0, float(np.max(np.abs(C))) * float(np.max(np.abs(B), initial=0.0)))
    if D.size and np.max(np.abs(D)) > _FEEDTHROUGH_TOL * scale:
        raise DataError(
            f"the plant has direct feedthrough (max |D| = {np.max(np.abs(D)):.3g}); the "
            "velocity-form MPC needs a strictly proper plant (D = 0): use a continuous or a "
            "delayed discrete Kautz model, or add a one-sample input delay"
        )


def plant_model(plant: Any, dt: float | None = None) -> PlantModel:
    """Discrete-time state-space plant for MPC, discretising continuous ones with ZOH.

    Parameters
    ----------
    plant : tuple, scipy.signal.lti or dlti, KautzModel or PlantModel
        ``(A, B, C)`` or ``(A, B, C, D)`` are taken as *discrete-time* matrices
        with sampling period ``dt`` (default 1.0).  A continuous system
        (``scipy.signal.lti``, a ``KautzModel`` with ``dt = 0``, a continuous
        ``PlantModel``) is discretised with a zero-order hold at ``dt``
        (:func:`scipy.signal.cont2discrete`).  ``D`` must be zero.
    dt : float, optional
        Sampling period.  Needed for continuous plants; for discrete ones it
        must be omitted or equal the plant's own.

    Returns
    -------
    PlantModel
        Discrete (``dt > 0``).

    Raises
    ------
    DataError
        If ``plant`` is of an unsupported type, has feedthrough, a continuous
        plant comes without ``dt``, or ``dt`` contradicts a discrete plant's.

    See Also
    --------
    PlantModel : The returned value object.

    Examples
    --------
    >>> import scipy.signal
    >>> from kautztwin.mpc import plant_model
    >>> p = plant_model(scipy.signal.lti([1.0], [1.0, 1.0]), dt=0.1)
    >>> round(float(p.A[0, 0]), 6), p.dt
    (0.904837, 0.1)
    """
    A, B, C, D, pdt = _plant_arrays(plant)
    _check_strictly_proper(C, B, D)
    if dt is not None:
        dt = float(dt)
        if not np.isfinite(dt) or dt <= 0:
            raise DataError(f"dt must be a positive sampling period, got {dt}")
    if pdt is None:  # bare matrices: discrete with the given period
        return PlantModel(A, B, C, dt if dt is not None else 1.0)
    if pdt > 0:
        if dt is not None and not np.isclose(dt, pdt, rtol=1e-12, atol=0.0):
            raise DataError(f"dt = {dt} differs from the discrete plant's sampling period {pdt}")
        return PlantModel(A, B, C, pdt)
    if dt is None:
        raise DataError("the plant is continuous-time: pass dt > 0 to discretise it (ZOH)")
    Ad, Bd, Cd, _, _ = scipy.signal.cont2discrete((A, B, C, D), dt, method="zoh")
    return PlantModel(Ad, Bd, Cd, dt)


def _continuous_plant(plant: Any) -> PlantModel:
    """Continuous-time plant: bare matrices are taken as continuous."""
    A, B, C, D, pdt = _plant_arrays(plant)
    _check_strictly_proper(C, B, D)
    if pdt is not None and pdt > 0:
        raise DataError(f"the plant is discrete-time (dt = {pdt}); a continuous one is needed")
    return PlantModel(A, B, C, 0.0)
