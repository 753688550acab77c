r"""Output-error identification of a MIMO Kautz model by variable projection.

For fixed poles every output is linear in its coefficients: with the filter states
:math:`X_j` of input ``j`` (the delayed Kautz network driven by :math:`u_j - u_{0,j}`,
:func:`~kautztwin.ident.kautz_oe.filter_states`) the simulated outputs are
:math:`\hat Y = [X_1 \cdots X_m\ 1]\,\Theta`, and the coefficient matrices and offsets
:math:`\Theta` are one least-squares solve with a right-hand side per output.  Only the
poles are searched (``scipy.optimize.least_squares`` over continuous-time log-rates and
frequencies, the parametrisation of :func:`~kautztwin.ident.identify_output_error`): once
over one *shared* set, or once per output (*per-output* poles, a MISO problem each).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_choice, check_int, check_number, check_positive
from ...basis import KautzBasis
from ...basis._blocks import PAIR, REAL, parse_poles
from ...exceptions import DataError, DimensionError
from ..kautz_oe import _oe_bounds, _oe_x, _OEProblem, continuous_poles
from .model import MIMOKautzModel

__all__ = ["MIMOFit", "check_mimo_data", "identify_mimo"]

_STRUCTURES = ("shared", "per_output")
_INITIAL = ("zero", "estimate")


def check_mimo_data(u: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate a MIMO input/output record; return ``u, y`` as (n_samples, channels) arrays.

    Parameters
    ----------
    u : array-like of shape (n_samples, n_inputs) or (n_samples,)
    y : array-like of shape (n_samples, n_outputs) or (n_samples,)

    Returns
    -------
    u, y : ndarray of shape (n_samples, n_inputs), (n_samples, n_outputs)

    Raises
    ------
    DimensionError
        If a signal is not 1-D or 2-D.
    DataError
        If the lengths differ, a value is NaN or inf, or a channel is constant.
    """
    arrays = []
    for name, x in (("u", u), ("y", y)):
        a = np.asarray(x, dtype=float)
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2 or 0 in a.shape:
            raise DimensionError(
                f"{name} must be 1-D or 2-D (n_samples, n_channels) and non-empty, "
                f"got shape {a.shape}"
            )
        arrays.append(a)
    u2, y2 = arrays
    if u2.shape[0] != y2.shape[0]:
        raise DataError(
            f"u and y must have one length: u has {u2.shape[0]} samples, y {y2.shape[0]}"
        )
    for name, a in (("u", u2), ("y", y2)):
        bad = ~np.isfinite(a)
        if bad.any():
            k, c = (int(i) for i in np.argwhere(bad)[0])
            raise DataError(f"{name}[{k}, {c}] is {a[k, c]}: the record must be finite")
        flat = np.flatnonzero(np.ptp(a, axis=0) == 0)
        if flat.size:
            raise DataError(
                f"{name}[:, {int(flat[0])}] is constant: a channel without variation cannot be "
                "identified (drop it, or excite it)"
            )
    return u2, y2


@dataclass(frozen=True, eq=False)
class MIMOFit:
    """Result of :func:`identify_mimo`.

    Parameters
    ----------
    model : MIMOKautzModel
        The fitted model (filters from rest at the first sample).
    fit_percent : ndarray of shape (n_outputs,)
        Simulation fit per output on the samples used (after the burn-in; with the
        estimated initial response when ``initial_state='estimate'``), percent.
    initial_coefficients : tuple of ndarray
        Per output, the weights of the undelayed basis sequences :math:`A^k B` that make up
        the free response of the record's unknown initial state (zeros with
        ``initial_state='zero'``).
    n_evaluations : int
        Residual evaluations over all starts and outputs.
    success : bool
        Whether every search met its tolerance.
    message : str
        The solver's message (per output for per-output poles).
    cost : float
        Final value of the search's cost (half the sum of squared scaled errors).
    """

    model: MIMOKautzModel
    fit_percent: NDArray[np.float64]
    initial_coefficients: tuple[NDArray[np.float64], ...]
    n_evaluations: int
    success: bool
    message: str
    cost: float = float("nan")

    def initial_response(self, n_samples: int) -> NDArray[np.float64]:
        """Free response of the estimated initial state over ``n_samples`` samples.

        Parameters
        ----------
        n_samples : int

        Returns
        -------
        ndarray of shape (n_samples, n_outputs)
        """
        n_samples = check_int(n_samples, "n_samples", 0)
        out = np.zeros((n_samples, self.model.n_outputs))
        for i, (b, c) in enumerate(zip(self.model.bases, self.initial_coefficients, strict=True)):
            if np.any(c):
                out[:, i] = c @ b.evaluate(np.arange(1, n_samples + 1) * b.dt)
        return out

    def simulate(self, u: ArrayLike, *, initial: bool = True) -> NDArray[np.float64]:
        """Simulation of ``u`` from the estimation record's initial state, or from rest.

        Parameters
        ----------
        u : array-like of shape (n_samples, n_inputs)
            The estimation input, or a continuation of it (``initial=True``), or any input.
        initial : bool, default=True
            Add the estimated initial response (it belongs to the estimation record only).

        Returns
        -------
        ndarray of shape (n_samples, n_outputs)
        """
        yhat = np.atleast_2d(self.model.simulate(np.asarray(u, dtype=float)).T).T
        if initial:
            yhat = yhat + self.initial_response(yhat.shape[0])
        return yhat


class _Regressors:
    """Regressor matrix ``[X_1 .. X_m (1) (F)]`` of a basis for a centred input record."""

    def __init__(self, v: NDArray, fit_offset: bool, estimate_x0: bool) -> None:
        self.v = v
        self.fit_offset = fit_offset
        self.estimate_x0 = estimate_x0

    def matrix(self, basis: KautzBasis) -> NDArray[np.float64]:
        n, m = self.v.shape
        # filter_states for all inputs at once: one evaluation of the delayed sequences
        # F[:, k] = A^{k-1} B (F[:, 0] = 0) and one batched exact convolution
        F = basis.evaluate(np.arange(n + 1) * basis.dt)
        X = scipy.signal.fftconvolve(F[None, :, :n], self.v.T[:, None, :], axes=2)[:, :, :n]
        cols = [X.transpose(2, 0, 1).reshape(n, m * basis.n_functions)]
        if self.fit_offset:
            cols.append(np.ones((n, 1)))
        if self.estimate_x0:
            # the free response of every output lies in the span of the undelayed sequences
            # A^k B: one column per basis function (exact when the plant is in the model set)
            cols.append(F[:, 1:].T)
        return np.hstack(cols)


class _MIMOProblem(_OEProblem):
    """Variable projection over one pole set for the outputs ``y`` (columns), scaled."""

    def __init__(
        self, kinds: tuple[str, ...], reg: _Regressors, y: NDArray, dt: float, use: NDArray,
    ) -> None:
        self.kinds = kinds
        self.dt = dt
        self.reg = reg
        self.use = use
        self.y = y[use]
        self.scale = np.maximum(np.std(self.y, axis=0), 1e-300)
        self.n_eval = 0

    def solve(self, x: NDArray) -> tuple[KautzBasis, NDArray, NDArray]:  # type: ignore[override]
        self.n_eval += 1
        basis = self.basis(x)
        X = self.reg.matrix(basis)[self.use]
        theta, *_ = np.linalg.lstsq(X, self.y / self.scale, rcond=None)
        return basis, theta * self.scale, (self.y / self.scale - X @ theta).ravel()

    def residual(self, x: NDArray) -> NDArray:
        """Scaled residuals of all outputs (the search differentiates it numerically)."""
        return self.solve(x)[2]


def _real_starts(m: int, lo: float, hi: float) -> list[tuple[tuple[str, ...], NDArray]]:
    """Log-spaced real rates over two spreads of ``[lo, hi]`` (as the SISO fit starts)."""
    centre = math.sqrt(lo * hi)
    starts = []
    for spread in (hi / lo, (hi / lo) ** 0.5):
        rates = centre * spread ** (np.linspace(-0.5, 0.5, m) if m > 1 else np.zeros(1))
        starts.append(((REAL,) * m, np.sort(rates)))
    return starts


def _starts(
    init: object, n: int, dt: float, rate_lo: float
) -> list[tuple[tuple[str, ...], NDArray]]:
    """Block kinds and continuous parameters of every start for one pole search."""
    if isinstance(init, KautzBasis):
        return [parse_poles(continuous_poles(init), 0.0)]
    if isinstance(init, int | np.integer) and not isinstance(init, bool):
        m = check_int(init, "n_poles", 1)
        return _real_starts(m, max(rate_lo, 3.0 / (n * dt)), 0.3 / dt)
    return [parse_poles(init, 0.0)]


def _search(
    starts: list[tuple[tuple[str, ...], NDArray]], reg: _Regressors, y: NDArray, dt: float,
    use: NDArray, n: int, rate_lo: float, max_iter: int, tol: float,
) -> tuple[KautzBasis, NDArray, float, int, bool, str]:
    """Best of the starts: ``(basis, theta, cost, n_evaluations, success, message)``."""
    best = None
    n_eval = 0
    for kinds, params in starts:
        prob = _MIMOProblem(kinds, reg, y, dt, use)
        lo_b, hi_b = _oe_bounds(kinds, n, dt, rate_lo)
        span = hi_b - lo_b
        x0 = np.clip(_oe_x(kinds, params), lo_b + 1e-6 * span, hi_b - 1e-6 * span)
        sol = scipy.optimize.least_squares(
            prob.residual, x0, bounds=(lo_b, hi_b), method="trf", x_scale="jac",
            ftol=tol, xtol=tol, gtol=tol, max_nfev=max_iter * (x0.size + 1),
        )
        n_eval += prob.n_eval
        if best is None or sol.cost < best[0].cost:
            best = (sol, prob)
    sol, prob = best
    basis, theta, _ = prob.solve(sol.x)
    return basis, theta, float(sol.cost), n_eval, bool(sol.success), str(sol.message)


def _fit_percent(y: NDArray, yhat: NDArray) -> NDArray[np.float64]:
    err = np.linalg.norm(y - yhat, axis=0)
    spread = np.linalg.norm(y - y.mean(axis=0), axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return 100.0 * (1.0 - err / spread)


def identify_mimo(
    u: ArrayLike,
    y: ArrayLike,
    init: int | ArrayLike | KautzBasis | list,
    *,
    dt: float,
    poles: str = "shared",
    burn_in: int = 0,
    initial_state: str = "zero",
    fit_offset: bool = True,
    input_offset: ArrayLike | None = None,
    min_rate: float | None = None,
    max_iter: int = 50,
    tol: float = 1e-8,
) -> MIMOFit:
    r"""Output-error identification of a MIMO Kautz model (variable projection over the poles).

    Every output is :math:`\hat y_i = y_{0,i} + \sum_j c_{ij}^T x_j`, with :math:`x_j` the
    delayed discrete Kautz network driven by input ``j`` from rest at the first sample (exact
    when the plant starts at the equilibrium of :math:`u_0`).  For given poles the
    coefficients and offsets are linear least squares; the poles are searched, shared by
    all outputs or separately per output.  The error of each output is divided by its
    standard deviation, so every output counts alike in the shared search.

    Parameters
    ----------
    u : array-like of shape (n_samples, n_inputs)
        Input record (1-D: one input), finite, no constant channel.
    y : array-like of shape (n_samples, n_outputs)
        Output record (1-D: one output), finite, no constant channel.
    init : int, array-like of complex, KautzBasis, or list of these
        Starting poles: the number of real poles (several spreads are tried), continuous-time
        locations (``Re < 0``; their real/pair structure is kept) or a basis.  With
        ``poles='per_output'`` a list gives one entry per output.
    dt : float
        Sampling period, s.
    poles : {'shared', 'per_output'}, default='shared'
        One pole set for all outputs, or one per output (more parameters; better when the
        outputs have different dynamics).
    burn_in : int, default=0
        Samples left out of the error at the start, while an unknown initial state dies out.
    initial_state : {'zero', 'estimate'}, default='zero'
        ``'estimate'`` adds each output's free response (the span of the undelayed basis
        sequences, linear) to the fit: for records that do not start at rest.
    fit_offset : bool, default=True
        Estimate the output offsets.
    input_offset : array-like of shape (n_inputs,), optional
        Input operating point; ``u[0]`` when omitted.
    min_rate : float, optional
        Slowest decay rate of a pole, 1/s; ``3 / T`` (record length ``T``) when omitted.
    max_iter : int, default=50
        Iteration budget per start.
    tol : float, default=1e-8
        ``ftol``/``xtol``/``gtol`` of the solver.

    Returns
    -------
    MIMOFit

    Raises
    ------
    DimensionError
        If a signal is not 1-D or 2-D, or ``input_offset`` has the wrong length.
    DataError
        If the lengths differ, a value is not finite, a channel is constant, or the record
        is too short for the parameters asked.

    See Also
    --------
    identify_output_error : The single-input single-output fit this generalises.
    MIMOKautzEstimator : Order and structure chosen on held-out data.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin import KautzBasis
    >>> from kautztwin.ident.mimo import MIMOKautzModel, identify_mimo
    >>> rng = np.random.default_rng(0)
    >>> true = MIMOKautzModel(KautzBasis([0.95, 0.7], dt=1.0, delayed=True),
    ...                       rng.normal(size=(2, 2, 2)))
    >>> u = np.repeat(rng.uniform(-1, 1, (60, 2)), 10, axis=0)
    >>> fit = identify_mimo(u, true.simulate(u), 2, dt=1.0, input_offset=[0.0, 0.0])
    >>> np.round(np.sort(fit.model.poles.real), 6), bool(fit.fit_percent.min() > 99.99)
    (array([0.7 , 0.95]), True)
    """
    u2, y2 = check_mimo_data(u, y)
    dt = check_positive(dt, "dt")
    poles = check_choice(poles, "poles", _STRUCTURES)
    n, n_in = u2.shape
    n_out = y2.shape[1]
    u0 = _input_offset(input_offset, u2)
    rate_lo = _rate_lo(min_rate, n, dt)
    if poles == "per_output" and isinstance(init, list):
        if len(init) != n_out:
            raise DimensionError(f"init lists {len(init)} entries for {n_out} outputs")
        inits = list(init)
    else:
        inits = [init] * (n_out if poles == "per_output" else 1)
    all_starts = [_starts(i, n, dt, rate_lo) for i in inits]
    return _fit_record(
        u2, y2, all_starts, dt=dt, u0=u0, rate_lo=rate_lo, burn_in=burn_in,
        initial_state=initial_state, fit_offset=fit_offset, max_iter=max_iter, tol=tol,
    )


def _input_offset(input_offset: ArrayLike | None, u2: NDArray) -> NDArray[np.float64]:
    if input_offset is None:
        return u2[0].copy()
    u0 = np.atleast_1d(np.asarray(input_offset, dtype=float))
    if u0.shape != (u2.shape[1],):
        raise DimensionError(f"input_offset has shape {u0.shape}; expected ({u2.shape[1]},)")
    for k, val in enumerate(u0):
        check_number(val, f"input_offset[{k}]")
    return u0


def _rate_lo(min_rate: float | None, n: int, dt: float) -> float:
    rate_lo = 3.0 / (n * dt) if min_rate is None else check_number(min_rate, "min_rate")
    if not 0 < rate_lo < 10.0 / dt:
        raise DataError(f"min_rate must lie in (0, 10 / dt), got {min_rate!r}")
    return rate_lo


def _fit_record(
    u2: NDArray, y2: NDArray, all_starts: list, *, dt: float, u0: NDArray, rate_lo: float,
    burn_in: int, initial_state: str, fit_offset: bool, max_iter: int, tol: float,
) -> MIMOFit:
    """The fit of :func:`identify_mimo` on checked data: one pole search per start group.

    ``all_starts`` holds one list of starts for the shared set, or one per output.
    """
    initial_state = check_choice(initial_state, "initial_state", _INITIAL)
    burn_in = check_int(burn_in, "burn_in", 0)
    max_iter = check_int(max_iter, "max_iter", 1)
    tol = check_positive(tol, "tol")
    n, n_in = u2.shape
    n_out = y2.shape[1]
    use = np.ones(n, bool)
    use[:burn_in] = False
    usable = int(use.sum())
    estimate_x0 = initial_state == "estimate"
    for starts in all_starts:
        n_f = sum(2 if k == PAIR else 1 for k in starts[0][0])
        n_par = n_f * (n_in + int(estimate_x0)) + int(bool(fit_offset)) + starts[0][1].size
        if usable < 2 * n_par + 2:
            raise DataError(
                f"{usable} usable samples after the burn-in are too few to fit {n_par} "
                f"parameters per output (at least {2 * n_par + 2} needed)"
            )
    reg = _Regressors(u2 - u0, bool(fit_offset), estimate_x0)
    groups = [list(range(n_out))] if len(all_starts) == 1 else [[i] for i in range(n_out)]
    bases: list[KautzBasis] = [None] * n_out  # type: ignore[list-item]
    coefs: list[NDArray] = [None] * n_out  # type: ignore[list-item]
    y0 = np.zeros(n_out)
    yhat = np.empty_like(y2)
    x0_coef: list[NDArray] = [np.zeros(0)] * n_out
    total_cost = 0.0
    n_eval, success, messages = 0, True, []
    for outputs, starts in zip(groups, all_starts, strict=True):
        basis, theta, cost, ne, ok, msg = _search(
            starts, reg, y2[:, outputs], dt, use, n, rate_lo, max_iter, tol
        )
        total_cost += cost
        n_eval += ne
        success &= ok
        messages.append(msg)
        n_f = basis.n_functions
        X = reg.matrix(basis)
        yhat[:, outputs] = X @ theta
        col = n_in * n_f
        if fit_offset:
            y0[outputs] = theta[col]
            col += 1
        for k, i in enumerate(outputs):
            bases[i] = basis
            coefs[i] = theta[: n_in * n_f, k].reshape(n_in, n_f)
            x0_coef[i] = theta[col:, k].copy() if estimate_x0 else np.zeros(n_f)
    model = MIMOKautzModel(bases if len(groups) > 1 else bases[0], coefs, u0, y0)
    return MIMOFit(
        model=model,
        fit_percent=_fit_percent(y2[use], yhat[use]),
        initial_coefficients=tuple(x0_coef),
        n_evaluations=n_eval,
        success=bool(success),
        message=messages[0] if len(messages) == 1 else "; ".join(
            f"output {i}: {m}" for i, m in enumerate(messages)
        ),
        cost=total_cost,
    )
