r"""Discrete Laguerre/Kautz-parameterised MPC: the basis, the weights and the design of 6.1.

The control increments over the prediction horizon are expanded on an
orthonormal basis, :math:`\Delta u(k_i+m) = L(m)^T\eta` (discrete time) or
:math:`\dot u(t_i+\tau) = L(\tau)^T\eta` (continuous time), so the optimisation
has ``N`` decision variables instead of one per step (kautz-math.md section 6,
after Wang 2009).  Only two properties of the basis are used: the linear
recursion :math:`L(m+1) = A_L L(m)` (or :math:`\dot L = A_p L`) and
orthonormality, so any :class:`~kautztwin.KautzBasis` can replace the Laguerre
one.

This module holds the basis and weight handling shared by both designs, the
design value object :class:`MPCDesign` and the discrete design of section 6.1
(:func:`discrete_mpc_design`).  The plant conversion is in
:mod:`kautztwin.mpc.plant`, the continuous design of section 6.2 in
:mod:`kautztwin.mpc.continuous`, constraints and the QP in
:mod:`kautztwin.mpc.problem`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Real
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from .._validation import check_int
from ..basis import KautzBasis, LaguerreBasis
from ..exceptions import DataError, DimensionError, PoleError
from .plant import PlantModel, _readonly, plant_model

__all__ = ["MPCDesign", "discrete_mpc_design"]


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
    return _discrete_build(P, basis, check_int(horizon, "horizon", 1), Q, r)[0]


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
