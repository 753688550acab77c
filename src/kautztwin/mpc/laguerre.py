r"""Laguerre/Kautz-parameterised MPC: prediction matrices and unconstrained gains.

The control increments over the prediction horizon are expanded on an
orthonormal basis, :math:`\Delta u(k_i+m) = L(m)^T\eta` (discrete time) or
:math:`\dot u(t_i+\tau) = L(\tau)^T\eta` (continuous time), so the optimisation
has ``N`` decision variables instead of one per step (kautz-math.md section 6,
after Wang 2009).  Only two properties of the basis are used: the linear
recursion :math:`L(m+1) = A_L L(m)` (or :math:`\dot L = A_p L`) and
orthonormality, so any :class:`~kautztwin.KautzBasis` can replace the Laguerre
one.

This module holds the plant conversion (:func:`plant_model`), the discrete
design of section 6.1 (:func:`discrete_mpc_design`) and the continuous design of
section 6.2 (:func:`continuous_mpc_design`, :func:`continuous_phi`,
:func:`continuous_cost_matrices`).  Constraints and the QP are in
:mod:`kautztwin.mpc.problem`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Real
from typing import Any

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..basis import KautzBasis, LaguerreBasis
from ..exceptions import DataError, DimensionError, PoleError

__all__ = [
    "MPCDesign",
    "PlantModel",
    "continuous_cost_matrices",
    "continuous_mpc_design",
    "continuous_phi",
    "discrete_mpc_design",
    "plant_model",
]

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


# ----------------------------------------------------------------------------- basis
def _one_basis(spec: Any, discrete: bool, index: int | None) -> KautzBasis:
    where = "basis" if index is None else f"basis[{index}]"
    if isinstance(spec, KautzBasis):
        basis = spec
    elif (
        isinstance(spec, (tuple, list))
        and len(spec) == 2
        and isinstance(spec[0], Real)
        and isinstance(spec[1], (int, np.integer))
        and not isinstance(spec[1], bool)
    ):
        try:
            basis = LaguerreBasis(float(spec[0]), int(spec[1]), dt=1.0 if discrete else 0.0)
        except PoleError as exc:
            kind = "in (-1, 1)" if discrete else "< 0 (a pole location, s = -p)"
            raise PoleError(f"{where}: Laguerre pole must be {kind}: {exc}") from exc
    else:
        raise DataError(
            f"{where} must be a KautzBasis or a Laguerre spec (pole, n_functions), got {spec!r}"
        )
    if discrete and not basis.is_discrete:
        raise DataError(f"{where} is continuous-time; discrete MPC needs a basis with dt > 0")
    if not discrete and basis.is_discrete:
        raise DataError(f"{where} is discrete-time; continuous MPC needs a basis with dt = 0")
    if basis.delayed:
        raise DataError(f"{where} is delayed (L(0) = 0); MPC needs the undelayed sequences")
    return basis


def _basis_matrices(
    basis: Any, n_inputs: int, discrete: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64], tuple[KautzBasis, ...]]:
    """Block-diagonal ``A_L`` and ``L0`` of shape ``(n_functions_total, n_inputs)``."""
    is_list = isinstance(basis, (list, tuple)) and not (
        len(basis) == 2 and isinstance(basis[0], Real) and not isinstance(basis[0], bool)
    )
    if is_list:
        if len(basis) != n_inputs:
            raise DimensionError(
                f"basis lists {len(basis)} bases but the plant has {n_inputs} inputs"
            )
        bases = tuple(_one_basis(b, discrete, i) for i, b in enumerate(basis))
    else:
        bases = (_one_basis(basis, discrete, None),) * n_inputs
    A_L = scipy.linalg.block_diag(*[np.array(b.A) for b in bases])
    sizes = [b.n_functions for b in bases]
    L0 = np.zeros((sum(sizes), n_inputs))
    start = 0
    for q, b in enumerate(bases):
        L0[start : start + sizes[q], q] = b.B
        start += sizes[q]
    return A_L, L0, bases


def _weights(
    Q: ArrayLike | None, r: ArrayLike, C: NDArray, bases: Sequence[KautzBasis]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Augmented state weight, output weight and per-input increment weights."""
    n_y, n = C.shape
    if Q is None:
        Q = 1.0
    Qa = np.asarray(Q, dtype=float)
    if Qa.ndim == 2 and Qa.shape == (n, n):
        Q_aug = Qa
        Q_y = Qa[n - n_y :, n - n_y :]
    else:
        if Qa.ndim == 0:
            Q_y = float(Qa) * np.eye(n_y)
        elif Qa.shape == (n_y,):
            Q_y = np.diag(Qa)
        elif Qa.shape == (n_y, n_y):
            Q_y = Qa
        else:
            raise DimensionError(
                f"Q must be a scalar, shape ({n_y},), ({n_y}, {n_y}) (outputs) or ({n}, {n}) "
                f"(augmented state), got shape {Qa.shape}"
            )
        Q_aug = C.T @ Q_y @ C
    if not np.all(np.isfinite(Q_aug)) or not np.allclose(Q_aug, Q_aug.T):
        raise DataError("Q must be finite and symmetric")
    if np.min(np.linalg.eigvalsh(0.5 * (Q_aug + Q_aug.T))) < -1e-12 * max(1.0, np.abs(Q_aug).max()):
        raise DataError("Q must be positive semidefinite")
    ra = np.asarray(r, dtype=float)
    n_u = len(bases)
    if ra.ndim == 0:
        ra = np.full(n_u, float(ra))
    if ra.shape != (n_u,):
        raise DimensionError(f"r must be a scalar or have shape ({n_u},), got shape {ra.shape}")
    if not np.all(np.isfinite(ra)) or np.any(ra < 0):
        raise DataError(f"r must be finite and >= 0, got {ra.tolist()}")
    return np.array(Q_aug), np.array(Q_y), ra


def _increment_penalty(r: NDArray, bases: Sequence[KautzBasis]) -> NDArray[np.float64]:
    """``R_L = blkdiag(r_q I_{N_q})``."""
    return np.diag(
        np.concatenate([np.full(b.n_functions, rq) for rq, b in zip(r, bases, strict=True)])
    )


# ----------------------------------------------------------------------------- design
@dataclass(frozen=True, eq=False)
class MPCDesign:
    r"""Unconstrained Laguerre/Kautz MPC design: the matrices of kautz-math.md 6.1/6.2.

    The cost over the horizon is
    :math:`J = \eta^T\Omega\eta + 2\eta^T\Psi(x - x_s) + \text{const}`, with
    :math:`x` the augmented state (:math:`[\Delta x_m; y]` in discrete time,
    :math:`[\dot x_m; y]` in continuous time) and :math:`x_s = [0; r]`.

    Parameters
    ----------
    A, B, C : ndarray
        Augmented model, shapes ``(n, n)``, ``(n, n_inputs)``, ``(n_outputs, n)``
        with ``n = n_states + n_outputs``.
    A_L : ndarray of shape (n_functions, n_functions)
        Basis recursion matrix (block diagonal over the inputs): ``A_l`` in
        discrete time, ``A_p`` in continuous time.
    L0 : ndarray of shape (n_functions, n_inputs)
        ``L(0)``; column ``q`` holds input ``q``'s basis in its block.
    Omega : ndarray of shape (n_functions, n_functions)
        Hessian of the cost (including ``R_L``).
    Psi : ndarray of shape (n_functions, n)
        Coupling of ``eta`` with the state error.
    K_mpc : ndarray of shape (n_inputs, n)
        Receding-horizon state feedback, ``Delta u = -K_mpc (x - x_s)``
        (continuous: ``du/dt``).
    Q : ndarray of shape (n, n)
        Augmented state weight.
    R_L : ndarray of shape (n_functions, n_functions)
        Penalty on ``eta``.
    horizon : float
        ``N_p`` in samples (discrete) or ``T_p`` in seconds (continuous).
    dt : float
        Sampling period of the plant; ``0`` for the continuous design.

    See Also
    --------
    discrete_mpc_design : Build the discrete design (section 6.1).
    continuous_mpc_design : Build the continuous design (section 6.2).
    MPCProblem : The constrained problem built on the discrete design.
    """

    A: NDArray[np.float64]
    B: NDArray[np.float64]
    C: NDArray[np.float64]
    A_L: NDArray[np.float64]
    L0: NDArray[np.float64]
    Omega: NDArray[np.float64]
    Psi: NDArray[np.float64]
    K_mpc: NDArray[np.float64]
    Q: NDArray[np.float64]
    R_L: NDArray[np.float64]
    horizon: float
    dt: float

    def __post_init__(self) -> None:
        for name in ("A", "B", "C", "A_L", "L0", "Omega", "Psi", "K_mpc", "Q", "R_L"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))

    @property
    def n_functions(self) -> int:
        """Number of decision variables (basis functions over all inputs)."""
        return int(self.L0.shape[0])

    def closed_loop_poles(self) -> NDArray[np.complex128]:
        """Eigenvalues of :math:`A - B K_{mpc}` (unconstrained receding-horizon loop).

        Returns
        -------
        ndarray of complex, shape (n,)
            Sorted by real part, then imaginary part (``numpy.sort_complex``).
        """
        return np.sort_complex(np.linalg.eigvals(self.A - self.B @ self.K_mpc))

    def optimal_eta(self, x: ArrayLike, setpoint: ArrayLike = 0.0) -> NDArray[np.float64]:
        r"""Unconstrained optimum :math:`\eta^* = -\Omega^{-1}\Psi(x - x_s)`.

        Parameters
        ----------
        x : array-like of shape (n,)
            Augmented state.
        setpoint : float or array-like of shape (n_outputs,), default=0.0
            Output set-point ``r``; ``x_s = [0; r]``.

        Returns
        -------
        ndarray of shape (n_functions,)
        """
        e = _state_error(x, setpoint, self.C.shape[0], self.A.shape[0])
        return -np.linalg.solve(self.Omega, self.Psi @ e)


def _state_error(x: ArrayLike, setpoint: ArrayLike, n_y: int, n: int) -> NDArray[np.float64]:
    x = np.asarray(x, dtype=float).reshape(-1)
    if x.size != n:
        raise DimensionError(f"x has {x.size} entries but the augmented state has {n}")
    r = np.broadcast_to(np.asarray(setpoint, dtype=float).reshape(-1), (n_y,))
    e = x.copy()
    e[n - n_y :] -= r
    return e


def _augment_discrete(P: PlantModel) -> tuple[NDArray, NDArray, NDArray]:
    n_x, n_y = P.n_states, P.n_outputs
    A = np.zeros((n_x + n_y, n_x + n_y))
    A[:n_x, :n_x] = P.A
    A[n_x:, :n_x] = P.C @ P.A
    A[n_x:, n_x:] = np.eye(n_y)
    B = np.vstack([P.B, P.C @ P.B])
    C = np.hstack([np.zeros((n_y, n_x)), np.eye(n_y)])
    return A, B, C


def _augment_continuous(P: PlantModel) -> tuple[NDArray, NDArray, NDArray]:
    n_x, n_y = P.n_states, P.n_outputs
    A = np.zeros((n_x + n_y, n_x + n_y))
    A[:n_x, :n_x] = P.A
    A[n_x:, :n_x] = P.C
    B = np.vstack([P.B, np.zeros((n_y, P.n_inputs))])
    C = np.hstack([np.zeros((n_y, n_x)), np.eye(n_y)])
    return A, B, C


def _check_horizon(horizon: Any) -> int:
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
        raise DataError(f"horizon must be a positive integer number of samples, got {horizon!r}")
    return int(horizon)


def _discrete_sequences(
    A: NDArray, B: NDArray, A_L: NDArray, L0: NDArray, horizon: int
) -> tuple[NDArray, NDArray, NDArray]:
    """``L(m)`` (m = 0..Np), ``phi(m)^T`` (m = 0..Np) and ``A^m`` (m = 0..Np)."""
    n, N = A.shape[0], L0.shape[0]
    L = np.empty((horizon + 1,) + L0.shape)
    phiT = np.zeros((horizon + 1, n, N))
    Apow = np.empty((horizon + 1, n, n))
    L[0] = L0
    Apow[0] = np.eye(n)
    for m in range(1, horizon + 1):
        L[m] = A_L @ L[m - 1]
        phiT[m] = A @ phiT[m - 1] + B @ L[m - 1].T
        Apow[m] = A @ Apow[m - 1]
    return L, phiT, Apow


def discrete_mpc_design(
    plant: Any,
    basis: Any,
    horizon: int,
    *,
    Q: ArrayLike | None = None,
    r: ArrayLike = 0.1,
    dt: float | None = None,
) -> MPCDesign:
    r"""Discrete-time Laguerre/Kautz MPC (kautz-math.md 6.1): ``Omega``, ``Psi``, ``K_mpc``.

    Parameters
    ----------
    plant : tuple, scipy.signal system, KautzModel or PlantModel
        See :func:`plant_model`; continuous plants are discretised (ZOH) at ``dt``.
    basis : KautzBasis, (pole, n_functions) or list of these
        Discrete orthonormal basis of the increments (``dt > 0``, undelayed);
        ``(a, N)`` is ``LaguerreBasis(a, N, dt=1)``.  A list gives one basis per
        input (MIMO); a single basis is used for every input.
    horizon : int
        Prediction horizon ``N_p`` in samples.
    Q : float or array-like, optional
        Output weight (scalar, ``(n_outputs,)`` or ``(n_outputs, n_outputs)``;
        the state weight is then ``C^T Q C``) or the full augmented-state weight
        of shape ``(n, n)``.  Default ``C^T C``.
    r : float or array-like of shape (n_inputs,), default=0.1
        Increment weight; ``R_L = blkdiag(r_q I)``, which by orthonormality is
        the penalty :math:`r\sum_{k\ge0}\Delta u(k)^2` of the whole sequence.
    dt : float, optional
        Sampling period for continuous plants (see :func:`plant_model`).

    Returns
    -------
    MPCDesign

    Raises
    ------
    DataError
        On an unsupported plant or basis, or invalid weights or horizon.
    DimensionError
        If the weights or the list of bases do not fit the plant.

    See Also
    --------
    continuous_mpc_design : The continuous-time counterpart.
    MPCProblem : Add constraints and solve the QP.

    Notes
    -----
    With the augmented model :math:`x(k+1) = Ax(k) + B\Delta u(k)`,

    .. math::

        \phi(m)^T = A\phi(m-1)^T + BL(m-1)^T,\quad
        \Omega = \sum_{m=1}^{N_p}\phi(m)Q\phi(m)^T + R_L,\quad
        \Psi = \sum_{m=1}^{N_p}\phi(m)QA^m,\quad
        K_{mpc} = L(0)^T\Omega^{-1}\Psi .

    With a Laguerre pole ``a = 0`` and ``N = N_c`` this is classical MPC with
    control horizon ``N_c``.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.mpc import discrete_mpc_design
    >>> plant = ([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0])
    >>> d = discrete_mpc_design(plant, (0.5, 4), 20, r=0.1)
    >>> np.round(d.K_mpc, 6)
    array([[3.08288 , 1.308187, 1.621535]])
    """
    P = plant_model(plant, dt)
    return _discrete_build(P, basis, _check_horizon(horizon), Q, r)[0]


@dataclass(frozen=True)
class _Sequences:
    """What :class:`MPCProblem` needs besides the design."""

    L: NDArray[np.float64]  # (Np+1, N, n_u): L(m)
    phi_t: NDArray[np.float64]  # (Np+1, n, N): phi(m)^T
    a_pow: NDArray[np.float64]  # (Np+1, n, n): A^m
    Q_y: NDArray[np.float64]  # (n_y, n_y) output weight
    r: NDArray[np.float64]  # (n_u,) increment weights
    bases: tuple[KautzBasis, ...]


def _discrete_build(
    P: PlantModel, basis: Any, Np: int, Q: ArrayLike | None, r: ArrayLike
) -> tuple[MPCDesign, _Sequences]:
    A, B, C = _augment_discrete(P)
    A_L, L0, bases = _basis_matrices(basis, P.n_inputs, discrete=True)
    Q_aug, Q_y, rw = _weights(Q, r, C, bases)
    R_L = _increment_penalty(rw, bases)
    L, phiT, Apow = _discrete_sequences(A, B, A_L, L0, Np)
    Omega = np.einsum("mni,nk,mkj->ij", phiT[1:], Q_aug, phiT[1:]) + R_L
    Psi = np.einsum("mni,nk,mkj->ij", phiT[1:], Q_aug, Apow[1:])
    Omega = 0.5 * (Omega + Omega.T)
    K = L0.T @ _solve_spd(Omega, Psi)
    design = MPCDesign(A, B, C, A_L, L0, Omega, Psi, K, Q_aug, R_L, float(Np), P.dt)
    return design, _Sequences(L, phiT, Apow, Q_y, rw, bases)


def _solve_spd(Omega: NDArray, rhs: NDArray) -> NDArray[np.float64]:
    """Solve ``Omega X = rhs`` (Cholesky; a clear error if Omega is singular)."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(Omega), rhs)
    except np.linalg.LinAlgError as exc:
        raise DataError(
            "Omega is not positive definite: use r > 0, a longer horizon or fewer functions"
        ) from exc


# ----------------------------------------------------------------------------- continuous
def continuous_phi(
    A: ArrayLike,
    B: ArrayLike,
    A_p: ArrayLike,
    L0: ArrayLike,
    tau: float,
    *,
    method: str = "expm",
) -> NDArray[np.float64]:
    r"""Continuous-time prediction matrix :math:`\Phi(\tau)` of kautz-math.md 6.2.

    :math:`\Phi(\tau) = \int_0^\tau e^{A(\tau-\gamma)}BL(\gamma)^Td\gamma`, so that
    :math:`x(t_i+\tau) = e^{A\tau}x(t_i) + \Phi(\tau)\eta`.

    Parameters
    ----------
    A : array-like of shape (n, n)
        Augmented state matrix.
    B : array-like of shape (n, n_inputs)
        Augmented input matrix.
    A_p : array-like of shape (n_functions, n_functions)
        Basis matrix, :math:`\dot L = A_p L`.
    L0 : array-like of shape (n_functions, n_inputs) or (n_functions,)
        ``L(0)``.
    tau : float
        Time ``>= 0``.
    method : {'expm', 'sylvester'}, default='expm'
        ``'expm'``: the block exponential
        :math:`\exp(\begin{bmatrix}A & BL(0)^T\\ 0 & A_p^T\end{bmatrix}\tau)`;
        ``'sylvester'``: :math:`\Phi = Xe^{A_p^T\tau} - e^{A\tau}X` with
        :math:`AX - XA_p^T = -BL(0)^T` (needs disjoint spectra).

    Returns
    -------
    ndarray of shape (n, n_functions)

    Raises
    ------
    DataError
        On an unknown ``method`` or a negative ``tau``.

    See Also
    --------
    continuous_cost_matrices : The integrals of :math:`\Phi` that make ``Omega`` and ``Psi``.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, -1)
    A_p = np.atleast_2d(np.asarray(A_p, dtype=float))
    L0 = np.asarray(L0, dtype=float).reshape(A_p.shape[0], -1)
    tau = float(tau)
    if tau < 0 or not np.isfinite(tau):
        raise DataError(f"tau must be finite and >= 0, got {tau}")
    G = B @ L0.T
    if method == "expm":
        return _block_expm(A, G, A_p, tau)[:n, n:]
    if method == "sylvester":
        X = scipy.linalg.solve_sylvester(A, -A_p.T, -G)
        return X @ scipy.linalg.expm(A_p.T * tau) - scipy.linalg.expm(A * tau) @ X
    raise DataError(f"method must be 'expm' or 'sylvester', got {method!r}")


def _block_expm(A: NDArray, G: NDArray, A_p: NDArray, tau: float) -> NDArray[np.float64]:
    n, N = A.shape[0], A_p.shape[0]
    H = np.zeros((n + N, n + N))
    H[:n, :n] = A
    H[:n, n:] = G
    H[n:, n:] = A_p.T
    return scipy.linalg.expm(H * tau)


def continuous_cost_matrices(
    A: ArrayLike,
    B: ArrayLike,
    A_p: ArrayLike,
    L0: ArrayLike,
    Q: ArrayLike,
    prediction_time: float,
    *,
    method: str = "vanloan",
    n_doublings: int | None = None,
    n_panels: int = 40,
    n_nodes: int = 12,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    r"""The integrals :math:`\int_0^{T_p}\Phi^TQ\Phi` and :math:`\int_0^{T_p}\Phi^TQe^{A\tau}`.

    Parameters
    ----------
    A, B : array-like
        Augmented model, shapes ``(n, n)`` and ``(n, n_inputs)``.
    A_p : array-like of shape (n_functions, n_functions)
        Basis matrix.
    L0 : array-like of shape (n_functions, n_inputs)
        ``L(0)``.
    Q : array-like of shape (n, n)
        State weight.
    prediction_time : float
        ``T_p > 0`` in seconds.
    method : {'vanloan', 'quadrature'}, default='vanloan'
        ``'vanloan'``: Van Loan's block exponential on ``T_p / 2**k`` followed
        by ``k`` interval doublings; ``'quadrature'``: composite Gauss-Legendre
        (``n_panels`` panels of ``n_nodes`` nodes) on the block exponential.
    n_doublings : int, optional
        ``k`` for ``'vanloan'``; by default the smallest ``k`` with
        :math:`\|H\|_1 T_p / 2^k \le 1/2`.
    n_panels, n_nodes : int, default=40, 12
        Quadrature resolution.

    Returns
    -------
    Omega0 : ndarray of shape (n_functions, n_functions)
        :math:`\int_0^{T_p}\Phi(\tau)^TQ\Phi(\tau)d\tau` (``Omega`` without ``R_L``).
    Psi : ndarray of shape (n_functions, n)
        :math:`\int_0^{T_p}\Phi(\tau)^TQe^{A\tau}d\tau`.

    Raises
    ------
    DataError
        On an unknown ``method`` or a non-positive ``prediction_time``.

    See Also
    --------
    continuous_phi : The prediction matrix :math:`\Phi(\tau)`.
    continuous_mpc_design : Uses these integrals.

    Notes
    -----
    With :math:`H = \begin{bmatrix}A & BL(0)^T\\0 & A_p^T\end{bmatrix}` and
    :math:`\tilde Q = \operatorname{blkdiag}(Q, 0)`,
    :math:`W(T) = \int_0^T e^{H^T\tau}\tilde Qe^{H\tau}d\tau` holds
    ``Omega0 = W_22`` and ``Psi = W_21``.  Van Loan:
    :math:`\exp(\begin{bmatrix}-H^T & \tilde Q\\0 & H\end{bmatrix}T)` has blocks
    :math:`F_{12}, F_{22}` with :math:`W(T) = F_{22}^TF_{12}`; it loses accuracy
    for long intervals, so it is applied on :math:`T_0 = T_p/2^k` and doubled,
    :math:`W(2T) = W(T) + e^{H^TT}W(T)e^{HT}`.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, -1)
    A_p = np.atleast_2d(np.asarray(A_p, dtype=float))
    N = A_p.shape[0]
    L0 = np.asarray(L0, dtype=float).reshape(N, -1)
    Q = np.asarray(Q, dtype=float).reshape(n, n)
    T = float(prediction_time)
    if not np.isfinite(T) or T <= 0:
        raise DataError(f"prediction_time must be > 0, got {prediction_time}")
    H = np.zeros((n + N, n + N))
    H[:n, :n] = A
    H[:n, n:] = B @ L0.T
    H[n:, n:] = A_p.T
    Qt = np.zeros((n + N, n + N))
    Qt[:n, :n] = Q
    if method == "vanloan":
        if n_doublings is None:
            h = float(np.linalg.norm(H, 1)) * T
            n_doublings = max(0, int(np.ceil(np.log2(h / 0.5)))) if h > 0.5 else 0
        T0 = T / 2 ** int(n_doublings)
        m = n + N
        Z = np.zeros((2 * m, 2 * m))
        Z[:m, :m] = -H.T
        Z[:m, m:] = Qt
        Z[m:, m:] = H
        F = scipy.linalg.expm(Z * T0)
        W = F[m:, m:].T @ F[:m, m:]
        E = F[m:, m:]  # e^{H T0}
        for _ in range(int(n_doublings)):
            W = W + E.T @ W @ E
            E = E @ E
        W = 0.5 * (W + W.T)
    elif method == "quadrature":
        x, w = np.polynomial.legendre.leggauss(int(n_nodes))
        half = 0.5 * T / int(n_panels)
        # e^{H (a_i + s_j)} = e^{H a_i} e^{H s_j}: one exponential per node offset, and the
        # panel starts by repeated multiplication with e^{H * panel width}
        E_nodes = np.array([scipy.linalg.expm(H * (half * (xi + 1.0))) for xi in x])
        E_panel = scipy.linalg.expm(H * (2.0 * half))
        E_start = np.eye(H.shape[0])
        W = np.zeros_like(H)
        for _ in range(int(n_panels)):
            Et = E_start @ E_nodes  # (n_nodes, m, m)
            W += half * np.einsum("j,jki,kl,jlm->im", w, Et, Qt, Et)
            E_start = E_start @ E_panel
    else:
        raise DataError(f"method must be 'vanloan' or 'quadrature', got {method!r}")
    return W[n:, n:].copy(), W[n:, :n].copy()


def continuous_mpc_design(
    plant: Any,
    basis: Any,
    prediction_time: float,
    *,
    Q: ArrayLike | None = None,
    r: ArrayLike = 0.1,
    penalty: str = "infinite",
    method: str = "vanloan",
) -> MPCDesign:
    r"""Continuous-time Laguerre/Kautz MPC (kautz-math.md 6.2): ``Omega``, ``Psi``, ``K_mpc``.

    Parameters
    ----------
    plant : tuple, scipy.signal.lti, KautzModel or PlantModel
        Continuous-time plant; bare matrices ``(A, B, C)`` are taken as continuous.
    basis : KautzBasis, (pole, n_functions) or list of these
        Continuous orthonormal basis of :math:`\dot u` (``dt = 0``); ``(pole, N)``
        is ``LaguerreBasis(pole, N)`` with the pole *location* ``pole < 0``
        (Wang's ``p`` is ``-pole``).
    prediction_time : float
        ``T_p`` in seconds.
    Q : float or array-like, optional
        As in :func:`discrete_mpc_design`; default ``C^T C``.
    r : float or array-like of shape (n_inputs,), default=0.1
        Weight on :math:`\dot u`.
    penalty : {'infinite', 'finite'}, default='infinite'
        ``'infinite'``: :math:`R_L = rI`, the penalty :math:`r\int_0^\infty\dot u^2`;
        ``'finite'``: the exact horizon penalty
        :math:`r(I - e^{A_pT_p}e^{A_p^TT_p})`.
    method : {'vanloan', 'quadrature'}, default='vanloan'
        How the cost integrals are computed (:func:`continuous_cost_matrices`).

    Returns
    -------
    MPCDesign
        With ``dt = 0`` and ``horizon = T_p``.

    Raises
    ------
    DataError
        On an unsupported plant or basis or invalid weights.

    See Also
    --------
    discrete_mpc_design : The discrete-time counterpart.

    Notes
    -----
    Augmented model :math:`x = [\dot x_m; y]`,
    :math:`A = \begin{bmatrix}A_m & 0\\C_m & 0\end{bmatrix}`,
    :math:`B = \begin{bmatrix}B_m\\0\end{bmatrix}`; the optimum is
    :math:`\dot u(t_i) = -K_{mpc}(x - x_s)` with
    :math:`K_{mpc} = L(0)^T\Omega^{-1}\Psi`.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.mpc import continuous_mpc_design
    >>> plant = ([[0.0, 1.0], [-1.0, -0.4]], [0.0, 1.0], [1.0, 0.0])
    >>> d = continuous_mpc_design(plant, (-1.0, 4), 10.0, r=0.05)
    >>> np.round(d.K_mpc, 6)
    array([[5.725868, 3.367629, 4.88106 ]])
    """
    P = _continuous_plant(plant)
    A, B, C = _augment_continuous(P)
    A_p, L0, bases = _basis_matrices(basis, P.n_inputs, discrete=False)
    Q_aug, _, rw = _weights(Q, r, C, bases)
    T = float(prediction_time)
    if not np.isfinite(T) or T <= 0:
        raise DataError(f"prediction_time must be > 0, got {prediction_time}")
    R_L = _increment_penalty(rw, bases)
    if penalty == "finite":
        Ep = scipy.linalg.expm(A_p * T)
        R_L = R_L @ (np.eye(A_p.shape[0]) - Ep @ Ep.T)
        R_L = 0.5 * (R_L + R_L.T)
    elif penalty != "infinite":
        raise DataError(f"penalty must be 'infinite' or 'finite', got {penalty!r}")
    Omega0, Psi = continuous_cost_matrices(A, B, A_p, L0, Q_aug, T, method=method)
    Omega = Omega0 + R_L
    Omega = 0.5 * (Omega + Omega.T)
    K = L0.T @ _solve_spd(Omega, Psi)
    return MPCDesign(A, B, C, A_p, L0, Omega, Psi, K, Q_aug, R_L, T, 0.0)
