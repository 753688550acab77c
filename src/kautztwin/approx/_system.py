"""Conversion of the LTI system descriptions users pass into one SISO state space."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from ..exceptions import DataError, DimensionError


@dataclass(frozen=True)
class SISOStateSpace:
    """A SISO realisation ``(A, B, C, D)`` with its sampling period (0: continuous)."""

    A: NDArray[np.float64]
    B: NDArray[np.float64]  # (n,)
    C: NDArray[np.float64]  # (n,)
    D: float
    dt: float


def as_state_space(system: Any) -> SISOStateSpace:
    """Accept scipy ``lti``/``dlti``, python-control systems, ``(num, den)`` or ``(A, B, C, D)``.

    Tuples are continuous time; a tuple ``(num, den, dt)`` or ``(A, B, C, D, dt)``
    is discrete with period ``dt``.
    """
    dt = 0.0
    if isinstance(system, (scipy.signal.lti, scipy.signal.dlti)):
        ss = system.to_ss()
        A, B, C, D = ss.A, ss.B, ss.C, ss.D
        dt = float(getattr(system, "dt", None) or 0.0)
    elif type(system).__module__.split(".")[0] == "control":
        import control  # only reached when python-control produced the object

        ss = control.ss(system)
        A, B, C, D = ss.A, ss.B, ss.C, ss.D
        dt = 0.0 if not ss.dt else float(ss.dt)
    elif isinstance(system, (tuple, list)) and len(system) in (2, 3):
        if len(system) == 3:
            dt = float(system[2])
        num = np.atleast_1d(np.asarray(system[0], dtype=float))
        den = np.atleast_1d(np.asarray(system[1], dtype=float))
        if num.ndim != 1 or den.ndim != 1:
            raise DimensionError("num and den must be 1-D coefficient lists (SISO systems only)")
        if num.size > den.size:
            raise DataError(
                f"the system is improper: deg num = {num.size - 1} > deg den = {den.size - 1}"
            )
        A, B, C, D = scipy.signal.tf2ss(num, den)
    elif isinstance(system, (tuple, list)) and len(system) in (4, 5):
        if len(system) == 5:
            dt = float(system[4])
        A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in system[:4])
        if B.shape[0] != A.shape[0]:
            B = B.T
    else:
        raise DataError(
            "system must be a scipy.signal lti/dlti, a python-control system, (num, den) or "
            f"(A, B, C, D); got {type(system).__name__}"
        )
    A = np.atleast_2d(np.asarray(A, dtype=float))
    B = np.atleast_2d(np.asarray(B, dtype=float))
    C = np.atleast_2d(np.asarray(C, dtype=float))
    D = np.atleast_2d(np.asarray(D, dtype=float))
    if B.shape[1] != 1 or C.shape[0] != 1:
        raise DimensionError(
            f"only SISO systems are supported; got {B.shape[1]} inputs and {C.shape[0]} outputs"
        )
    for name, m in (("A", A), ("B", B), ("C", C), ("D", D)):
        if not np.all(np.isfinite(m)):
            raise DataError(f"system matrix {name} contains NaN or inf")
    return SISOStateSpace(A, B[:, 0], C[0], float(D[0, 0]), dt)
