r"""Prediction and cost maps of the MPC over the horizon, built once per problem.

With the increments :math:`\Delta u(k+m) = L(m)^T\eta`, everything the controller
predicts is affine in the decision variables: the outputs
:math:`y(k+m) = CA^mx + C\phi(m)^T\eta`, the increments and the inputs
:math:`u(k+m) = u_{prev} + \sum_{i\le m}L(i)^T\eta` (kautz-math.md 6.1).
:class:`HorizonMaps` stacks these maps over the horizon, together with the QP cost
(``E = 2 Omega``, ``F = 2 Psi (x - x_s)``) and the unconstrained optimum
``eta = K_x (x - x_s)``, so that a solve is a few matrix-vector products.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from .laguerre import MPCDesign, _Sequences
from .plant import PlantModel
from .results import _squeeze

__all__ = ["HorizonMaps", "simulate_model"]


class HorizonMaps:
    r"""Prediction and cost maps over the horizon ``N_p`` (the state-free part of the QP).

    Parameters
    ----------
    design : MPCDesign
        The discrete unconstrained design.
    seq : _Sequences
        ``L(m)``, ``phi(m)^T`` and ``A^m`` over the horizon (from ``_discrete_build``).
    horizon : int
        ``N_p``.
    n_inputs, n_outputs : int
        Plant dimensions.

    Attributes
    ----------
    D : ndarray of shape (N_p n_inputs, n_variables)
        Increments over the horizon, ``du = D eta``.
    S : ndarray of shape (N_p n_inputs, n_variables)
        Input change over the horizon, ``u - u_prev = S eta``.
    Y_eta, Y_x : ndarray
        Outputs ``y = Y_x x + Y_eta eta``.
    W_eta, W_z : ndarray
        The whole plan ``[y; du; u] = W_eta eta + W_z [x; u_prev]``.
    P0 : ndarray of shape (n, n)
        State part of the cost, :math:`\sum_m A^{mT}QA^m`.
    E, Fx, Kx : ndarray
        QP Hessian ``2 Omega``, linear-term map ``2 Psi`` and unconstrained gain
        ``-Omega^{-1} Psi``.
    """

    def __init__(
        self, design: MPCDesign, seq: _Sequences, horizon: int, n_inputs: int, n_outputs: int
    ) -> None:
        Np, n_u, n_y = horizon, n_inputs, n_outputs
        n = design.A.shape[0]
        N = design.n_functions
        L = seq.L[:Np]  # (Np, N, n_u)
        S = np.cumsum(L, axis=0)  # sum_{i<=j} L(i)
        C = design.C
        self.D = np.transpose(L, (0, 2, 1)).reshape(Np * n_u, N)  # du
        self.S = np.transpose(S, (0, 2, 1)).reshape(Np * n_u, N)  # u - u_prev
        self.Y_eta = np.einsum("pn,mnj->mpj", C, seq.phi_t[1:]).reshape(Np * n_y, N)
        self.Y_x = np.einsum("pn,mnk->mpk", C, seq.a_pow[1:]).reshape(Np * n_y, n)
        # plan = W_eta @ eta + W_z @ [x; u_prev] stacks y (Np n_y), du and u (Np n_u each)
        self.W_eta = np.vstack([self.Y_eta, self.D, self.S])
        self.W_z = np.zeros((Np * (n_y + 2 * n_u), n + n_u))
        self.W_z[: Np * n_y, :n] = self.Y_x
        self.W_z[Np * (n_y + n_u) :, n:] = np.tile(np.eye(n_u), (Np, 1))
        self.P0 = np.einsum("mki,kl,mlj->ij", seq.a_pow[1:], design.Q, seq.a_pow[1:])

        # ---- cost: F = Fx @ (x - x_s); unconstrained eta = Kx @ (x - x_s)
        self.E = 2.0 * design.Omega
        self.Fx = 2.0 * design.Psi
        self.cho = scipy.linalg.cho_factor(design.Omega)
        self.Kx = -scipy.linalg.cho_solve(self.cho, design.Psi)
        self._shape = (Np, n_u, n_y)

    def plan(
        self, x: NDArray, eta: NDArray, up: NDArray, siso: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Outputs, inputs and increments over the horizon for ``eta`` (squeezed for SISO)."""
        Np, n_u, n_y = self._shape
        y = (self.Y_x @ x + self.Y_eta @ eta).reshape(Np, n_y)
        du = (self.D @ eta).reshape(Np, n_u)
        u = (self.S @ eta).reshape(Np, n_u) + up
        return _squeeze(y, siso), _squeeze(u, siso), _squeeze(du, siso)


def simulate_model(P: PlantModel, u: NDArray, x: NDArray) -> NDArray[np.float64]:
    """Outputs ``y(0), ..., y(n_steps - 1)`` of ``x(k+1) = A x + B u(k)`` from ``x``.

    Parameters
    ----------
    P : PlantModel
        The discrete prediction model.
    u : ndarray of shape (n_steps, n_inputs)
        Checked, finite inputs.
    x : ndarray of shape (n_states,)
        Initial state.

    Returns
    -------
    ndarray of shape (n_steps, n_outputs)
    """
    X = np.empty((u.shape[0], P.n_states))
    BU = u @ P.B.T
    for k in range(u.shape[0]):
        X[k] = x
        x = P.A @ x + BU[k]
    return X @ P.C.T
