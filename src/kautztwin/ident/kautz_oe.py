r"""Output-error identification of a discrete Kautz model from input/output data.

The twin's accurate path (:class:`kautztwin.twin.Updater`) and its initial
identification (:class:`kautztwin.twin.DigitalTwin`) call
:func:`identify_output_error`: the model is :math:`\hat y(k) = c^T x_f(k) + d`
on the delayed discrete Kautz network :math:`x_f(k+1) = A x_f(k) + B (u(k) - u_0)`,
its poles searched by variable projection (``c`` and ``d`` by linear least
squares for every candidate set of poles).  :func:`filter_states` (the
network's states for an input sequence) and :func:`continuous_poles` are the
two primitives the twin's update module shares with it.

The continuous-time counterpart for sampled records (transfer functions with
delay, several records, covariances) is
:class:`~kautztwin.ident.TransferFunctionEstimator`; the impulse/step-record
counterpart is :func:`kautztwin.optimize_poles`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from .._validation import check_choice, check_int, check_number, check_positive
from ..approx.model import KautzModel
from ..basis import KautzBasis
from ..basis._blocks import PAIR, REAL, discrete_matrices, parse_poles
from ..basis._propagate import discrete_functions
from ..exceptions import DataError, DimensionError
from ..metrics import fit_percent_or_nan

__all__ = ["OutputErrorFit", "continuous_poles", "filter_states", "identify_output_error"]

_FD_STEP = math.sqrt(np.finfo(float).eps)  # forward-difference step of the Jacobian


def filter_states(
    basis: KautzBasis, u: NDArray, x0: NDArray | None = None
) -> NDArray[np.float64]:
    """Filter states ``x(k)``, ``k = 0..n`` (``n + 1`` rows) of ``x(k+1) = A x(k) + B u(k)``.

    Exact convolution of the delayed basis sequences with ``u`` (FFT), plus the
    free response ``A^k x0``.

    Parameters
    ----------
    basis : KautzBasis
        A delayed discrete basis.
    u : ndarray of shape (n,)
        Input sequence (already centred on the operating point).
    x0 : ndarray of shape (n_functions,), optional
        Initial state (zeros when omitted).

    Returns
    -------
    ndarray of shape (n + 1, n_functions)
        Row ``k`` is the state at sample ``k``; the last row is the state after the input.
    """
    n = u.size
    k = np.arange(n + 1)
    F = basis.evaluate(k * basis.dt)  # delayed: F[:, 0] = 0, F[:, k] = A^{k-1} B
    X = _InputSpectrum(u).convolve(F)
    if x0 is not None and np.any(x0):
        X += discrete_functions(np.asarray(basis.A)[None], np.asarray(x0)[None], k)[0]
    return X.T


class _InputSpectrum:
    """An input's spectrum, kept to convolve many sequences with it (one FFT of ``u``).

    An output-error fit evaluates hundreds of bases on one input: the input's
    FFT is taken once here, each evaluation then costs the FFT of the basis
    sequences and one inverse FFT.
    """

    def __init__(self, u: NDArray) -> None:
        self.n = u.size
        self.size = scipy.fft.next_fast_len(max(2 * self.n, 1), real=True)  # no wrap-around
        self.spectrum = scipy.fft.rfft(u, self.size)

    def convolve(self, F: NDArray) -> NDArray[np.float64]:
        """Rows of ``F`` (``(m, n + 1)``) convolved with the input: its first ``n + 1`` samples."""
        Y = scipy.fft.rfft(F, self.size, axis=1) * self.spectrum
        return scipy.fft.irfft(Y, self.size, axis=1)[:, : self.n + 1]


def continuous_poles(basis: KautzBasis) -> NDArray[np.complex128]:
    """Continuous-time equivalents ``log(xi) / dt`` of a discrete basis' poles.

    Parameters
    ----------
    basis : KautzBasis
        A discrete basis (a continuous one returns its own poles).

    Returns
    -------
    ndarray of complex
    """
    if not basis.is_discrete:
        return np.array(basis.poles)
    out = []
    for p in basis.poles:
        mag = max(abs(p), 1e-12)
        if abs(p.imag) <= 1e-12 * max(1.0, abs(p)):
            out.append(complex(math.log(mag) / basis.dt))
        else:
            out.append(complex(math.log(mag), np.angle(p)) / basis.dt)
    return np.asarray(out)


@dataclass(frozen=True, eq=False)
class OutputErrorFit:
    r"""Result of :func:`identify_output_error`.

    Parameters
    ----------
    model : KautzModel
        Fitted model on a delayed discrete basis (``y = c^T x_f``).
    offset : float
        Fitted output offset ``d``.
    input_offset : float
        Input operating point :math:`u_0`: the model is
        :math:`\hat y = c^T x_f + d` with the filter driven by :math:`u - u_0`.
    fit_percent : float
        Simulation fit on the samples used (after the burn-in), percent.
    n_evaluations : int
        Residual evaluations (each evaluates every start, in one batch; the
        Jacobians evaluate no residual).
    success : bool
        Whether the search (of all starts together) met its tolerance.
    message : str
        The solver's message.
    """

    model: KautzModel
    offset: float
    input_offset: float
    fit_percent: float
    n_evaluations: int
    success: bool
    message: str

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Simulated output for an input sequence from a zero filter state.

        Parameters
        ----------
        u : array-like of shape (n_samples,)

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        u = np.asarray(u, dtype=float) - self.input_offset
        return filter_states(self.model.basis, u)[:-1] @ self.model.coefficients + self.offset


class _OEProblem:
    """Variable projection for output error: poles searched, ``c`` and ``d`` by least squares.

    The residual is ``y - X(x) theta(x)`` with ``theta`` the least-squares solution for the
    regressors ``X`` of the poles ``x``; :meth:`jacobian` is its Jacobian by Golub and
    Pereyra's formula, both terms, so the search takes the steps a difference Jacobian
    would (Kaufman's approximation, the first term alone, ended 1 of 162 captured
    re-identification fits on a worse optimum).  A Jacobian costs one batched evaluation
    of the perturbed basis sequences and one convolution instead of a residual evaluation
    per searched parameter.

    **Several starts as one problem.**  With ``n_starts`` > 1 the search vector holds one
    start's coordinates after another and the residual their residuals one after another:
    the starts do not interact (the Jacobian is block diagonal), so the joint minimum is
    every start's own minimum, and each step evaluates all starts in one batch (the basis
    sequences, the convolutions and the factorizations), which costs little more than one
    start: the evaluation is dominated by per-call overhead, not arithmetic.
    """

    def __init__(
        self, kinds: tuple[str, ...], u: NDArray, y: NDArray, dt: float, burn_in: int,
        fit_offset: bool, initial_state: bool = False, n_starts: int = 1,
    ) -> None:
        self.kinds = kinds
        self.u = u
        self.dt = dt
        self.n_starts = n_starts
        self._grid = np.arange(u.size + 1)
        self._spectrum = _InputSpectrum(u)
        use = np.isfinite(y)
        use[:burn_in] = False
        self.use = use
        self.y = y[use]
        self.fit_offset = fit_offset
        self.burn_in = burn_in
        self.initial_state = initial_state
        self.n_eval = 0
        self.upper: NDArray | None = None  # search bounds: a difference step stays inside
        self._last: tuple | None = None

    def block_params(self, xs: NDArray) -> NDArray[np.float64]:
        """z-plane block parameters of search points ``xs`` (one point per row)."""
        xs = np.atleast_2d(xs)
        out = np.empty_like(xs)
        for row, x in enumerate(xs):
            col = 0
            for kind in self.kinds:
                rate = math.exp(x[col]) * self.dt
                if kind == REAL:
                    out[row, col] = math.exp(-rate)
                    col += 1
                else:
                    z = np.exp(complex(-rate, x[col + 1] * self.dt))
                    out[row, col], out[row, col + 1] = z.real, abs(z.imag)
                    col += 2
        return out

    def sequences(self, xs: NDArray) -> NDArray[np.float64]:
        """Delayed basis sequences ``F[:, k] = A^{k-1} B`` of every row of ``xs``: (b, n_f, n + 1).

        The same values as ``basis(x).evaluate(k * dt)`` (one batched recursion for all rows).
        """
        A, B = discrete_matrices(self.kinds, self.block_params(xs))
        F = np.zeros((A.shape[0], A.shape[1], self._grid.size))
        F[:, :, 1:] = discrete_functions(A, B, self._grid[:-1])
        return F

    def _columns(self, F: NDArray, constant: float = 1.0) -> NDArray:
        """Regressors of the sequences ``F``, ``(n_f, n + 1)`` or a batch ``(b, n_f, n + 1)``.

        Columns ``[x_f, (free response), (1)]`` on the used samples, ``c`` first: the
        filter states are the sequences convolved with the input (the input's spectrum
        kept), the free response their undelayed values from the burn-in on.

        ``constant`` fills the offset's column (0 for derivatives of the regressors).
        """
        batch = F.reshape(-1, F.shape[-2], F.shape[-1])
        b, n_f, n_k = batch.shape
        X = self._spectrum.convolve(batch.reshape(b * n_f, n_k))[:, :-1]
        X = X.reshape(b, n_f, n_k - 1).transpose(0, 2, 1)
        cols = [X]
        if self.initial_state:  # the undelayed sequences A^(k - b) B from the first fitted k = b
            m = self.u.size - self.burn_in
            free = np.zeros_like(X)
            free[:, self.burn_in:] = batch[:, :, 1: m + 1].transpose(0, 2, 1)
            cols.append(free)
        if self.fit_offset:
            cols.append(np.full((b, n_k - 1, 1), constant))
        out = np.concatenate(cols, axis=2)[:, self.use]
        return out[0] if F.ndim == 2 else out

    def _fit(self, x: NDArray) -> tuple[NDArray, ...]:
        """``(F, X, theta, r, U, s, Vt)`` of every start at ``x``, kept for the Jacobian there.

        ``theta`` is the minimum-norm least-squares solution by the SVD of ``X`` with
        lstsq's rank rule (``rcond=None``); ``U, s, Vt`` are the SVD's factors of the kept
        rank, one per start (lists), ``r`` the residuals ``(n_starts, n_used)``.
        """
        if self._last is None or not np.array_equal(self._last[0], x):
            self.n_eval += 1
            F = self.sequences(np.reshape(x, (self.n_starts, -1)))
            X = self._columns(F)
            Us, Ss, Vts = [], [], []
            theta = np.empty((self.n_starts, X.shape[2]))
            factors = np.linalg.svd(X, full_matrices=False)
            for i, (U, s, Vt) in enumerate(zip(*factors, strict=True)):
                keep = s > s[0] * max(X.shape[1:]) * np.finfo(float).eps
                U, s, Vt = U[:, keep], s[keep], Vt[keep]
                theta[i] = Vt.T @ ((U.T @ self.y) / s)
                Us.append(U)
                Ss.append(s)
                Vts.append(Vt)
            r = self.y - np.einsum("skj,sj->sk", X, theta)
            self._last = (np.array(x, dtype=float), F, X, theta, r, Us, Ss, Vts)
        return self._last[1:]

    def costs(self, x: NDArray) -> NDArray[np.float64]:
        """Sum of squared residuals of every start at ``x``."""
        r = self._fit(x)[3]
        return np.einsum("sk,sk->s", r, r)

    def basis(self, x: NDArray, start: int = 0) -> KautzBasis:
        """The basis of one start at ``x`` (its coordinates: one per real pole, two per pair)."""
        per_start = sum(2 if kind == PAIR else 1 for kind in self.kinds)
        row = np.reshape(x, (-1, per_start))[start]
        return KautzBasis._from_blocks(self.kinds, self.block_params(row)[0], self.dt, True)

    def solve(self, x: NDArray, start: int = 0) -> tuple[KautzBasis, NDArray, NDArray]:
        """Basis, ``theta`` and fitted values (on the used samples) of one start at ``x``."""
        _, X, theta, *_ = self._fit(x)
        return self.basis(x, start), theta[start], X[start] @ theta[start]

    def residual(self, x: NDArray) -> NDArray:
        return self._fit(x)[3].ravel()

    def jacobian(self, x: NDArray) -> NDArray[np.float64]:
        r"""Jacobian of :meth:`residual` (Golub & Pereyra's variable-projection formula).

        With :math:`X_j = \partial X / \partial x_j`, :math:`X^+` the pseudo-inverse of
        the regressors, :math:`P^\perp = I - X X^+` and :math:`r` the residual, column
        :math:`j` is :math:`-P^\perp X_j \theta - (X^+)^T X_j^T r` (exact: ``theta``'s
        own change with :math:`x` is in it).  The derivatives of the basis sequences
        are forward differences in the search coordinates (step
        :math:`\sqrt{\epsilon}\max(1, |x_j|)`, as scipy's ``'2-point'``, backwards at
        the upper bound), all of them, for every start, from one batched recursion; no
        residual is evaluated again, which is what a difference Jacobian of the residual
        costs per searched parameter.  Several starts give a block-diagonal Jacobian.
        """
        F, X, theta, r, Us, Ss, Vts = self._fit(x)
        n_s = self.n_starts
        xs = np.reshape(x, (n_s, -1))
        n_x = xs.shape[1]
        step = _FD_STEP * np.maximum(1.0, np.abs(xs))
        if self.upper is not None:
            step = np.where(xs + step > self.upper, -step, step)
        points = (xs[:, None, :] + step[:, :, None] * np.eye(n_x)).reshape(n_s * n_x, n_x)
        dF = self.sequences(points).reshape(n_s, n_x, *F.shape[1:])
        dF = (dF - F[:, None]) / step[:, :, None, None]  # (n_s, n_x, n_f, n + 1)
        dX = self._columns(dF.reshape(n_s * n_x, *F.shape[1:]), constant=0.0)
        dX = dX.reshape(n_s, n_x, *X.shape[1:])  # (n_s, n_x, n_used, n_theta)
        n_used = X.shape[1]
        J = np.zeros((n_s * n_used, n_s * n_x))
        for i, (U, s, Vt) in enumerate(zip(Us, Ss, Vts, strict=True)):
            a = (dX[i] @ theta[i]).T  # column j: X_j theta
            g = np.einsum("jkp,k->pj", dX[i], r[i])  # column j: X_j^T r
            J[i * n_used: (i + 1) * n_used, i * n_x: (i + 1) * n_x] = (
                U @ (U.T @ a) - a - U @ ((Vt @ g) / s[:, None])
            )
        return J


def _oe_x(kinds: tuple[str, ...], params: NDArray) -> NDArray:
    """Search coordinates (log-rates, angular frequencies) of continuous block parameters."""
    x = np.array(params, dtype=float)
    col = 0
    for kind in kinds:
        x[col] = math.log(params[col])
        col += 2 if kind == PAIR else 1
    return x


def _oe_bounds(
    kinds: tuple[str, ...], n: int, dt: float, min_rate: float
) -> tuple[NDArray, NDArray]:
    lo, hi = [], []
    for kind in kinds:
        lo.append(math.log(min_rate))
        hi.append(math.log(10.0 / dt))
        if kind == PAIR:
            lo.append(1e-3 / (n * dt))
            hi.append(math.pi / dt * (1 - 1e-6))
    return np.array(lo), np.array(hi)


def identify_output_error(
    u: ArrayLike,
    y: ArrayLike,
    init: int | ArrayLike | KautzBasis,
    *,
    dt: float,
    burn_in: int = 0,
    fit_offset: bool = True,
    input_offset: float | None = None,
    min_rate: float | None = None,
    max_iter: int = 50,
    tol: float = 1e-8,
    initial_state: str = "zero",
) -> OutputErrorFit:
    r"""Output-error identification of a Kautz model from input/output data (variable projection).

    The model is :math:`\hat y(k) = c^T x_f(k) + d` with the delayed discrete
    Kautz network :math:`x_f(k+1) = A x_f(k) + B (u(k) - u_0)` started from
    rest at the first sample: exact when the plant starts at the equilibrium
    of the input ``u_0 = u[0]``.  For given poles :math:`c` and :math:`d` are the linear
    least-squares solution, so only the poles are searched
    (``scipy.optimize.least_squares`` over continuous-time log-rates and
    frequencies, so every iterate is stable, with Golub and Pereyra's
    variable-projection Jacobian: one batched evaluation of the perturbed basis
    sequences per Jacobian instead of a residual evaluation per searched
    parameter).  The first ``burn_in`` samples
    are left out of the error while the unknown initial state dies out.

    Parameters
    ----------
    u : array-like of shape (n_samples,)
        Input, finite.
    y : array-like of shape (n_samples,)
        Output; NaN samples are left out.
    init : int, array-like of complex, or KautzBasis
        Starting poles: continuous-time locations (``Re < 0``; their
        real/pair structure is kept), a 2-D array of them (one start per
        row, all of one structure), a basis (continuous, or discrete on
        ``dt``), or the number of real poles (then two spreads are tried).
        Several starts are searched together, as one problem whose residual
        is theirs one after another (one batched evaluation of all starts per
        step); the start that ends with the smallest error is returned.
    dt : float
        Sampling period, s.
    burn_in : int, default=0
        Samples left out at the start.
    fit_offset : bool, default=True
        Estimate the offset ``d``.
    input_offset : float, optional
        Input operating point :math:`u_0`; ``u[0]`` when omitted.
    min_rate : float, optional
        Slowest allowed decay rate of a pole, 1/s; ``3 / T`` (``T`` the record
        length) when omitted.  A mode that does not decay within the record
        cannot be told apart from the offset: without this bound the fit
        tends to spend a pole on it, which predicts badly once the plant
        changes.  The fastest rate is ``10 / dt``.
    max_iter : int, default=50
        Iteration budget: at most ``max_iter * (m + 1)`` evaluations, ``m``
        the number of searched coordinates of one start.
    tol : float, default=1e-8
        ``ftol``/``xtol``/``gtol`` of the solver.
    initial_state : {'zero', 'estimate'}, default='zero'
        ``'zero'``: the filters start from rest at the first sample (the
        state at sample ``burn_in`` is their response to the inputs before).
        ``'estimate'`` also fits the free response of an unknown state at
        sample ``burn_in``: for given poles it lies in the span of the
        undelayed basis sequences :math:`A^{k-b} B` started there, so it adds
        ``n_functions`` linear nuisance parameters (as
        :func:`~kautztwin.ident.identify_mimo` does from the first sample).
        For a window that starts where the plant's state is not the model's
        response to the earlier inputs: after a change of the plant, the
        burn-in ran on other dynamics.  ``fit_percent`` includes that
        response; the returned model predicts from its filter state, as always.

    Returns
    -------
    OutputErrorFit

    Raises
    ------
    DimensionError
        If ``u`` and ``y`` are not 1-D of one length.
    DataError
        If ``u`` is not finite or too few usable samples remain.
    PoleError
        If ``init`` holds invalid poles.

    See Also
    --------
    kautztwin.optimize_poles : The same variable projection for impulse/step records.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import identify_output_error
    >>> from kautztwin.twin.update import RecursiveKautzEstimator
    >>> rng = np.random.default_rng(1)
    >>> u = np.repeat(rng.uniform(-1, 1, 40), 10)
    >>> true = RecursiveKautzEstimator(np.exp([-0.2, -0.9]), dt=0.1, coef_init=[1.0, 0.3])
    >>> res = identify_output_error(u, true.simulate(u), [-1.0, -5.0], dt=0.1, input_offset=0.0)
    >>> np.round(np.sort(res.model.poles.real), 4), bool(res.fit_percent > 99.99)
    (array([0.4066, 0.8187]), True)
    """
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.ndim != 1 or u.shape != y.shape:
        raise DimensionError(
            f"u and y must be 1-D of one length, got shapes {u.shape} and {y.shape}"
        )
    if not np.all(np.isfinite(u)):
        raise DataError("u contains NaN or inf")
    dt = check_positive(dt, "dt")
    burn_in = check_int(burn_in, "burn_in", 0)
    n = u.size
    u0 = float(u[0]) if input_offset is None else check_number(input_offset, "input_offset")
    u = u - u0
    rate_lo = 3.0 / (n * dt) if min_rate is None else check_number(min_rate, "min_rate")
    if not 0 < rate_lo < 10.0 / dt:
        raise DataError(f"min_rate must lie in (0, 10 / dt), got {min_rate!r}")
    if isinstance(init, KautzBasis):
        starts = [parse_poles(continuous_poles(init), 0.0)]
    elif isinstance(init, int | np.integer) and not isinstance(init, bool):
        m = check_int(init, "init", 1)
        lo, hi = max(rate_lo, 3.0 / (n * dt)), 0.3 / dt
        centre = math.sqrt(lo * hi)
        starts = []
        for spread in (hi / lo, (hi / lo) ** 0.5):
            rates = centre * spread ** (np.linspace(-0.5, 0.5, m) if m > 1 else np.zeros(1))
            starts.append(((REAL,) * m, np.sort(rates)))
    else:
        try:
            rows = np.asarray(init) if np.ndim(init) == 2 else [init]
        except ValueError:  # ragged: parse_poles says what is wrong
            rows = [init]
        starts = [parse_poles(row, 0.0) for row in rows]
        if any(kinds != starts[0][0] for kinds, _ in starts):
            raise DataError(
                "the starts in init (its rows) must share one structure: the same number "
                "of real poles and complex pairs, in one order"
            )
    initial_state = check_choice(initial_state, "initial_state", ("zero", "estimate"))
    estimate_x0 = initial_state == "estimate"
    n_par = starts[0][1].size * (2 if estimate_x0 else 1) + int(bool(fit_offset))
    usable = int(np.isfinite(y[burn_in:]).sum())
    if usable < 2 * n_par + 2:
        raise DataError(
            f"{usable} usable samples after the burn-in are too few to fit {n_par} parameters"
        )
    kinds = starts[0][0]
    n_starts = len(starts)
    prob = _OEProblem(kinds, u, y, dt, burn_in, bool(fit_offset), estimate_x0, n_starts)
    lo_b, hi_b = _oe_bounds(kinds, n, dt, rate_lo)
    prob.upper = hi_b
    inside = (lo_b + 1e-6 * (hi_b - lo_b), hi_b - 1e-6 * (hi_b - lo_b))
    x0 = np.concatenate([np.clip(_oe_x(kinds, params), *inside) for _, params in starts])
    sol = scipy.optimize.least_squares(
        prob.residual, x0, jac=prob.jacobian, bounds=(np.tile(lo_b, n_starts),
                                                     np.tile(hi_b, n_starts)),
        method="trf", x_scale="jac",
        ftol=tol, xtol=tol, gtol=tol, max_nfev=max_iter * (lo_b.size + 1),
    )
    best = int(np.argmin(prob.costs(sol.x)))  # the first of equals, as one start after another
    basis, theta, fitted = prob.solve(sol.x, best)
    n_f = basis.n_functions
    offset = float(theta[-1]) if fit_offset else 0.0
    model = KautzModel(basis, theta[:n_f])
    if estimate_x0:
        yhat = fitted
    else:
        yhat = (filter_states(basis, u)[:-1] @ theta[:n_f] + offset)[prob.use]
    return OutputErrorFit(
        model=model, offset=offset, input_offset=u0, fit_percent=fit_percent_or_nan(prob.y, yhat),
        n_evaluations=prob.n_eval,
        success=bool(sol.success), message=str(sol.message),
    )

