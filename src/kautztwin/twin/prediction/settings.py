r"""Design of the twin's MPC: :class:`MPCSettings` and :func:`build_mpc` (model + design -> QP).

:class:`MPCSettings` holds the controller design (horizon, Laguerre basis of
the increments, weights and the plant's limits); :func:`build_mpc` turns a
model and the settings into a :class:`~kautztwin.mpc.MPCProblem`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._validation import check_int, check_number
from ...approx.model import KautzModel
from ...exceptions import DataError
from ...mpc import MPCProblem

__all__ = ["MPCSettings", "build_mpc"]


def _number_or_inf(value: Any, name: str) -> float:
    """:func:`~kautztwin._validation.check_number`, except that ``+-inf`` passes (open limits)."""
    if isinstance(value, float | np.floating) and math.isinf(value):
        return float(value)
    return check_number(value, name)


@dataclass(frozen=True)
class MPCSettings:
    r"""Design of the twin's Laguerre MPC and the plant's limits.

    The controller plans the increments of its command ``v`` on a discrete
    Laguerre basis (``laguerre_pole``, ``n_functions``) over ``horizon``
    samples.  The plant receives ``u = v + d``, where ``d`` is the excitation
    dither of amplitude ``dither`` (zero for none); the controller's limits
    are therefore the plant's limits tightened by the dither,

    .. math::

        u_{min} + a \le v \le u_{max} - a,\qquad |\Delta v| \le \Delta u_{max} - 2a,

    so the applied input meets the plant's limits whatever the dither does.

    Parameters
    ----------
    horizon : int
        Prediction horizon ``N_p`` in samples.
    laguerre_pole : float
        Pole ``a`` of the discrete Laguerre basis of the increments, ``0 <= a < 1``.
    n_functions : int
        Number of Laguerre functions (decision variables).
    r : float
        Weight on the command increments (the output weight is 1).
    u_min, u_max : float
        Input limits of the plant.
    du_max : float
        Largest input change per sample of the plant (symmetric rate limit).
    y_min, y_max : float, default=-inf, inf
        Output limits (soft in the QP: relaxed to the least violation when infeasible).
    dither : float, default=0.0
        Amplitude of the excitation dither added to the command.
    n_dense : int, default=20
        The limits are imposed at the first ``n_dense`` steps of the horizon ...
    sparse_every : int, default=5
        ... and at every ``sparse_every``-th step after them (fewer rows, same behaviour).

    Raises
    ------
    DataError
        If a value is out of range or the dither leaves no room for the command.

    See Also
    --------
    build_mpc : Build the problem for a model.
    kautztwin.mpc.MPCProblem : The QP.

    Examples
    --------
    >>> from kautztwin.twin.prediction import MPCSettings
    >>> s = MPCSettings(50, 0.8, 4, 1.0, u_min=0.0, u_max=1.0, du_max=0.1, dither=0.02)
    >>> s.controller_limits()["u_max"], round(s.controller_limits()["du_max"], 6)
    (0.98, 0.06)
    """

    horizon: int
    laguerre_pole: float
    n_functions: int
    r: float
    u_min: float
    u_max: float
    du_max: float
    y_min: float = -math.inf
    y_max: float = math.inf
    dither: float = 0.0
    n_dense: int = 20
    sparse_every: int = 5

    def __post_init__(self) -> None:
        for name in ("horizon", "n_functions", "n_dense", "sparse_every"):
            object.__setattr__(self, name, check_int(getattr(self, name), name, 1))
        for name in ("laguerre_pole", "r", "u_min", "u_max", "du_max", "y_min", "y_max", "dither"):
            object.__setattr__(self, name, _number_or_inf(getattr(self, name), name))
        if not 0.0 <= self.laguerre_pole < 1.0:
            raise DataError(f"laguerre_pole must lie in [0, 1), got {self.laguerre_pole}")
        if not self.r > 0:
            raise DataError(f"r must be > 0, got {self.r}")
        finite = math.isfinite(self.u_min) and math.isfinite(self.u_max)
        if not (finite and self.u_min < self.u_max):
            raise DataError(f"need finite u_min < u_max, got {self.u_min} and {self.u_max}")
        if not self.y_min < self.y_max:
            raise DataError(f"need y_min < y_max, got {self.y_min} and {self.y_max}")
        if self.dither < 0:
            raise DataError(f"dither must be >= 0, got {self.dither}")
        if not self.du_max > 2 * self.dither:
            raise DataError(
                f"du_max = {self.du_max:g} must exceed twice the dither amplitude "
                f"({2 * self.dither:g}) to leave the controller a rate"
            )
        if not self.u_max - self.u_min > 2 * self.dither:
            raise DataError(
                f"the input range [{self.u_min:g}, {self.u_max:g}] is too narrow for a dither of "
                f"{self.dither:g}"
            )

    def controller_limits(self) -> dict[str, float]:
        """Limits of the controller's command: the plant's, tightened by the dither.

        Returns
        -------
        dict
            Keys ``u_min``, ``u_max``, ``du_min``, ``du_max``, ``y_min``, ``y_max``.
        """
        a = self.dither
        du = self.du_max - 2 * a
        return {
            "u_min": self.u_min + a, "u_max": self.u_max - a, "du_min": -du, "du_max": du,
            "y_min": self.y_min, "y_max": self.y_max,
        }

    def constraint_steps(self) -> NDArray[np.int64]:
        """Horizon steps at which the limits are imposed.

        Returns
        -------
        ndarray of int
        """
        n = min(self.n_dense, self.horizon)
        return np.unique(
            np.concatenate([np.arange(n), np.arange(n, self.horizon, self.sparse_every)])
        ).astype(np.int64)

    def with_weight(self, r: float) -> MPCSettings:
        """The same design with another increment weight.

        Parameters
        ----------
        r : float

        Returns
        -------
        MPCSettings
        """
        return replace(self, r=float(r))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (infinite limits as ``None``).

        Returns
        -------
        dict
        """
        out: dict[str, Any] = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            out[name] = None if isinstance(v, float) and not math.isfinite(v) else v
        return out


def build_mpc(
    model: KautzModel, settings: MPCSettings, *, u_shift: float = 0.0, y_shift: float = 0.0
) -> MPCProblem:
    """Build the twin's MPC problem for a model (once; it is re-solved every sample).

    Parameters
    ----------
    model : KautzModel
        Prediction model on a delayed discrete basis (``y = c^T x_f``).
    settings : MPCSettings
        Design and limits.
    u_shift, y_shift : float, default=0.0
        Subtracted from the input and output limits (to simulate in deviation
        coordinates around an operating point).

    Returns
    -------
    MPCProblem

    Examples
    --------
    >>> import kautztwin as kt
    >>> from kautztwin.twin.prediction import MPCSettings, build_mpc
    >>> model = kt.KautzModel(kt.KautzBasis([0.9], dt=0.1, delayed=True), [1.0])
    >>> s = MPCSettings(30, 0.7, 3, 0.1, u_min=-1.0, u_max=1.0, du_max=0.5)
    >>> build_mpc(model, s).n_variables
    3
    """
    lim = settings.controller_limits()
    return MPCProblem(
        model, (settings.laguerre_pole, settings.n_functions), settings.horizon,
        r=settings.r, u_min=lim["u_min"] - u_shift, u_max=lim["u_max"] - u_shift,
        du_min=lim["du_min"], du_max=lim["du_max"],
        y_min=lim["y_min"] - y_shift, y_max=lim["y_max"] - y_shift,
        constraint_steps=settings.constraint_steps(),
    )
