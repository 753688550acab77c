r"""Fast path of the twin's update module: recursive least squares on Kautz-filtered regressors.

:class:`RecursiveKautzEstimator` drives the delayed discrete Kautz network with
the input, :math:`x_f(k+1) = A x_f(k) + B u(k)` (kautz-math.md 3.2), and
follows :math:`y(k) \approx c^T x_f(k) + d` by recursive least squares with
exponential forgetting: :math:`O(N^2)` per sample, about 12 microseconds for four
functions and the offset (``benchmarks/bench_update.py``: 1.9x faster than refitting the
forgetting factor's memory by least squares at every sample).

Two options serve a nonlinear plant (the hydraulic profile uses both): a **quadratic input
channel**, a second bank of the same filters driven by :math:`(u - u_0)^2 / s`, so that the
linear model's local gain may follow the operating point; and **directional forgetting**,
which forgets only the information along the current regressor, so that directions the
closed loop does not excite keep theirs instead of winding up.
:meth:`RecursiveKautzEstimator.set_directional` switches the mode: the twin's
:class:`~kautztwin.twin.update.Updater` forgets exponentially while it is desynchronised.

Size: the module passes 600 lines because it is the one class, and the class carries its
scikit-learn-style documentation (about half of its lines are docstrings) for both options.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_number, check_positive
from ...approx.model import KautzModel
from ...basis import KautzBasis
from ...exceptions import DataError, DimensionError, NotFittedError
from ...ident.kautz_oe import filter_states
from ..digital.discretize import _delayed_basis, discretize_model

__all__ = ["RecursiveKautzEstimator"]


class RecursiveKautzEstimator:
    r"""Recursive least squares with forgetting on Kautz-filtered regressors.

    The input drives the delayed discrete Kautz network on the sampling
    period, :math:`x_f(k+1) = A x_f(k) + B u(k)`, whose states are the
    regressors; the output is modelled as :math:`y(k) \approx c^T x_f(k) + d`
    (``d`` only with ``fit_offset``).  Each :meth:`update` makes the a-priori
    prediction, corrects :math:`\theta = [c; d]` with the standard RLS gain and
    advances the filter:

    .. math::

        g = \frac{P\varphi}{\lambda + \varphi^T P \varphi},\quad
        \theta \leftarrow \theta + g\,(y - \varphi^T\theta),\quad
        P \leftarrow (P - g\,\varphi^T P)/\lambda .

    Anti-windup: with forgetting and poor excitation :math:`P` grows like
    :math:`\lambda^{-k}` in the unexcited directions; its trace is therefore
    clamped to ``max_trace`` (scaling :math:`P` down, counted in
    ``n_clamped_``), and :meth:`reset_covariance` restarts it.

    With ``quadratic_scale`` :math:`s` the regressors gain a second bank of the
    same filters, :math:`x_q(k+1) = A x_q(k) + B (u(k) - u_0)^2 / s`, and the
    output model becomes :math:`y \approx c^T x_f + d + c_q^T x_q`: a
    Hammerstein-type correction whose linearisation at the input :math:`u`
    has the coefficients :math:`c + 2 (u - u_0) c_q / s`.  ``coef_`` and
    ``model_`` are the linear part; :attr:`parameters_` is
    :math:`[c; d; c_q]`.

    With ``directional`` the forgetting acts only along the regressor
    (Kulhavy's directional forgetting): with the information matrix
    :math:`R = P^{-1}`, each measurement first removes the share
    :math:`1 - \lambda` of the information along :math:`\varphi`,

    .. math::

        R \leftarrow R - (1-\lambda)\,\frac{R\varphi\varphi^T R}{\varphi^T R \varphi},
        \qquad
        P \leftarrow P + \frac{1-\lambda}{\lambda\,\varphi^T R\varphi}\,\varphi\varphi^T,

    then adds the measurement's (the standard update with :math:`\lambda = 1`).
    The information in directions the input does not excite is kept, so the
    covariance cannot wind up there.

    Size: the class is over 400 lines for its scikit-learn-style documentation (about
    half of it is docstrings); the recursion itself is :meth:`update` and ``_correct``.

    Parameters
    ----------
    poles : array-like of complex or KautzBasis
        Discrete pole locations (``|p| < 1``) on the period ``dt``, or a basis
        (a continuous one is discretised with poles ``exp(p dt)``).
    dt : float, default=1.0
        Sampling period, s.
    forgetting : float, default=0.99
        Forgetting factor :math:`\lambda \in (0, 1]`; the memory is about
        :math:`1/(1-\lambda)` samples.
    delta : float, default=100.0
        Initial covariance :math:`P = \delta I` (large: little trust in ``coef_init``).
    max_trace : float, default=1e4
        Anti-windup bound on :math:`\operatorname{tr} P`.
    fit_offset : bool, default=True
        Estimate the output offset ``d``.
    coef_init : array-like of shape (n_functions,), optional
        Initial coefficients ``c`` (zeros when omitted).
    offset_init : float, default=0.0
        Initial offset ``d``.
    input_offset : float, default=0.0
        Operating point :math:`u_0` of the input: the filter is driven by
        :math:`u - u_0`.  Centring the input keeps the regressors nearly
        orthogonal to the constant of the offset, which the recursion needs
        when the input varies little around a large mean.
    quadratic_scale : float, optional
        Input scale :math:`s > 0` of a quadratic input channel (a second filter
        bank driven by :math:`(u - u_0)^2 / s`; its coefficients start at zero);
        ``None``: none.  The input's usual amplitude keeps both channels'
        regressors of one size.
    directional : bool, default=False
        Forget only along the regressor (see above) instead of exponentially
        in every direction.

    Attributes
    ----------
    basis_ : KautzBasis
        The delayed discrete basis.
    coef_ : ndarray of shape (n_functions,)
        Current coefficients ``c``.
    offset_ : float
        Current offset ``d`` (0 without ``fit_offset``).
    covariance_ : ndarray of shape (n_params, n_params)
        Current :math:`P` (a copy).
    state_ : ndarray of shape (n_functions,) or (2 n_functions,)
        Current filter state :math:`x_f(k)`, followed by :math:`x_q(k)` with
        the quadratic channel (a copy).
    quadratic_coef_ : ndarray of shape (n_functions,) or (0,)
        Coefficients :math:`c_q` of the quadratic channel (empty without it).
    n_updates_ : int
        Measurements used since the last reset.
    n_clamped_ : int
        Times the covariance trace was clamped.

    Raises
    ------
    DataError
        On an invalid parameter (at the first use, as scikit-learn estimators do).

    See Also
    --------
    Updater : Runs this estimator as the twin's fast path.
    kautztwin.KautzBasis : The basis and its network realisation.

    Notes
    -----
    The regressors are orthonormal filters, so for a white input their
    covariance is the identity and the recursion is well conditioned.  A
    system whose pulse response lies in the span of the basis (its poles
    among the basis poles) is recovered exactly from noise-free data.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.twin.update import RecursiveKautzEstimator
    >>> rng = np.random.default_rng(0)
    >>> u = rng.standard_normal(400)
    >>> true = RecursiveKautzEstimator([0.5, 0.8], dt=0.1, coef_init=[1.0, -0.5], offset_init=2.0)
    >>> y = true.simulate(u)
    >>> est = RecursiveKautzEstimator([0.5, 0.8], dt=0.1, forgetting=1.0, delta=1e6).fit(u, y)
    >>> np.round(est.coef_, 4), round(est.offset_, 4)
    (array([ 1. , -0.5]), 2.0)
    """

    def __init__(
        self,
        poles: ArrayLike | KautzBasis,
        *,
        dt: float = 1.0,
        forgetting: float = 0.99,
        delta: float = 100.0,
        max_trace: float = 1e4,
        fit_offset: bool = True,
        coef_init: ArrayLike | None = None,
        offset_init: float = 0.0,
        input_offset: float = 0.0,
        quadratic_scale: float | None = None,
        directional: bool = False,
    ) -> None:
        self.poles = poles
        self.dt = dt
        self.forgetting = forgetting
        self.delta = delta
        self.max_trace = max_trace
        self.fit_offset = fit_offset
        self.coef_init = coef_init
        self.offset_init = offset_init
        self.input_offset = input_offset
        self.quadratic_scale = quadratic_scale
        self.directional = directional

    # ------------------------------------------------------------------ setup
    def _check_params(self) -> None:
        check_positive(self.dt, "dt")
        lam = check_number(self.forgetting, "forgetting")
        if not 0 < lam <= 1:
            raise DataError(f"forgetting must lie in (0, 1], got {self.forgetting!r}")
        for name in ("delta", "max_trace"):
            check_positive(getattr(self, name), name)
        for name in ("offset_init", "input_offset"):
            check_number(getattr(self, name), name)
        if self.quadratic_scale is not None:
            check_positive(self.quadratic_scale, "quadratic_scale")
        if not isinstance(self.directional, bool | np.bool_):
            raise DataError(f"directional must be True or False, got {self.directional!r}")

    def reset(self) -> RecursiveKautzEstimator:
        """(Re)initialise: basis, ``theta`` from the initial values, ``P = delta I``, zero state.

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.

        Raises
        ------
        DataError
            On an invalid parameter.
        DimensionError
            If ``coef_init`` does not have one entry per basis function.
        """
        self._check_params()
        basis = _delayed_basis(self.poles, float(self.dt))
        n = basis.n_functions
        coef = np.zeros(n) if self.coef_init is None else np.asarray(self.coef_init, float)
        if coef.shape != (n,):
            raise DimensionError(
                f"coef_init has shape {coef.shape} but the basis has {n} functions"
            )
        if not np.all(np.isfinite(coef)):
            raise DataError("coef_init contains NaN or inf")
        self._install(basis, coef, float(self.offset_init), np.zeros(n), float(self.delta))
        return self

    def _install(
        self, basis: KautzBasis, coef: NDArray, offset: float, state: NDArray, delta: float
    ) -> None:
        n = basis.n_functions
        self.basis_ = basis
        self._n = n
        self._A = np.array(basis.A)
        self._B = np.array(basis.B)
        self._lam = float(self.forgetting)
        self._max_trace = float(self.max_trace)
        self._u0 = float(self.input_offset)
        self._offset = bool(self.fit_offset)
        self._scale = None if self.quadratic_scale is None else float(self.quadratic_scale)
        self._directional = bool(self.directional)
        self._q0 = n + int(self._offset)  # where the quadratic channel starts
        n_par = self._q0 + (n if self._scale is not None else 0)
        self._theta = np.zeros(n_par)
        self._theta[:n] = coef
        self._d = offset  # the fixed offset when it is not estimated
        if self._offset:
            self._theta[n] = offset
        self._phi = np.zeros(n_par)
        self._phi[:n] = state[:n]
        if self._offset:
            self._phi[n] = 1.0
        if self._scale is not None and state.size == 2 * n:
            self._phi[self._q0:] = state[n:]
        self._set_covariance(delta)
        self.n_updates_ = 0
        self.n_clamped_ = 0

    def _set_covariance(self, delta: float) -> None:
        n_par = self._theta.size
        self._P = delta * np.eye(n_par)
        self._R = np.eye(n_par) / delta if self._directional else None

    def set_directional(self, on: bool) -> None:
        """Switch between directional and exponential forgetting from now on.

        The estimate and the covariance carry over (switching on rebuilds the
        information matrix :math:`R = P^{-1}`); a reset or a reseed returns to
        the ``directional`` parameter.

        Parameters
        ----------
        on : bool
            Forget only along the regressor (``True``) or in every direction.
        """
        self._check_is_fitted()
        if bool(on) == self._directional:
            return
        self._directional = bool(on)
        self._R = None
        if self._directional:
            try:
                self._R = np.linalg.inv(self._P)
            except np.linalg.LinAlgError:
                self._set_covariance(float(self.delta))

    @property
    def directional_(self) -> bool:
        """Whether the forgetting is directional now (see :meth:`set_directional`)."""
        self._check_is_fitted()
        return self._directional

    def quadratic_input(self, u: float | NDArray) -> float | NDArray:
        """The quadratic channel's input ``(u - u0)^2 / s`` (with ``quadratic_scale`` only).

        Parameters
        ----------
        u : float or ndarray
            Plant inputs.

        Returns
        -------
        float or ndarray
            What drives the quadratic bank.
        """
        v = u - self._u0
        return v * v / self._scale

    def _check_is_fitted(self) -> None:
        if not hasattr(self, "_theta"):
            raise NotFittedError(
                "this RecursiveKautzEstimator is not initialised; call reset(), fit() or "
                "partial_fit() first"
            )

    def reseed(
        self,
        model: KautzModel,
        *,
        offset: float = 0.0,
        state: ArrayLike | None = None,
        delta: float | None = None,
    ) -> RecursiveKautzEstimator:
        """Continue from another model (new poles and coefficients) without losing the run.

        Parameters
        ----------
        model : KautzModel
            The new model: continuous (discretised on ``dt``) or on a delayed
            discrete basis with the same ``dt``.
        offset : float, default=0.0
            Its offset ``d``.
        state : array-like of shape (n_functions,) or (2 n_functions,), optional
            The new basis' filter state at the current sample (zeros when omitted);
            with the quadratic channel, its bank's state may follow (else zeros).
            The quadratic channel's coefficients restart at zero.
        delta : float, optional
            New initial covariance scale; ``self.delta`` when omitted.

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.
        """
        self._check_params()
        md = discretize_model(model, float(self.dt))
        n = md.n_functions
        x = np.zeros(n) if state is None else np.asarray(state, dtype=float)
        if x.shape != (n,) and not (self.quadratic_scale is not None and x.shape == (2 * n,)):
            raise DimensionError(f"state has shape {x.shape} but the model has {n} functions")
        d = float(self.delta) if delta is None else float(delta)
        self._install(md.basis, np.array(md.coefficients), float(offset), x, d)
        return self

    # ------------------------------------------------------------------ recursion
    def predict(self) -> float:
        """A-priori prediction of the current sample's output, :math:`\\theta^T\\varphi(k)`.

        Returns
        -------
        float
        """
        self._check_is_fitted()
        out = float(self._theta @ self._phi)
        return out if self._offset else out + self._d

    @property
    def parameters_(self) -> NDArray[np.float64]:
        """Current parameter vector :math:`\\theta = [c; d]` (a copy; no ``d`` without offset)."""
        self._check_is_fitted()
        return self._theta.copy()

    def predict_with(self, theta: NDArray[np.float64]) -> float:
        """Prediction of the current sample's output with other parameters (e.g. frozen ones).

        Parameters
        ----------
        theta : ndarray of shape (n_params,)
            A parameter vector like :attr:`parameters_`.

        Returns
        -------
        float
        """
        out = float(theta @ self._phi)
        return out if self._offset else out + self._d

    def update(self, u: float, y: float = math.nan) -> float:
        """One sample: predict ``y(k)``, correct with the measured ``y``, advance with ``u(k)``.

        Parameters
        ----------
        u : float
            Input applied at this sample (drives the filter to the next sample).
        y : float, default=nan
            Measured output of this sample; NaN (a dropout) only advances the filter.

        Returns
        -------
        float
            The a-priori prediction of ``y(k)`` (made before ``y`` was used).

        Raises
        ------
        DataError
            If ``u`` is not finite.
        """
        if not hasattr(self, "_theta"):
            self.reset()
        u = float(u)
        if not math.isfinite(u):
            raise DataError(f"u must be finite, got {u}")
        phi = self._phi
        theta = self._theta
        yhat = float(theta @ phi)
        if not self._offset:
            yhat += self._d
        if y == y:  # not NaN
            self._correct(float(y) - yhat)
        self._advance_filters(u)
        return yhat

    def _correct(self, error: float) -> None:
        """The measurement update, with exponential or directional forgetting.

        Directional: the information along ``phi`` first loses the share ``1 - lambda``
        (``R`` and ``P`` by rank-one updates), then the measurement's is added as
        without forgetting; ``R = P^-1`` is rebuilt every 64 updates.
        """
        phi, P, R = self._phi, self._P, self._R
        lam, directional = self._lam, self._directional
        if directional and lam < 1.0:
            Rphi = R @ phi
            r = float(phi @ Rphi)
            if r > 0 and math.isfinite(r):
                R -= np.outer(Rphi, Rphi) * ((1.0 - lam) / r)
                P += np.outer(phi, phi) * ((1.0 - lam) / (lam * r))
        Pphi = P @ phi
        denom = (1.0 if directional else lam) + float(phi @ Pphi)
        if not (denom > 0 and math.isfinite(denom)):
            self.reset_covariance()
            return
        g = Pphi / denom
        self._theta += g * error
        P -= np.outer(g, Pphi)
        if directional:
            R += np.outer(phi, phi)
        elif lam < 1.0:
            P /= lam
        self.n_updates_ += 1
        if self.n_updates_ % 64 == 0:
            P += P.T
            P *= 0.5
            if directional:  # R the inverse of P again
                try:
                    self._R = np.linalg.inv(P)
                except np.linalg.LinAlgError:
                    self.reset_covariance()
                    return
        self._clamp_trace()

    def _clamp_trace(self) -> None:
        tr = float(self._P.trace())
        if tr > self._max_trace:
            self._P *= self._max_trace / tr
            if self._R is not None:
                self._R *= tr / self._max_trace
            self.n_clamped_ += 1
        elif not tr > 0:  # lost positive definiteness (rounding): restart
            self.reset_covariance()

    def _advance_filters(self, u: float, n_steps: int = 1) -> None:
        """Drive the filter bank(s) with ``u`` held over ``n_steps`` samples."""
        n, phi = self._n, self._phi
        v = u - self._u0
        w = None if self._scale is None else self.quadratic_input(u)
        q0 = self._q0
        for _ in range(int(n_steps)):
            phi[:n] = self._A @ phi[:n] + self._B * v
            if w is not None:
                phi[q0:] = self._A @ phi[q0:] + self._B * w

    def revise_last_input(self, u_used: float, u_applied: float) -> None:
        """Correct the last step's input: the plant applied ``u_applied``, not ``u_used``.

        The filter is linear in the input, so the state after the last
        :meth:`update` / :meth:`advance` becomes the one that ``u_applied``
        would have given (a live plant reports the input it really applied).

        Parameters
        ----------
        u_used : float
            The input the last step advanced the filter with.
        u_applied : float
            The input the plant applied over that period.
        """
        self._check_is_fitted()
        delta = float(u_applied) - float(u_used)
        if math.isfinite(delta) and delta != 0.0:
            self._phi[:self._n] += self._B * delta
            if self._scale is not None:
                dq = self.quadratic_input(float(u_applied)) - self.quadratic_input(float(u_used))
                self._phi[self._q0:] += self._B * dq

    def advance(self, u: float, n_steps: int = 1) -> None:
        """Advance the filter with input ``u`` without using a measurement.

        Parameters
        ----------
        u : float
            Input held over the steps.
        n_steps : int, default=1
            Number of samples.
        """
        self._check_is_fitted()
        self._advance_filters(float(u), n_steps)

    def reset_covariance(self, delta: float | None = None) -> None:
        """Restart the covariance at ``delta * I`` (``self.delta`` when omitted).

        Parameters
        ----------
        delta : float, optional
            New scale.
        """
        self._check_is_fitted()
        d = float(self.delta) if delta is None else float(delta)
        self._set_covariance(d)

    def partial_fit(self, u: ArrayLike, y: ArrayLike) -> RecursiveKautzEstimator:
        """Run :meth:`update` over a batch of samples (continuing the recursion).

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Inputs (finite).
        y : array-like of shape (n_samples,)
            Outputs; NaN samples only advance the filter.

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.

        Raises
        ------
        DimensionError
            If ``u`` and ``y`` are not 1-D of one length.
        DataError
            If ``u`` is not finite.
        """
        u = np.asarray(u, dtype=float)
        y = np.asarray(y, dtype=float)
        if u.ndim != 1 or u.shape != y.shape:
            raise DimensionError(
                f"u and y must be 1-D of one length, got shapes {u.shape} and {y.shape}"
            )
        if not np.all(np.isfinite(u)):
            raise DataError("u contains NaN or inf")
        if not hasattr(self, "_theta"):
            self.reset()
        for uk, yk in zip(u.tolist(), y.tolist(), strict=True):
            self.update(uk, yk)
        return self

    def fit(self, u: ArrayLike, y: ArrayLike) -> RecursiveKautzEstimator:
        """Reset, then run the recursion over ``u`` and ``y`` from a zero filter state.

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Inputs.
        y : array-like of shape (n_samples,)
            Outputs (NaN: dropout).

        Returns
        -------
        RecursiveKautzEstimator
            ``self``.
        """
        return self.reset().partial_fit(u, y)

    def regressors(
        self, u: ArrayLike, x0: ArrayLike | None = None, *, final: bool = False
    ) -> NDArray[np.float64]:
        """The regressors :math:`\varphi(k)` of an input sequence, laid out as :attr:`parameters_`.

        Parameters
        ----------
        u : array-like of shape (n_samples,)
            Inputs.
        x0 : array-like, optional
            Initial filter state, shaped as :attr:`state_` (zeros when omitted:
            at rest at ``input_offset``; the estimator's own state is untouched).
        final : bool, default=False
            Also return the row of the sample after the last (the state the
            sequence leaves).

        Returns
        -------
        ndarray of shape (n_samples, n_params) or (n_samples + 1, n_params)
            Row ``k``: the filter states at sample ``k`` (driven by the inputs
            before it), the offset's 1 and the quadratic channel's states.
        """
        if not hasattr(self, "_theta"):
            self.reset()
        u = np.asarray(u, dtype=float)
        if u.ndim != 1:
            raise DimensionError(f"u must be 1-D, got shape {u.shape}")
        n, q0 = self._n, self._q0
        x = None if x0 is None else np.asarray(x0, dtype=float).reshape(-1)
        size = n if self._scale is None else 2 * n
        if x is not None and x.shape != (size,):
            raise DimensionError(f"x0 has shape {x.shape}; the filter state has {size} entries")
        rows = u.size + 1 if final else u.size
        X = np.empty((rows, self._theta.size))
        X[:, :n] = filter_states(self.basis_, u - self._u0, None if x is None else x[:n])[:rows]
        if self._offset:
            X[:, n] = 1.0
        if self._scale is not None:
            xq = None if x is None else x[n:]
            X[:, q0:] = filter_states(self.basis_, self.quadratic_input(u), xq)[:rows]
        return X

    def simulate(
        self, u: ArrayLike, x0: ArrayLike | None = None, *, linear: bool = False
    ) -> NDArray[np.float64]:
        """Output of the current model for an input sequence (parameters frozen).

        Parameters
        ----------
        u, x0
            Inputs and initial filter state, as in :meth:`regressors`.
        linear : bool, default=False
            Leave the quadratic channel out: the linear part ``c``, ``d`` alone
            (what :attr:`model_` and a model version hold; a virtual step test).

        Returns
        -------
        ndarray of shape (n_samples,)
            ``y(k) = c^T x_f(k) + d (+ c_q^T x_q(k))`` for ``k = 0 .. n_samples - 1``,
            the filters driven by ``u - input_offset``.
        """
        X = self.regressors(u, x0)
        theta = self._theta
        if linear and self._scale is not None:
            X, theta = X[:, :self._q0], theta[:self._q0]
        out = X @ theta
        return out if self._offset else out + self._d

    def steady_input(self, y: float) -> float:
        """The constant input whose steady output is ``y`` (the static map inverted).

        Linear: :math:`u_0 + (y - d)/g` with the static gain :math:`g = c^T (I-A)^{-1} B`.
        With the quadratic channel, the root of :math:`d + g v + g_q v^2 / s = y` nearest
        the linear answer (the linear answer when there is none).

        Parameters
        ----------
        y : float
            Steady output.

        Returns
        -------
        float
            The input; NaN when the linear part has no static gain.
        """
        self._check_is_fitted()
        n = self._n
        dc = np.linalg.solve(np.eye(n) - self._A, self._B)
        g = float(self.coef_ @ dc)
        if abs(g) < 1e-12:
            return math.nan
        v = (float(y) - self.offset_) / g
        if self._scale is not None:
            a = float(self.quadratic_coef_ @ dc) / self._scale
            disc = g * g + 4.0 * a * (float(y) - self.offset_)
            if abs(a) > 1e-12 and disc >= 0.0:
                roots = (-g + np.array([1.0, -1.0]) * math.sqrt(disc)) / (2.0 * a)
                v = float(roots[np.argmin(np.abs(roots - v))])
        return self._u0 + v

    # ------------------------------------------------------------------ results
    @property
    def coef_(self) -> NDArray[np.float64]:
        """Current coefficients ``c`` (a copy)."""
        self._check_is_fitted()
        return self._theta[: self._n].copy()

    @property
    def offset_(self) -> float:
        """Current offset ``d``."""
        self._check_is_fitted()
        return float(self._theta[self._n]) if self._offset else self._d

    @property
    def covariance_(self) -> NDArray[np.float64]:
        """Current covariance ``P`` (a copy)."""
        self._check_is_fitted()
        return self._P.copy()

    @property
    def state_(self) -> NDArray[np.float64]:
        """Current filter state ``x_f(k)``, then ``x_q(k)`` with the quadratic channel (a copy)."""
        self._check_is_fitted()
        if self._scale is None:
            return self._phi[: self._n].copy()
        return np.concatenate([self._phi[: self._n], self._phi[self._q0:]])

    @property
    def quadratic_coef_(self) -> NDArray[np.float64]:
        """Coefficients ``c_q`` of the quadratic channel (a copy; empty without it)."""
        self._check_is_fitted()
        return self._theta[self._q0:].copy()

    @property
    def model_(self) -> KautzModel:
        """The current linear model ``c`` on :attr:`basis_` (a new immutable object).

        The quadratic channel, when there is one, is not part of it.
        """
        return KautzModel(self.basis_, self.coef_)

    def __repr__(self) -> str:
        extra = "" if self.quadratic_scale is None else (
            f", quadratic_scale={self.quadratic_scale}")
        if self.directional:
            extra += ", directional=True"
        return (
            f"RecursiveKautzEstimator(n_functions={getattr(self, '_n', '?')}, dt={self.dt}, "
            f"forgetting={self.forgetting}{extra})"
        )
