"""Conversions of the LTI descriptions users pass (scipy, python-control, matrices) to matrices."""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from ..._validation import check_finite
from ...exceptions import DataError, DimensionError

__all__ = ["merged_eigenvalues", "system_matrices"]


def system_matrices(system: Any) -> tuple[NDArray, NDArray, NDArray, NDArray, float]:
    """``(A, B, C, D, dt)`` of a scipy, python-control or tuple description (dt 0: continuous)."""
    if isinstance(system, (scipy.signal.lti, scipy.signal.dlti)):
        ss = system.to_ss()
        mats = (ss.A, ss.B, ss.C, ss.D)
        dt = float(getattr(system, "dt", None) or 0.0)
    elif type(system).__module__.split(".")[0] == "control":
        import control  # only reached when python-control produced the object

        if system.dt is True:
            raise DataError("the system has an unspecified sampling period (dt=True); give one")
        dt = 0.0 if not system.dt else float(system.dt)
        if isinstance(system, control.TransferFunction) and not system.issiso():
            mats = _channel_realisation(system)
        else:
            ss = control.ss(system)
            mats = (ss.A, ss.B, ss.C, ss.D)
    elif isinstance(system, (tuple, list)) and len(system) in (4, 5):
        mats = tuple(system[:4])
        dt = float(system[4]) if len(system) == 5 else 0.0
    else:
        raise DataError(
            "system must be a scipy.signal StateSpace/lti/dlti, a python-control system or "
            f"(A, B, C, D[, dt]); got {type(system).__name__}"
        )
    A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in mats)
    n = A.shape[0] if A.size else 0
    if A.size and A.shape != (n, n) or B.shape[0] != n or C.shape[1] != n or D.shape != (
        C.shape[0], B.shape[1]
    ):
        raise DimensionError(
            f"inconsistent system matrices: A {A.shape}, B {B.shape}, C {C.shape}, D {D.shape}"
        )
    for name, m in (("A", A), ("B", B), ("C", C), ("D", D)):
        check_finite(m, f"system matrix {name}")
    return A, B, C, D, dt


def _channel_realisation(tf: Any) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """A (non-minimal) MIMO realisation of a transfer-function matrix, channel by channel.

    python-control converts MIMO transfer functions only with slycot; each channel's own
    controllable realisation (``scipy.signal.tf2ss``) stacked block-diagonally needs none.
    """
    n_out, n_in = tf.noutputs, tf.ninputs
    blocks = []
    D = np.zeros((n_out, n_in))
    for i in range(n_out):
        for j in range(n_in):
            num = np.atleast_1d(np.asarray(tf.num_array[i, j], dtype=float))
            den = np.atleast_1d(np.asarray(tf.den_array[i, j], dtype=float))
            a, b, c, d = scipy.signal.tf2ss(num, den)
            D[i, j] = float(np.asarray(d).reshape(-1)[0]) if np.size(d) else 0.0
            blocks.append((i, j, a, b, c))
    n = sum(a.shape[0] for *_, a, _, _ in blocks)
    A = np.zeros((n, n))
    B = np.zeros((n, n_in))
    C = np.zeros((n_out, n))
    k = 0
    for i, j, a, b, c in blocks:
        s = a.shape[0]
        A[k : k + s, k : k + s] = a
        B[k : k + s, j] = b[:, 0]
        C[i, k : k + s] = c[0]
        k += s
    return A, B, C, D


def merged_eigenvalues(A: NDArray, tol: float = 1e-6) -> NDArray[np.complex128]:
    """Eigenvalues of ``A``, each cluster closer than ``tol`` (a repeated eigenvalue split by
    rounding, ~sqrt(eps) for a double one) replaced by its mean."""
    eig = np.linalg.eigvals(A).astype(complex)
    out = eig.copy()
    done = np.zeros(eig.size, bool)
    for k in range(eig.size):
        if done[k]:
            continue
        group = (~done) & (np.abs(eig - eig[k]) <= tol)
        out[group] = eig[group].mean()
        done |= group
    real = np.abs(out.imag) <= tol
    out[real] = out[real].real
    return out
