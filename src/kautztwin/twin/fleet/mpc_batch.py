r"""The MPC's small QPs of a whole fleet solved together: a batched dual active-set solver.

Every asset's Kautz/Laguerre MPC is the QP

.. math::

    \min_\eta\ \tfrac12\eta^TE\eta + F^T\eta \quad\text{s.t.}\quad M\eta \le \gamma

with a handful of variables (``n_variables`` Laguerre coefficients) and a
few hundred one-sided rows.  :func:`solve_qp_batch` solves the QPs of many
assets at once with a primal-dual active-set iteration on the dual: for a
working set ``W`` (at most ``n_variables`` rows) the KKT system

.. math::

    (M_W E^{-1} M_W^T)\,\lambda_W = M_W\eta_0 - \gamma_W,\qquad
    \eta = \eta_0 - E^{-1}M_W^T\lambda_W,\qquad \eta_0 = -E^{-1}F

is one padded ``(n_variables x n_variables)`` solve per asset, done for all
assets in one :func:`numpy.linalg.solve`.  A row with a negative multiplier
leaves the working set, else the most violated row enters it; an asset is
done when every multiplier is ``>= -tol`` and every row is met to ``tol``
(the KKT conditions of the convex QP: its unique optimum).  The working
sets warm-start the next sample's solve.  Assets that do not converge in
``max_iter`` iterations, whose working set would exceed ``n_variables``
rows, or whose QP is infeasible are returned with ``status = 0``: the caller
solves them with the scalar path (DAQP with its soft-constraint and
clipped fallbacks, :class:`~kautztwin.mpc.MPCProblem`), so the constraint
guarantees are DAQP's.

:class:`BatchedController` holds the fleet's QP data (rows normalised to
unit norm as DAQP equilibrates them) and the controllers' filter states,
built from each asset's :class:`~kautztwin.mpc.MPCProblem` through its
public maps.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...mpc import MPCProblem

__all__ = ["BatchedController", "QPBatch", "extract_qp", "solve_qp_batch"]

_ZERO_ROW = 1e-12


class QPBatch:
    """The per-asset QP data of one :class:`~kautztwin.mpc.MPCProblem` in array form.

    The rows are two-sided, ``lo <= M eta <= hi`` (a one-sided row has an
    infinite bound), each scaled to unit norm; the bounds are affine in
    ``z = [x; u_prev]``: ``hi = hi0 + G z``, ``lo = lo0 + G z``.

    Parameters
    ----------
    problem : MPCProblem
        A SISO problem.

    Attributes
    ----------
    Einv : ndarray of shape (n_variables, n_variables)
    Fx : ndarray of shape (n_variables, n)
        ``F = Fx e`` with ``e = x - x_s``.
    M : ndarray of shape (n_rows, n_variables)
        Rows scaled to unit norm (zero rows kept as zeros).
    lo0, hi0 : ndarray of shape (n_rows,)
    G : ndarray of shape (n_rows, n + 1)
    L0 : ndarray of shape (n_variables,)
        ``du(k) = L0 . eta``.
    """

    def __init__(self, problem: MPCProblem) -> None:
        n = problem.plant.n_states + problem.plant.n_outputs
        self.Einv = np.linalg.inv(problem.E)
        self.Fx = 2.0 * np.asarray(problem.design.Psi, dtype=float)
        # the public one-sided form M1 eta <= g0 + G1 z, read at z = 0 and the unit vectors
        M1, g0 = problem.constraints(np.zeros(n), 0.0)
        G1 = np.empty((g0.size, n + 1))
        for j in range(n + 1):
            z = np.zeros(n + 1)
            z[j] = 1.0
            G1[:, j] = problem.constraints(z[:n], z[n])[1] - g0
        m2 = g0.size // 2
        # G1 comes from differences of bounds: equal to rounding of the bounds' size
        g_tol = 1e-12 * max(1.0, float(np.abs(g0[np.abs(g0) < 1e29]).max(initial=1.0)))
        paired = (g0.size % 2 == 0 and np.array_equal(M1[m2:], -M1[:m2])
                  and np.allclose(G1[m2:], -G1[:m2], rtol=0.0, atol=g_tol))
        if paired:  # every limit finite on both sides: [Mc; -Mc]
            M, hi0, lo0, G = M1[:m2], g0[:m2], -g0[m2:], G1[:m2]
        else:  # each one-sided row on its own
            M, hi0, lo0, G = M1, g0, np.full(g0.size, -np.inf), G1
        norms = np.linalg.norm(M, axis=1)
        nonzero = norms > _ZERO_ROW * max(1.0, float(norms.max(initial=0.0)))
        scale = np.where(nonzero, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
        bscale = np.where(nonzero, scale, 1.0)  # a zero row keeps its bounds: 0 in [lo, hi]?
        self.M = M * scale[:, None]
        self.hi0 = hi0 * bscale
        self.lo0 = lo0 * bscale
        self.G = G * bscale[:, None]
        self.L0 = np.asarray(problem.design.L0, dtype=float)[:, 0]
        self.n_rows = int(self.hi0.size)


def extract_qp(problem: MPCProblem) -> QPBatch:
    """The array form of a problem (see :class:`QPBatch`).

    Parameters
    ----------
    problem : MPCProblem

    Returns
    -------
    QPBatch
    """
    return QPBatch(problem)


def solve_qp_batch(
    Einv: NDArray, F: NDArray, M: NDArray, upper: NDArray, lower: NDArray | None = None, *,
    working: NDArray | None = None, tol: float = 1e-9, max_iter: int = 25,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.intp]]:
    r"""Solve ``min 1/2 eta^T E eta + F^T eta  s.t.  lower <= M eta <= upper`` for a batch of QPs.

    Parameters
    ----------
    Einv : ndarray of shape (B, n, n)
        Inverse Hessians (symmetric positive definite ``E``).
    F : ndarray of shape (B, n)
        Linear terms.
    M : ndarray of shape (B, m, n)
        Rows (best scaled to unit norm: ``tol`` is a distance then).
    upper : ndarray of shape (B, m)
        Upper bounds (``inf``: none).
    lower : ndarray of shape (B, m), optional
        Lower bounds (``-inf``: none); one-sided rows ``M eta <= upper`` when omitted.
    working : ndarray of int of shape (B, n), optional
        Warm start: each QP's initial working set, ``-1`` for an empty slot,
        ``j`` for row ``j``'s upper bound, ``m + j`` for its lower bound (the
        previous solve's final sets).
    tol : float, default=1e-9
        Primal feasibility and multiplier tolerance.
    max_iter : int, default=25
        Active-set changes per QP.

    Returns
    -------
    eta : ndarray of shape (B, n)
        Solutions (meaningful where ``status == 1``).
    status : ndarray of int of shape (B,)
        1: optimal (the KKT conditions hold to ``tol``); 0: not solved here
        (iteration limit, a full or singular working set, an infeasible
        QP): solve it with a general solver.
    working : ndarray of int of shape (B, n)
        Final working sets (for the next warm start).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.fleet.mpc_batch import solve_qp_batch
    >>> Einv = np.tile(np.eye(2), (2, 1, 1))             # E = I: project -F onto the box
    >>> F = np.array([[-2.0, 0.0], [0.5, 0.5]])
    >>> M = np.tile(np.eye(2), (2, 1, 1))
    >>> eta, status, _ = solve_qp_batch(Einv, F, M, np.ones((2, 2)), -np.ones((2, 2)))
    >>> (eta.round(6) + 0.0).tolist(), status.tolist()
    ([[1.0, 0.0], [-0.5, -0.5]], [1, 1])
    """
    B, m, n = M.shape
    lo = np.full((B, m), -np.inf) if lower is None else lower
    eta0 = -np.einsum("bij,bj->bi", Einv, F)
    W = np.full((B, n), -1, dtype=np.intp) if working is None else working.astype(np.intp).copy()
    status = np.zeros(B, dtype=np.int64)
    eta = eta0.copy()
    todo = np.arange(B)
    for _ in range(max_iter + 1):
        if todo.size == 0:
            break
        Wt = W[todo]
        used = Wt >= 0
        base = np.where(used, Wt % m, 0)
        sign = np.where(Wt >= m, -1.0, 1.0) * used  # 0 on empty slots
        MW = M[todo[:, None], base] * sign[..., None]  # (b, n, n): empty slots are zero rows
        gW = np.where(used, np.where(Wt >= m, -lo[todo[:, None], base],
                                     upper[todo[:, None], base]), 0.0)
        Ei = Einv[todo]
        e0 = eta0[todo]
        S = np.einsum("bij,bjk,blk->bil", MW, Ei, MW)
        S[~used[..., None] & np.eye(n, dtype=bool)] = 1.0  # identity on empty slots
        rhs = np.where(used, np.einsum("bij,bj->bi", MW, e0) - gW, 0.0)
        try:
            lam = np.linalg.solve(S, rhs[..., None])[..., 0]
            bad = ~np.isfinite(lam).all(axis=1)
        except np.linalg.LinAlgError:
            lam = np.zeros_like(rhs)
            bad = np.ones(todo.size, dtype=bool)
            for r in range(todo.size):
                try:
                    lam[r] = np.linalg.solve(S[r], rhs[r])
                    bad[r] = not np.isfinite(lam[r]).all()
                except np.linalg.LinAlgError:
                    pass
        et = e0 - np.einsum("bij,bkj,bk->bi", Ei, MW, lam)
        eta[todo] = et
        lam_m = np.where(used, lam, np.inf)
        jmin = np.argmin(lam_m, axis=1)
        rows = np.arange(todo.size)
        lmin = lam_m[rows, jmin]
        drop = (lmin < -tol) & ~bad
        Me = np.einsum("bmn,bn->bm", M[todo], et)
        viol = np.concatenate([Me - upper[todo], lo[todo] - Me], axis=1)
        imax = np.argmax(viol, axis=1)
        vmax = viol[rows, imax]
        done = ~drop & ~bad & (vmax <= tol)
        status[todo[done]] = 1
        dr = np.flatnonzero(drop)  # the most negative multiplier leaves
        W[todo[dr], jmin[dr]] = -1
        add = np.flatnonzero(~drop & ~bad & ~done)  # else the most violated bound enters
        if add.size:
            Wa = W[todo[add]]
            free = Wa < 0
            has = free.any(axis=1)
            slot = np.argmax(free, axis=1)
            already = ((Wa % m == (imax[add] % m)[:, None]) & (Wa >= 0)).any(axis=1)
            ok = has & ~already
            W[todo[add[ok]], slot[ok]] = imax[add[ok]]
            bad[add[~ok]] = True  # a full working set, or the row's other bound (degenerate)
        todo = todo[~done & ~bad]
    return eta, status, W


class BatchedController:
    """The controllers of a fleet: QP data and filter states as ``(n_assets, ...)`` arrays.

    One slot per asset, filled by :meth:`install` from the asset's
    :class:`~kautztwin.mpc.MPCProblem` and the filter states of
    :class:`~kautztwin.twin.prediction.MPCController` (the same model and
    command history give the same states).  :meth:`solve` forms every
    asset's linear term and bounds and calls :func:`solve_qp_batch`.

    Parameters
    ----------
    n_assets : int
    n_states : int
        Model order (filter states per asset).
    n_variables : int
        QP variables.
    n_rows : int
        Two-sided constraint rows.
    input_offset : float
        The models' input operating point.
    """

    def __init__(
        self, n_assets: int, n_states: int, n_variables: int, n_rows: int, input_offset: float,
    ) -> None:
        N, n, nv, m = n_assets, n_states, n_variables, n_rows
        self.n_assets, self.n_states, self.n_variables, self.n_rows = N, n, nv, m
        self.input_offset = float(input_offset)
        self.A = np.zeros((N, n, n))
        self.B = np.zeros((N, n))
        self.c = np.zeros((N, n))
        self.xv = np.zeros((N, n))
        self.xv_prev = np.zeros((N, n))
        self.xd = np.zeros((N, n))
        self.Einv = np.zeros((N, nv, nv))
        self.Fx = np.zeros((N, nv, n + 1))
        self.M = np.zeros((N, m, nv))
        self.lo0 = np.zeros((N, m))
        self.hi0 = np.zeros((N, m))
        self.G = np.zeros((N, m, n + 2))
        self.L0 = np.zeros((N, nv))
        self.working = np.full((N, nv), -1, dtype=np.intp)

    def install(
        self, i: int, problem: MPCProblem | QPBatch, A: NDArray, B: NDArray, c: NDArray,
        xv: NDArray, xv_prev: NDArray, xd: NDArray,
    ) -> None:
        """Put asset ``i``'s problem and filter states into the arrays.

        Parameters
        ----------
        i : int
        problem : MPCProblem or QPBatch
        A, B, c, xv, xv_prev, xd : ndarray
            The controller model and its filter states.
        """
        q = problem if isinstance(problem, QPBatch) else extract_qp(problem)
        if q.n_rows != self.n_rows or q.Einv.shape[0] != self.n_variables:
            raise ValueError(
                f"asset {i}: the QP has {q.n_rows} rows and {q.Einv.shape[0]} variables, the "
                f"fleet {self.n_rows} and {self.n_variables}"
            )
        self.A[i], self.B[i], self.c[i] = A, B, c
        self.xv[i], self.xv_prev[i], self.xd[i] = xv, xv_prev, xd
        self.Einv[i], self.Fx[i], self.M[i], self.G[i], self.L0[i] = (
            q.Einv, q.Fx, q.M, q.G, q.L0)
        self.lo0[i], self.hi0[i] = q.lo0, q.hi0
        self.working[i] = -1

    def state(self, y_fb: NDArray) -> NDArray[np.float64]:
        """The MPC states ``[xv - xv_prev; y - c . xd]`` of every asset.

        Parameters
        ----------
        y_fb : ndarray of shape (n_assets,)

        Returns
        -------
        ndarray of shape (n_assets, n_states + 1)
        """
        y_eff = y_fb - np.einsum("bi,bi->b", self.c, self.xd)
        return np.concatenate([self.xv - self.xv_prev, y_eff[:, None]], axis=1)

    def solve(
        self, x: NDArray, reference: NDArray, v_prev: NDArray, sel: NDArray[np.intp],
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """First moves ``u_next`` of the assets ``sel`` (status 1) or status 0 (solve elsewhere).

        Parameters
        ----------
        x : ndarray of shape (n_assets, n_states + 1)
        reference : ndarray of shape (n_assets,)
        v_prev : ndarray of shape (n_assets,)
        sel : ndarray of int

        Returns
        -------
        u_next : ndarray of shape (len(sel),)
        status : ndarray of int of shape (len(sel),)
        """
        xs = x[sel]
        e = xs.copy()
        e[:, -1] -= reference[sel]
        F = np.einsum("bij,bj->bi", self.Fx[sel], e)
        z = np.concatenate([xs, v_prev[sel, None]], axis=1)
        off = np.einsum("bmj,bj->bm", self.G[sel], z)
        eta, status, W = solve_qp_batch(self.Einv[sel], F, self.M[sel], self.hi0[sel] + off,
                                        self.lo0[sel] + off, working=self.working[sel])
        self.working[sel] = W
        u_next = v_prev[sel] + np.einsum("bi,bi->b", eta, self.L0[sel])
        return u_next, status

    def advance(self, v: NDArray, d: NDArray) -> None:
        """Advance every asset's filter states with its command and dither.

        Parameters
        ----------
        v, d : ndarray of shape (n_assets,)
        """
        self.xv_prev = self.xv
        dv = (v - self.input_offset)[:, None]
        self.xv = np.einsum("bij,bj->bi", self.A, self.xv) + self.B * dv
        self.xd = np.einsum("bij,bj->bi", self.A, self.xd) + self.B * d[:, None]

    @property
    def nbytes(self) -> int:
        """Bytes held in the arrays."""
        return int(sum(getattr(self, a).nbytes for a in (
            "A", "B", "c", "xv", "xv_prev", "xd", "Einv", "Fx", "M", "lo0", "hi0", "G", "L0",
            "working")))
