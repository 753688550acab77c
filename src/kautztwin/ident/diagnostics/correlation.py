r"""Residual tests: autocorrelation and Ljung-Box whiteness, residual-input cross-correlation.

The functions take one sequence or a list of sequences (one per record): lagged products
are summed within each sequence only, never across the gap between two records.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.signal
import scipy.stats
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_finite, check_int
from ...exceptions import DataError, DimensionError

__all__ = [
    "CrossCorrelationTest",
    "WhitenessTest",
    "autocorrelation",
    "cross_correlation",
    "cross_correlation_test",
    "whiteness_test",
]

#: MATLAB ``resid``'s default number of lags
DEFAULT_MAX_LAG = 25


# =============================================================================== helpers
def _segments(x: Any, name: str) -> list[NDArray[np.float64]]:
    """One 1-D float array per record (a single 1-D array-like is one record)."""
    if isinstance(x, np.ndarray) and x.ndim == 1 or (
        isinstance(x, Sequence) and len(x) > 0 and np.ndim(x[0]) == 0
    ):
        segs = [np.asarray(x, dtype=float)]
    elif isinstance(x, Sequence | np.ndarray) and len(x) > 0:
        segs = [np.asarray(s, dtype=float) for s in x]
    else:
        raise DimensionError(f"{name} must be a 1-D sequence or a non-empty list of them")
    for i, s in enumerate(segs):
        if s.ndim != 1:
            raise DimensionError(f"{name}[{i}] must be 1-D, got shape {s.shape}")
        check_finite(s, name if len(segs) == 1 else f"{name}[{i}]")
    return segs


def _check_alpha(alpha: float, name: str = "alpha") -> float:
    a = float(alpha)
    if not 0 < a < 1:
        raise DataError(f"{name} must lie in (0, 1); got {alpha!r}")
    return a


def _max_lag(max_lag: Any, n_total: int) -> int:
    m = check_int(max_lag, "max_lag", 1)
    if m >= n_total - 1:
        raise DataError(f"max_lag = {m} needs more than {m + 1} residual samples; got {n_total}")
    return m


def _lagged_products(a: list[NDArray], b: list[NDArray], lags: NDArray) -> NDArray:
    """``sum_s sum_t a_s(t + k) b_s(t)`` for every lag ``k`` (within each segment)."""
    out = np.zeros(lags.size)
    for x, y in zip(a, b, strict=True):
        n = x.size
        for i, k in enumerate(lags):
            if abs(k) >= n:
                continue
            out[i] += x[k:] @ y[: n - k] if k >= 0 else x[: n + k] @ y[-k:]
    return out


def _pairs(segs: list[NDArray], lags: NDArray) -> NDArray:
    """Number of sample pairs at each lag, summed over segments."""
    return np.array([sum(max(s.size - abs(int(k)), 0) for s in segs) for k in lags], dtype=float)


def _z(level: float) -> float:
    """Two-sided standard normal quantile of a confidence level."""
    return float(scipy.stats.norm.ppf(0.5 + level / 2))


# =============================================================================== correlations
def autocorrelation(e: ArrayLike | Sequence[ArrayLike], max_lag: int = DEFAULT_MAX_LAG
                    ) -> NDArray[np.float64]:
    r"""Sample autocorrelation :math:`r(k)`, ``k = 0..max_lag``, of one or several sequences.

    .. math:: r(k) = \frac{\sum_s \sum_t \tilde e_s(t+k)\,\tilde e_s(t)}
                          {\sum_s \sum_t \tilde e_s(t)^2}

    with :math:`\tilde e_s` the sequence ``s`` about its own mean (the biased estimator,
    so ``r`` is a positive semi-definite sequence and :math:`r(0) = 1`).

    Parameters
    ----------
    e : array-like of shape (n_samples,), or list of them
        The sequence, or one sequence per record.
    max_lag : int, default=25
        Largest lag.

    Returns
    -------
    ndarray of shape (max_lag + 1,)

    Raises
    ------
    DataError
        If a value is not finite, every sequence is constant, or ``max_lag`` is not below
        the number of samples minus one.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.diagnostics import autocorrelation
    >>> np.round(autocorrelation([1.0, -1.0, 1.0, -1.0, 1.0, -1.0], 2), 3)
    array([ 1.   , -0.833,  0.667])
    """
    segs = [s - s.mean() for s in _segments(e, "e")]
    m = _max_lag(max_lag, sum(s.size for s in segs))
    lags = np.arange(m + 1)
    prod = _lagged_products(segs, segs, lags)
    if prod[0] == 0:
        raise DataError("e is constant: its autocorrelation is undefined")
    return prod / prod[0]


def cross_correlation(e: ArrayLike | Sequence[ArrayLike], u: ArrayLike | Sequence[ArrayLike],
                      max_lag: int = DEFAULT_MAX_LAG) -> tuple[NDArray[np.int64],
                                                               NDArray[np.float64]]:
    r"""Sample cross-correlation of residual and input, lags ``-max_lag..max_lag``.

    .. math:: r_{eu}(k) = \frac{\sum_s \sum_t \tilde e_s(t+k)\,\tilde u_s(t)}
                               {\sqrt{\sum_s \sum_t \tilde e_s(t)^2\,
                                      \sum_s \sum_t \tilde u_s(t)^2}}

    A positive lag ``k`` pairs the residual with the input ``k`` samples *earlier*
    (dynamics the model misses); a negative lag with later inputs (feedback).

    Parameters
    ----------
    e, u : array-like of shape (n_samples,), or lists of them
        Residual and input, one sequence per record, of matching lengths.
    max_lag : int, default=25
        Largest lag.

    Returns
    -------
    lags : ndarray of shape (2 * max_lag + 1,)
    r : ndarray of shape (2 * max_lag + 1,)

    Raises
    ------
    DimensionError
        If ``e`` and ``u`` do not hold sequences of the same lengths.
    DataError
        If ``e`` or ``u`` is constant or not finite.
    """
    es, us = _paired(e, u)
    m = _max_lag(max_lag, sum(s.size for s in es))
    lags = np.arange(-m, m + 1)
    norm = np.sqrt(sum(s @ s for s in es) * sum(s @ s for s in us))
    return lags, _lagged_products(es, us, lags) / norm


def _paired(e: Any, u: Any) -> tuple[list[NDArray], list[NDArray]]:
    es, us = _segments(e, "e"), _segments(u, "u")
    if len(es) != len(us) or any(a.size != b.size for a, b in zip(es, us, strict=False)):
        raise DimensionError(
            "e and u must hold sequences of the same lengths; got "
            f"{[s.size for s in es]} and {[s.size for s in us]}"
        )
    es = [s - s.mean() for s in es]
    us = [s - s.mean() for s in us]
    if all(not np.any(s) for s in es):
        raise DataError("e is constant: its correlation with the input is undefined")
    if all(not np.any(s) for s in us):
        raise DataError("u is constant: the residual cannot be tested against it")
    return es, us


# =============================================================================== whiteness
@dataclass(frozen=True, eq=False)
class WhitenessTest:
    r"""Residual autocorrelation, its confidence bound and the Ljung-Box test (immutable).

    Parameters
    ----------
    lags : ndarray of shape (max_lag + 1,)
        ``0, 1, ..., max_lag``.
    autocorrelation : ndarray of shape (max_lag + 1,)
        :math:`r(k)`, with :math:`r(0) = 1`.
    bound : float
        :math:`z_{1-\alpha/2}/\sqrt N`: under whiteness each :math:`r(k)`, ``k >= 1``, lies
        within it with probability about :math:`1 - \alpha`.
    statistic : float
        Ljung-Box :math:`Q`.
    dof : int
        Degrees of freedom of its :math:`\chi^2` reference distribution.
    p_value : float
        :math:`P(\chi^2_{\mathrm{dof}} \ge Q)`.
    alpha : float
        Significance level.
    n_samples : int
        Number of residual samples ``N`` (all records).

    Attributes
    ----------
    white : bool
        ``p_value >= alpha``: whiteness is not rejected.
    n_outside : int
        Lags ``k >= 1`` whose :math:`|r(k)|` exceeds ``bound``.
    """

    lags: NDArray[np.int64]
    autocorrelation: NDArray[np.float64]
    bound: float
    statistic: float
    dof: int
    p_value: float
    alpha: float
    n_samples: int

    @property
    def white(self) -> bool:
        """Whether whiteness is not rejected at level ``alpha``."""
        return bool(self.p_value >= self.alpha)

    @property
    def n_outside(self) -> int:
        """Number of lags ``k >= 1`` outside the confidence bound."""
        return int(np.sum(np.abs(self.autocorrelation[1:]) > self.bound))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary.

        Returns
        -------
        dict
        """
        return {"white": self.white, "p_value": self.p_value, "statistic": self.statistic,
                "dof": self.dof, "alpha": self.alpha, "bound": self.bound,
                "n_outside": self.n_outside, "max_lag": int(self.lags[-1]),
                "n_samples": self.n_samples,
                "autocorrelation": self.autocorrelation.tolist()}


def whiteness_test(e: ArrayLike | Sequence[ArrayLike], *, max_lag: int = DEFAULT_MAX_LAG,
                   alpha: float = 0.05, n_fitted: int = 0) -> WhitenessTest:
    r"""Test whether a residual is white: autocorrelation bound and Ljung-Box portmanteau.

    The Ljung-Box statistic over lags ``1..h`` (``h = max_lag``) is

    .. math:: Q = N(N+2)\sum_{k=1}^{h}\frac{r(k)^2}{N_k},

    with :math:`N_k` the number of sample pairs at lag ``k`` (``N - k`` for one sequence,
    summed over the sequences of several records). Under whiteness :math:`Q` is about
    :math:`\chi^2` with ``h - n_fitted`` degrees of freedom; whiteness is rejected when the
    p-value falls below ``alpha``.

    Parameters
    ----------
    e : array-like of shape (n_samples,), or list of them
        Residual, or one residual per record.
    max_lag : int, default=25
        Lags ``h`` in the test (MATLAB ``resid`` shows 25).
    alpha : float, default=0.05
        Significance level of the test and of the per-lag bound.
    n_fitted : int, default=0
        Parameters of a noise model fitted to ``e`` (``p + q`` of an ARMA noise model);
        0 for the output error of a model without a noise model.

    Returns
    -------
    WhitenessTest

    Raises
    ------
    DataError
        On non-finite or constant ``e``, ``alpha`` outside (0, 1), ``max_lag`` too large
        for the data, or ``n_fitted >= max_lag``.

    See Also
    --------
    cross_correlation_test : Whether the residual is independent of the input.

    References
    ----------
    G. M. Ljung and G. E. P. Box, "On a measure of lack of fit in time series models",
    Biometrika 65 (1978) 297-303.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.diagnostics import whiteness_test
    >>> e = np.random.default_rng(0).standard_normal(1000)
    >>> whiteness_test(e).white, whiteness_test(np.cumsum(e)).white
    (True, False)
    """
    alpha = _check_alpha(alpha)
    segs = _segments(e, "e")
    n = sum(s.size for s in segs)
    r = autocorrelation(segs, max_lag)
    h = r.size - 1
    n_fitted = check_int(n_fitted, "n_fitted", 0)
    if n_fitted >= h:
        raise DataError(f"n_fitted = {n_fitted} leaves no degrees of freedom with max_lag = {h}")
    lags = np.arange(h + 1)
    pairs = _pairs(segs, lags[1:])
    if pairs[-1] == 0:
        raise DataError(f"max_lag = {h} is not shorter than any record (longest: "
                        f"{max(s.size for s in segs)} samples)")
    q = float(n * (n + 2) * np.sum(r[1:] ** 2 / pairs))
    dof = h - n_fitted
    return WhitenessTest(lags=lags, autocorrelation=r, bound=_z(1 - alpha) / float(np.sqrt(n)),
                         statistic=q, dof=dof, p_value=float(scipy.stats.chi2.sf(q, dof)),
                         alpha=alpha, n_samples=n)


# =============================================================================== cross test
@dataclass(frozen=True, eq=False)
class CrossCorrelationTest:
    r"""Residual-input cross-correlation, its bound and the portmanteau test (immutable).

    Parameters
    ----------
    lags : ndarray of shape (2 * max_lag + 1,)
        ``-max_lag .. max_lag``.
    cross_correlation : ndarray of shape (2 * max_lag + 1,)
        :math:`r_{eu}(k)`.
    bound : float
        :math:`z_{1-\alpha/2}\sqrt{P/N}`: under independence each :math:`r_{eu}(k)` lies
        within it with probability about :math:`1-\alpha` (``P`` accounts for the
        colour of residual and input, see :func:`cross_correlation_test`).
    statistic : float
        The portmanteau statistic :math:`S` of :func:`cross_correlation_test`.
    dof : int
        Degrees of freedom of its :math:`\chi^2` reference (the tested lags).
    p_value : float
        :math:`P(\chi^2_{\mathrm{dof}} \ge S)`.
    alpha : float
        Significance level.
    n_samples : int
        Number of samples ``N``.
    tested_lags : ndarray of int
        The lags in the statistic (``0..max_lag`` by default).

    Attributes
    ----------
    independent : bool
        ``p_value >= alpha``: independence of residual and input is not rejected.
    n_outside : int
        Tested lags whose :math:`|r_{eu}(k)|` exceeds ``bound``.
    """

    lags: NDArray[np.int64]
    cross_correlation: NDArray[np.float64]
    bound: float
    statistic: float
    dof: int
    p_value: float
    alpha: float
    n_samples: int
    tested_lags: NDArray[np.int64]

    @property
    def independent(self) -> bool:
        """Whether independence of residual and input is not rejected at level ``alpha``."""
        return bool(self.p_value >= self.alpha)

    @property
    def n_outside(self) -> int:
        """Number of tested lags outside the confidence bound."""
        sel = np.isin(self.lags, self.tested_lags)
        return int(np.sum(np.abs(self.cross_correlation[sel]) > self.bound))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary.

        Returns
        -------
        dict
        """
        return {"independent": self.independent, "p_value": self.p_value,
                "statistic": self.statistic, "dof": self.dof, "alpha": self.alpha,
                "bound": self.bound, "n_outside": self.n_outside,
                "tested_lags": [int(self.tested_lags[0]), int(self.tested_lags[-1])],
                "max_lag": int(self.lags[-1]), "n_samples": self.n_samples,
                "cross_correlation": self.cross_correlation.tolist()}


def _prewhitening_filter(segs: list[NDArray], order: int | None, max_order: int = 20
                         ) -> NDArray[np.float64]:
    """``A(q) = 1 + a_1 q^-1 + ... + a_p q^-p`` of an AR model of ``segs`` (Yule-Walker).

    The order is ``order``, or the one of smallest AIC ``N ln sigma_p^2 + 2p`` up to
    ``max_order`` (Levinson-Durbin recursion on the pooled autocorrelation).
    """
    n = sum(s.size for s in segs)
    top = min(max_order, max(0, n // 10)) if order is None else order
    if top == 0:
        return np.ones(1)
    r = _lagged_products(segs, segs, np.arange(top + 1)) / n
    a, err = np.ones(1), r[0]
    best_a, best_aic = a, n * np.log(err)
    for k in range(1, top + 1):
        refl = -(r[k] + a[1:] @ r[k - 1 : 0 : -1]) / err
        a = np.concatenate([a, [0.0]]) + refl * np.concatenate([a, [0.0]])[::-1]
        err *= 1 - refl**2
        if err <= 0:
            break
        aic = n * np.log(err) + 2 * k
        if order is not None or aic < best_aic:
            best_a, best_aic = a, aic
    return best_a


def _lag_regression(es: list[NDArray], us: list[NDArray], tested: NDArray
                    ) -> tuple[float, int]:
    """``e^T P e / (e^T e / N)`` with ``P`` the projection on the lagged inputs; its rank."""
    lo, hi = int(max(tested.max(), 0)), int(max(-tested.min(), 0))
    rows_e, rows_u = [], []
    for e, u in zip(es, us, strict=True):
        n = e.size
        if n - lo - hi < 1:
            continue
        idx = np.arange(lo, n - hi)
        rows_e.append(e[idx])
        rows_u.append(np.column_stack([u[idx - k] for k in tested]))
    if not rows_e:
        raise DataError("the records are too short for the lags of the test")
    e = np.concatenate(rows_e)
    X = np.vstack(rows_u)
    U, s, _ = np.linalg.svd(X, full_matrices=False)
    rank = int(np.sum(s > 1e-10 * s[0])) if s.size and s[0] > 0 else 0
    if rank == 0:
        raise DataError("u is constant: the residual cannot be tested against it")
    proj = U[:, :rank].T @ e
    lam = float(e @ e) / e.size
    return float(proj @ proj) / lam, rank


def cross_correlation_test(
    e: ArrayLike | Sequence[ArrayLike], u: ArrayLike | Sequence[ArrayLike], *,
    max_lag: int = DEFAULT_MAX_LAG, alpha: float = 0.05, two_sided: bool = False,
    ar_order: int | None = None, window: int | None = None,
) -> CrossCorrelationTest:
    r"""Test whether a residual is independent of the input (cross-correlation test).

    **Bound.** If :math:`e` and :math:`u` are independent stationary sequences, the sample
    cross-correlation at one lag is about normal with zero mean and variance
    :math:`P/N`, :math:`P = \sum_j r_u(j)\,r_e(j)` (Bartlett), which is 1 when either
    sequence is white. The per-lag bound is :math:`z_{1-\alpha/2}\sqrt{P/N}`, as MATLAB
    ``resid`` draws it; the autocorrelations in ``P`` are tapered with a triangular lag
    window of length ``window``.

    **Test.** The correlations at neighbouring lags are themselves correlated, so the
    portmanteau test is the regression form (Ljung, 16.6): the residual is first
    whitened by an autoregressive filter :math:`A(q)` fitted to it (Yule-Walker, order by
    AIC up to 20, or ``ar_order``) and the input is passed through the same filter; then
    :math:`\varepsilon = A(q)e` is projected on the lagged filtered inputs
    :math:`\varphi(t) = [A(q)u(t-k)]_{k}`, and

    .. math:: S = \frac{\varepsilon^T\Phi(\Phi^T\Phi)^{+}\Phi^T\varepsilon}
                       {\varepsilon^T\varepsilon/N}

    is about :math:`\chi^2` with :math:`\operatorname{rank}\Phi` degrees of freedom when
    the residual is independent of the input (exactly so, given the input, for a
    Gaussian white :math:`\varepsilon`), whatever the colour of the input.

    Parameters
    ----------
    e, u : array-like of shape (n_samples,), or lists of them
        Residual and input, one sequence per record, of matching lengths. Records whose
        input is constant carry no information and are left out.
    max_lag : int, default=25
        Largest lag shown and tested.
    alpha : float, default=0.05
        Significance level.
    two_sided : bool, default=False
        Test lags ``-max_lag..max_lag``; by default only ``0..max_lag`` (the residual
        against present and past inputs: correlation at negative lags shows feedback in
        closed-loop data, not a wrong model).
    ar_order : int, optional
        Order of the whitening filter (0: none); chosen by AIC when omitted.
    window : int, optional
        Length of the lag window in ``P``; by default ``max(2 max_lag, 4 sqrt(N))``,
        at most ``N - 1``.

    Returns
    -------
    CrossCorrelationTest

    Raises
    ------
    DimensionError
        If ``e`` and ``u`` do not match in length.
    DataError
        On non-finite or constant data, ``alpha`` outside (0, 1) or too large a
        ``max_lag``.

    See Also
    --------
    whiteness_test : Whether the residual is white.

    References
    ----------
    L. Ljung, *System Identification: Theory for the User*, 2nd ed., Prentice Hall, 1999,
    section 16.6 (model validation by residual analysis).

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.diagnostics import cross_correlation_test
    >>> rng = np.random.default_rng(0)
    >>> u, v = rng.standard_normal(1000), rng.standard_normal(1000)
    >>> e = v + 0.3 * np.concatenate([[0.0, 0.0], u[:-2]])     # misses u(t - 2)
    >>> cross_correlation_test(v, u).independent, cross_correlation_test(e, u).independent
    (True, False)
    """
    alpha = _check_alpha(alpha)
    es, us = _paired(e, u)
    keep = [i for i, s in enumerate(us) if np.any(s)]
    es, us = [es[i] for i in keep], [us[i] for i in keep]
    n = sum(s.size for s in es)
    lags, r = cross_correlation(es, us, max_lag)
    m = int(lags[-1])
    L = int(min(n - 1, max(2 * m, 4 * np.sqrt(n)))) if window is None else check_int(
        window, "window", 1)
    ll = np.arange(L)
    taper = 1 - ll / L
    re = taper * _lagged_products(es, es, ll)
    ru = taper * _lagged_products(us, us, ll)
    p = float(re[0] * ru[0] + 2 * re[1:] @ ru[1:]) / float(re[0] * ru[0])
    a = _prewhitening_filter(es, None if ar_order is None else check_int(ar_order, "ar_order",
                                                                          0))
    ef = [scipy.signal.lfilter(a, [1.0], s) for s in es]
    uf = [scipy.signal.lfilter(a, [1.0], s) for s in us]
    drop = a.size - 1  # filter start-up
    ef, uf = [s[drop:] for s in ef], [s[drop:] for s in uf]
    tested = lags if two_sided else lags[lags >= 0]
    stat, dof = _lag_regression(ef, uf, tested)
    return CrossCorrelationTest(
        lags=lags, cross_correlation=r, bound=_z(1 - alpha) * float(np.sqrt(max(p, 0.0) / n)),
        statistic=stat, dof=dof, p_value=float(scipy.stats.chi2.sf(stat, dof)), alpha=alpha,
        n_samples=n, tested_lags=tested,
    )
