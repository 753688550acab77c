"""Receding-horizon closed-loop simulation of an :class:`~kautztwin.mpc.MPCProblem`."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..exceptions import DataError, DimensionError
from .plant import plant_model
from .problem import MPCProblem
from .results import ClosedLoopResult, _squeeze

__all__ = ["simulate_closed_loop"]


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
