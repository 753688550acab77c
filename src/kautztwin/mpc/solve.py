r"""Solving the MPC QP: the DAQP wrapper, Hildreth, the fallbacks and the lean move path.

:class:`QPSolver` keeps the solver state between samples: DAQP's model (its
factorisation of ``E`` and its working set, the warm start) or Hildreth's
multipliers.  When the constraints cannot all be met it returns a compromise:
the output limits made soft (least violation) when the input limits alone are
feasible, else the unconstrained first move clipped to the input and rate
limits.  :meth:`QPSolver.move` is the lean path of
:meth:`MPCProblem.move <kautztwin.mpc.MPCProblem.move>`, kept in
:mod:`kautztwin.mpc.lean`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError
from .constraints import _INF, ConstraintRows, DAQPRows, Limits
from .hildreth import hildreth
from .lean import LeanMove
from .prediction import HorizonMaps
from .results import MPCMove

__all__ = ["QPSolver"]

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


class QPSolver:
    r"""The QP :math:`\min \tfrac12\eta^TE\eta + \eta^TF` s.t. the rows, re-solved per sample.

    Parameters
    ----------
    maps : HorizonMaps
        Cost and prediction maps.
    rows : ConstraintRows
        Constraint rows.
    limits : Limits
        The limits (for the clipped fallback).
    L0 : ndarray of shape (n_variables, n_inputs)
        ``L(0)`` of the basis: ``du(k) = L(0)^T eta``.
    n_states, n_inputs, n_outputs : int
        Plant dimensions.
    solver : {'daqp', 'hildreth'}
    warm_start : bool
    max_iter : int
    tol : float
        Checked solver settings (see :class:`~kautztwin.mpc.MPCProblem`).

    Attributes
    ----------
    lean : LeanMove or None
        The lean per-sample move (``None`` for Hildreth with constraints: its
        moves go through :meth:`solve`).
    """

    def __init__(
        self,
        maps: HorizonMaps,
        rows: ConstraintRows,
        limits: Limits,
        L0: NDArray,
        n_states: int,
        n_inputs: int,
        n_outputs: int,
        *,
        solver: str,
        warm_start: bool,
        max_iter: int,
        tol: float,
    ) -> None:
        self._maps, self._rows, self._limits, self._L0 = maps, rows, limits, L0
        self._n_x, self._n_u, self._n_y = n_states, n_inputs, n_outputs
        self._n = n_states + n_outputs
        self._N = L0.shape[0]
        self._m = rows.m
        self._solver = solver
        self._warm = warm_start
        self._max_iter = max_iter
        self._tol = tol
        self._daqp: Any = None
        self._daqp_soft: Any = None
        self._lam: NDArray | None = None
        if self._m and solver == "daqp":
            self._setup_daqp()
        if self._m and solver == "hildreth":
            self._h_rows, self._h_sign, self._h_M = rows.hildreth_rows()
        self.lean: LeanMove | None = None
        if not self._m or solver == "daqp":  # Hildreth: move() goes through solve()
            self.lean = LeanMove(
                maps,
                rows,
                self._drows if self._m else None,
                L0,
                n_states,
                n_inputs,
                n_outputs,
                warm_start=warm_start,
                max_iter=max_iter,
                tol=tol,
            )

    # ------------------------------------------------------------------ DAQP
    def _setup_daqp(self) -> None:
        try:
            import daqp
        except ImportError as exc:  # pragma: no cover - daqp is a dependency
            raise ImportError("solver='daqp' needs the daqp package: pip install daqp") from exc
        rows = DAQPRows(self._rows, self._N)
        self._drows = rows
        self._daqp_mod = daqp
        if not rows.perm.size:  # only zero rows: solve() checks them, no QP is needed
            return
        # set up without bounds: the real ones depend on the state and are set before every
        # solve (the state-free parts lo0/hi0 alone mean nothing and need not be feasible)
        self._open_hi = np.full(rows.perm.size, _INF)
        self._open_lo = np.full(rows.perm.size, -_INF)
        model = daqp.Model()
        flag, _ = model.setup(self._maps.E, np.zeros(self._N), rows.A, self._open_hi, self._open_lo)
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
                self._maps.E,
                np.zeros(self._N),
                self._drows.A,
                self._open_hi,
                self._open_lo,
                self._drows.sense_soft,
            )
            self._set_settings(model)
            self._daqp_soft = model
        return self._daqp_soft

    # ------------------------------------------------------------------ lean path
    def move(self, x: ArrayLike, setpoint: ArrayLike, u_prev: ArrayLike) -> MPCMove | None:
        """The first move by the lean path, or ``None`` where the full solve must decide.

        ``None`` means: Hildreth, arguments that need the full path's checks and messages,
        or a solve that did not meet every constraint (the full path finds the compromise).
        See :class:`~kautztwin.mpc.lean.LeanMove`.
        """
        lean = self.lean
        return None if lean is None else lean(x, setpoint, u_prev)

    # ------------------------------------------------------------------ solve
    def solve(
        self, f: NDArray, z: NDArray, e: NDArray
    ) -> tuple[NDArray, int, float, int, bool, str]:
        """``eta, iterations, solver_time, status, success, message`` for one sample.

        Parameters
        ----------
        f : ndarray of shape (n_variables,)
            Linear term ``F = 2 Psi (x - x_s)``.
        z : ndarray of shape (n + n_inputs,)
            ``[x; u_prev]``.
        e : ndarray of shape (n,)
            State error ``x - x_s``.
        """
        if self._m == 0:
            return self._maps.Kx @ e, 0, 0.0, 0, True, "unconstrained optimum"
        if self._solver == "daqp":
            return self._solve_daqp(f, z, e)
        eta, iterations, status, success, message = self._solve_hildreth(f, z)
        return eta, iterations, 0.0, status, success, message

    def _solve_daqp(
        self, f: NDArray, z: NDArray, e: NDArray
    ) -> tuple[NDArray, int, float, int, bool, str]:
        rows = self._drows
        if self._daqp is None:  # every row is a zero row: nothing for the QP to respect
            eta = self._maps.Kx @ e
            weak = rows.zero_row_violation(z)
            if weak > 0.0:
                return eta, 0, 0.0, -101, False, _ZERO_ROW_MESSAGE.format(weak)
            return eta, 0, 0.0, 0, True, "unconstrained optimum"
        off = rows.G @ z
        hi = rows.hi0 + off
        lo = rows.lo0 + off
        model = self._daqp
        if self._warm:
            model.update(f=f, bupper=hi, blower=lo)
        else:  # an explicit (empty) working set overrides DAQP's warm start
            model.update(f=f, bupper=hi, blower=lo, sense=rows.sense0)
        eta, _, flag, info = model.solve()
        iters, stime = int(info["iterations"]), float(info["solve_time"])
        if flag == 1:
            eta = np.asarray(eta, dtype=float)
            weak = rows.zero_row_violation(z) if rows.zero_idx.size else 0.0
            if weak > 0.0:
                return eta, iters, stime, -101, False, _ZERO_ROW_MESSAGE.format(weak)
            return eta, iters, stime, 1, True, "optimal"
        first = f"DAQP exit flag {flag} ({_DAQP_FLAGS.get(flag, 'failure')})"
        if self._rows.has_output_rows:
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

    def _solve_hildreth(self, f: NDArray, z: NDArray) -> tuple[NDArray, int, int, bool, str]:
        lo, hi = self._rows.bounds(z)
        rows, sign = self._h_rows, self._h_sign
        gamma = np.where(sign > 0, hi[rows], -lo[rows])
        lam0 = self._lam if self._warm else None
        res = hildreth(
            self._maps.E, f, self._h_M, gamma, max_iter=self._max_iter, tol=self._tol, lam0=lam0
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
        lim = self._limits
        eta = self._maps.Kx @ e
        n_u = self._n_u
        du0 = self._maps.D[:n_u] @ eta
        du0 = np.clip(du0, lim.du_lo, lim.du_hi)
        u0 = np.clip(up + du0, lim.u_lo, lim.u_hi)
        du0 = np.clip(u0 - up, lim.du_lo, lim.du_hi)
        # the minimum-norm eta with L(0)^T eta = du0 exactly (the later moves follow the basis)
        L0 = self._L0
        return L0 @ np.linalg.solve(L0.T @ L0, du0)
