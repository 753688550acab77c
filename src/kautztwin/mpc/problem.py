r"""Constrained Laguerre/Kautz MPC as a QP that is built once and re-solved fast.

:class:`MPCProblem` assembles, once, the cost matrices (``E = 2 Omega``, the
map from state and set-point to ``F``), the constraint matrix and the affine
map from ``(x, u_prev)`` to the constraint bounds (kautz-math.md 6.3).  Each
:meth:`MPCProblem.solve` then costs a few matrix-vector products and one
warm-started DAQP solve.  ``full_horizon=True`` gives the classical MPC with
one decision variable per step (the baseline that the basis parameterisation
is compared with).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ..basis import LaguerreBasis
from ..exceptions import DataError, DimensionError
from .hildreth import hildreth
from .laguerre import MPCDesign, PlantModel, _check_horizon, _discrete_build, plant_model

__all__ = [
    "ClosedLoopResult",
    "MPCMove",
    "MPCProblem",
    "MPCResult",
    "Prediction",
    "simulate_closed_loop",
    "solve_mpc",
]

_INF = 1e30  # DAQP's "no bound"
_DU, _U, _Y = 0, 1, 2  # constraint row kinds


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


# ----------------------------------------------------------------------------- helpers
def _bound(value: ArrayLike | None, n: int, name: str, default: float) -> NDArray[np.float64]:
    if value is None:
        return np.full(n, default)
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise DimensionError(f"{name} must be a scalar or have shape ({n},), got shape {a.shape}")
    if np.any(np.isnan(a)):
        raise DataError(f"{name} contains NaN")
    return a.copy()


def _pair(lo: NDArray, hi: NDArray, lo_name: str, hi_name: str) -> None:
    bad = np.flatnonzero(lo > hi)
    if bad.size:
        i = int(bad[0])
        raise DataError(f"{lo_name}[{i}] = {lo[i]:g} exceeds {hi_name}[{i}] = {hi[i]:g}")


def _steps(constraint_steps: Any, Np: int) -> NDArray[np.int64]:
    if constraint_steps is None:
        return np.arange(Np)
    if isinstance(constraint_steps, (int, np.integer)) and not isinstance(constraint_steps, bool):
        n = int(constraint_steps)
        if not 0 <= n <= Np:
            raise DataError(f"constraint_steps = {n} must lie in [0, horizon = {Np}]")
        return np.arange(n)
    s = np.unique(np.asarray(constraint_steps, dtype=np.int64).reshape(-1))
    if s.size and (s[0] < 0 or s[-1] >= Np):
        raise DataError(f"constraint_steps must lie in [0, {Np - 1}], got {s.tolist()}")
    return s


# ----------------------------------------------------------------------------- problem
class MPCProblem:
    r"""Laguerre/Kautz (or full-horizon) MPC with constraints, built once, solved many times.

    The plant is a discrete-time strictly proper model (continuous ones are
    discretised with a zero-order hold at ``dt``).  The control increments over
    the horizon are :math:`\Delta u(k+m) = L(m)^T\eta` with an orthonormal
    discrete basis; the QP in :math:`\eta` is

    .. math::

        \min_\eta\ \tfrac12\eta^TE\eta + \eta^TF \quad\text{s.t.}\quad
        \underline b(x, u_{prev}) \le M_c\eta \le \bar b(x, u_{prev}),

    with :math:`E = 2\Omega` and :math:`F = 2\Psi(x - x_s)` (kautz-math.md 6.1, 6.3).
    Everything that does not depend on the current state is built in the
    constructor; :meth:`solve` only forms ``F`` and the bounds and calls the solver.

    Parameters
    ----------
    plant : tuple, scipy.signal system, KautzModel or PlantModel
        Prediction model, see :func:`~kautztwin.mpc.plant_model`.
    basis : KautzBasis, (pole, n_functions) or list of these, optional
        Discrete orthonormal basis of the increments (one per input, or one for
        all).  ``(a, N)`` is a discrete Laguerre basis.  Required unless
        ``full_horizon=True``.
    horizon : int, default=50
        Prediction horizon ``N_p`` in samples.
    dt : float, optional
        Sampling period for continuous plants.
    Q : float or array-like, optional
        Output weight (default 1), or the augmented-state weight; see
        :func:`~kautztwin.mpc.discrete_mpc_design`.
    r : float or array-like of shape (n_inputs,), default=0.1
        Weight on the input increments.
    u_min, u_max : float or array-like of shape (n_inputs,), optional
        Input limits (``None`` or ``-inf``/``inf``: none).
    du_min, du_max : float or array-like of shape (n_inputs,), optional
        Limits on the increments ``u(k) - u(k-1)``.
    y_min, y_max : float or array-like of shape (n_outputs,), optional
        Output limits.
    constraint_steps : int or array-like of int, optional
        Horizon steps ``j`` at which the limits are imposed: ``u(k+j)``,
        ``du(k+j)`` and ``y(k+j+1)``.  An int ``n`` means the first ``n`` steps;
        default all ``horizon`` steps.
    full_horizon : bool, default=False
        Classical MPC: one increment per step and input (a Laguerre basis with
        pole 0 and ``N = horizon``), same cost and constraints.
    solver : {'daqp', 'hildreth'}, default='daqp'
        QP solver.  DAQP (dual active set) keeps its factorisation of ``E``
        between solves; Hildreth is the dependency-free fallback.
    warm_start : bool, default=True
        Start each solve from the previous solve's active set (DAQP) or
        multipliers (Hildreth).  ``False`` starts every solve from an empty
        active set (the factorisation of ``E`` is still reused), which makes a
        solve independent of the history.
    max_iter : int, default=5000
        Iteration limit of the QP solver.
    tol : float, default=1e-9
        Primal feasibility tolerance (DAQP) or multiplier tolerance (Hildreth).

    Attributes
    ----------
    plant : PlantModel
        The discrete prediction model.
    design : MPCDesign
        Unconstrained design (``Omega``, ``Psi``, ``K_mpc``).
    horizon : int
        ``N_p``.
    dt : float
        Sampling period.
    n_variables : int
        Number of decision variables.
    n_constraints : int
        Number of two-sided constraint rows.
    E : ndarray of shape (n_variables, n_variables)
        QP Hessian ``2 Omega``.

    Raises
    ------
    DataError
        On invalid settings (inconsistent limits, unknown solver, bad horizon).
    DimensionError
        If limits or weights do not fit the plant.

    See Also
    --------
    solve_mpc : One-shot use.
    simulate_closed_loop : Receding-horizon simulation.
    kautztwin.mpc.discrete_mpc_design : The unconstrained design.

    Examples
    --------
    >>> from kautztwin.mpc import MPCProblem
    >>> plant = ([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0])
    >>> mpc = MPCProblem(plant, (0.5, 4), 20, r=0.1, u_min=-0.5, u_max=0.5)
    >>> res = mpc.solve([0.0, 0.0, 0.0], setpoint=1.0, u_prev=0.0)
    >>> res.success, round(res.u_next, 6)
    (True, 0.5)
    """

    def __init__(
        self,
        plant: Any,
        basis: Any = None,
        horizon: int = 50,
        *,
        dt: float | None = None,
        Q: ArrayLike | None = None,
        r: ArrayLike = 0.1,
        u_min: ArrayLike | None = None,
        u_max: ArrayLike | None = None,
        du_min: ArrayLike | None = None,
        du_max: ArrayLike | None = None,
        y_min: ArrayLike | None = None,
        y_max: ArrayLike | None = None,
        constraint_steps: Any = None,
        full_horizon: bool = False,
        solver: str = "daqp",
        warm_start: bool = True,
        max_iter: int = 5000,
        tol: float = 1e-9,
    ) -> None:
        P = plant_model(plant, dt)
        Np = _check_horizon(horizon)
        if full_horizon:
            if basis is not None:
                raise DataError("give either basis or full_horizon=True, not both")
            basis = LaguerreBasis(0.0, Np, dt=P.dt)
        elif basis is None:
            raise DataError("basis is required (a KautzBasis or (pole, n)) unless full_horizon")
        if solver not in ("daqp", "hildreth"):
            raise DataError(f"solver must be 'daqp' or 'hildreth', got {solver!r}")
        if isinstance(max_iter, bool) or int(max_iter) < 1:
            raise DataError(f"max_iter must be a positive integer, got {max_iter!r}")
        if not np.isfinite(tol) or tol <= 0:
            raise DataError(f"tol must be > 0, got {tol}")
        design, seq = _discrete_build(P, basis, Np, Q, r)
        self._plant = P
        self._design = design
        self._Np = Np
        self._full = bool(full_horizon)
        self._solver = solver
        self._warm = bool(warm_start)
        self._max_iter = int(max_iter)
        self._tol = float(tol)
        self._siso = P.n_inputs == 1 and P.n_outputs == 1
        self._Q_y = seq.Q_y
        self._r = seq.r
        n_u, n_y, n_x = P.n_inputs, P.n_outputs, P.n_states
        n = n_x + n_y
        N = design.n_functions
        self._n, self._n_x, self._N = n, n_x, N

        # ---- limits
        self._u_lo = _bound(u_min, n_u, "u_min", -np.inf)
        self._u_hi = _bound(u_max, n_u, "u_max", np.inf)
        self._du_lo = _bound(du_min, n_u, "du_min", -np.inf)
        self._du_hi = _bound(du_max, n_u, "du_max", np.inf)
        self._y_lo = _bound(y_min, n_y, "y_min", -np.inf)
        self._y_hi = _bound(y_max, n_y, "y_max", np.inf)
        _pair(self._u_lo, self._u_hi, "u_min", "u_max")
        _pair(self._du_lo, self._du_hi, "du_min", "du_max")
        _pair(self._y_lo, self._y_hi, "y_min", "y_max")
        if np.any(self._du_lo > 0) or np.any(self._du_hi < 0):
            raise DataError("du_min <= 0 <= du_max is required (holding the input must be allowed)")
        steps = _steps(constraint_steps, Np)
        self._steps = steps

        # ---- prediction maps over the horizon
        L = seq.L[:Np]  # (Np, N, n_u)
        S = np.cumsum(L, axis=0)  # sum_{i<=j} L(i)
        C = design.C
        self._Dmap = np.transpose(L, (0, 2, 1)).reshape(Np * n_u, N)  # du
        self._Smap = np.transpose(S, (0, 2, 1)).reshape(Np * n_u, N)  # u - u_prev
        self._Yeta = np.einsum("pn,mnj->mpj", C, seq.phi_t[1:]).reshape(Np * n_y, N)
        self._Yx = np.einsum("pn,mnk->mpk", C, seq.a_pow[1:]).reshape(Np * n_y, n)
        # plan = Weta @ eta + Wz @ [x; u_prev] stacks y (Np n_y), du and u (Np n_u each)
        self._Weta = np.vstack([self._Yeta, self._Dmap, self._Smap])
        self._Wz = np.zeros((Np * (n_y + 2 * n_u), n + n_u))
        self._Wz[: Np * n_y, :n] = self._Yx
        self._Wz[Np * (n_y + n_u) :, n:] = np.tile(np.eye(n_u), (Np, 1))
        self._P0 = np.einsum("mki,kl,mlj->ij", seq.a_pow[1:], design.Q, seq.a_pow[1:])

        # ---- cost: F = Fx @ (x - x_s); unconstrained eta = Kx @ (x - x_s)
        self._E = 2.0 * design.Omega
        self._Fx = 2.0 * design.Psi
        self._cho = scipy.linalg.cho_factor(design.Omega)
        self._Kx = -scipy.linalg.cho_solve(self._cho, design.Psi)

        # ---- constraint rows: lo0 + G z <= Mc eta <= hi0 + G z, z = [x; u_prev]
        rows: list[NDArray] = []
        lo: list[float] = []
        hi: list[float] = []
        G: list[NDArray] = []
        kind: list[int] = []
        zero = np.zeros(n + n_u)
        for j in steps:
            for q in range(n_u):
                if np.isfinite(self._du_lo[q]) or np.isfinite(self._du_hi[q]):
                    rows.append(self._Dmap[j * n_u + q])
                    lo.append(self._du_lo[q])
                    hi.append(self._du_hi[q])
                    G.append(zero)
                    kind.append(_DU)
            for q in range(n_u):
                if np.isfinite(self._u_lo[q]) or np.isfinite(self._u_hi[q]):
                    rows.append(self._Smap[j * n_u + q])
                    lo.append(self._u_lo[q])
                    hi.append(self._u_hi[q])
                    g = zero.copy()
                    g[n + q] = -1.0
                    G.append(g)
                    kind.append(_U)
            for p in range(n_y):
                if np.isfinite(self._y_lo[p]) or np.isfinite(self._y_hi[p]):
                    rows.append(self._Yeta[j * n_y + p])
                    lo.append(self._y_lo[p])
                    hi.append(self._y_hi[p])
                    g = zero.copy()
                    g[:n] = -self._Yx[j * n_y + p]
                    G.append(g)
                    kind.append(_Y)
        m = len(rows)
        self._m = m
        self._Mc = np.array(rows).reshape(m, N)
        self._lo0 = np.clip(np.array(lo, dtype=float), -_INF, _INF)
        self._hi0 = np.clip(np.array(hi, dtype=float), -_INF, _INF)
        self._G = np.array(G).reshape(m, n + n_u)
        self._Gx = np.ascontiguousarray(self._G[:, :n])
        self._Gu = np.ascontiguousarray(self._G[:, n:])
        self._kind = np.array(kind, dtype=int)
        self._daqp: Any = None
        self._daqp_soft: Any = None
        self._lam: NDArray | None = None
        if m and solver == "daqp":
            self._setup_daqp()
        if m and solver == "hildreth":
            # one-sided rows M eta <= gamma (drop the infinite ones; bounds are finite offsets)
            up = self._hi0 < _INF
            dn = self._lo0 > -_INF
            self._h_rows = np.concatenate([np.flatnonzero(up), np.flatnonzero(dn)])
            self._h_sign = np.concatenate([np.ones(up.sum()), -np.ones(dn.sum())])
            self._h_M = self._Mc[self._h_rows] * self._h_sign[:, None]
        self._setup_lean()

    # ------------------------------------------------------------------ lean path
    def _setup_lean(self) -> None:
        """One matrix that maps ``v = [x; u_prev; r; 1]`` to ``[F; upper; lower]`` at once.

        :meth:`move` then costs one matrix-vector product, the solver call
        and ``du = L(0)^T eta``.  Without constraints the rows give the
        unconstrained optimum ``eta = K_x (x - x_s)`` directly.
        """
        n, n_x, N = self._n, self._n_x, self._N
        n_u, n_y = self._plant.n_inputs, self._plant.n_outputs
        n_v = n + n_u + n_y + 1
        r_cols = slice(n + n_u, n + n_u + n_y)
        if self._m == 0:
            W = np.zeros((N, n_v))
            W[:, :n] = self._Kx
            W[:, r_cols] = -self._Kx[:, n_x:]
            self._lean_split = (N, N)
        elif self._solver == "daqp":
            mp = self._perm.size
            W = np.zeros((N + 2 * mp, n_v))
            W[:N, :n] = self._Fx
            W[:N, r_cols] = -self._Fx[:, n_x:]
            W[N : N + mp, : n + n_u] = self._Gp
            W[N : N + mp, -1] = self._hi0p
            W[N + mp :, : n + n_u] = self._Gp
            W[N + mp :, -1] = self._lo0p
            self._lean_split = (N, N + mp)
        else:  # Hildreth: move() goes through solve()
            W = np.zeros((0, n_v))
            self._lean_split = (0, 0)
        self._lean_W = W
        self._lean_v = np.zeros(n_v)
        self._lean_v[-1] = 1.0
        self._lean_out = np.empty(W.shape[0])
        self._lean_L0 = np.ascontiguousarray(self._design.L0)
        self._lean_slices = (slice(0, n), slice(n, n + n_u), r_cols)

    # ------------------------------------------------------------------ DAQP
    def _setup_daqp(self) -> None:
        try:
            import daqp
        except ImportError as exc:  # pragma: no cover - daqp is a dependency
            raise ImportError("solver='daqp' needs the daqp package: pip install daqp") from exc
        N, m = self._N, self._m
        # rows that are unit vectors on distinct variables become DAQP simple bounds
        simple = np.full(N, -1)
        general = []
        for i in range(m):
            row = self._Mc[i]
            nz = np.flatnonzero(row)
            if (
                self._kind[i] == _DU
                and nz.size == 1
                and row[nz[0]] == 1.0
                and simple[nz[0]] < 0
                and not self._G[i].any()
            ):
                simple[nz[0]] = i
            else:
                general.append(i)
        # rows that the decision variables do not move at all (y(k+1) of a plant with C B = 0):
        # DAQP cannot use a zero row, so they stay out of the QP; their limits depend on the
        # state only and are checked after the solve (a violation is reported, not hidden)
        row_norms = np.linalg.norm(self._Mc, axis=1)
        zero_tol = 1e-12 * max(1.0, float(row_norms.max(initial=0.0)))
        self._zero_idx = np.array([i for i in general if row_norms[i] <= zero_tol], dtype=np.intp)
        general = [i for i in general if row_norms[i] > zero_tol]
        n_simple = N if np.any(simple >= 0) else 0
        # index into the bounds vector extended by one "no bound" entry (index m)
        perm = np.concatenate(
            [np.where(simple >= 0, simple, m)[:n_simple], np.asarray(general, dtype=np.intp)]
        )
        self._perm = perm.astype(np.intp)
        A_d = np.ascontiguousarray(self._Mc[general]).reshape(len(general), N)
        # equilibrate: every general row to unit norm (bounds scaled alike).  DAQP skips rows
        # of small norm as if they were zero (about 1e-5 here), and output rows at fast
        # sampling are that small (y(k+1) moves with C B), so unscaled they would be ignored
        row_scale = np.ones(perm.size)
        row_scale[n_simple:] = 1.0 / row_norms[np.asarray(general, dtype=np.intp)]
        A_d = A_d * row_scale[n_simple:, None]
        self._lo0p = np.clip(np.append(self._lo0, -_INF)[perm] * row_scale, -_INF, _INF)
        self._hi0p = np.clip(np.append(self._hi0, _INF)[perm] * row_scale, -_INF, _INF)
        self._Gp = np.ascontiguousarray(
            np.vstack([self._G, np.zeros(self._G.shape[1])])[perm] * row_scale[:, None]
        )
        self._sense0 = np.zeros(perm.size, dtype=np.int32)
        self._sense_soft = np.where(np.append(self._kind, _DU)[perm] == _Y, 8, 0).astype(np.int32)
        self._A_d = A_d
        self._daqp_mod = daqp
        if not perm.size:  # only zero rows: solve() checks them, no QP is needed
            return
        # set up without bounds: the real ones depend on the state and are set before every
        # solve (the state-free parts lo0/hi0 alone mean nothing and need not be feasible)
        self._open_hi = np.full(perm.size, _INF)
        self._open_lo = np.full(perm.size, -_INF)
        model = daqp.Model()
        flag, _ = model.setup(self._E, np.zeros(N), A_d, self._open_hi, self._open_lo)
        if flag < 0:  # pragma: no cover - setup fails only for non-convex E
            raise DataError(f"DAQP setup failed (exit flag {flag})")
        self._set_settings(model)
        self._daqp = model

    def _set_settings(self, model: Any) -> None:
        settings = model.settings
        settings.update(primal_tol=self._tol, iter_limit=self._max_iter)
        model.settings = settings

    def _soft_model(self) -> Any:
        if self._daqp_soft is None:
            model = self._daqp_mod.Model()
            model.setup(
                self._E,
                np.zeros(self._N),
                self._A_d,
                self._open_hi,
                self._open_lo,
                self._sense_soft,
            )
            self._set_settings(model)
            self._daqp_soft = model
        return self._daqp_soft

    def _bounds(self, z: NDArray) -> tuple[NDArray, NDArray]:
        """Lower and upper bounds of the constraint rows for ``z = [x; u_prev]``."""
        off = self._G @ z
        return self._lo0 + off, self._hi0 + off

    # ------------------------------------------------------------------ properties
    @property
    def plant(self) -> PlantModel:
        """The discrete prediction model."""
        return self._plant

    @property
    def design(self) -> MPCDesign:
        """The unconstrained design (``Omega``, ``Psi``, ``K_mpc``)."""
        return self._design

    @property
    def horizon(self) -> int:
        """Prediction horizon ``N_p`` in samples."""
        return self._Np

    @property
    def dt(self) -> float:
        """Sampling period of the prediction model."""
        return self._plant.dt

    @property
    def full_horizon(self) -> bool:
        """Whether this is the full-horizon (one variable per step) problem."""
        return self._full

    @property
    def n_variables(self) -> int:
        """Number of QP decision variables."""
        return self._N

    @property
    def n_constraints(self) -> int:
        """Number of two-sided constraint rows (each with a lower and an upper bound)."""
        return self._m

    @property
    def E(self) -> NDArray[np.float64]:  # noqa: N802 - the documented matrix name
        """QP Hessian ``E = 2 Omega`` (a copy)."""
        return self._E.copy()

    @property
    def output_weight(self) -> NDArray[np.float64]:
        """Output weight ``Q_y`` of shape ``(n_outputs, n_outputs)`` (a copy)."""
        return self._Q_y.copy()

    @property
    def increment_weight(self) -> NDArray[np.float64]:
        """Increment weights ``r`` of shape ``(n_inputs,)`` (a copy)."""
        return self._r.copy()

    @property
    def limits(self) -> dict[str, NDArray[np.float64]]:
        """The limits as a dict of arrays (``-inf``/``inf`` where there is none)."""
        return {
            "u_min": self._u_lo.copy(),
            "u_max": self._u_hi.copy(),
            "du_min": self._du_lo.copy(),
            "du_max": self._du_hi.copy(),
            "y_min": self._y_lo.copy(),
            "y_max": self._y_hi.copy(),
        }

    # ------------------------------------------------------------------ public maps
    def augmented_state(
        self, x_m: ArrayLike, x_m_prev: ArrayLike, y: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        r"""Augmented state :math:`[x_m(k) - x_m(k-1);\ y(k)]` from two plant states.

        Parameters
        ----------
        x_m : array-like of shape (n_states,)
            Plant (model) state now.
        x_m_prev : array-like of shape (n_states,)
            Plant state one sample earlier.
        y : array-like of shape (n_outputs,), optional
            Measured output; default ``C_m x_m``.

        Returns
        -------
        ndarray of shape (n_states + n_outputs,)
        """
        x_m = self._vec(x_m, self._n_x, "x_m")
        x_m_prev = self._vec(x_m_prev, self._n_x, "x_m_prev")
        yv = self._plant.C @ x_m if y is None else self._vec(y, self._plant.n_outputs, "y")
        return np.concatenate([x_m - x_m_prev, yv])

    def constraints(
        self, x: ArrayLike, u_prev: ArrayLike = 0.0
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        r"""One-sided constraint form :math:`M\eta \le \gamma` of kautz-math.md 6.3.

        Upper and lower bounds give rows of opposite sign; rows whose bound is
        infinite are left out.

        Parameters
        ----------
        x : array-like of shape (n,)
            Augmented state.
        u_prev : float or array-like of shape (n_inputs,), default=0.0
            Input applied at the previous sample.

        Returns
        -------
        M : ndarray of shape (n_rows, n_variables)
        gamma : ndarray of shape (n_rows,)
        """
        z = np.concatenate([self._vec(x, self._n, "x"), self._uprev(u_prev)])
        lo, hi = self._bounds(z)
        a, b = self._hi0 < _INF, self._lo0 > -_INF
        M = np.vstack([self._Mc[a], -self._Mc[b]])
        return M, np.concatenate([hi[a], -lo[b]])

    def predict(self, x: ArrayLike, eta: ArrayLike, *, u_prev: ArrayLike = 0.0) -> Prediction:
        r"""Open-loop prediction :math:`y(k+m) = CA^mx + C\phi(m)^T\eta` over the horizon.

        Parameters
        ----------
        x : array-like of shape (n,)
            Augmented state :math:`[\Delta x_m; y]`.
        eta : array-like of shape (n_variables,)
            Decision variables.
        u_prev : float or array-like of shape (n_inputs,), default=0.0
            Input applied at the previous sample.

        Returns
        -------
        Prediction
        """
        xv = self._vec(x, self._n, "x")
        ev = self._vec(eta, self._N, "eta")
        y, u, du = self._plan(xv, ev, self._uprev(u_prev))
        return Prediction(y, u, du)

    def what_if(self, u_plan: ArrayLike, x0: ArrayLike | None = None) -> NDArray[np.float64]:
        """Response of the prediction model to a planned input sequence.

        Simulates :math:`x(k+1) = A_mx(k) + B_mu(k)`, :math:`y(k) = C_mx(k)`
        from ``x0``; the same convention as :func:`scipy.signal.dlsim`.

        Parameters
        ----------
        u_plan : array-like of shape (n_steps, n_inputs) or (n_steps,)
            Planned inputs (1-D for a single-input plant).
        x0 : array-like of shape (n_states,), optional
            Initial model state; default zeros.

        Returns
        -------
        ndarray of shape (n_steps, n_outputs), or (n_steps,) for 1-D ``u_plan``
        of a single-output plant
            ``y(0), ..., y(n_steps - 1)``.

        Raises
        ------
        DimensionError
            If ``u_plan`` or ``x0`` do not fit the plant.
        """
        P = self._plant
        u = np.asarray(u_plan, dtype=float)
        one_d = u.ndim == 1
        if one_d:
            if P.n_inputs != 1:
                raise DimensionError(
                    f"u_plan is 1-D but the plant has {P.n_inputs} inputs; pass (n_steps, n_inputs)"
                )
            u = u[:, None]
        if u.ndim != 2 or u.shape[1] != P.n_inputs:
            raise DimensionError(
                f"u_plan has shape {u.shape} but the plant has {P.n_inputs} inputs"
            )
        if not np.all(np.isfinite(u)):
            raise DataError("u_plan contains NaN or inf")
        x = np.zeros(P.n_states) if x0 is None else self._vec(x0, P.n_states, "x0")
        X = np.empty((u.shape[0], P.n_states))
        BU = u @ P.B.T
        for k in range(u.shape[0]):
            X[k] = x
            x = P.A @ x + BU[k]
        y = X @ P.C.T
        return y[:, 0] if one_d and P.n_outputs == 1 else y

    # ------------------------------------------------------------------ solve
    def solve(
        self, x: ArrayLike, setpoint: ArrayLike = 0.0, *, u_prev: ArrayLike = 0.0
    ) -> MPCResult:
        r"""Solve the QP for the current state and set-point.

        Parameters
        ----------
        x : array-like of shape (n_states + n_outputs,)
            Augmented state :math:`[x_m(k) - x_m(k-1);\ y(k)]`
            (see :meth:`augmented_state`).
        setpoint : float or array-like of shape (n_outputs,), default=0.0
            Output set-point ``r`` (constant over the horizon).
        u_prev : float or array-like of shape (n_inputs,), default=0.0
            Input applied at the previous sample, ``u(k-1)``; input limits
            act on ``u_prev + cumulative increments``.

        Returns
        -------
        MPCResult
            ``success=False`` with a message when the constraints cannot all be
            met; the plan is then a compromise: soft output constraints (least
            violation) when the input limits alone are feasible, else the
            unconstrained first move clipped to the input and rate limits.

        Raises
        ------
        DimensionError
            If ``x``, ``setpoint`` or ``u_prev`` do not fit the plant.
        DataError
            If an argument holds NaN or inf.
        """
        t0 = time.perf_counter()
        n, n_x = self._n, self._n_x
        z = np.empty(n + self._plant.n_inputs)
        z[:n] = self._vec(x, n, "x")
        z[n:] = self._uprev(u_prev)
        r = np.asarray(setpoint, dtype=float).reshape(-1)
        n_y = self._plant.n_outputs
        if r.size == 1 and n_y > 1:
            r = np.full(n_y, float(r[0]))
        if r.size != n_y or not np.isfinite(r).all():
            raise DimensionError(
                f"setpoint must be a finite scalar or have {n_y} entries, got {np.shape(setpoint)}"
            )
        e = z[:n].copy()
        e[n_x:] -= r
        f = self._Fx @ e
        iterations, solver_time, status = 0, 0.0, 0
        success, message, viol = True, "unconstrained optimum", 0.0
        if self._m == 0:
            eta = self._Kx @ e
        elif self._solver == "daqp":
            eta, iterations, solver_time, status, success, message = self._solve_daqp(f, z, e)
        else:
            eta, iterations, status, success, message = self._solve_hildreth(f, z)
        if not success:
            lo, hi = self._bounds(z)
            Me = self._Mc @ eta
            viol = float(max(0.0, np.max(Me - hi), np.max(lo - Me)))
        plan = self._Weta @ eta + self._Wz @ z
        plan.setflags(write=False)
        eta.setflags(write=False)
        cost = float(eta @ (self._design.Omega @ eta + f) + e @ (self._P0 @ e))
        Np, n_u = self._Np, self._plant.n_inputs
        y = plan[: Np * n_y].reshape(Np, n_y)
        du = plan[Np * n_y : Np * (n_y + n_u)].reshape(Np, n_u)
        u = plan[Np * (n_y + n_u) :].reshape(Np, n_u)
        if self._siso:
            y, du, u = y[:, 0], du[:, 0], u[:, 0]
        elapsed = time.perf_counter() - t0
        return MPCResult(
            success, message, u, y, cost, du, eta, iterations, elapsed, solver_time, status, viol
        )

    def move(self, x: ArrayLike, setpoint: ArrayLike = 0.0, *, u_prev: ArrayLike = 0.0) -> MPCMove:
        r"""Lean solve for a control loop: the first move only.

        The same QP as :meth:`solve`, with the same warm start (the two may
        be mixed), but without the plan over the horizon, the predicted cost
        and the result object: state, set-point and previous input go through
        one precomputed matrix-vector product into the solver's linear term
        and bounds, and only :math:`\Delta u(k) = L(0)^T\eta` comes back.  When
        the constraints cannot all be met (rare) it falls back to
        :meth:`solve` for the compromise, so the move is always the one
        :meth:`solve` would apply.  The Hildreth solver always goes through
        :meth:`solve`.

        Parameters
        ----------
        x : array-like of shape (n_states + n_outputs,)
            Augmented state :math:`[x_m(k) - x_m(k-1);\ y(k)]`.
        setpoint : float or array-like of shape (n_outputs,), default=0.0
            Output set-point.
        u_prev : float or array-like of shape (n_inputs,), default=0.0
            Input applied at the previous sample.

        Returns
        -------
        MPCMove

        Raises
        ------
        DimensionError
            If ``x``, ``setpoint`` or ``u_prev`` do not fit the plant.
        DataError
            If an argument holds NaN or inf.

        See Also
        --------
        solve : The full result (plan, prediction, cost).

        Examples
        --------
        >>> from kautztwin.mpc import MPCProblem
        >>> plant = ([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0])
        >>> mpc = MPCProblem(plant, (0.5, 4), 20, r=0.1, u_min=-0.5, u_max=0.5)
        >>> mv = mpc.move([0.0, 0.0, 0.0], setpoint=1.0, u_prev=0.0)
        >>> mv.success, round(float(mv.u[0]), 6)
        (True, 0.5)
        """
        if self._m and self._daqp is None:  # Hildreth, or no row DAQP could use
            return self._move_from(self.solve(x, setpoint, u_prev=u_prev))
        v = self._lean_v
        sx, su, sr = self._lean_slices
        xa = np.asarray(x, dtype=float)
        if xa.size != self._n:  # a scalar would broadcast; the full path names the error
            return self._move_from(self.solve(x, setpoint, u_prev=u_prev))
        try:
            v[sx] = xa
            v[su] = u_prev
            v[sr] = setpoint
        except (ValueError, TypeError):
            # the full path names the offending argument
            return self._move_from(self.solve(x, setpoint, u_prev=u_prev))
        if not np.isfinite(v).all():
            return self._move_from(self.solve(x, setpoint, u_prev=u_prev))
        out = np.dot(self._lean_W, v, out=self._lean_out)
        a, b = self._lean_split
        iterations, solver_time, status = 0, 0.0, 0
        if self._m == 0:
            eta = out
        else:
            model = self._daqp
            if self._warm:
                model.update(f=out[:a], bupper=out[a:b], blower=out[b:])
            else:
                model.update(f=out[:a], bupper=out[a:b], blower=out[b:], sense=self._sense0)
            eta, _, status, info = model.solve()
            if status != 1 or (
                self._zero_idx.size
                and self._zero_row_violation(v[: sx.stop + self._plant.n_inputs]) > 0.0
            ):
                return self._move_from(self.solve(x, setpoint, u_prev=u_prev))
            iterations, solver_time = info["iterations"], info["solve_time"]
        du = eta @ self._lean_L0
        return MPCMove(du, v[su] + du, True, status, iterations, solver_time)

    @staticmethod
    def _move_from(res: MPCResult) -> MPCMove:
        du = np.atleast_1d(res.du[0]).copy()
        u = np.atleast_1d(res.u[0]).copy()
        return MPCMove(du, u, res.success, res.status, res.iterations, res.solver_time)

    def _solve_daqp(
        self, f: NDArray, z: NDArray, e: NDArray
    ) -> tuple[NDArray, int, float, int, bool, str]:
        if self._daqp is None:  # every row is a zero row: nothing for the QP to respect
            eta = self._Kx @ e
            weak = self._zero_row_violation(z)
            if weak > 0.0:
                return eta, 0, 0.0, -101, False, _ZERO_ROW_MESSAGE.format(weak)
            return eta, 0, 0.0, 0, True, "unconstrained optimum"
        off = self._Gp @ z
        hi = self._hi0p + off
        lo = self._lo0p + off
        model = self._daqp
        if self._warm:
            model.update(f=f, bupper=hi, blower=lo)
        else:  # an explicit (empty) working set overrides DAQP's warm start
            model.update(f=f, bupper=hi, blower=lo, sense=self._sense0)
        eta, _, flag, info = model.solve()
        iters, stime = int(info["iterations"]), float(info["solve_time"])
        if flag == 1:
            eta = np.asarray(eta, dtype=float)
            weak = self._zero_row_violation(z) if self._zero_idx.size else 0.0
            if weak > 0.0:
                return eta, iters, stime, -101, False, _ZERO_ROW_MESSAGE.format(weak)
            return eta, iters, stime, 1, True, "optimal"
        first = f"DAQP exit flag {flag} ({_DAQP_FLAGS.get(flag, 'failure')})"
        if np.any(self._kind == _Y):
            soft = self._soft_model()
            soft.update(f=f, bupper=hi, blower=lo)
            eta_s, _, flag_s, info_s = soft.solve()
            iters += int(info_s["iterations"])
            stime += float(info_s["solve_time"])
            if flag_s in (1, 2):
                return (
                    np.asarray(eta_s, dtype=float),
                    iters,
                    stime,
                    int(flag_s),
                    False,
                    f"{first}; output constraints relaxed (soft) to the least violation",
                )
        eta_c = self._clipped(e, z[self._n :])
        return (
            eta_c,
            iters,
            stime,
            -100,
            False,
            f"{first}; fell back to the clipped unconstrained move",
        )

    def _zero_row_violation(self, z: NDArray) -> float:
        """Largest violation of the limits that the decision variables do not move (0 if none)."""
        idx = self._zero_idx
        off = self._G[idx] @ z
        h, lw = self._hi0[idx] + off, self._lo0[idx] + off
        over = np.maximum(-h, lw)  # the rows' value is 0
        tol = 1e-6 * np.maximum(1.0, np.minimum(np.abs(self._hi0[idx]), np.abs(self._lo0[idx])))
        return float(np.max(over)) if np.any(over > tol) else 0.0

    def _solve_hildreth(self, f: NDArray, z: NDArray) -> tuple[NDArray, int, int, bool, str]:
        lo, hi = self._bounds(z)
        rows, sign = self._h_rows, self._h_sign
        gamma = np.where(sign > 0, hi[rows], -lo[rows])
        lam0 = self._lam if self._warm else None
        res = hildreth(
            self._E, f, self._h_M, gamma, max_iter=self._max_iter, tol=self._tol, lam0=lam0
        )
        self._lam = np.array(res.lam) if res.converged else None
        if res.converged:
            return np.array(res.x), res.iterations, 1, True, "optimal (Hildreth)"
        return (
            np.array(res.x),
            res.iterations,
            -4,
            False,
            f"Hildreth: {res.message}; returned its last iterate as a compromise",
        )

    def _clipped(self, e: NDArray, up: NDArray) -> NDArray[np.float64]:
        """Unconstrained first move clipped to the rate and input limits."""
        eta = self._Kx @ e
        n_u = self._plant.n_inputs
        du0 = self._Dmap[:n_u] @ eta
        du0 = np.clip(du0, self._du_lo, self._du_hi)
        u0 = np.clip(up + du0, self._u_lo, self._u_hi)
        du0 = np.clip(u0 - up, self._du_lo, self._du_hi)
        # the minimum-norm eta with L(0)^T eta = du0 exactly (the later moves follow the basis)
        L0 = self._design.L0
        return L0 @ np.linalg.solve(L0.T @ L0, du0)

    def _plan(
        self, x: NDArray, eta: NDArray, up: NDArray
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        Np, P = self._Np, self._plant
        y = (self._Yx @ x + self._Yeta @ eta).reshape(Np, P.n_outputs)
        du = (self._Dmap @ eta).reshape(Np, P.n_inputs)
        u = (self._Smap @ eta).reshape(Np, P.n_inputs) + up
        return _squeeze(y, self._siso), _squeeze(u, self._siso), _squeeze(du, self._siso)

    # ------------------------------------------------------------------ input checks
    def _vec(self, v: ArrayLike, n: int, name: str) -> NDArray[np.float64]:
        a = np.asarray(v, dtype=float).reshape(-1)
        if a.size != n:
            raise DimensionError(f"{name} has {a.size} entries but {n} are expected")
        if not np.isfinite(a).all():
            raise DataError(f"{name} contains NaN or inf")
        return a

    def _uprev(self, u_prev: ArrayLike) -> NDArray[np.float64]:
        n_u = self._plant.n_inputs
        if isinstance(u_prev, (float, int)) and not isinstance(u_prev, bool):
            if not np.isfinite(u_prev):
                raise DataError("u_prev contains NaN or inf")
            return np.full(n_u, float(u_prev))
        a = np.asarray(u_prev, dtype=float).reshape(-1)
        if a.size == 1 and n_u > 1:
            a = np.full(n_u, float(a[0]))
        return self._vec(a, n_u, "u_prev")

    def __repr__(self) -> str:
        kind = "full-horizon" if self._full else "basis"
        return (
            f"MPCProblem({kind}, n_variables={self._N}, horizon={self._Np}, "
            f"n_constraints={self._m}, solver={self._solver!r})"
        )


_ZERO_ROW_MESSAGE = (
    "limits at horizon steps that the inputs cannot influence are broken by the current "
    "state (by {:.3g}); the other limits are met"
)

_DAQP_FLAGS = {
    2: "soft optimal",
    -1: "infeasible",
    -2: "cycling",
    -3: "unbounded",
    -4: "iteration limit",
    -5: "non-convex",
    -6: "overdetermined initial active set",
}


# ----------------------------------------------------------------------------- one-shot
def solve_mpc(
    plant: Any,
    x: ArrayLike,
    setpoint: ArrayLike = 0.0,
    *,
    basis: Any = None,
    horizon: int = 50,
    u_prev: ArrayLike = 0.0,
    **options: Any,
) -> MPCResult:
    """Build an :class:`MPCProblem` and solve it once.

    For repeated solves (a control loop) build the :class:`MPCProblem` once
    and call :meth:`MPCProblem.solve`; this function rebuilds everything.

    Parameters
    ----------
    plant : tuple, scipy.signal system, KautzModel or PlantModel
        Prediction model.
    x : array-like of shape (n_states + n_outputs,)
        Augmented state :math:`[\\Delta x_m; y]`.
    setpoint : float or array-like of shape (n_outputs,), default=0.0
        Output set-point.
    basis : KautzBasis or (pole, n_functions), optional
        Basis of the increments (see :class:`MPCProblem`).
    horizon : int, default=50
        Prediction horizon in samples.
    u_prev : float or array-like of shape (n_inputs,), default=0.0
        Previous input.
    **options
        Further keyword arguments of :class:`MPCProblem` (weights, limits,
        ``dt``, ``full_horizon``, ``solver``, ...).

    Returns
    -------
    MPCResult

    See Also
    --------
    MPCProblem : Build once, solve many times.

    Examples
    --------
    >>> from kautztwin.mpc import solve_mpc
    >>> plant = ([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0])
    >>> res = solve_mpc(plant, [0, 0, 0], 1.0, basis=(0.5, 4), horizon=20, du_max=0.5)
    >>> res.success, round(float(res.du[0]), 6)
    (True, 0.5)
    """
    problem = MPCProblem(plant, basis, horizon, **options)
    return problem.solve(x, setpoint, u_prev=u_prev)


# ----------------------------------------------------------------------------- closed loop
def simulate_closed_loop(
    plant: Any,
    problem: MPCProblem,
    setpoints: ArrayLike,
    n_steps: int | None = None,
    disturbances: ArrayLike | None = None,
    *,
    x0: ArrayLike | None = None,
    u0: ArrayLike = 0.0,
    state_source: str = "model",
    tol: float = 1e-6,
) -> ClosedLoopResult:
    r"""Receding-horizon simulation: solve, apply the first move, step the plant, repeat.

    At every sample ``k`` the controller measures ``y(k)``, forms the
    augmented state, calls ``problem.solve`` and applies
    ``u(k) = u(k-1) + Delta u(k)`` (plus the input disturbance) to the plant.

    Parameters
    ----------
    plant : tuple, scipy.signal system, KautzModel or PlantModel
        The simulated plant, sampled at ``problem.dt`` (continuous plants are
        discretised with ZOH).  It may differ from the problem's model.
    problem : MPCProblem
        The controller.
    setpoints : float or array-like of shape (n_steps,) or (n_steps, n_outputs)
        Set-point at each sample (a scalar needs ``n_steps``).
    n_steps : int, optional
        Number of samples; default ``len(setpoints)``.
    disturbances : array-like of shape (n_steps,) or (n_steps, n_inputs), optional
        Input (load) disturbance added to the plant input, unknown to the controller.
    x0 : array-like of shape (n_plant_states,), optional
        Initial plant state (default zeros); the plant is taken at rest before
        ``k = 0`` (``x(-1) = x0``).
    u0 : float or array-like of shape (n_inputs,), default=0.0
        Input before ``k = 0``.
    state_source : {'model', 'plant'}, default='model'
        Where :math:`\Delta x_m` comes from: ``'model'`` runs the prediction
        model in parallel on the applied increments (works for any plant,
        offset-free through the measured ``y``); ``'plant'`` uses the plant's
        own state (full state feedback; the plant must be the model's realisation).
    tol : float, default=1e-6
        A limit counts as violated when exceeded by more than
        ``tol * max(1, |limit|)``.

    Returns
    -------
    ClosedLoopResult

    Raises
    ------
    DimensionError
        If set-points, disturbances or the plant do not fit the problem.
    DataError
        On invalid options.

    See Also
    --------
    MPCProblem.solve : One step of the loop.
    """
    if not isinstance(problem, MPCProblem):
        raise DataError(f"problem must be an MPCProblem, got {type(problem).__name__}")
    M = problem.plant
    P = plant_model(plant, problem.dt)
    n_u, n_y = M.n_inputs, M.n_outputs
    if P.n_inputs != n_u or P.n_outputs != n_y:
        raise DimensionError(
            f"the plant has {P.n_inputs} inputs and {P.n_outputs} outputs but the problem's "
            f"model has {n_u} and {n_y}"
        )
    if state_source not in ("model", "plant"):
        raise DataError(f"state_source must be 'model' or 'plant', got {state_source!r}")
    if state_source == "plant" and P.n_states != M.n_states:
        raise DimensionError(
            f"state_source='plant' needs the model's {M.n_states} states, the plant has "
            f"{P.n_states}"
        )
    sp = np.asarray(setpoints, dtype=float)
    if n_steps is None:
        if sp.ndim == 0:
            raise DataError("n_steps is required when setpoints is a scalar")
        n_steps = sp.shape[0]
    n_steps = int(n_steps)
    if n_steps < 1:
        raise DataError(f"n_steps must be >= 1, got {n_steps}")
    if sp.ndim == 0:
        sp = np.full((n_steps, n_y), float(sp))
    elif sp.ndim == 1 and n_y == 1:
        sp = sp[:, None]
    if sp.shape != (n_steps, n_y):
        raise DimensionError(f"setpoints has shape {np.shape(setpoints)}; expected ({n_steps},)")
    d = np.zeros((n_steps, n_u))
    if disturbances is not None:
        da = np.asarray(disturbances, dtype=float)
        da = da[:, None] if da.ndim == 1 and n_u == 1 else da
        if da.shape != (n_steps, n_u):
            raise DimensionError(
                f"disturbances has shape {np.shape(disturbances)}; expected ({n_steps}, {n_u})"
            )
        d = da
    x = np.zeros(P.n_states) if x0 is None else np.asarray(x0, dtype=float).reshape(-1)
    if x.size != P.n_states:
        raise DimensionError(f"x0 has {x.size} entries but the plant has {P.n_states} states")
    u_prev = np.broadcast_to(np.asarray(u0, dtype=float).reshape(-1), (n_u,)).copy()
    x_prev = x.copy()
    dxh = np.zeros(M.n_states)
    Y = np.empty((n_steps + 1, n_y))
    U = np.empty((n_steps, n_u))
    DU = np.empty((n_steps, n_u))
    times = np.empty(n_steps)
    qp_times = np.empty(n_steps)
    iters = np.zeros(n_steps, dtype=np.int64)
    n_failed = 0
    for k in range(n_steps):
        y = P.C @ x
        Y[k] = y
        dx = x - x_prev if state_source == "plant" else dxh
        xa = np.concatenate([dx, y])
        t0 = time.perf_counter()
        res = problem.solve(xa, sp[k], u_prev=u_prev)
        times[k] = time.perf_counter() - t0
        qp_times[k] = res.solver_time
        iters[k] = res.iterations
        n_failed += not res.success
        du = np.atleast_1d(res.du[0])
        u = u_prev + du
        DU[k], U[k] = du, u
        x_prev = x
        x = P.A @ x + P.B @ (u + d[k])
        dxh = M.A @ dxh + M.B @ du
        u_prev = u
    Y[n_steps] = P.C @ x
    err = Y[1:] - sp
    cost = float(
        np.einsum("ki,ij,kj->", err, problem.output_weight, err)
        + np.sum(DU**2 * problem.increment_weight)
    )
    lim = problem.limits

    violated = np.zeros(n_steps, dtype=bool)
    max_violation = 0.0
    for v, lo, hi in (
        (U, lim["u_min"], lim["u_max"]),
        (DU, lim["du_min"], lim["du_max"]),
        (Y[1:], lim["y_min"], lim["y_max"]),
    ):
        over_hi, over_lo = v - hi, lo - v  # > 0 where a limit is broken; -inf without one
        violated |= np.any(over_hi > tol * np.maximum(1.0, np.abs(hi)), axis=1)
        violated |= np.any(over_lo > tol * np.maximum(1.0, np.abs(lo)), axis=1)
        over = np.maximum(over_hi, over_lo)
        max_violation = max(max_violation, float(np.max(over)))
    siso = n_u == 1 and n_y == 1
    return ClosedLoopResult(
        np.arange(n_steps + 1) * problem.dt,
        _squeeze(Y, siso),
        _squeeze(U, siso),
        _squeeze(DU, siso),
        _squeeze(sp, siso),
        cost,
        int(np.sum(violated)),
        max_violation,
        times,
        qp_times,
        iters,
        int(n_failed),
    )
