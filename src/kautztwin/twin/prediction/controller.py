r"""The twin's prediction/control module: :class:`MPCController`, Laguerre MPC on the current model.

:func:`_prepare_controller` builds the problem and the filter states for a
model version from the command histories; it is a pure function, so the
background optimisation worker (:mod:`kautztwin.twin.optimization.background`)
runs it too, and :meth:`MPCController._install` advances its result over
the samples applied since, bit for bit as a :meth:`MPCController.rebuild`.

A live plant applies an input some samples after the twin decided it (link
latency, a loop that is behind the plant).  :meth:`MPCController.solve` with
``delay = d`` is then a predictor over the known transport delay: the model
state is carried through the ``d`` inputs already decided but not yet applied,
the measured output is moved by the model's predicted change over those ``d``
periods (a Smith predictor), and the MPC plans the input for sample ``k + d``,
the first one it can still change.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...approx.model import KautzModel
from ...exceptions import TwinError
from ...mpc import MPCProblem, MPCResult
from .settings import MPCSettings, build_mpc

__all__ = ["MAX_DELAY", "MPCController", "TwinError"]

#: longest input delay, samples, the predictor of :meth:`MPCController.solve` covers
MAX_DELAY = 256


def _filter_states(
    A: NDArray, B: NDArray, w: NDArray, n_keep: int = 2
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Last two states ``x(n), x(n-1)`` of ``x(k+1) = A x(k) + B w(k)`` from rest."""
    x = np.zeros(A.shape[0])
    prev = x.copy()
    for wk in w.tolist():
        prev = x
        x = A @ x + B * wk
    return x, prev


def _delay_maps(A: NDArray, B: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``A^j`` for ``j = 0..MAX_DELAY`` and the rows ``A^j B`` for ``j < MAX_DELAY`` (predictor)."""
    n = A.shape[0]
    powers = np.empty((MAX_DELAY + 1, n, n))
    powers[0] = np.eye(n)
    for j in range(MAX_DELAY):
        powers[j + 1] = A @ powers[j]
    return powers, powers[:MAX_DELAY] @ B


@dataclass(frozen=True, eq=False)
class _PreparedController:
    """An MPC problem and its filter states after the first ``n`` samples of the histories."""

    model: KautzModel
    settings: MPCSettings
    problem: MPCProblem
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    c: NDArray[np.float64]
    xv: NDArray[np.float64]
    xv_prev: NDArray[np.float64]
    xd: NDArray[np.float64]
    n: int
    v_tail: NDArray[np.float64]
    d_tail: NDArray[np.float64]


def _prepare_controller(
    model: KautzModel, settings: MPCSettings, v_history: ArrayLike, d_history: ArrayLike,
    input_offset: float,
) -> _PreparedController:
    """Build the problem and the filter states (a pure function: it also runs in the worker)."""
    problem = build_mpc(model, settings)
    A = np.array(model.basis.A)
    B = np.array(model.basis.B)
    c = np.array(model.coefficients)
    v_raw = np.asarray(v_history, dtype=float)
    v = v_raw - input_offset
    d = np.asarray(d_history, dtype=float)
    xv, xv_prev = _filter_states(A, B, v)
    xd, _ = _filter_states(A, B, d)
    return _PreparedController(model, settings, problem, A, B, c, xv, xv_prev, xd, int(v.size),
                               v_raw[-MAX_DELAY:].copy(), d[-MAX_DELAY:].copy())


class MPCController:
    r"""The twin's prediction/control module: Laguerre MPC on the current model version.

    The MPC problem is built once per model version (:meth:`rebuild`) and
    re-solved every sample (:meth:`solve`).  The controller runs its own copy
    of the model's filter state, split into the part driven by its command
    ``v`` and the part driven by the excitation dither ``d``:

    .. math::

        x(k) = x_v(k) + x_d(k),\qquad
        \text{MPC state} = \big[x_v(k) - x_v(k-1);\ y(k) - c^T x_d(k)\big],

    so the controller tracks with the dither's predicted response removed
    from the feedback and does not fight the excitation.

    With an input delay of :math:`d` samples (a live plant applies the input
    decided at sample :math:`j` over period :math:`j + d`), the inputs of
    periods :math:`k .. k+d-1` are already decided: :math:`w(k-d) .. w(k-1)`
    (command and dither as issued, :meth:`advance`).  The state is carried
    through them and the output is predicted from the measured one,

    .. math::

        x(k+d) = A^d x(k) + \sum_{j=0}^{d-1} A^{d-1-j} B\, w(k-d+j),\qquad
        \hat y(k+d) = y(k) + c^T\big(x(k+d) - x(k)\big),

    and the MPC solves from :math:`[x_v(k+d) - x_v(k+d-1);\ \hat y(k+d) - c^T x_d(k+d)]`:
    its first move is the input of period :math:`k + d`.

    Parameters
    ----------
    input_offset : float, default=0.0
        The models' input operating point :math:`u_0`.

    Attributes
    ----------
    model : KautzModel or None
        The model the controller runs on.
    settings : MPCSettings or None
        Its design.
    problem : MPCProblem or None
        The built problem.
    n_builds : int
        Times the problem was built.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.twin.prediction import MPCController, MPCSettings
    >>> model = kt.KautzModel(kt.KautzBasis([0.9], dt=0.1, delayed=True), [1.0])
    >>> ctl = MPCController()
    >>> ctl.rebuild(model, MPCSettings(30, 0.7, 3, 0.1, u_min=-1, u_max=1, du_max=0.5),
    ...             np.zeros(10), np.zeros(10))
    >>> res = ctl.solve(0.0, 1.0, 0.0)
    >>> res.success, 0.0 < res.u_next <= 0.5
    (True, True)
    """

    def __init__(self, *, input_offset: float = 0.0) -> None:
        self.input_offset = float(input_offset)
        self.model: KautzModel | None = None
        self.settings: MPCSettings | None = None
        self.problem: MPCProblem | None = None
        self.n_builds = 0
        self._issued: deque[tuple[float, float]] = deque(maxlen=MAX_DELAY)

    def rebuild(
        self, model: KautzModel, settings: MPCSettings, v_history: ArrayLike,
        d_history: ArrayLike,
    ) -> None:
        """Build the problem for ``model`` and rebuild the filter states from the histories.

        Parameters
        ----------
        model : KautzModel
            The model version (delayed discrete basis).
        settings : MPCSettings
            The design.
        v_history, d_history : array-like of shape (n_samples,)
            Commands and dither applied so far (the plant at rest at the
            input offset before them).
        """
        self._install(_prepare_controller(model, settings, v_history, d_history,
                                          self.input_offset))

    def _install(
        self, prepared: _PreparedController, v_since: ArrayLike = (), d_since: ArrayLike = ()
    ) -> None:
        """Run on a prepared controller, advanced over the samples applied since it was prepared.

        The advance repeats the operations of :func:`_filter_states`, so the
        states equal those of a :meth:`rebuild` on the whole history, bit for bit.
        """
        if not self._issued and prepared.n:  # the first build: the inputs sent before it
            v_tail, d_tail = prepared.v_tail, prepared.d_tail
            self._issued.extend(zip(v_tail.tolist(), d_tail.tolist(), strict=True))
        self.problem = prepared.problem
        self.model = prepared.model
        self.settings = prepared.settings
        self._A, self._B, self._c = prepared.A, prepared.B, prepared.c
        self._powers, self._AB = _delay_maps(prepared.A, prepared.B)
        self._xv, self._xv_prev, self._xd = prepared.xv, prepared.xv_prev, prepared.xd
        for v, d in zip(np.asarray(v_since, dtype=float).tolist(),
                        np.asarray(d_since, dtype=float).tolist(), strict=True):
            self._propagate(v, d)  # inputs already issued: not issued again
        self.n_builds += 1

    def solve(self, y: float, reference: float, v_prev: float, delay: int = 0) -> MPCResult:
        """Solve the MPC for the current sample.

        Parameters
        ----------
        y : float
            Output feedback (measured, or the twin's prediction for a bad sample).
        reference : float
            Reference (filtered set-point).
        v_prev : float
            Previous command.
        delay : int, default=0
            Samples from this decision to the period the plant applies it
            (0: at once, as a simulated plant).  The state is predicted over
            the inputs decided in the last ``delay`` samples (see the class
            notes); at most :data:`MAX_DELAY`, and no more than have been decided.

        Returns
        -------
        MPCResult
        """
        if self.problem is None:
            raise TwinError("the controller has no model yet; call rebuild() first")
        xv, xv_prev, xd = self._xv, self._xv_prev, self._xd
        y_eff = float(y)
        d = min(int(delay), len(self._issued)) if delay else 0
        if d > 0:  # x(k+d) = A^d x(k) + sum_j A^(d-1-j) B w(k-d+j), one product each
            w = np.array(list(self._issued)[-d:], dtype=float)
            wv, wd = w[:, 0] - self.input_offset, w[:, 1]
            P, AB = self._powers, self._AB
            x0 = xv + xd
            xv_prev = xv if d == 1 else P[d - 1] @ xv + AB[d - 2::-1].T @ wv[:-1]
            xv = P[d] @ xv + AB[d - 1::-1].T @ wv
            xd = P[d] @ xd + AB[d - 1::-1].T @ wd
            y_eff += float(self._c @ (xv + xd - x0))
        y_eff -= float(self._c @ xd)
        x = np.concatenate([xv - xv_prev, [y_eff]])
        return self.problem.solve(x, reference, u_prev=v_prev)

    def advance(self, v: float, d: float) -> None:
        """Advance the filter states with the command and dither applied over this period.

        Parameters
        ----------
        v, d : float
        """
        self._propagate(v, d)
        self._issued.append((float(v), float(d)))

    def _propagate(self, v: float, d: float) -> None:
        self._xv_prev = self._xv
        self._xv = self._A @ self._xv + self._B * (float(v) - self.input_offset)
        self._xd = self._A @ self._xd + self._B * float(d)

    def revise_last_input(self, delta: float) -> None:
        """The plant applied ``delta`` more than the last :meth:`advance` said (a live plant).

        Parameters
        ----------
        delta : float
            Applied input minus the input of the last :meth:`advance` (``v + d``).
        """
        if math.isfinite(delta) and delta != 0.0 and getattr(self, "_xv", None) is not None:
            self._xv = self._xv + self._B * float(delta)

    def __repr__(self) -> str:
        n = None if self.model is None else self.model.n_functions
        return f"MPCController(n_functions={n}, builds={self.n_builds})"

