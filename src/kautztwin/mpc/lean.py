r"""The lean per-sample path of the MPC: the first move from one product and at most one QP.

:class:`LeanMove` is what :meth:`MPCProblem.move <kautztwin.mpc.MPCProblem.move>` runs at
every sample.  Everything that does not change between samples is built once:

* the QP is written in the deviation :math:`\delta = \eta - \eta_u(x)` from the
  unconstrained optimum :math:`\eta_u = K_x(x - x_s)`.  Since
  :math:`E\eta_u + F = 0`, the cost becomes :math:`\tfrac12\delta^TE\delta` with no
  linear term, and the bounds :math:`lo + Gz - A\eta_u \le A\delta \le hi + Gz - A\eta_u`
  are affine in :math:`v = [x;\ u_{prev};\ r;\ 1]`.  DAQP is set up once without a
  linear term, so a sample only hands it new bounds (its update is then a copy of
  the bounds, not the products with ``f`` that a linear term needs);
* one matrix maps ``v`` at once to the unconstrained first move and input and
  the slacks of :math:`\delta = 0`: ``[upper; -lower]`` of the DAQP rows and those
  of the rows the inputs cannot move (:class:`~kautztwin.mpc.constraints.DAQPRows`,
  less their margin).  DAQP reads the upper bounds in place and the lower ones
  negated back into a preallocated buffer (negation is exact: the same numbers);
* the product is written into a preallocated buffer that DAQP reads through
  fixed views, so a sample allocates only DAQP's own result and the returned move;
* every reduction and negation calls the ufunc itself (``np.minimum.reduce``,
  ``np.negative(..., out=)``), not the method wrappers around it.

A sample is therefore: three assignments into ``v``, one matrix-vector product, a
screen (when every slack of :math:`\delta = 0` is :math:`\ge 0` the unconstrained
optimum meets every row and is the QP's solution: DAQP is not called), else DAQP's
update and solve, and :math:`\Delta u(k) = L(0)^T\eta_u + L(0)^T\delta`.  One
reduction over all slacks screens a sample; only when it fails are the rows the
inputs cannot move looked at on their own (any of them below its margin: the
sample goes to :meth:`~kautztwin.mpc.MPCProblem.solve`).  The screen
asks for exact feasibility (no tolerance), so it never accepts a point that DAQP
would not.  Arguments are not validated on this path beyond what is free: a wrong
shape shows up as a failed assignment into ``v`` and a non-finite value as a
non-finite (Python) sum of ``v``, and either sends the call to
:meth:`MPCProblem.solve <kautztwin.mpc.MPCProblem.solve>`, which names the problem.
So does every sample where the QP is not solved with all constraints met, so that
the compromise is the one :meth:`~kautztwin.mpc.MPCProblem.solve` finds.

The reformulation is exact: the QP in :math:`\delta` has the same rows, scaled the
same way, and its solution plus :math:`\eta_u` is the solution of the QP in
:math:`\eta`; the tests compare the two moves along closed loops.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError
from .constraints import _INF, ConstraintRows, DAQPRows
from .prediction import HorizonMaps
from .results import MPCMove

__all__ = ["LeanMove"]

# a zero-row slack (in units of its tolerance) below this goes to solve() to be decided there
_ZERO_ROW_MARGIN = 1e-9
# the ufuncs themselves: ndarray.min() goes through a Python wrapper first
_min = np.minimum.reduce
_negative = np.negative


class LeanMove:
    r"""First move of the MPC QP per sample, with everything state-free precomputed.

    Parameters
    ----------
    maps : HorizonMaps
        Cost and prediction maps.
    rows : ConstraintRows
        The constraint rows.
    drows : DAQPRows or None
        The rows as DAQP takes them (``None`` without constraints).
    L0 : ndarray of shape (n_variables, n_inputs)
        ``L(0)`` of the basis: ``du(k) = L(0)^T eta``.
    n_states, n_inputs, n_outputs : int
        Plant dimensions.
    warm_start : bool
        Start each solve from the previous working set (else from an empty one).
    max_iter : int
        DAQP iteration limit.
    tol : float
        DAQP primal feasibility tolerance.

    Notes
    -----
    The DAQP model here is separate from the one of
    :meth:`~kautztwin.mpc.MPCProblem.solve`: each keeps its own warm start.  The QP is
    strictly convex, so both give the same (unique) solution.
    """

    def __init__(
        self,
        maps: HorizonMaps,
        rows: ConstraintRows,
        drows: DAQPRows | None,
        L0: NDArray,
        n_states: int,
        n_inputs: int,
        n_outputs: int,
        *,
        warm_start: bool,
        max_iter: int,
        tol: float,
    ) -> None:
        n, n_u, n_y = n_states + n_outputs, n_inputs, n_outputs
        N = L0.shape[0]
        n_v = n + n_u + n_y + 1
        # v = [x; u_prev; r; 1]; e = x - x_s = P v
        P = np.zeros((n, n_v))
        P[:, :n] = np.eye(n)
        P[n_states:, n + n_u : n + n_u + n_y] = -np.eye(n_y)
        Kv = maps.Kx @ P  # eta_u = Kv v
        du_u = L0.T @ Kv  # unconstrained first move
        u_u = du_u.copy()
        u_u[:, n : n + n_u] += np.eye(n_u)  # ... and the input it gives
        blocks = [du_u, u_u]
        mp = 0 if drows is None else drows.perm.size
        if mp:
            A_full = np.zeros((mp, N))
            n_simple = mp - drows.A.shape[0]
            A_full[:n_simple, :n_simple] = np.eye(n_simple)  # simple bounds: unit rows
            A_full[n_simple:] = drows.A
            shift = A_full @ Kv
            # [upper; -lower]: the slacks of delta = 0 (eta_u feasible iff all >= 0); DAQP
            # reads upper as it is and lower negated back (sign-exact, so the same numbers)
            blocks += [
                self._bound_rows(drows.hi0, drows.G, shift, _INF, n_v),
                -self._bound_rows(drows.lo0, drows.G, shift, -_INF, n_v),
            ]
        n_zero = 0 if drows is None else drows.zero_idx.size
        if n_zero:
            blocks.append(self._zero_rows(rows, drows.zero_idx, n_v))
        # Fortran order: numpy's product with a vector is fastest this way for a tall matrix
        self._W = np.asfortranarray(np.vstack(blocks))
        self._out = np.empty(self._W.shape[0])
        self._v = np.zeros(n_v)
        self._v[-1] = 1.0
        out, h = self._out, 2 * n_u
        self._head = out[:h]  # [du; u] of the unconstrained optimum
        self._bu = out[h : h + mp]  # DAQP's upper bounds, read in place
        self._nbl = out[h + mp : h + 2 * mp]  # minus DAQP's lower bounds ...
        self._bl = np.empty(mp)  # ... negated into this buffer when DAQP is called
        # every slack of the screen in one view: [upper; -lower; zero rows less their margin]
        self._slack = out[h:]
        self._zero = out[h + 2 * mp :]
        self._has_slack = self._slack.size > 0
        self._n_zero = n_zero
        self._n = n
        self._n_u = n_u
        self._sx = slice(0, n)
        self._su = slice(n, n + n_u)
        self._sr = slice(n + n_u, n + n_u + n_y)
        # scalar u_prev and setpoint of a SISO plant go in by index (cheaper than a slice)
        self._iu = n if n_u == 1 else -1
        self._ir = n + n_u if n_y == 1 else -1
        self._L0T2 = np.ascontiguousarray(np.vstack([L0.T, L0.T]))  # [du; u] - head
        self._warm = warm_start
        self._model: Any = None
        if mp:
            self._sense0 = drows.sense0.copy()
            self._model = self._setup_daqp(maps.E, drows.A, mp, max_iter, tol)

    # ------------------------------------------------------------------ set-up
    @staticmethod
    def _bound_rows(b0: NDArray, G: NDArray, shift: NDArray, inf: float, n_v: int) -> NDArray:
        """Rows of ``[G | 0 | 0 | b0] - A Kv``; a bound at DAQP's infinity stays exactly there."""
        W = np.zeros((b0.size, n_v))
        W[:, : G.shape[1]] = G
        W -= shift
        W[:, -1] = b0
        W[b0 == inf] = 0.0
        W[b0 == inf, -1] = inf
        return W

    @staticmethod
    def _zero_rows(rows: ConstraintRows, idx: NDArray, n_v: int) -> NDArray:
        """Slacks of the rows the inputs cannot move, in units of their tolerance (>= 0: met).

        The same test as :meth:`DAQPRows.zero_row_violation`: ``hi + G z >= -tol`` and
        ``lo + G z <= tol``, as ``(hi + G z) / tol + 1`` and ``-(lo + G z) / tol + 1``.
        """
        lo0, hi0, G = rows.lo0[idx], rows.hi0[idx], rows.G[idx]
        tol = 1e-6 * np.maximum(1.0, np.minimum(np.abs(hi0), np.abs(lo0)))
        nz = G.shape[1]
        W = np.zeros((2 * idx.size, n_v))
        W[: idx.size, :nz] = G / tol[:, None]
        W[: idx.size, -1] = hi0 / tol + 1.0
        W[idx.size :, :nz] = -G / tol[:, None]
        W[idx.size :, -1] = -lo0 / tol + 1.0
        W[:, -1] -= _ZERO_ROW_MARGIN  # the screen's ">= 0" is then "slack >= margin"
        return W

    def _setup_daqp(self, E: NDArray, A: NDArray, mp: int, max_iter: int, tol: float) -> Any:
        import daqp

        model = daqp.Model()
        # no linear term: DAQP's update is then a copy of the bounds (no products with f)
        flag, _ = model.setup(
            E, None, A, np.full(mp, _INF), np.full(mp, -_INF), self._sense0.copy()
        )
        if flag < 0:  # pragma: no cover - the problem's own set-up has passed with this E
            raise DataError(f"DAQP setup failed (exit flag {flag})")
        settings = model.settings
        settings.update(primal_tol=tol, iter_limit=max_iter)
        model.settings = settings
        return model

    # ------------------------------------------------------------------ per sample
    def __call__(self, x: ArrayLike, setpoint: ArrayLike, u_prev: ArrayLike) -> MPCMove | None:
        """The first move, or ``None`` where :meth:`MPCProblem.solve` must decide.

        ``None`` means: arguments of the wrong shape or not finite, or a sample where
        the constraints are not all met (the full path finds the compromise).
        """
        v = self._v
        try:
            if len(x) != self._n:  # type: ignore[arg-type]  # a scalar would broadcast
                return None
            v[self._sx] = x
            if type(u_prev) is float and self._iu >= 0:
                v[self._iu] = u_prev
            else:
                v[self._su] = u_prev
            if type(setpoint) is float and self._ir >= 0:
                v[self._ir] = setpoint
            else:
                v[self._sr] = setpoint
        except (ValueError, TypeError):
            return None  # the full path names the offending argument
        # a Python sum: nan and inf propagate without numpy's floating-point warnings (an
        # overflow of finite values also lands here; solve() then takes them as they are)
        if not math.isfinite(sum(v.tolist())):
            return None
        self._W.dot(v, self._out)
        # one reduction screens every row: DAQP's rows and the rows the inputs cannot move
        if not self._has_slack or _min(self._slack) >= 0.0:
            # the unconstrained optimum meets every row exactly: it is the QP's solution
            t = self._head.copy()
            n_u = self._n_u
            return MPCMove(t[:n_u], t[n_u:], True, 0 if self._model is None else 1, 0, 0.0)
        if self._n_zero and _min(self._zero) < 0.0:
            return None  # a row the inputs cannot move is (nearly) broken: solve() decides
        model = self._model
        if model is None:
            return None  # pragma: no cover - a negative slack without DAQP rows is a zero row
        _negative(self._nbl, out=self._bl)
        if self._warm:
            model.update(bupper=self._bu, blower=self._bl)
        else:
            model.update(bupper=self._bu, blower=self._bl, sense=self._sense0)
        delta, _, status, info = model.solve()
        if status != 1:
            return None
        t = self._L0T2.dot(delta)
        t += self._head
        n_u = self._n_u
        return MPCMove(t[:n_u], t[n_u:], True, 1, info["iterations"], info["solve_time"])
