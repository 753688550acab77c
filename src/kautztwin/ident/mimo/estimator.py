"""The MIMO Kautz estimator: number of poles and pole structure chosen on held-out data."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_choice, check_int, check_number, check_positive
from ...basis._blocks import REAL, parse_poles
from ...exceptions import DataError, NotFittedError
from ..kautz_oe import continuous_poles
from .fit import (
    MIMOFit,
    _fit_percent,
    _fit_record,
    _input_offset,
    _rate_lo,
    _starts,
    check_mimo_data,
)

__all__ = ["MIMOKautzEstimator"]

# held-out normalised mean square below which a model counts as exact (fit 99.9999 %)
_EXACT = 1e-12


def _warm(basis: Any, rate_lo: float, hi: float) -> list:
    """Start for one more real pole: the previous poles plus one in the widest log-gap."""
    if basis is None:
        return []
    kinds, params = parse_poles(continuous_poles(basis), 0.0)
    rates = []
    col = 0
    for kind in kinds:
        rates.append(params[col])
        col += 2 if kind != REAL else 1
    edges = np.log(np.sort(np.concatenate([[rate_lo], rates, [hi]])))
    k = int(np.argmax(np.diff(edges)))
    new = math.exp(0.5 * (edges[k] + edges[k + 1]))
    return [((*kinds, REAL), np.concatenate([params, [new]]))]


class MIMOKautzEstimator:
    r"""Output-error MIMO Kautz model with the order and pole structure chosen on held-out data.

    With ``n_poles='auto'`` (or ``poles='auto'``) the last ``holdout`` share of the record
    is held out: every candidate (1 to ``max_poles`` poles; shared poles, per-output poles)
    is fitted to the first part and simulated over the whole record, and scored by its
    normalised mean squared error on the held-out samples (per output for per-output
    poles, the mean over the outputs otherwise).  The pick is the smallest order within one
    standard error of the best (relative :math:`\sqrt{2 / n_{held\,out}}`, white residuals),
    so an order that validates worse is never preferred and noise-level gains buy no poles
    (on noise-free data, every order with a held-out fit above 99.9999 % counts as exact);
    the search stops once two more poles bring no gain beyond that margin.  Per-output
    poles are chosen over shared ones only when they beat them by the same margin.  Each
    order is started from the spreads of real poles and from the previous order's poles
    plus one.  The winner is then refitted to the whole record, started from its poles.

    Parameters
    ----------
    n_poles : int, array-like of complex, or 'auto', default='auto'
        Number of real poles, starting pole locations (continuous time), or ``'auto'``.
    poles : {'shared', 'per_output', 'auto'}, default='shared'
        Pole structure; ``'auto'`` chooses on the held-out data.
    max_poles : int, default=6
        Largest order ``'auto'`` tries.
    holdout : float, default=0.25
        Share of the record (at its end) held out for the choice.
    burn_in : int, default=0
        Samples left out of the error at the start.
    initial_state : {'zero', 'estimate'}, default='zero'
        See :func:`identify_mimo`.
    fit_offset : bool, default=True
        Estimate the output offsets.
    input_offset : array-like of shape (n_inputs,), 'auto' or None, default='auto'
        Input operating point.  ``None``: ``u[0]`` (the plant rests at the equilibrium of
        the first input).  ``'auto'``: ``u[0]`` or zero (the plant rests at the
        equilibrium of a zero input, e.g. a heater switched on at the first sample),
        whichever a probe fit (2 shared poles, or ``n_poles``) predicts better on the
        held-out end of the record; the same as ``u[0]`` when ``u[0]`` is zero.
    min_rate : float, optional
        Slowest pole decay rate, 1/s (``3 / T`` when omitted).
    max_iter : int, default=50
        Iteration budget per start.
    tol : float, default=1e-8
        Solver tolerance.

    Attributes
    ----------
    model_ : MIMOKautzModel
        The fitted model.
    fit_ : MIMOFit
        The final fit (estimation statistics).
    n_poles_ : ndarray of int, shape (n_outputs,)
        Poles per output (all equal for shared poles).
    poles_ : str
        The structure used, ``'shared'`` or ``'per_output'``.
    selection_ : list of dict
        Every candidate tried: ``poles``, ``n_poles``, ``holdout_fit_percent`` (per output).
    input_offset_ : ndarray of shape (n_inputs,)
        The input operating point used.
    offset_selection_ : list of dict
        With ``input_offset='auto'`` and a nonzero first input: each candidate
        (``input_offset``) with its probe fit's ``holdout_fit_percent``; else empty.
    n_inputs_, n_outputs_ : int
        Channel counts.

    See Also
    --------
    identify_mimo : One fit of a given order and structure.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin import KautzBasis
    >>> from kautztwin.ident.mimo import MIMOKautzEstimator, MIMOKautzModel
    >>> rng = np.random.default_rng(0)
    >>> true = MIMOKautzModel(KautzBasis([0.95, 0.7], dt=1.0, delayed=True),
    ...                       rng.normal(size=(2, 2, 2)))
    >>> u = np.repeat(rng.uniform(-1, 1, (80, 2)), 10, axis=0)
    >>> y = true.simulate(u) + 0.01 * rng.normal(size=(800, 2))
    >>> est = MIMOKautzEstimator(max_poles=3, input_offset=[0.0, 0.0]).fit(u, y, dt=1.0)
    >>> est.poles_, est.n_poles_.tolist()
    ('shared', [2, 2])
    """

    def __init__(
        self,
        n_poles: int | ArrayLike | str = "auto",
        *,
        poles: str = "shared",
        max_poles: int = 6,
        holdout: float = 0.25,
        burn_in: int = 0,
        initial_state: str = "zero",
        fit_offset: bool = True,
        input_offset: ArrayLike | str | None = "auto",
        min_rate: float | None = None,
        max_iter: int = 50,
        tol: float = 1e-8,
    ) -> None:
        self.n_poles = n_poles
        self.poles = poles
        self.max_poles = max_poles
        self.holdout = holdout
        self.burn_in = burn_in
        self.initial_state = initial_state
        self.fit_offset = fit_offset
        self.input_offset = input_offset
        self.min_rate = min_rate
        self.max_iter = max_iter
        self.tol = tol

    def _settings(self, dt: float, u0: NDArray, rate_lo: float) -> dict[str, Any]:
        return {
            "dt": dt, "u0": u0, "rate_lo": rate_lo, "burn_in": self.burn_in,
            "initial_state": self.initial_state, "fit_offset": bool(self.fit_offset),
            "max_iter": self.max_iter, "tol": self.tol,
        }

    def fit(self, u: ArrayLike, y: ArrayLike, *, dt: float = 1.0) -> MIMOKautzEstimator:
        """Fit to one input/output record.

        Parameters
        ----------
        u : array-like of shape (n_samples, n_inputs)
        y : array-like of shape (n_samples, n_outputs)
        dt : float, default=1.0
            Sampling period, s.

        Returns
        -------
        MIMOKautzEstimator
            ``self``.

        Raises
        ------
        DataError, DimensionError
            On a bad record or setting (see :func:`identify_mimo`).
        """
        u2, y2 = check_mimo_data(u, y)
        dt = check_positive(dt, "dt")
        structure = check_choice(self.poles, "poles", ("shared", "per_output", "auto"))
        n, n_out = y2.shape[0], y2.shape[1]
        rate_lo = _rate_lo(self.min_rate, n, dt)
        auto = isinstance(self.n_poles, str)
        if auto and self.n_poles != "auto":
            raise DataError(f"n_poles must be an int, poles or 'auto', got {self.n_poles!r}")
        self.selection_: list[dict[str, Any]] = []
        self.offset_selection_: list[dict[str, Any]] = []
        u0 = self._choose_offset(u2, y2, dt)
        self.input_offset_ = u0
        if not auto and structure != "auto":
            starts = _starts(self.n_poles, n, dt, rate_lo)
            groups = [starts] * (n_out if structure == "per_output" else 1)
            fit = _fit_record(u2, y2, groups, **self._settings(dt, u0, rate_lo))
            return self._finish(fit, structure, u2.shape[1])
        n_est = self._holdout_split(n)
        structures = ("shared", "per_output") if structure == "auto" else (structure,)
        orders = (
            range(1, check_int(self.max_poles, "max_poles", 1) + 1) if auto else [None]
        )
        rate_est = _rate_lo(self.min_rate, n_est, dt)
        settings = self._settings(dt, u0, rate_est)
        # one standard error of a held-out mean square (white residuals): the margin a
        # larger model must beat to count as better
        se = math.sqrt(2.0 / (n - n_est))
        cands: dict[tuple[str, int], list[tuple[float, Any]]] = {}
        for struct in structures:
            n_groups = 1 if struct == "shared" else n_out
            prev: list[Any] = [None] * n_groups
            for order in orders:
                base = _starts(order if auto else self.n_poles, n_est, dt, rate_est)
                groups = [
                    base + _warm(prev[g], rate_est, 0.3 / dt) for g in range(n_groups)
                ]
                try:
                    fit = _fit_record(u2[:n_est], y2[:n_est], groups, **settings)
                except DataError:
                    if order == 1 or not auto:
                        raise
                    break  # too few samples for this order and above
                yhat = fit.simulate(u2, initial=True)
                score = _fit_percent(y2[n_est:], yhat[n_est:])
                nmse = (1.0 - score / 100.0) ** 2
                self.selection_.append({
                    "poles": struct,
                    "n_poles": fit.model.bases[0].n_functions,
                    "holdout_fit_percent": score.tolist(),
                    "estimation_fit_percent": fit.fit_percent.tolist(),
                })
                stalled = True
                for g in range(n_groups):
                    prev[g] = fit.model.bases[g]
                    outs = list(range(n_out)) if struct == "shared" else [g]
                    hist = cands.setdefault((struct, g), [])
                    hist.append((float(np.mean(nmse[outs])), prev[g]))
                    best_before = min(h[0] for h in hist[:-2]) if len(hist) > 2 else math.inf
                    stalled &= min(h[0] for h in hist[-2:]) >= best_before * (1.0 - se)
                if stalled:
                    break  # two more poles brought no significant improvement
        chosen, picks = self._choose(cands, structures, n_out, se)
        starts = [[parse_poles(continuous_poles(b), 0.0)] for b in picks]
        fit = _fit_record(u2, y2, starts, **self._settings(dt, u0, rate_lo))
        return self._finish(fit, chosen, u2.shape[1])

    def _holdout_split(self, n: int) -> int:
        holdout = check_number(self.holdout, "holdout")
        if not 0.05 <= holdout <= 0.8:
            raise DataError(f"holdout must lie in [0.05, 0.8], got {holdout}")
        return n - int(round(holdout * n))

    def _choose_offset(self, u2: NDArray, y2: NDArray, dt: float) -> NDArray[np.float64]:
        """The input operating point: as given, or ``u[0]`` against zero on held-out data."""
        if not (isinstance(self.input_offset, str) and self.input_offset == "auto"):
            if isinstance(self.input_offset, str):
                raise DataError(
                    f"input_offset must be 'auto', None or one number per input, got "
                    f"{self.input_offset!r}"
                )
            return _input_offset(self.input_offset, u2)
        first = u2[0].copy()
        if not np.any(first):
            return first
        n_est = self._holdout_split(u2.shape[0])
        rate_est = _rate_lo(self.min_rate, n_est, dt)
        probe = 2 if isinstance(self.n_poles, str) else self.n_poles
        best, best_err = first, math.inf
        for u0 in (first, np.zeros_like(first)):
            starts = _starts(probe, n_est, dt, rate_est)
            try:
                fit = _fit_record(u2[:n_est], y2[:n_est], [starts],
                                  **self._settings(dt, u0, rate_est))
            except DataError:
                return first  # too few samples to compare: the documented fallback
            score = _fit_percent(y2[n_est:], fit.simulate(u2, initial=True)[n_est:])
            self.offset_selection_.append({
                "input_offset": u0.tolist(), "holdout_fit_percent": score.tolist(),
            })
            err = float(np.mean((1.0 - score / 100.0) ** 2))
            if err < best_err:
                best, best_err = u0, err
        return best

    @staticmethod
    def _choose(
        cands: dict[tuple[str, int], list[tuple[float, Any]]], structures: tuple[str, ...],
        n_out: int, se: float,
    ) -> tuple[str, list[Any]]:
        """Smallest order within one standard error of the best held-out error, per group;
        per-output poles only where they beat shared poles by more than that margin."""
        picks: dict[str, list[Any]] = {}
        errors: dict[str, float] = {}
        for s in structures:
            picks[s], errs = [], []
            for g in range(1 if s == "shared" else n_out):
                hist = cands[(s, g)]
                best = min(h[0] for h in hist)
                # below _EXACT (fit 99.9999 %) every order counts as exact: the smallest wins
                err, basis = next(h for h in hist if h[0] <= max(best * (1.0 + se), _EXACT))
                picks[s].append(basis)
                errs.append(err)
            errors[s] = float(np.mean(errs))
        chosen = structures[0]
        for s in structures[1:]:
            if errors[s] < errors[chosen] * (1.0 - se):
                chosen = s
        return chosen, picks[chosen]

    def _finish(self, fit: MIMOFit, structure: str, n_in: int) -> MIMOKautzEstimator:
        self.fit_ = fit
        self.model_ = fit.model
        self.poles_ = structure
        self.n_poles_ = np.array([b.n_functions for b in fit.model.bases])
        self.n_inputs_ = n_in
        self.n_outputs_ = fit.model.n_outputs
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise NotFittedError(
                "this MIMOKautzEstimator is not fitted yet; call fit(u, y) first"
            )

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Simulated outputs for ``u`` from rest (the model's :meth:`~MIMOKautzModel.simulate`).

        Parameters
        ----------
        u : array-like of shape (n_samples, n_inputs)

        Returns
        -------
        ndarray of shape (n_samples, n_outputs)
        """
        self._check_fitted()
        return self.model_.simulate(u)

    simulate = predict

    def score(self, u: ArrayLike, y: ArrayLike) -> float:
        """Mean simulation fit percent over the outputs on a record starting at rest.

        Parameters
        ----------
        u : array-like of shape (n_samples, n_inputs)
        y : array-like of shape (n_samples, n_outputs)

        Returns
        -------
        float
        """
        self._check_fitted()
        u2, y2 = check_mimo_data(u, y)
        yhat = np.atleast_2d(self.model_.simulate(u2).T).T
        return float(np.mean(_fit_percent(y2, yhat)))
