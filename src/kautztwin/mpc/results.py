"""Value objects returned by the MPC: one solve, its first move, a prediction, a closed loop.

All arrays are read-only copies, so a result can be handed around (history, plots) without
the solver changing it later.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ClosedLoopResult", "MPCMove", "MPCResult", "Prediction"]


def _readonly(x: ArrayLike) -> NDArray[np.float64]:
    """A read-only float copy; a float array that is already read-only is kept as it is."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64 and not x.flags.writeable:
        return x
    a = np.array(x, dtype=float, copy=True)
    a.setflags(write=False)
    return a


def _squeeze(a: NDArray, siso: bool) -> NDArray[np.float64]:
    return a[:, 0] if siso and a.ndim == 2 else a


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class MPCResult:
    r"""Result of one MPC solve (:meth:`MPCProblem.solve`, :func:`solve_mpc`).

    Arrays over the horizon have shape ``(horizon, n_inputs)`` /
    ``(horizon, n_outputs)``, or ``(horizon,)`` for a SISO plant.

    Parameters
    ----------
    success : bool
        True when the QP was solved with all constraints met.  False when the
        constraints were infeasible (a compromise is returned) or the solver failed.
    message : str
        What happened, in words.
    u : ndarray
        Planned inputs :math:`u(k), \dots, u(k+N_p-1)`; apply ``u[0]``.
    y_pred : ndarray
        Predicted outputs :math:`y(k+1), \dots, y(k+N_p)` of the model under ``u``.
    cost : float
        Predicted cost :math:`J = \eta^T\Omega\eta + 2\eta^T\Psi(x-x_s) + \sum_m\|A^m(x-x_s)\|_Q^2`.
    du : ndarray
        Planned increments :math:`\Delta u(k+m) = L(m)^T\eta`.
    eta : ndarray of shape (n_variables,)
        Decision variables (basis coefficients; one per step for the full-horizon problem).
    iterations : int
        QP solver iterations (DAQP active-set changes or Hildreth sweeps; 0 if
        no QP was needed).
    solve_time : float
        Wall time of the whole solve in seconds (bounds, QP, plan).
    solver_time : float
        Time reported by the QP solver itself (DAQP's ``solve_time``).
    status : int
        Solver exit flag: DAQP's (1 optimal, 2 soft-optimal, -1 infeasible, ...);
        Hildreth 1 converged, -4 not; 0 unconstrained; -100 clipped fallback;
        -101 optimal, but limits that the inputs cannot influence (their rows of
        the constraint matrix are zero) are broken by the current state.
    max_violation : float
        Largest predicted constraint violation of the plan (0 if feasible).

    See Also
    --------
    MPCProblem.solve : Produces it.
    """

    success: bool
    message: str
    u: NDArray[np.float64]
    y_pred: NDArray[np.float64]
    cost: float
    du: NDArray[np.float64]
    eta: NDArray[np.float64]
    iterations: int = 0
    solve_time: float = 0.0
    solver_time: float = 0.0
    status: int = 0
    max_violation: float = 0.0

    def __post_init__(self) -> None:
        for name in ("u", "y_pred", "du", "eta"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))

    @property
    def u_next(self) -> NDArray[np.float64] | float:
        """The input to apply now, ``u[0]`` (a float for SISO plants)."""
        u0 = self.u[0]
        return float(u0) if np.ndim(u0) == 0 else u0


class MPCMove(NamedTuple):
    r"""First move of one MPC solve, from the lean path :meth:`MPCProblem.move`.

    A plain (immutable) named tuple: building it costs a fraction of a
    microsecond, so a control loop that only needs the move to apply does not
    pay for the plan over the horizon that :class:`MPCResult` carries.

    Parameters
    ----------
    du : ndarray of shape (n_inputs,)
        Increment to apply now, :math:`\Delta u(k) = L(0)^T\eta`.
    u : ndarray of shape (n_inputs,)
        Input to apply now, ``u_prev + du``.
    success : bool
        True when the QP was solved with all constraints met (as in
        :attr:`MPCResult.success`; a compromise move otherwise).
    status : int
        Solver exit flag (as in :attr:`MPCResult.status`).
    iterations : int
        QP solver iterations.
    solver_time : float
        Time reported by the QP solver itself, s.

    See Also
    --------
    MPCProblem.move : Produces it.
    MPCResult : The full result with the plan over the horizon.
    """

    du: NDArray[np.float64]
    u: NDArray[np.float64]
    success: bool
    status: int
    iterations: int
    solver_time: float


@dataclass(frozen=True, eq=False)
class Prediction:
    """Open-loop prediction over the horizon for given decision variables.

    Parameters
    ----------
    y : ndarray
        Outputs :math:`y(k+1), \\dots, y(k+N_p)`.
    u : ndarray
        Inputs :math:`u(k), \\dots, u(k+N_p-1)`.
    du : ndarray
        Increments :math:`\\Delta u(k), \\dots, \\Delta u(k+N_p-1)`.

    See Also
    --------
    MPCProblem.predict : Produces it.
    """

    y: NDArray[np.float64]
    u: NDArray[np.float64]
    du: NDArray[np.float64]

    def __post_init__(self) -> None:
        for name in ("y", "u", "du"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))


@dataclass(frozen=True, eq=False)
class ClosedLoopResult:
    r"""Receding-horizon closed-loop run (:func:`simulate_closed_loop`).

    Parameters
    ----------
    t : ndarray of shape (n_steps + 1,)
        Times ``k * dt``.
    y : ndarray of shape (n_steps + 1, n_outputs) or (n_steps + 1,)
        Plant outputs (``y[0]`` is the initial one).
    u : ndarray of shape (n_steps, n_inputs) or (n_steps,)
        Applied inputs.
    du : ndarray of shape (n_steps, n_inputs) or (n_steps,)
        Applied increments.
    setpoint : ndarray of shape (n_steps, n_outputs) or (n_steps,)
        Set-point given to each solve.
    cost : float
        :math:`\sum_{k<n} e(k+1)^TQe(k+1) + \Delta u(k)^TR\Delta u(k)` with
        :math:`e(k+1) = y(k+1) - r(k)` and :math:`R = \operatorname{diag}(r)`.
    violations : int
        Number of steps ``k`` at which ``u(k)``, ``du(k)`` or ``y(k+1)`` broke a
        limit by more than the tolerance.
    max_violation : float
        Largest violation of any limit.
    solve_times : ndarray of shape (n_steps,)
        Wall time of each solve in seconds.
    solver_times : ndarray of shape (n_steps,)
        Time the QP solver itself reported for each solve (0 without a QP).
    iterations : ndarray of int, shape (n_steps,)
        QP iterations per solve.
    n_failed : int
        Solves that returned ``success=False``.

    See Also
    --------
    simulate_closed_loop : Produces it.
    """

    t: NDArray[np.float64]
    y: NDArray[np.float64]
    u: NDArray[np.float64]
    du: NDArray[np.float64]
    setpoint: NDArray[np.float64]
    cost: float
    violations: int
    max_violation: float
    solve_times: NDArray[np.float64]
    solver_times: NDArray[np.float64]
    iterations: NDArray[np.int64]
    n_failed: int

    def __post_init__(self) -> None:
        for name in ("t", "y", "u", "du", "setpoint", "solve_times", "solver_times"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))
        it = np.array(self.iterations, dtype=np.int64, copy=True)
        it.setflags(write=False)
        object.__setattr__(self, "iterations", it)
