r"""Continuous-time Laguerre/Kautz MPC (kautz-math.md 6.2): prediction and cost integrals.

The derivative of the input is expanded on a continuous orthonormal basis,
:math:`\dot u(t_i+\tau) = L(\tau)^T\eta` with :math:`\dot L = A_pL`.
:func:`continuous_phi` is the prediction matrix :math:`\Phi(\tau)`,
:func:`continuous_cost_matrices` its cost integrals (Van Loan or quadrature) and
:func:`continuous_mpc_design` the unconstrained design from them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ..exceptions import DataError
from .laguerre import MPCDesign, _basis_matrices, _increment_penalty, _solve_spd, _weights
from .plant import PlantModel, _continuous_plant

__all__ = ["continuous_cost_matrices", "continuous_mpc_design", "continuous_phi"]


def _augment_continuous(P: PlantModel) -> tuple[NDArray, NDArray, NDArray]:
    n_x, n_y = P.n_states, P.n_outputs
    A = np.zeros((n_x + n_y, n_x + n_y))
    A[:n_x, :n_x] = P.A
    A[n_x:, :n_x] = P.C
    B = np.vstack([P.B, np.zeros((n_y, P.n_inputs))])
    C = np.hstack([np.zeros((n_y, n_x)), np.eye(n_y)])
    return A, B, C


def continuous_phi(
    A: ArrayLike,
    B: ArrayLike,
    A_p: ArrayLike,
    L0: ArrayLike,
    tau: float,
    *,
    method: str = "expm",
) -> NDArray[np.float64]:
    r"""Continuous-time prediction matrix :math:`\Phi(\tau)` of kautz-math.md 6.2.

    :math:`\Phi(\tau) = \int_0^\tau e^{A(\tau-\gamma)}BL(\gamma)^Td\gamma`, so that
    :math:`x(t_i+\tau) = e^{A\tau}x(t_i) + \Phi(\tau)\eta`.

    Parameters
    ----------
    A : array-like of shape (n, n)
        Augmented state matrix.
    B : array-like of shape (n, n_inputs)
        Augmented input matrix.
    A_p : array-like of shape (n_functions, n_functions)
        Basis matrix, :math:`\dot L = A_p L`.
    L0 : array-like of shape (n_functions, n_inputs) or (n_functions,)
        ``L(0)``.
    tau : float
        Time ``>= 0``.
    method : {'expm', 'sylvester'}, default='expm'
        ``'expm'``: the block exponential
        :math:`\exp(\begin{bmatrix}A & BL(0)^T\\ 0 & A_p^T\end{bmatrix}\tau)`;
        ``'sylvester'``: :math:`\Phi = Xe^{A_p^T\tau} - e^{A\tau}X` with
        :math:`AX - XA_p^T = -BL(0)^T` (needs disjoint spectra).

    Returns
    -------
    ndarray of shape (n, n_functions)

    Raises
    ------
    DataError
        On an unknown ``method`` or a negative ``tau``.

    See Also
    --------
    continuous_cost_matrices : The integrals of :math:`\Phi` that make ``Omega`` and ``Psi``.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, -1)
    A_p = np.atleast_2d(np.asarray(A_p, dtype=float))
    L0 = np.asarray(L0, dtype=float).reshape(A_p.shape[0], -1)
    tau = float(tau)
    if tau < 0 or not np.isfinite(tau):
        raise DataError(f"tau must be finite and >= 0, got {tau}")
    G = B @ L0.T
    if method == "expm":
        return _block_expm(A, G, A_p, tau)[:n, n:]
    if method == "sylvester":
        X = scipy.linalg.solve_sylvester(A, -A_p.T, -G)
        return X @ scipy.linalg.expm(A_p.T * tau) - scipy.linalg.expm(A * tau) @ X
    raise DataError(f"method must be 'expm' or 'sylvester', got {method!r}")


def _block_expm(A: NDArray, G: NDArray, A_p: NDArray, tau: float) -> NDArray[np.float64]:
    n, N = A.shape[0], A_p.shape[0]
    H = np.zeros((n + N, n + N))
    H[:n, :n] = A
    H[:n, n:] = G
    H[n:, n:] = A_p.T
    return scipy.linalg.expm(H * tau)


def continuous_cost_matrices(
    A: ArrayLike,
    B: ArrayLike,
    A_p: ArrayLike,
    L0: ArrayLike,
    Q: ArrayLike,
    prediction_time: float,
    *,
    method: str = "vanloan",
    n_doublings: int | None = None,
    n_panels: int = 40,
    n_nodes: int = 12,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    r"""The integrals :math:`\int_0^{T_p}\Phi^TQ\Phi` and :math:`\int_0^{T_p}\Phi^TQe^{A\tau}`.

    Parameters
    ----------
    A, B : array-like
        Augmented model, shapes ``(n, n)`` and ``(n, n_inputs)``.
    A_p : array-like of shape (n_functions, n_functions)
        Basis matrix.
    L0 : array-like of shape (n_functions, n_inputs)
        ``L(0)``.
    Q : array-like of shape (n, n)
        State weight.
    prediction_time : float
        ``T_p > 0`` in seconds.
    method : {'vanloan', 'quadrature'}, default='vanloan'
        ``'vanloan'``: Van Loan's block exponential on ``T_p / 2**k`` followed
        by ``k`` interval doublings; ``'quadrature'``: composite Gauss-Legendre
        (``n_panels`` panels of ``n_nodes`` nodes) on the block exponential.
    n_doublings : int, optional
        ``k`` for ``'vanloan'``; by default the smallest ``k`` with
        :math:`\|H\|_1 T_p / 2^k \le 1/2`.
    n_panels, n_nodes : int, default=40, 12
        Quadrature resolution.

    Returns
    -------
    Omega0 : ndarray of shape (n_functions, n_functions)
        :math:`\int_0^{T_p}\Phi(\tau)^TQ\Phi(\tau)d\tau` (``Omega`` without ``R_L``).
    Psi : ndarray of shape (n_functions, n)
        :math:`\int_0^{T_p}\Phi(\tau)^TQe^{A\tau}d\tau`.

    Raises
    ------
    DataError
        On an unknown ``method`` or a non-positive ``prediction_time``.

    See Also
    --------
    continuous_phi : The prediction matrix :math:`\Phi(\tau)`.
    continuous_mpc_design : Uses these integrals.

    Notes
    -----
    With :math:`H = \begin{bmatrix}A & BL(0)^T\\0 & A_p^T\end{bmatrix}` and
    :math:`\tilde Q = \operatorname{blkdiag}(Q, 0)`,
    :math:`W(T) = \int_0^T e^{H^T\tau}\tilde Qe^{H\tau}d\tau` holds
    ``Omega0 = W_22`` and ``Psi = W_21``.  Van Loan:
    :math:`\exp(\begin{bmatrix}-H^T & \tilde Q\\0 & H\end{bmatrix}T)` has blocks
    :math:`F_{12}, F_{22}` with :math:`W(T) = F_{22}^TF_{12}`; it loses accuracy
    for long intervals, so it is applied on :math:`T_0 = T_p/2^k` and doubled,
    :math:`W(2T) = W(T) + e^{H^TT}W(T)e^{HT}`.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, -1)
    A_p = np.atleast_2d(np.asarray(A_p, dtype=float))
    N = A_p.shape[0]
    L0 = np.asarray(L0, dtype=float).reshape(N, -1)
    Q = np.asarray(Q, dtype=float).reshape(n, n)
    T = float(prediction_time)
    if not np.isfinite(T) or T <= 0:
        raise DataError(f"prediction_time must be > 0, got {prediction_time}")
    H = np.zeros((n + N, n + N))
    H[:n, :n] = A
    H[:n, n:] = B @ L0.T
    H[n:, n:] = A_p.T
    Qt = np.zeros((n + N, n + N))
    Qt[:n, :n] = Q
    if method == "vanloan":
        if n_doublings is None:
            h = float(np.linalg.norm(H, 1)) * T
            n_doublings = max(0, int(np.ceil(np.log2(h / 0.5)))) if h > 0.5 else 0
        T0 = T / 2 ** int(n_doublings)
        m = n + N
        Z = np.zeros((2 * m, 2 * m))
        Z[:m, :m] = -H.T
        Z[:m, m:] = Qt
        Z[m:, m:] = H
        F = scipy.linalg.expm(Z * T0)
        W = F[m:, m:].T @ F[:m, m:]
        E = F[m:, m:]  # e^{H T0}
        for _ in range(int(n_doublings)):
            W = W + E.T @ W @ E
            E = E @ E
        W = 0.5 * (W + W.T)
    elif method == "quadrature":
        x, w = np.polynomial.legendre.leggauss(int(n_nodes))
        half = 0.5 * T / int(n_panels)
        # e^{H (a_i + s_j)} = e^{H a_i} e^{H s_j}: one exponential per node offset, and the
        # panel starts by repeated multiplication with e^{H * panel width}
        E_nodes = np.array([scipy.linalg.expm(H * (half * (xi + 1.0))) for xi in x])
        E_panel = scipy.linalg.expm(H * (2.0 * half))
        E_start = np.eye(H.shape[0])
        W = np.zeros_like(H)
        for _ in range(int(n_panels)):
            Et = E_start @ E_nodes  # (n_nodes, m, m)
            W += half * np.einsum("j,jki,kl,jlm->im", w, Et, Qt, Et)
            E_start = E_start @ E_panel
    else:
        raise DataError(f"method must be 'vanloan' or 'quadrature', got {method!r}")
    return W[n:, n:].copy(), W[n:, :n].copy()


def continuous_mpc_design(
    plant: Any,
    basis: Any,
    prediction_time: float,
    *,
    Q: ArrayLike | None = None,
    r: ArrayLike = 0.1,
    penalty: str = "infinite",
    method: str = "vanloan",
) -> MPCDesign:
    r"""Continuous-time Laguerre/Kautz MPC (kautz-math.md 6.2): ``Omega``, ``Psi``, ``K_mpc``.

    Parameters
    ----------
    plant : tuple, scipy.signal.lti, KautzModel or PlantModel
        Continuous-time plant; bare matrices ``(A, B, C)`` are taken as continuous.
    basis : KautzBasis, (pole, n_functions) or list of these
        Continuous orthonormal basis of :math:`\dot u` (``dt = 0``); ``(pole, N)``
        is ``LaguerreBasis(pole, N)`` with the pole *location* ``pole < 0``
        (Wang's ``p`` is ``-pole``).
    prediction_time : float
        ``T_p`` in seconds.
    Q : float or array-like, optional
        As in :func:`discrete_mpc_design`; default ``C^T C``.
    r : float or array-like of shape (n_inputs,), default=0.1
        Weight on :math:`\dot u`.
    penalty : {'infinite', 'finite'}, default='infinite'
        ``'infinite'``: :math:`R_L = rI`, the penalty :math:`r\int_0^\infty\dot u^2`;
        ``'finite'``: the exact horizon penalty
        :math:`r(I - e^{A_pT_p}e^{A_p^TT_p})`.
    method : {'vanloan', 'quadrature'}, default='vanloan'
        How the cost integrals are computed (:func:`continuous_cost_matrices`).

    Returns
    -------
    MPCDesign
        With ``dt = 0`` and ``horizon = T_p``.

    Raises
    ------
    DataError
        On an unsupported plant or basis or invalid weights.

    See Also
    --------
    discrete_mpc_design : The discrete-time counterpart.

    Notes
    -----
    Augmented model :math:`x = [\dot x_m; y]`,
    :math:`A = \begin{bmatrix}A_m & 0\\C_m & 0\end{bmatrix}`,
    :math:`B = \begin{bmatrix}B_m\\0\end{bmatrix}`; the optimum is
    :math:`\dot u(t_i) = -K_{mpc}(x - x_s)` with
    :math:`K_{mpc} = L(0)^T\Omega^{-1}\Psi`.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.mpc import continuous_mpc_design
    >>> plant = ([[0.0, 1.0], [-1.0, -0.4]], [0.0, 1.0], [1.0, 0.0])
    >>> d = continuous_mpc_design(plant, (-1.0, 4), 10.0, r=0.05)
    >>> np.round(d.K_mpc, 6)
    array([[5.725868, 3.367629, 4.88106 ]])
    """
    P = _continuous_plant(plant)
    A, B, C = _augment_continuous(P)
    A_p, L0, bases = _basis_matrices(basis, P.n_inputs, discrete=False)
    Q_aug, _, rw = _weights(Q, r, C, bases)
    T = float(prediction_time)
    if not np.isfinite(T) or T <= 0:
        raise DataError(f"prediction_time must be > 0, got {prediction_time}")
    R_L = _increment_penalty(rw, bases)
    if penalty == "finite":
        Ep = scipy.linalg.expm(A_p * T)
        R_L = R_L @ (np.eye(A_p.shape[0]) - Ep @ Ep.T)
        R_L = 0.5 * (R_L + R_L.T)
    elif penalty != "infinite":
        raise DataError(f"penalty must be 'infinite' or 'finite', got {penalty!r}")
    Omega0, Psi = continuous_cost_matrices(A, B, A_p, L0, Q_aug, T, method=method)
    Omega = Omega0 + R_L
    Omega = 0.5 * (Omega + Omega.T)
    K = L0.T @ _solve_spd(Omega, Psi)
    return MPCDesign(A, B, C, A_p, L0, Omega, Psi, K, Q_aug, R_L, T, 0.0)
