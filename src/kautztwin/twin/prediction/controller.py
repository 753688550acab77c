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


class _FilterState:
    r"""The controller's filter states ``x_v, x_d`` of ``x(k+1) = A x(k) + B w(k)``, from rest.

    A state is advanced one sample at a time, except at every
    :data:`MAX_DELAY`-th input counted from the start of the history (a
    block boundary): there it is the block map from the last boundary,

    .. math::

        x(jL) = A^L x((j-1)L) + \sum_{i=0}^{L-1} A^{L-1-i} B\, w((j-1)L + i),

    the predictor's formula of :meth:`MPCController.solve`.  The states are
    thus a fixed function of the history, whatever sample they were built at:
    a controller built on the first ``n`` inputs and advanced over the rest
    holds the states of one built on the whole history, bit for bit, while a
    build costs one product per block and at most ``L`` single steps instead
    of a Python step per input of the history.  Both ways agree with the
    plain recursion to rounding (the block map is the same sum).
    """

    __slots__ = ("A", "B", "PL", "M", "xv", "xv_prev", "xd", "x0", "buf", "nb")

    def __init__(self, A: NDArray, B: NDArray, PL: NDArray, M: NDArray) -> None:
        n = A.shape[0]
        self.A, self.B, self.PL, self.M = A, B, PL, M
        self.xv, self.xv_prev, self.xd = np.zeros(n), np.zeros(n), np.zeros(n)
        self.x0 = np.zeros((n, 2))  # [x_v, x_d] at the last block boundary
        self.buf = np.empty((MAX_DELAY, 2))  # [v - offset, d] since then
        self.nb = 0

    @classmethod
    def from_history(
        cls, A: NDArray, B: NDArray, PL: NDArray, M: NDArray, wv: NDArray, wd: NDArray
    ) -> _FilterState:
        """The states after the inputs ``wv`` (command less the offset) and ``wd`` (dither)."""
        f = cls(A, B, PL, M)
        n = int(wv.size)
        first = MAX_DELAY * ((n - 1) // MAX_DELAY) if n else 0  # last boundary before input n
        w = np.stack([wv, wd], axis=1)
        for j in range(0, first, MAX_DELAY):
            f.buf[:] = w[j:j + MAX_DELAY]  # the buffer the online advance fills
            f._close_block()
        for v, d in w[first:].tolist():
            f.advance(v, d)
        return f

    def copy(self) -> _FilterState:
        """An independent copy (the matrices are shared: they are never written)."""
        f = _FilterState(self.A, self.B, self.PL, self.M)
        f.xv, f.xv_prev, f.xd = self.xv, self.xv_prev, self.xd
        f.x0, f.buf, f.nb = self.x0.copy(), self.buf.copy(), self.nb
        return f

    def advance(self, wv: float, wd: float) -> None:
        """One input: ``wv`` the command less the input offset, ``wd`` the dither."""
        i = self.nb
        self.buf[i, 0] = wv
        self.buf[i, 1] = wd
        self.xv_prev = self.xv
        if i + 1 == MAX_DELAY:
            self._close_block()
        else:
            self.xv = self.A @ self.xv + self.B * wv
            self.xd = self.A @ self.xd + self.B * wd
            self.nb = i + 1

    def revise_last(self, delta: float) -> None:
        """The last input's command was ``delta`` larger than advanced."""
        self.xv = self.xv + self.B * delta
        if self.nb:  # at a boundary the closed block already holds the input
            self.buf[self.nb - 1, 0] += delta
        else:
            self.x0[:, 0] = self.xv

    def _close_block(self) -> None:
        x = self.PL @ self.x0 + self.M @ self.buf
        self.x0 = x
        self.xv, self.xd = x[:, 0].copy(), x[:, 1].copy()
        self.nb = 0


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
    powers: NDArray[np.float64]
    AB: NDArray[np.float64]
    filter: _FilterState
    n: int
    v_tail: NDArray[np.float64]
    d_tail: NDArray[np.float64]

    @property
    def xv(self) -> NDArray[np.float64]:
        """Command-driven filter state ``x_v(n)``."""
        return self.filter.xv

    @property
    def xv_prev(self) -> NDArray[np.float64]:
        """``x_v(n - 1)``."""
        return self.filter.xv_prev

    @property
    def xd(self) -> NDArray[np.float64]:
        """Dither-driven filter state ``x_d(n)``."""
        return self.filter.xd


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
    d = np.asarray(d_history, dtype=float)
    powers, AB = _delay_maps(A, B)
    M = np.ascontiguousarray(AB[::-1].T)  # column i: A^(L-1-i) B
    filt = _FilterState.from_history(A, B, powers[MAX_DELAY], M, v_raw - input_offset, d)
    return _PreparedController(model, settings, problem, A, B, c, powers, AB, filt,
                               int(v_raw.size), v_raw[-MAX_DELAY:].copy(), d[-MAX_DELAY:].copy())


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

        The advance is the one of :class:`_FilterState`, so the states equal
        those of a :meth:`rebuild` on the whole history, bit for bit.
        """
        if not self._issued and prepared.n:  # the first build: the inputs sent before it
            v_tail, d_tail = prepared.v_tail, prepared.d_tail
            self._issued.extend(zip(v_tail.tolist(), d_tail.tolist(), strict=True))
        self.problem = prepared.problem
        self.model = prepared.model
        self.settings = prepared.settings
        self._c = prepared.c
        self._powers, self._AB = prepared.powers, prepared.AB
        self._filter = prepared.filter.copy()  # a prepared controller may be installed again
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
        f = self._filter
        xv, xv_prev, xd = f.xv, f.xv_prev, f.xd
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
        self._filter.advance(float(v) - self.input_offset, float(d))

    def revise_last_input(self, delta: float) -> None:
        """The plant applied ``delta`` more than the last :meth:`advance` said (a live plant).

        Parameters
        ----------
        delta : float
            Applied input minus the input of the last :meth:`advance` (``v + d``).
        """
        if math.isfinite(delta) and delta != 0.0 and getattr(self, "_filter", None) is not None:
            self._filter.revise_last(float(delta))

    def __repr__(self) -> str:
        n = None if self.model is None else self.model.n_functions
        return f"MPCController(n_functions={n}, builds={self.n_builds})"

