r"""Constrained Laguerre/Kautz MPC as a QP that is built once and re-solved fast.

:class:`MPCProblem` is the facade that wires the parts: the prediction and cost
maps (:mod:`kautztwin.mpc.prediction`), the constraint rows and their bounds'
affine map from ``(x, u_prev)`` (:mod:`kautztwin.mpc.constraints`, kautz-math.md
6.3), the warm-started solver with its fallbacks (:mod:`kautztwin.mpc.solve`)
and the lean per-sample move (:mod:`kautztwin.mpc.lean`).  Each
:meth:`MPCProblem.solve` then costs a few matrix-vector products and one
warm-started DAQP solve.  ``full_horizon=True``
gives the classical MPC with one decision variable per step (the baseline that
the basis parameterisation is compared with).

Size: the class runs to about 500
lines because its public methods carry their full numpydoc documentation; the
work itself is in the modules above.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_int
from ..basis import LaguerreBasis
from ..exceptions import DataError, DimensionError
from .constraints import ConstraintRows, Limits, parse_steps
from .laguerre import MPCDesign, _discrete_build
from .plant import PlantModel, plant_model
from .prediction import HorizonMaps, simulate_model
from .results import MPCMove, MPCResult, Prediction
from .solve import QPSolver

__all__ = ["MPCProblem", "solve_mpc"]


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
        Np = check_int(horizon, "horizon", 1)
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
        self._siso = P.n_inputs == 1 and P.n_outputs == 1
        self._Q_y = seq.Q_y
        self._r = seq.r
        n_u, n_y, n_x = P.n_inputs, P.n_outputs, P.n_states
        n = n_x + n_y
        N = design.n_functions
        self._n, self._n_x, self._N = n, n_x, N
        self._limits = Limits.parse(n_u, n_y, u_min, u_max, du_min, du_max, y_min, y_max)
        steps = parse_steps(constraint_steps, Np)
        self._maps = HorizonMaps(design, seq, Np, n_u, n_y)
        self._rows = ConstraintRows(self._limits, steps, self._maps, n, n_u, n_y, N)
        self._m = self._rows.m
        self._qp = QPSolver(
            self._maps,
            self._rows,
            self._limits,
            design.L0,
            n_x,
            n_u,
            n_y,
            solver=solver,
            warm_start=bool(warm_start),
            max_iter=int(max_iter),
            tol=float(tol),
        )
        self._lean = self._qp.lean

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
        return self._maps.E.copy()

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
        return self._limits.as_dict()

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
        return self._rows.one_sided(z)

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
        y, u, du = self._maps.plan(xv, ev, self._uprev(u_prev), self._siso)
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
        y = simulate_model(P, u, x)
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
        f = self._maps.Fx @ e
        eta, iterations, solver_time, status, success, message = self._qp.solve(f, z, e)
        viol = self._rows.violation(eta, z) if not success else 0.0
        plan = self._maps.W_eta @ eta + self._maps.W_z @ z
        plan.setflags(write=False)
        eta.setflags(write=False)
        cost = float(eta @ (self._design.Omega @ eta + f) + e @ (self._maps.P0 @ e))
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

        The same QP as :meth:`solve`, without the plan over the horizon, the
        predicted cost and the result object, and written for a per-sample
        loop (:mod:`kautztwin.mpc.lean`): the QP is posed in the deviation from
        the unconstrained optimum, so state, set-point and previous input go
        through one precomputed matrix-vector product into the unconstrained
        move and DAQP's bounds; when that optimum meets every constraint row
        (often, away from the limits) it is the solution and DAQP is not
        called; else DAQP is updated and solved in place.  Only
        :math:`\Delta u(k) = L(0)^T\eta` comes back.  When the constraints
        cannot all be met (rare) it falls back to :meth:`solve` for the
        compromise, so the move is always the one :meth:`solve` would apply
        (to the solver's tolerance; the tests hold the two to 1e-9).  The
        Hildreth solver always goes through :meth:`solve`.

        The arguments are not validated on this path beyond what costs
        nothing: a wrong shape or a NaN/inf sends the call to :meth:`solve`,
        which names the problem.  :meth:`move` and :meth:`solve` keep separate
        DAQP warm starts and may be mixed (the QP is strictly convex: its
        solution does not depend on the start).

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
            ``solver_time`` and ``iterations`` are 0 on a sample where the
            unconstrained optimum was the solution (DAQP not called).

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
        lean = self._lean
        if lean is not None:
            mv = lean(x, setpoint, u_prev)
            if mv is not None:
                return mv
        return self._move_from(self.solve(x, setpoint, u_prev=u_prev))

    @staticmethod
    def _move_from(res: MPCResult) -> MPCMove:
        du = np.atleast_1d(res.du[0]).copy()
        u = np.atleast_1d(res.u[0]).copy()
        return MPCMove(du, u, res.success, res.status, res.iterations, res.solver_time)

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
