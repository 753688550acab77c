r"""Constraint handling of the MPC QP: limits, constraint rows, row scaling and zero rows.

The limits on ``u``, ``du`` and ``y`` at the constrained horizon steps become two-sided
rows :math:`lo_0 + Gz \le M_c\eta \le hi_0 + Gz` with ``z = [x; u_prev]``
(kautz-math.md 6.3): :class:`ConstraintRows` builds them once.  For DAQP they are
re-arranged by :class:`DAQPRows` (unit rows as simple bounds, the other rows
equilibrated to unit norm, rows the inputs cannot move set aside and checked after
the solve); for Hildreth they are turned into one-sided rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError, DimensionError
from .prediction import HorizonMaps

__all__ = ["ConstraintRows", "DAQPRows", "Limits"]

_INF = 1e30  # DAQP's "no bound"
_DU, _U, _Y = 0, 1, 2  # constraint row kinds


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


def parse_steps(steps: Any, Np: int) -> NDArray[np.int64]:
    """Horizon steps with limits: all (``None``), the first ``n`` (an int) or the listed ones."""
    if steps is None:
        return np.arange(Np)
    if isinstance(steps, (int, np.integer)) and not isinstance(steps, bool):
        n = int(steps)
        if not 0 <= n <= Np:
            raise DataError(f"constraint_steps = {n} must lie in [0, horizon = {Np}]")
        return np.arange(n)
    s = np.unique(np.asarray(steps, dtype=np.int64).reshape(-1))
    if s.size and (s[0] < 0 or s[-1] >= Np):
        raise DataError(f"constraint_steps must lie in [0, {Np - 1}], got {s.tolist()}")
    return s


@dataclass(frozen=True, eq=False)
class Limits:
    """Checked limits on the inputs, increments and outputs (``-inf``/``inf``: none).

    Parameters
    ----------
    u_lo, u_hi, du_lo, du_hi : ndarray of shape (n_inputs,)
        Input and increment limits.
    y_lo, y_hi : ndarray of shape (n_outputs,)
        Output limits.
    """

    u_lo: NDArray[np.float64]
    u_hi: NDArray[np.float64]
    du_lo: NDArray[np.float64]
    du_hi: NDArray[np.float64]
    y_lo: NDArray[np.float64]
    y_hi: NDArray[np.float64]

    @classmethod
    def parse(
        cls,
        n_inputs: int,
        n_outputs: int,
        u_min: ArrayLike | None,
        u_max: ArrayLike | None,
        du_min: ArrayLike | None,
        du_max: ArrayLike | None,
        y_min: ArrayLike | None,
        y_max: ArrayLike | None,
    ) -> Limits:
        """Check the limits given to :class:`~kautztwin.mpc.MPCProblem` and broadcast them.

        Raises
        ------
        DimensionError
            If a limit does not fit the plant.
        DataError
            On NaN, a lower limit above its upper one, or ``du`` limits that exclude 0.
        """
        n_u, n_y = n_inputs, n_outputs
        lim = cls(
            _bound(u_min, n_u, "u_min", -np.inf),
            _bound(u_max, n_u, "u_max", np.inf),
            _bound(du_min, n_u, "du_min", -np.inf),
            _bound(du_max, n_u, "du_max", np.inf),
            _bound(y_min, n_y, "y_min", -np.inf),
            _bound(y_max, n_y, "y_max", np.inf),
        )
        _pair(lim.u_lo, lim.u_hi, "u_min", "u_max")
        _pair(lim.du_lo, lim.du_hi, "du_min", "du_max")
        _pair(lim.y_lo, lim.y_hi, "y_min", "y_max")
        if np.any(lim.du_lo > 0) or np.any(lim.du_hi < 0):
            raise DataError("du_min <= 0 <= du_max is required (holding the input must be allowed)")
        return lim

    def as_dict(self) -> dict[str, NDArray[np.float64]]:
        """The limits as a dict of copies keyed ``u_min``, ``u_max``, ..., ``y_max``."""
        return {
            "u_min": self.u_lo.copy(),
            "u_max": self.u_hi.copy(),
            "du_min": self.du_lo.copy(),
            "du_max": self.du_hi.copy(),
            "y_min": self.y_lo.copy(),
            "y_max": self.y_hi.copy(),
        }


class ConstraintRows:
    r"""The two-sided rows :math:`lo_0 + Gz \le M_c\eta \le hi_0 + Gz`, ``z = [x; u_prev]``.

    Rows are built step by step (``du`` rows, then ``u`` rows, then ``y`` rows of each
    constrained step), only for limits that are finite on at least one side.

    Parameters
    ----------
    limits : Limits
        The checked limits.
    steps : ndarray of int
        Constrained horizon steps.
    maps : HorizonMaps
        Prediction maps of the problem.
    n : int
        Augmented state size ``n_states + n_outputs``.
    n_inputs, n_outputs, n_variables : int
        Problem dimensions.

    Attributes
    ----------
    Mc : ndarray of shape (m, n_variables)
    lo0, hi0 : ndarray of shape (m,)
        State-free parts of the bounds (clipped to DAQP's ``+-1e30``).
    G : ndarray of shape (m, n + n_inputs)
    kind : ndarray of int, shape (m,)
        Row kinds (``du``, ``u`` or ``y``).
    m : int
        Number of rows.
    """

    def __init__(
        self,
        limits: Limits,
        steps: NDArray[np.int64],
        maps: HorizonMaps,
        n: int,
        n_inputs: int,
        n_outputs: int,
        n_variables: int,
    ) -> None:
        n_u, n_y, N = n_inputs, n_outputs, n_variables
        lim = limits
        rows: list[NDArray] = []
        lo: list[float] = []
        hi: list[float] = []
        G: list[NDArray] = []
        kind: list[int] = []
        zero = np.zeros(n + n_u)
        for j in steps:
            for q in range(n_u):
                if np.isfinite(lim.du_lo[q]) or np.isfinite(lim.du_hi[q]):
                    rows.append(maps.D[j * n_u + q])
                    lo.append(lim.du_lo[q])
                    hi.append(lim.du_hi[q])
                    G.append(zero)
                    kind.append(_DU)
            for q in range(n_u):
                if np.isfinite(lim.u_lo[q]) or np.isfinite(lim.u_hi[q]):
                    rows.append(maps.S[j * n_u + q])
                    lo.append(lim.u_lo[q])
                    hi.append(lim.u_hi[q])
                    g = zero.copy()
                    g[n + q] = -1.0
                    G.append(g)
                    kind.append(_U)
            for p in range(n_y):
                if np.isfinite(lim.y_lo[p]) or np.isfinite(lim.y_hi[p]):
                    rows.append(maps.Y_eta[j * n_y + p])
                    lo.append(lim.y_lo[p])
                    hi.append(lim.y_hi[p])
                    g = zero.copy()
                    g[:n] = -maps.Y_x[j * n_y + p]
                    G.append(g)
                    kind.append(_Y)
        m = len(rows)
        self.m = m
        self.Mc = np.array(rows).reshape(m, N)
        self.lo0 = np.clip(np.array(lo, dtype=float), -_INF, _INF)
        self.hi0 = np.clip(np.array(hi, dtype=float), -_INF, _INF)
        self.G = np.array(G).reshape(m, n + n_u)
        self.kind = np.array(kind, dtype=int)

    @property
    def has_output_rows(self) -> bool:
        """Whether some rows limit outputs (only those can be softened)."""
        return bool(np.any(self.kind == _Y))

    def bounds(self, z: NDArray) -> tuple[NDArray, NDArray]:
        """Lower and upper bounds of the constraint rows for ``z = [x; u_prev]``."""
        off = self.G @ z
        return self.lo0 + off, self.hi0 + off

    def violation(self, eta: NDArray, z: NDArray) -> float:
        """Largest violation of the rows by ``eta`` (0 if none)."""
        lo, hi = self.bounds(z)
        Me = self.Mc @ eta
        return float(max(0.0, np.max(Me - hi), np.max(lo - Me)))

    def one_sided(self, z: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        r"""``M, gamma`` of :math:`M\eta \le \gamma`; rows with an infinite bound are left out."""
        lo, hi = self.bounds(z)
        a, b = self.hi0 < _INF, self.lo0 > -_INF
        M = np.vstack([self.Mc[a], -self.Mc[b]])
        return M, np.concatenate([hi[a], -lo[b]])

    def hildreth_rows(self) -> tuple[NDArray, NDArray, NDArray]:
        """Row indices, signs and matrix of the finite one-sided rows ``sign * Mc eta <= ...``."""
        # one-sided rows M eta <= gamma (drop the infinite ones; bounds are finite offsets)
        up = self.hi0 < _INF
        dn = self.lo0 > -_INF
        h_rows = np.concatenate([np.flatnonzero(up), np.flatnonzero(dn)])
        h_sign = np.concatenate([np.ones(up.sum()), -np.ones(dn.sum())])
        return h_rows, h_sign, self.Mc[h_rows] * h_sign[:, None]


class DAQPRows:
    """The rows arranged for DAQP: simple bounds first, equilibrated general rows, zero rows.

    Rows that are unit vectors on distinct variables become DAQP simple bounds.  Rows that
    the decision variables do not move at all (``y(k+1)`` of a plant with ``C B = 0``) stay
    out of the QP: DAQP cannot use a zero row, and their limits depend on the state only,
    so they are checked after the solve (:meth:`zero_row_violation`).  The other rows are
    scaled to unit norm, bounds alike: DAQP skips rows of small norm as if they were zero
    (about 1e-5 here), and output rows at fast sampling are that small.

    Parameters
    ----------
    rows : ConstraintRows
        The constraint rows.
    n_variables : int
        Number of decision variables.

    Attributes
    ----------
    perm : ndarray of int
        Index of each DAQP row into the bounds extended by one "no bound" entry.
    A : ndarray
        Scaled general rows.
    lo0, hi0 : ndarray
        Scaled state-free bounds in DAQP order.
    G : ndarray
        Scaled state maps of the bounds in DAQP order.
    sense0, sense_soft : ndarray of int32
        DAQP senses: an empty working set, and output rows marked soft.
    zero_idx : ndarray of int
        Rows left out of the QP.
    """

    def __init__(self, rows: ConstraintRows, n_variables: int) -> None:
        N, m = n_variables, rows.m
        self._rows = rows
        # rows that are unit vectors on distinct variables become DAQP simple bounds
        simple = np.full(N, -1)
        general = []
        for i in range(m):
            row = rows.Mc[i]
            nz = np.flatnonzero(row)
            if (
                rows.kind[i] == _DU
                and nz.size == 1
                and row[nz[0]] == 1.0
                and simple[nz[0]] < 0
                and not rows.G[i].any()
            ):
                simple[nz[0]] = i
            else:
                general.append(i)
        # rows that the decision variables do not move at all (y(k+1) of a plant with C B = 0):
        # DAQP cannot use a zero row, so they stay out of the QP; their limits depend on the
        # state only and are checked after the solve (a violation is reported, not hidden)
        row_norms = np.linalg.norm(rows.Mc, axis=1)
        zero_tol = 1e-12 * max(1.0, float(row_norms.max(initial=0.0)))
        self.zero_idx = np.array([i for i in general if row_norms[i] <= zero_tol], dtype=np.intp)
        general = [i for i in general if row_norms[i] > zero_tol]
        n_simple = N if np.any(simple >= 0) else 0
        # index into the bounds vector extended by one "no bound" entry (index m)
        perm = np.concatenate(
            [np.where(simple >= 0, simple, m)[:n_simple], np.asarray(general, dtype=np.intp)]
        )
        self.perm = perm.astype(np.intp)
        A_d = np.ascontiguousarray(rows.Mc[general]).reshape(len(general), N)
        # equilibrate: every general row to unit norm (bounds scaled alike).  DAQP skips rows
        # of small norm as if they were zero (about 1e-5 here), and output rows at fast
        # sampling are that small (y(k+1) moves with C B), so unscaled they would be ignored
        row_scale = np.ones(perm.size)
        row_scale[n_simple:] = 1.0 / row_norms[np.asarray(general, dtype=np.intp)]
        A_d = A_d * row_scale[n_simple:, None]
        self.lo0 = np.clip(np.append(rows.lo0, -_INF)[perm] * row_scale, -_INF, _INF)
        self.hi0 = np.clip(np.append(rows.hi0, _INF)[perm] * row_scale, -_INF, _INF)
        self.G = np.ascontiguousarray(
            np.vstack([rows.G, np.zeros(rows.G.shape[1])])[perm] * row_scale[:, None]
        )
        self.sense0 = np.zeros(perm.size, dtype=np.int32)
        self.sense_soft = np.where(np.append(rows.kind, _DU)[perm] == _Y, 8, 0).astype(np.int32)
        self.A = A_d

    def zero_row_violation(self, z: NDArray) -> float:
        """Largest violation of the limits that the decision variables do not move (0 if none)."""
        rows, idx = self._rows, self.zero_idx
        off = rows.G[idx] @ z
        h, lw = rows.hi0[idx] + off, rows.lo0[idx] + off
        over = np.maximum(-h, lw)  # the rows' value is 0
        tol = 1e-6 * np.maximum(1.0, np.minimum(np.abs(rows.hi0[idx]), np.abs(rows.lo0[idx])))
        return float(np.max(over)) if np.any(over > tol) else 0.0
