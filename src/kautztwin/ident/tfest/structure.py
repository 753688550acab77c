r"""Structure selection of ``n_poles='auto'``: cheap screening of all orders, then refinement.

The search, for orders :math:`n = 1 \dots n_\max` (the *bound*, :func:`search_bound`):

1. **Screening** (:meth:`_Search.screen`) on a uniform resampling of the
   records: for every order the balanced truncation of a high-order ARX model
   (input delayed by the whole-sample delay of an ARX loss scan), the ARX(n, n)
   poles, and *warm starts* from the lower orders (the best poles of order
   :math:`n-1` plus one real pole, of :math:`n-2` plus one pair, of :math:`n-1`
   plus one slow pole), mapped to continuous poles :math:`s = \ln z / T_s`.
   Each start costs one variable-projection evaluation of the continuous
   output-error problem (:class:`~.problem._Problem`): numerator, offsets and
   initial states by linear least squares, so each start is a complete model;
   with a delay to estimate, the delay is tuned on a small grid.
2. **Criterion** (:class:`_Scorer`) of every start and number of zeros (one
   more small solve each, from one QR factorisation of the projected
   regressors; the training RSS of the full numerator is the start's cost):
   with a validation part (``validate_from``) the validation fit; else, for
   input/output records, the fit on the last third of each estimation record
   of the model estimated on the first two thirds
   (initial states and slow modes cost what they cost out of sample); for
   several records that start at rest, each record held out in turn.
   With the internal split a structure is represented by its *estimate*, the
   candidate that fits the training rows best (:meth:`_Search.estimates`),
   not by whichever start happens to score best on the held-out rows (which
   would let those rows choose among local minima and favour orders with many
   starts); an estimate that fits its training rows worse than a structure it
   contains is an unconverged start and does not compete.  Screening then
   stops after ``_PATIENCE`` orders without a better pick.
3. **Refinement** (:func:`~.refine.refine_order`): brief output-error
   refinements of the best structures of the pick's order and its neighbours
   (with the internal split: the pick's order and the one below; repeated
   while the pick moves, skipping orders the pick has left), warm started
   from the lower orders; then the pick to convergence, also from VARPRO
   poles of the high-order ARX model's impulse response (that last
   refinement stops at an iterate with a mode slower than the records: the
   criterion rejects such a model).  Refined models join the candidates.
4. **Choice** (:meth:`_Search.pick`): the best criterion minus a small
   per-pole margin, so a higher order is returned only if it scores above every
   lower order (never one that validates worse on the data it was chosen on).
   With the internal split the chosen structure is then estimated on the whole
   records.  A pick at the bound warns.
5. **Integrator** (:func:`search_structure`, :mod:`.integrator`): when the
   high-order ARX model has a mode slower than the records (an integrating
   plant), steps 1-4 run first for ``G(s)/s``, ``G`` on the integrated input
   with a trend per record for the unknown input level; the stable structures
   then challenge that pick: screened until two orders in a row do not improve
   their pick, and refined only if their screened pick comes within ``_NEAR``
   points of the integrating criterion.  The integrating model is returned if
   its criterion is better by the per-pole margin.

Size: over 600 lines because screening, scoring and refinement share the
candidate bookkeeping of one search; the parts are separate classes
(:class:`_Scorer`, :class:`_Search`) and functions.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import NDArray

from ...exceptions import ConvergenceWarning, DataError, KautzTwinError
from ..arx import _regressors
from ..records import MIN_SAMPLES, Record
from .integrator import (
    check_integrable,
    inner_estimator,
    input_level,
    integrated,
    integrating_model,
    mean_level,
)
from .model import TransferFunctionModel
from .problem import (
    _den_from_theta,
    _orth,
    _Problem,
    _theta_bounds,
    _theta_from_poles,
    _trend,
    _weighted_lstsq,
)
from .refine import check_samples, refine_order
from .statistics import finalize

if TYPE_CHECKING:
    from .estimator import TransferFunctionEstimator

__all__: list[str] = []

#: smallest bound of the search, and the largest (long records)
MIN_BOUND, MAX_BOUND = 10, 20
#: estimation samples per searched order above MIN_BOUND ("more with a long record")
SAMPLES_PER_ORDER = 100
#: without a validation part, each extra pole must buy this many points of held-out fit
_PARSIMONY = 0.5
#: with a validation part, differences below this many points per pole are noise
_NOISE = 0.02
#: iterations of a brief refinement; rounds of brief refinements about the pick
_QUICK_ITER, _ROUNDS = 6, 6
#: the lowest order screened within this many points of the best is refined briefly too
_NEAR = 2.0
#: without a validation part, the structure is chosen on the last third of each record
_INNER = 2.0 / 3.0
#: with the internal split, an estimate that fits its training rows this many points worse
#: than a structure it contains is an unconverged start and does not compete
_NESTED = 0.1
#: with the internal split, screening stops after this many orders without a better pick
_PATIENCE = 2
#: samples of the impulse response given to VARPRO, and its budget (``optimize_poles``'
#: ``max_iter``: ``parameters + 1`` residual evaluations besides the Jacobians)
_VARPRO_SAMPLES, _VARPRO_ITER = 120, 1


@dataclass
class _Candidate:
    """One screened or refined structure and its scores."""

    n: int
    m: int
    poles: NDArray
    tau: float
    criterion: float
    fit: float
    rss: float
    refined: bool = False
    den: NDArray | None = None
    sol: Any = None
    caught: list[Any] = field(default_factory=list)


# =========================================================================== bound
def n_parameters(tf: TransferFunctionEstimator, est: list[Record], n: int, m: int) -> int:
    """Parameters of order ``n`` with ``m`` zeros: numerator, denominator, delay, nuisance."""
    free = sum((1 if tf.offset else 0) + (n if _free(tf, r) else 0) for r in est)
    return (m + 1) + n + free + (1 if tf.delay is True else 0)


def _free(tf: TransferFunctionEstimator, r: Record) -> bool:
    return tf.initial_state == "estimate" or (tf.initial_state == "auto" and r.kind == "io")


def search_bound(tf: TransferFunctionEstimator, est: list[Record]) -> tuple[int, str]:
    """Largest order searched and why: the data's support, at least 10, more with long records.

    ``MIN_BOUND`` poles, one more per ``SAMPLES_PER_ORDER`` estimation samples
    beyond ``MIN_BOUND * SAMPLES_PER_ORDER`` (at most ``MAX_BOUND``), or
    ``max_order`` when given; then lowered until the estimation samples are at
    least three times the parameters (zeros ``n - 1``, offsets, initial states).
    For ``G`` of an integrating model ``G(s)/s`` (:mod:`.integrator`) the bound
    counts the integrator, as ``n_poles`` does: ``G`` has one pole less.
    """
    n_samples = sum(r.n_samples for r in est)
    if tf.max_order is None:
        bound = int(min(MAX_BOUND, max(MIN_BOUND, n_samples // SAMPLES_PER_ORDER)))
        why = (f"{bound} = clip(estimation samples / {SAMPLES_PER_ORDER}, {MIN_BOUND}, "
               f"{MAX_BOUND})")
    else:
        bound = int(tf.max_order)
        why = f"max_order = {bound}"
    if _trend(tf):
        bound = max(1, bound - 1)
        why += f" poles with the integrator: G has at most {bound}"
    n = bound
    while n > 1 and 3 * n_parameters(tf, est, n, n - 1) > n_samples:
        n -= 1
    if n < bound:
        why += f", lowered to {n}: the estimation samples must be >= 3 x the parameters"
    return n, why


# =========================================================================== screening data
def _uniform(est: list[Record], dt: float) -> list[tuple[NDArray, NDArray]]:
    """Input (from its rest level) and output of every record on a uniform grid of step ``dt``."""
    out = []
    for r in est:
        tg = r.t[0] + dt * np.arange(int(math.floor(r.duration / dt + 1e-9)) + 1)
        y = np.interp(tg, r.t, r.y)
        if r.kind == "io":
            k = np.clip(np.searchsorted(r.t, tg, side="right") - 1, 0, r.t.size - 1)
            u = r.u[k] - r.u_before
        elif r.kind == "step":
            u = np.where(tg >= r.start, float(r.amplitude), 0.0)  # type: ignore[arg-type]
        else:
            u = np.zeros(tg.size)
            u[min(int(round((r.start - r.t[0]) / dt)), tg.size - 1)] = r.amplitude / dt
        out.append((u, y))
    return out


def _stable(a: NDArray) -> NDArray[np.float64]:
    """``a`` with roots outside the unit circle reflected inside (and pulled off it)."""
    z = np.roots(a)
    if z.size == 0:
        return a
    mag = np.abs(z)
    z = np.where(mag > 1, z / np.maximum(mag, 1e-300) ** 2, z)
    z = np.where(np.abs(z) > 0.9999, 0.9999 * z / np.abs(z), z)
    return np.real(np.poly(z))


def _arx(segs: list[tuple[NDArray, NDArray]], na: int, nb: int, nk: int, first: int
         ) -> tuple[NDArray, NDArray, float]:
    """Least-squares ARX(na, nb, nk), one offset per record, rows from ``first``: a, b, loss."""
    rows, tgt = [], []
    for j, (u, y) in enumerate(segs):
        Phi = _regressors(u, y, na, nb, nk)[first:]
        off = np.zeros((Phi.shape[0], len(segs)))
        off[:, j] = 1.0
        rows.append(np.hstack([Phi, off]))
        tgt.append(y[first:])
    Phi, yy = np.vstack(rows), np.concatenate(tgt)
    scale = np.linalg.norm(Phi, axis=0)
    scale[scale == 0] = 1.0
    theta = np.linalg.lstsq(Phi / scale, yy, rcond=None)[0] / scale
    r = yy - Phi @ theta
    return np.concatenate([[1.0], theta[:na]]), theta[na:na + nb], float(r @ r)


def _best_nk(segs: list[tuple[NDArray, NDArray]], max_nk: int) -> int:
    """Input lag (whole-sample delay plus one for the hold) of the least ARX(4, 4, nk) loss."""
    first = 4 + max_nk + 3
    losses = [_arx(segs, 4, 4, nk, first)[2] for nk in range(1, max_nk + 1)]
    return 1 + int(np.argmin(losses))


def _sqrt_psd(P: NDArray) -> NDArray[np.float64]:
    w, V = np.linalg.eigh((P + P.T) / 2)
    return V * np.sqrt(np.maximum(w, 0.0))


def _balanced_denominators(A: NDArray, B: NDArray, C: NDArray, n_max: int
                           ) -> dict[int, NDArray]:
    """Denominators of the balanced truncations of a stable discrete ``(A, B, C)`` to ``1..n_max``.

    Square-root balancing with the discrete Gramians; the truncation to order
    ``n`` keeps the ``n`` largest Hankel singular values.
    """
    out: dict[int, NDArray] = {}
    B = B.reshape(-1, 1)
    C = C.reshape(1, -1)
    try:
        P = scipy.linalg.solve_discrete_lyapunov(A, B @ B.T)
        Q = scipy.linalg.solve_discrete_lyapunov(A.T, C.T @ C)
        Lp, Lq = _sqrt_psd(P), _sqrt_psd(Q)
        U, sv, Vt = np.linalg.svd(Lq.T @ Lp)
    except (np.linalg.LinAlgError, ValueError):
        return out
    keep = int(np.sum(sv > 1e-12 * sv[0])) if sv.size and sv[0] > 0 else 0
    for n in range(1, min(n_max, keep) + 1):
        S = np.diag(sv[:n] ** -0.5)
        T = Lp @ Vt[:n].T @ S
        Ti = S @ U[:, :n].T @ Lq.T
        out[n] = np.real(np.poly(np.linalg.eigvals(Ti @ A @ T)))
    return out


def _shift(segs: list[tuple[NDArray, NDArray]], nk: int) -> list[tuple[NDArray, NDArray]]:
    """The inputs delayed by ``nk - 1`` samples (the reductions spend no poles on the delay)."""
    return [(np.concatenate([np.zeros(nk - 1), u[: u.size - nk + 1]]) if nk > 1 else u, y)
            for u, y in segs]


def _reduced_denominators(segs: list[tuple[NDArray, NDArray]], nk: int, n_high: int,
                          n_max: int, slow: float = 0.0
                          ) -> tuple[dict[int, NDArray], tuple[NDArray, NDArray] | None, bool]:
    """Discrete denominators of orders ``1..n_max``: balanced truncations of a high-order ARX.

    ARX(``n_high``, ``n_high``) on the input delayed by ``nk - 1`` samples, made
    stable, balanced and truncated (the idea of Zhu's ASYM method).  Also
    returns the high-order model ``(a, b)`` and whether, before it was made
    stable, it had a positive real pole at or beyond ``exp(-slow)`` (a mode no
    slower than ``slow`` per sample may be resolved; this one is an integrator
    or slower than the records).
    """
    a, b, _ = _arx(_shift(segs, nk), n_high, n_high, 1, n_high)
    z = np.roots(a)
    real = z[(np.abs(z.imag) <= 1e-9 * np.maximum(np.abs(z), 1e-300)) & (z.real > 0)].real
    has_slow = bool(real.size and np.max(real) >= math.exp(-slow))
    a = _stable(a)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tf2ss' BadCoefficients on leading zeros
        A, B, C, _ = scipy.signal.tf2ss(np.concatenate([[0.0], b]), a)
    return _balanced_denominators(A, B, C, n_max), (a, b), has_slow


def _continuous(a: NDArray, dt: float, rate_lo: float, rate_hi: float) -> NDArray[np.complex128]:
    """Continuous poles ``ln(z) / dt`` of a discrete denominator (negative reals folded)."""
    z = np.roots(a).astype(complex)
    real = np.abs(z.imag) <= 1e-9 * np.maximum(np.abs(z), 1e-300)
    z = np.where(real, np.abs(z.real) + 0j, z)  # ringing poles on the negative axis: fast reals
    z = np.where(np.abs(z) < 1e-12, 1e-12, z)
    s = np.log(z) / dt
    s = np.where(real, s.real + 0j, s)
    rate = np.clip(-s.real, rate_lo, rate_hi)
    return -rate + 1j * s.imag


# =========================================================================== scoring
class _Scorer:
    """Criterion and training fit of a denominator and delay, for every number of zeros.

    For every fold ``(train, test)`` (one boolean mask per record each) the
    numerator, offsets and initial states are solved on the ``train`` rows; the
    model is simulated over the whole records and scored on the ``test`` rows.
    A record without training rows (held out whole) gets its offset from its
    test rows.  The criterion is the fit percent of the test rows of all folds
    pooled (on the scale of the whole records with :meth:`per_sample_spread`).
    """

    def __init__(self, tf: TransferFunctionEstimator, records: list[Record],
                 folds: list[tuple[list[NDArray], list[NDArray]]]) -> None:
        self.tf = tf
        self.records = records
        self.folds = folds
        self.y = [np.asarray(r.y) for r in records]
        self.sw = [np.sqrt(np.asarray(r.weights)) for r in records]
        self.relative_to: float | None = None
        self.w_test = float(sum(np.sum(np.asarray(r.weights)[te]) for _, tes in folds
                                for r, te in zip(records, tes, strict=True)))
        self.slowest: float | None = None
        self.n_eval = 0

    def unresolved(self, den: NDArray) -> bool:
        """Whether ``den`` has a mode slower than the records resolve (scored ``-inf``)."""
        return self.slowest is not None and bool(np.min(-np.roots(den).real) < self.slowest)

    def per_sample_spread(self) -> None:
        """Score the test rows on the scale of the whole records (their spread per weight)."""
        spread = weight = 0.0
        for y, sw in zip(self.y, self.sw, strict=True):
            w = sw**2
            spread += float(np.sum(w * (y - np.sum(w * y) / np.sum(w)) ** 2))
            weight += float(np.sum(w))
        self.relative_to = spread / weight

    def score(self, den: NDArray, tau: float, ms: list[int]
              ) -> dict[int, tuple[float, float, float]]:
        """``{m: (criterion, training fit, training RSS)}`` for the numbers of zeros ``ms``.

        The training fit and RSS are those of the first fold.  A model whose
        simulation breaks down numerically scores ``-inf``.
        """
        try:
            with np.errstate(all="ignore"):
                return self._score(den, tau, ms)
        except (np.linalg.LinAlgError, ValueError):
            return {m: (-math.inf, math.nan, math.inf) for m in ms}

    def _fold(self, cols: list[tuple[NDArray, NDArray]], ms: list[int], train: list[NDArray],
              test: list[NDArray]) -> dict[int, tuple[NDArray, bool]]:
        """For every ``m``: sums (test error, test spread, train error, train spread), finite.

        The nuisance columns are projected out of the numerator regressors once
        for all numbers of zeros: the regressors of ``m`` zeros are the first
        ``m + 1`` columns and the projection acts column by column.  One QR
        factorisation of the (column-scaled) projected regressors then gives
        every numerator: the least-squares problem of the first ``k`` columns
        is the ``k x k`` triangular block against the first ``k`` rotated
        targets (solved by ``lstsq`` with the cut-off of the full problem).
        The per-record maps from the numerator to the nuisance parameters are
        linear too (``c = C_y - C_R b``), so all simulated outputs are one
        product.
        """
        Rt, yt = [], []
        maps = []
        for (R, N), y, sw, tr, te in zip(cols, self.y, self.sw, train, test, strict=True):
            if tr.any():
                s = sw[tr]
                Q = _orth(N[tr] * s[:, None])
                Rm, yw = R[tr] * s[:, None], y[tr] * s
                Rt.append(Rm - Q @ (Q.T @ Rm))
                yt.append(yw - Q @ (Q.T @ yw))
            use = tr if tr.any() else te
            maps.append(_weighted_lstsq(N[use], np.column_stack([y[use], R[use]]), sw[use]))
        Rs, ys = np.vstack(Rt), np.concatenate(yt)
        scale = np.linalg.norm(Rs, axis=0)
        scale[scale == 0] = 1.0
        Qr, Tr = np.linalg.qr(Rs / scale)
        qy = Qr.T @ ys
        eps = np.finfo(float).eps
        B = np.zeros((Rs.shape[1], len(ms)))
        for j, m in enumerate(ms):
            k = m + 1
            B[:k, j] = np.linalg.lstsq(Tr[:k, :k], qy[:k], rcond=eps * max(Rs.shape[0], k)
                                       )[0] / scale[:k]
        sums = np.zeros((len(ms), 4))
        for (R, N), y, sw, tr, te, C in zip(cols, self.y, self.sw, train, test, maps,
                                             strict=True):
            Yh = R @ B + N @ (C[:, :1] - C[:, 1:] @ B)
            for k, mask in ((0, te), (2, tr)):
                if mask.any():
                    w = sw[mask] ** 2
                    ym = y[mask]
                    sums[:, k] += w @ (ym[:, None] - Yh[mask]) ** 2
                    sums[:, k + 1] += float(np.sum(w * (ym - np.sum(w * ym) / np.sum(w)) ** 2))
        finite = np.all(np.isfinite(B), axis=0)
        return {m: (sums[j], bool(finite[j])) for j, m in enumerate(ms)}

    def _score(self, den: NDArray, tau: float, ms: list[int]
               ) -> dict[int, tuple[float, float, float]]:
        n = den.size - 1
        prob = _Problem(self.records, n, n - 1, intersample=self.tf.intersample,
                        offset=bool(self.tf.offset), initial_state=self.tf.initial_state,
                        trend=_trend(self.tf))
        cols = prob.all_columns(den, tau)
        self.n_eval += 1
        unresolved = self.unresolved(den)
        folds = [self._fold(cols, ms, train, test) for train, test in self.folds]
        out = {}
        for m in ms:
            err = spread = 0.0
            ok = True
            for per_m in folds:
                sums, fin = per_m[m]
                ok = ok and fin
                err += sums[0]
                spread += sums[1]
            first = folds[0][m][0]
            if self.relative_to is not None:
                spread = self.relative_to * self.w_test
            crit = 100.0 * (1.0 - math.sqrt(err / spread)) if spread > 0 else -math.inf
            fit = 100.0 * (1.0 - math.sqrt(first[2] / first[3])) if first[3] > 0 else math.nan
            ok = ok and math.isfinite(crit) and not unresolved  # slower than the records: no
            out[m] = (crit if ok else -math.inf, fit, float(first[2]))
        return out


def _inner_split(tf: TransferFunctionEstimator, est: list[Record]
                 ) -> tuple[list[Record], list[NDArray], list[NDArray]]:
    """Estimation records cut at ``_INNER`` of their duration: fit parts, train and test masks.

    A record whose first part could not carry a first-order model (two samples
    per parameter), or whose step falls in its last part, is not cut.
    """
    fit, train, test = [], [], []
    for r in est:
        cut = r.t[0] + _INNER * r.duration
        mask = r.t < cut
        need = max(MIN_SAMPLES, 2 * n_parameters(tf, [r], 1, 0))
        ok = (mask.sum() >= need and (~mask).sum() >= 2
              and (r.kind == "io" or r.start < cut))  # type: ignore[operator]
        if not ok:
            mask = np.ones(r.n_samples, dtype=bool)
        fit.append(r.select(mask) if not mask.all() else r)
        train.append(mask)
        test.append(~mask)
    return fit, train, test


# =========================================================================== the search
class _Search:
    """Screening, scoring and refinement of candidate structures on one estimation set."""

    def __init__(self, tf: TransferFunctionEstimator, fit_recs: list[Record], scorer: _Scorer,
                 bound: int, *, honest: bool = False) -> None:
        self.tf = tf
        self.honest = honest
        self.fit_recs = fit_recs
        self.scorer = scorer
        self.dt = float(min(np.median(np.diff(r.t)) for r in fit_recs))
        span = float(max(r.duration for r in fit_recs))
        self.rate_lo, self.rate_hi = 0.01 / span, 50.0 / self.dt
        self.segs = _uniform(fit_recs, self.dt)
        self.impulse = any(r.kind == "impulse" for r in fit_recs)
        tau_max = 0.25 * float(min(r.duration for r in fit_recs))
        if tf.delay is True:
            self.nk = _best_nk(self.segs, int(min(10, max(1, tau_max // self.dt))))
            self.taus = sorted({min(max(0.0, (self.nk - 1 + f) * self.dt), tau_max)
                                for f in (0.0, -1.0, -0.5, 0.5, 1.0, 1.5)})
        else:
            fixed = 0.0 if tf.delay is False else float(tf.delay)
            self.nk = 1 + int(math.floor(fixed / self.dt + 1e-9))
            self.taus = [fixed]
        n_samples = sum(r.n_samples for r in fit_recs)
        self.bound = bound
        while self.bound > 1 and 3 * n_parameters(tf, fit_recs, self.bound,
                                                  self.bound - 1) > n_samples:
            self.bound -= 1
        self.n_high = int(min(max(3 * self.bound, 30), max(self.bound + 1, n_samples // 20)))
        self.cands: list[_Candidate] = []
        self.best_poles: dict[int, tuple[NDArray, float]] = {}
        self.refined: dict[tuple[int, int], _Candidate] = {}
        self._probs: dict[int, _Problem] = {}
        self.high: tuple[NDArray, NDArray] | None = None
        self.starts: dict[int, list[tuple[str, NDArray]]] = {}
        self.slow_rate = 2.0 / span
        self.screened_to = self.bound
        self.slow_mode = False
        #: the scorer's first-fold training rows are exactly ``fit_recs`` (set by the caller):
        #: a start's cost is then its training RSS with the full numerator, no extra simulation
        self.cost_from_score = False
        #: screening stops after ``_PATIENCE`` orders without a better pick (a challenger
        #: family, :func:`search_structure`; always with ``honest``)
        self.patience = False
        #: set by :meth:`run` when a challenger's screened pick was not refined
        self.unrefined = False
        self._reduced: dict[int, NDArray] | None = None

    def zeros_for(self, n: int) -> list[int]:
        ms = ([min(int(self.tf.n_zeros), n - 1)] if self.tf.n_zeros is not None
              else list(range(n)))
        return [m for m in ms if not (self.impulse and m >= n)]

    def clip_poles(self, p: NDArray, n: int) -> NDArray | None:
        p = np.asarray(p, dtype=complex)
        if p.size != n or not np.all(np.isfinite(p)):
            return None
        lo, hi = _theta_bounds(n, self.rate_lo, self.rate_hi)
        try:
            th = np.clip(_theta_from_poles(p, n), lo + 1e-6, hi - 1e-6)
        except KautzTwinError:
            return None
        return np.roots(_den_from_theta(th, n)).astype(complex)

    def cost(self, p: NDArray, tau: float) -> float:
        n = p.size
        if n not in self._probs:
            self._probs[n] = _Problem(self.fit_recs, n, n - 1, intersample=self.tf.intersample,
                                      offset=bool(self.tf.offset),
                                      initial_state=self.tf.initial_state,
                                      trend=_trend(self.tf))
        try:
            with np.errstate(all="ignore"):
                r = self._probs[n].residual(np.real(np.poly(p)), tau)
        except (np.linalg.LinAlgError, ValueError):
            return math.inf
        cost = float(r @ r)
        return cost if math.isfinite(cost) else math.inf

    def screen(self, per_pole: float = 0.0) -> None:
        """Candidates of every order: reduced high-order ARX poles and lower-order warm starts.

        The starts of order ``n`` (logged in ``self.starts[n]`` with their origin):
        the balanced truncation of the high-order ARX model, the ARX(n, n)
        poles, the best poles of order ``n - 1`` plus one real pole and of
        order ``n - 2`` plus one pair (both from the truncation), and the best
        poles of order ``n - 1`` plus one slow pole (``2 / record length``) when
        they have none.  Each start costs one variable-projection evaluation.

        With ``self.honest`` the screening stops once ``_PATIENCE`` orders in a
        row have not raised the best ``criterion - per_pole * n`` of the
        estimates (:meth:`estimates`); with ``self.patience`` likewise, of all
        candidates.
        """
        dens = self.prepare()
        best, since = -math.inf, 0
        for n in range(1, self.bound + 1):
            if (self.honest or self.patience) and n > 1:
                pool = self.estimates() if self.honest else self.cands
                score = max((c.criterion - per_pole * c.n for c in pool), default=-math.inf)
                since = 0 if score > best else since + 1
                best = max(best, score)
                if since >= _PATIENCE:
                    self.screened_to = n - 1
                    break
            labelled: list[tuple[str, NDArray]] = []
            if n in dens:
                labelled.append(("reduced high-order ARX",
                                 _continuous(dens[n], self.dt, self.rate_lo, self.rate_hi)))
            try:
                a, _, _ = _arx(self.segs, n, n, self.nk, n + self.nk)
                labelled.append((f"ARX({n}, {n})", _continuous(_stable(a), self.dt,
                                                               self.rate_lo, self.rate_hi)))
            except (np.linalg.LinAlgError, ValueError):
                pass
            ref = labelled[0][1] if labelled else np.zeros(0, dtype=complex)
            for k, kind in ((1, "real"), (2, "pair")):
                if n - k not in self.best_poles:
                    continue
                lower = self.best_poles[n - k][0]
                extra = _extra_poles(lower, ref, kind, self.rate_hi)
                if extra is not None:
                    labelled.append((f"order {n - k} + {kind}", np.concatenate([lower, extra])))
            if n - 1 in self.best_poles and not np.any(
                    -self.best_poles[n - 1][0].real < 5 * self.slow_rate):
                # one slow mode (drift, slow settling) that an ARX model does not resolve
                labelled.append((f"order {n - 1} + slow",
                                 np.append(self.best_poles[n - 1][0], -self.slow_rate + 0j)))
            self.starts[n] = labelled
            starts = [p for _, p in labelled]
            tau0 = self.best_poles[n - 1][1] if n - 1 in self.best_poles else self.taus[0]
            ms = self.zeros_for(n)
            # (cost, poles, delay, scores of every m or None when still to be scored)
            scored: list[tuple[float, NDArray, float, dict[int, Any] | None]] = []
            for p in starts:
                pc = self.clip_poles(p, n)
                if pc is None:
                    continue
                if self.cost_from_score:
                    # the training RSS of the full numerator is the search's cost: one
                    # simulation scores the start and ranks it
                    sc = self.scorer.score(np.real(np.poly(pc)), tau0,
                                           sorted(set(ms) | {n - 1}))
                    c, scores = sc[n - 1][2], {m: sc[m] for m in ms}
                else:
                    c, scores = self.cost(pc, tau0), None
                if math.isfinite(c):
                    scored.append((c, pc, tau0, scores))
            if not scored:
                continue
            i = int(np.argmin([x[0] for x in scored]))
            for tau in self.taus:  # the delay of the best start on the grid
                if tau != tau0:
                    c = self.cost(scored[i][1], tau)
                    if c < scored[i][0]:
                        scored[i] = (c, scored[i][1], tau, None)
            _, pc, tau, _ = scored[i]
            self.best_poles[n] = (pc, tau)
            for _, pc, tau, scores in scored:  # every start is a candidate, scored for every m
                if scores is None:
                    scores = self.scorer.score(np.real(np.poly(pc)), tau, ms)
                for m, (crit, fit, rss) in scores.items():
                    self.cands.append(_Candidate(n, m, pc, tau, crit, fit, rss))

    def prepare(self) -> dict[int, NDArray]:
        """The reduced high-order ARX denominators (once); sets ``high`` and ``slow_mode``."""
        if self._reduced is None:
            n_uniform = sum(u.size for u, _ in self.segs)
            self._reduced, self.high, self.slow_mode = _reduced_denominators(
                self.segs, self.nk, self.n_high, self.bound, slow=1.0 / max(n_uniform, 1))
        return self._reduced

    def varpro(self, init: NDArray, max_iter: int = _VARPRO_ITER) -> NDArray | None:
        """VARPRO poles, from ``init``, for the impulse response of the high-order ARX model.

        :func:`kautztwin.optimize_poles` with its ``max_iter`` (a budget of
        ``max_iter * (parameters + 1)`` residual evaluations besides the
        Jacobians: with 1, a few iterations, which is all a start needs) on
        ``_VARPRO_SAMPLES`` samples spanning about five time constants of the
        slowest pole of ``init``.
        """
        from ...approx import optimize_poles

        if self.high is None:
            return None
        a, b = self.high
        slowest = float(np.min(-np.asarray(init).real))
        n_t = int(min(_VARPRO_SAMPLES, max(20, math.ceil(5.0 / (slowest * self.dt)))))
        step = max(1, math.ceil(5.0 / (slowest * self.dt) / n_t))  # cover ~5 time constants
        imp = np.zeros(n_t * step + 1)
        imp[0] = 1.0 / self.dt
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            h = scipy.signal.lfilter(np.concatenate([[0.0], b]), a, imp)
        # from the first sample after the pulse: a sum of exponentials in t (the held
        # pulse's response sampled), whose poles are the model's
        h = h[1::step]
        if not np.all(np.isfinite(h)) or np.ptp(h) == 0:
            return None
        t = self.dt * step * np.arange(h.size)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = optimize_poles(t, h, init, kind="impulse", max_iter=max_iter)
        except (KautzTwinError, np.linalg.LinAlgError, ValueError):
            return None
        return np.asarray(res.basis.poles, dtype=complex)

    def refine(self, c: _Candidate, *, recs: list[Record] | None = None,
               max_iter: int | None = None, warm: bool = True) -> _Candidate:
        """Output-error refinement of ``c`` from its poles and warm starts, then its score.

        ``max_iter`` iterations (``tf.max_iter`` when omitted) from the best of:
        ``c``'s poles and, with ``warm``, the refined poles of the next lower
        order plus the missing ones and (full refinements) the VARPRO poles of
        the high-order ARX model's impulse response.  A brief refinement on the
        search's records is scored for every number of zeros.
        """
        starts = [(c.poles, c.tau)]
        lower = [r for r in self.cands if r.sol is not None and r.n < c.n] if warm else []
        if lower and c.n in self.best_poles:
            top = max(r.n for r in lower)
            low = max((r for r in lower if r.n == top), key=lambda r: r.criterion)
            kind = "real" if c.n - low.n == 1 else ("pair" if c.n - low.n == 2 else None)
            extra = (None if kind is None else
                     _extra_poles(low.poles, self.best_poles[c.n][0], kind, self.rate_hi))
            if extra is not None:
                grown = self.clip_poles(np.concatenate([low.poles, extra]), c.n)
                if grown is not None:
                    starts.append((grown, low.tau))
        vp = self.varpro(c.poles) if warm and max_iter is None else None
        vp = None if vp is None else self.clip_poles(vp, c.n)
        if vp is not None:
            starts.append((vp, c.tau))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                _, den, tau, sol = refine_order(self.tf, recs or self.fit_recs, c.n, c.m,
                                                starts=starts, max_iter=max_iter,
                                                min_rate=self.scorer.slowest,
                                                stop_unresolved=recs is None and max_iter is None)
            except (np.linalg.LinAlgError, ValueError) as exc:
                if isinstance(exc, KautzTwinError):
                    raise
                return c  # the refinement broke down numerically: keep the screened model
        ms = [c.m] if (recs is not None or max_iter is None) else self.zeros_for(c.n)
        poles = np.roots(den).astype(complex)
        out = None
        if not self.honest and self.scorer.unresolved(den):
            # a mode slower than the records: the criterion rejects it for every m, whatever
            # the simulation (its training fit only matters to the internal split's estimates)
            scores = {m: (-math.inf, math.nan, math.inf) for m in ms}
        else:
            scores = self.scorer.score(den, tau, ms)
        for m, (crit, fit, rss) in scores.items():
            r = _Candidate(c.n, m, poles, tau, crit, fit, rss, refined=(
                max_iter is None and m == c.m), den=den, sol=sol, caught=list(caught))
            if m == c.m:
                out = r
            if recs is None:
                if r.refined:
                    self.refined[(c.n, c.m)] = r
                self.cands.append(r)
        assert out is not None
        return out

    def estimates(self) -> list[_Candidate]:
        """The estimate of every structure: its candidate of least training RSS, if credible.

        Used with the internal split (``self.honest``), where the criterion is
        a fit on held-out rows of the estimation records: a structure is judged
        by the model its training rows give (the start that fits them best),
        never by the start that happens to score best on the held-out rows
        (choosing among starts there would fit the held-out rows too).  An
        estimate that fits its training rows worse than a structure it
        contains (fewer or equal poles and zeros) by more than ``_NESTED``
        points is an unconverged start, not evidence for its structure, and is
        left out.
        """
        rep: dict[tuple[int, int], _Candidate] = {}
        for c in sorted(self.cands, key=lambda c: (c.n, c.m, not c.refined)):
            k = (c.n, c.m)
            if k not in rep or c.rss < rep[k].rss * (1.0 - 1e-12):
                rep[k] = c
        out = []
        for (n, m), c in rep.items():
            nested = [r.fit for (k, j), r in rep.items()
                      if k <= n and j <= m and (k, j) != (n, m) and math.isfinite(r.fit)]
            if not math.isfinite(c.fit) or (nested and c.fit < max(nested) - _NESTED):
                continue
            out.append(c)
        return out

    def pick(self, per_pole: float) -> _Candidate:
        """Best ``criterion - per_pole * n`` (ties: fewer poles and zeros, refined first).

        A higher order therefore wins only with a criterion above every
        lower-order candidate's (by ``per_pole`` points per extra pole).  With
        ``self.honest`` only :meth:`estimates` compete.
        """
        pool = self.estimates() if getattr(self, "honest", False) else self.cands
        if not pool:
            pool = self.cands
        chosen = None
        for c in sorted(pool, key=lambda c: (c.n, c.m, not c.refined)):
            if chosen is None or (c.criterion - per_pole * c.n
                                  > chosen.criterion - per_pole * chosen.n):
                chosen = c
        assert chosen is not None
        return chosen

    def per_order(self) -> dict[int, _Candidate]:
        """The best-scoring candidate of every order (with ``self.honest``: of its estimates).

        An order without a credible estimate (see :meth:`estimates`) is
        represented by its candidate of least training RSS, which a refinement
        may make credible.
        """
        per_n: dict[int, _Candidate] = {}
        pool = self.estimates() if getattr(self, "honest", False) else self.cands
        for c in pool:
            if c.n not in per_n or c.criterion > per_n[c.n].criterion:
                per_n[c.n] = c
        for c in self.cands:
            if c.n not in per_n or (c.n not in {e.n for e in pool}
                                    and c.rss < per_n[c.n].rss):
                per_n[c.n] = c
        return per_n

    def run(self, per_pole: float, *, polish: bool = True, reach: float | None = None
            ) -> _Candidate:
        """Screen every order; refine briefly about the pick until it settles; then fully.

        With ``reach`` (a challenger family, :func:`search_structure`) the
        screening stops after ``_PATIENCE`` orders without a better pick, and
        a screened pick whose criterion is below ``reach - _NEAR`` is returned
        as it is (``self.unrefined``): it is not refined.

        The best screened structure of the pick's order and of its two neighbouring
        orders (and of the lowest order screened within ``_NEAR`` points of the
        best) gets ``_QUICK_ITER`` iterations of output-error refinement, warm
        started from the lower orders, in increasing order; an order the pick
        has moved away from in the meantime (no longer the pick or next to it)
        is skipped.  This repeats while the pick's order changes (at most
        ``_ROUNDS`` times).  The pick is then refined to convergence
        (``polish``; the inner split refits the pick on the whole records
        instead); if a screened or briefly refined model still scores best it
        is returned as it is.  The refinement to convergence stops at its
        first iterate with a mode slower than the records
        (:func:`~.refine.refine_order`'s ``stop_unresolved``): the criterion
        rejects such a model, and such a refinement was not seen to come back
        (brief refinements do come back from there, and are not stopped).
        """
        self.patience = self.patience or reach is not None
        self.screen(per_pole)
        if not self.cands:
            raise DataError("the structure search found no usable model for these records")
        if reach is not None and self.pick(per_pole).criterion < reach - _NEAR:
            self.unrefined = True
            return self.pick(per_pole)
        per_n = self.per_order()
        ranked = sorted(per_n.values(), key=lambda c: -c.criterion)
        low = min((c for c in ranked if c.criterion >= ranked[0].criterion - _NEAR),
                  key=lambda c: c.n)
        done: set[int] = set()
        todo = {low.n}

        def near() -> set[int]:
            p = self.pick(per_pole).n
            # honest: the pick and the order below (a higher order is not explored further:
            # its held-out score is already discounted by the screening's order of estimates)
            return {k for k in ((p - 1, p) if self.honest else (p - 1, p, p + 1))
                    if k in per_n}

        for _ in range(_ROUNDS):
            todo = (todo | near()) - done
            if not todo:
                break
            for n in sorted(todo):
                if n != low.n and n not in near():
                    continue  # the pick has moved away from this order
                self.refine(per_n[n], max_iter=_QUICK_ITER)
                done.add(n)
                if self.honest:  # a refined estimate may now represent its order
                    per_n = self.per_order()
            todo = set()
        chosen = self.pick(per_pole)
        if polish and not chosen.refined:
            self.refine(chosen)
        return self.pick(per_pole)


def _extra_poles(lower: NDArray, ref: NDArray, kind: str, rate_hi: float) -> NDArray | None:
    """One real pole or one pair from ``ref`` (farthest from ``lower``) to add to ``lower``."""
    if kind == "real":
        reals = ref[np.abs(ref.imag) <= 1e-9 * np.abs(ref)]
        if not reals.size:
            return np.array([-rate_hi / 5 + 0j])
        pool = reals
    else:
        pool = ref[ref.imag > 1e-9 * np.abs(ref)]
        if not pool.size:
            return None
    if lower.size:
        dist = [float(np.min(np.abs(lower - q))) for q in pool]
        q = pool[int(np.argmax(dist))]
    else:
        q = pool[0]
    return np.array([q]) if kind == "real" else np.array([q, np.conj(q)])


def search_structure(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record]
                     ) -> tuple[TransferFunctionModel, list[Any]]:
    """Choose and fit the structure; return the model and the chosen one's warnings.

    The stable search (:func:`_search`, see the module docstring); with
    ``integrator=None``, when the stable search's high-order ARX model shows a
    mode the stable structures cannot resolve (a positive real pole at or
    beyond ``exp(-1 / n_samples)``: an integrator or a mode slower than the
    records) and the records are held input/output records, the search for
    ``G(s)/s`` (:mod:`.integrator`) runs first, and the stable structures
    challenge its pick: they are screened (until ``_PATIENCE`` orders in a row
    do not improve their pick) and refined only if their screened pick comes
    within ``_NEAR`` points of the criterion they must reach.  The integrating
    model is returned if its criterion beats the stable one's by the per-pole
    margin.  With ``integrator=True`` only the integrating search runs, with
    ``False`` only the stable one.  Sets ``tf.search_`` (bound, criterion,
    candidates, timings, the integrator's trial) on the estimator.
    """
    t_start = time.perf_counter()
    mode = getattr(tf, "integrator", None)
    info: dict[str, Any] = {"tried": False, "chosen": False}
    model = caught = at_bound = None
    crit = -math.inf
    stable = None
    if mode is not True:
        stable = _prepare(tf, recs, est)
        if mode is False or _trend(tf):
            info["reason"] = "integrator=False"
        elif not stable.search.slow_mode:
            info["reason"] = "no mode slower than the records in the high-order ARX model"
        elif check_integrable(tf, recs) is not None:
            info["reason"] = check_integrable(tf, recs)
        if "reason" in info:
            model, caught, crit, _, at_bound = _search(tf, recs, est, stable)
    elif check_integrable(tf, recs) is not None:
        raise DataError(str(check_integrable(tf, recs)))
    if mode is True or (mode is None and "reason" not in info):
        mean = mean_level(est)
        inner = inner_estimator(tf)
        est_v = [integrated(r, mean) for r in est]
        try:
            m_v, caught_v, crit_v, _, at_bound_v = _search(
                inner, [integrated(r, mean) for r in recs], est_v)
        except (KautzTwinError, np.linalg.LinAlgError, ValueError) as exc:
            if stable is None:
                raise
            info.update(tried=True, reason=f"the integrating search failed: {exc}")
            model, caught, crit, _, at_bound = _search(tf, recs, est, stable)
        else:
            assert m_v is not None
            tf.n_evaluations_ += inner.n_evaluations_
            margin = float(inner.search_["points_per_pole"])
            if stable is not None:  # the stable structures challenge the integrating pick
                model, caught, crit, _, at_bound = _search(tf, recs, est, stable,
                                                           reach=crit_v - margin)
            info.update(tried=True, criterion=crit_v, stable_criterion=crit)
            if stable is not None:
                info["stable_refined"] = not stable.search.unrefined
            if mode is True or crit_v > crit + margin:
                level = input_level(inner, m_v, est_v, mean)
                rows = tuple({**r, "n_poles": r["n_poles"] + 1, "integrator": True}
                             for r in m_v.order_selection)
                stable_search = getattr(tf, "search_", None) if stable is not None else None
                model = integrating_model(tf, recs, est, m_v, level, rows)
                caught, at_bound = caught_v, at_bound_v
                info.update(chosen=True, input_level=level)
                tf.search_ = {**inner.search_, "chosen": {
                    **inner.search_["chosen"], "n_poles": model.n_poles, "integrator": True}}
                if stable_search is not None:
                    info["stable_search"] = stable_search
            else:
                info["search"] = inner.search_
    assert model is not None and caught is not None
    tf.search_["integrator"] = info
    tf.search_["search_s"] = time.perf_counter() - t_start
    if at_bound is not None:
        warnings.warn(at_bound, ConvergenceWarning, stacklevel=3)
    return model, caught


@dataclass
class _Prepared:
    """A search set up on its records: the search, its criterion's name, the bound's rule."""

    search: _Search
    criterion: str
    validation: bool
    why: str


def _prepare(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record]
             ) -> _Prepared:
    """The search of ``tf`` on the records: its criterion, scorer and high-order ARX model."""
    bound, why = search_bound(tf, est)
    check_samples(tf, est, 1, 0)
    validation = tf.validate_from is not None and any(
        np.sum(r.t >= float(tf.validate_from)) >= 2 for r in recs)
    if validation:
        T = float(tf.validate_from)  # type: ignore[arg-type]
        train, test = [], []
        for r in recs:
            v = r.t >= T
            train.append(~v if (~v).sum() >= MIN_SAMPLES else v)
            test.append(v if v.sum() >= 2 else np.zeros(r.n_samples, dtype=bool))
        scorer = _Scorer(tf, recs, [(train, test)])
        search = _Search(tf, est, scorer, bound)
        # every record trains on exactly its estimation part: the estimation records
        search.cost_from_score = len(est) == len(recs) and all(
            np.array_equal(tr, r.t < T) and e.n_samples == int(tr.sum())
            for tr, r, e in zip(train, recs, est, strict=True))
        criterion = "validation fit"
    elif len(est) > 1 and not any(_free(tf, r) for r in est):
        # records that start at rest (step, impulse, zero initial state): each record is
        # held out in turn; its offset comes from itself, everything else from the others
        whole = [np.ones(r.n_samples, dtype=bool) for r in est]
        none = [np.zeros(r.n_samples, dtype=bool) for r in est]
        folds = [([none[j] if j == k else whole[j] for j in range(len(est))],
                  [whole[j] if j == k else none[j] for j in range(len(est))])
                 for k in range(len(est))]
        scorer = _Scorer(tf, est, folds)
        search = _Search(tf, est, scorer, bound)
        criterion = ("leave-one-record-out fit (each record simulated from the model of the "
                     "others; its offset from itself)")
    else:
        fit_recs, train, test = _inner_split(tf, est)
        scorer = _Scorer(tf, est, [(train, test)])
        scorer.per_sample_spread()
        search = _Search(tf, fit_recs, scorer, bound, honest=True)
        search.cost_from_score = True  # fit_recs are the training rows of the one fold
        criterion = (f"fit on the last {1 - _INNER:.0%} of each estimation record, the model "
                     f"estimated on the first {_INNER:.0%}")
    scorer.slowest = 1.0 / float(max(r.duration for r in est))
    search.prepare()
    return _Prepared(search, criterion, validation, why)


def _search(tf: TransferFunctionEstimator, recs: list[Record], est: list[Record],
            prepared: _Prepared | None = None, *, reach: float | None = None
            ) -> tuple[TransferFunctionModel | None, list[Any], float, _Search, str | None]:
    """One search: model, warnings, criterion of the pick, the search, bound warning.

    With ``reach`` (a challenger, see :meth:`_Search.run`) a pick that is not
    refined has no model (``None``): it cannot be chosen.
    """
    t_start = time.perf_counter()
    prep = prepared if prepared is not None else _prepare(tf, recs, est)
    search, criterion, validation, why = prep.search, prep.criterion, prep.validation, prep.why
    scorer = search.scorer
    split = search.fit_recs is not est
    tol = _PARSIMONY if split else _NOISE
    chosen = search.run(tol, polish=not split, reach=reach)
    crit = chosen.criterion
    if search.unrefined:
        tf.n_evaluations_ += scorer.n_eval + sum(p.n_eval for p in search._probs.values())
        tf.search_ = _summary(search, why, criterion, tol, chosen,
                              time.perf_counter() - t_start)
        return None, [], crit, search, None
    if split:
        # the structure is chosen; its final estimate uses the whole estimation records
        chosen = search.refine(chosen, recs=est, warm=False)
    tf.n_evaluations_ += scorer.n_eval + sum(p.n_eval for p in search._probs.values())
    t_search = time.perf_counter() - t_start
    prob = _Problem(est, chosen.n, chosen.m, intersample=tf.intersample,
                    offset=bool(tf.offset), initial_state=tf.initial_state, trend=_trend(tf))
    den = chosen.den if chosen.den is not None else np.real(np.poly(chosen.poles))
    sol = chosen.sol if chosen.sol is not None else SimpleNamespace(
        success=True, message="screened model (reduced high-order ARX poles; numerator, "
        "offsets and initial states by least squares) chosen over its output-error refinement")
    model = finalize(tf, prob, recs, den, chosen.tau, tf.delay is True, sol)
    train = scorer.folds[0][0]  # the rows the candidates' fit, RSS and AIC refer to
    N_s = float(sum(np.sum(np.asarray(r.weights)[tr]) for r, tr in zip(
        scorer.records, train, strict=True)))
    rows = []
    per_n = search.per_order()
    for n in sorted(per_n):
        best_n = per_n[n]
        p = n_parameters(tf, search.fit_recs, n, best_n.m)
        aic = N_s * math.log(max(best_n.rss, 1e-300) / N_s) + 2 * p + N_s * (
            math.log(2 * math.pi) + 1)
        rows.append({
            "n_poles": n, "n_zeros": best_n.m, "aic": aic, "fit_percent": best_n.fit,
            "validation_fit_percent": best_n.criterion if validation else None,
            "criterion": best_n.criterion, "refined": best_n.refined, "delay": best_n.tau,
        })
    model = dataclasses.replace(model, order_selection=tuple(rows))
    tf.search_ = _summary(search, why, criterion, tol, chosen, t_search)
    at_bound = None
    if chosen.n >= search.bound:
        extra = 1 if _trend(tf) else 0  # G of G(s)/s: the model has the integrator too
        at_bound = (
            f"the chosen order {chosen.n + extra} is the search bound ({why}; the data support "
            f"{search.bound + extra}): a higher order may fit better; raise max_order if the "
            "records can support it")
    return model, chosen.caught, crit, search, at_bound


def _summary(search: _Search, why: str, criterion: str, tol: float, chosen: _Candidate,
             t_search: float) -> dict[str, Any]:
    """``tf.search_`` of one search: bound, criterion, candidates, refinements, time, pick."""
    out = {
        "bound": search.bound, "bound_rule": why, "criterion": criterion,
        "screened_to": search.screened_to,
        "points_per_pole": tol, "n_candidates": len(search.cands),
        "refined": [list(k) for k in sorted(search.refined)], "search_s": t_search,
        "chosen": {"n_poles": chosen.n, "n_zeros": chosen.m, "refined": chosen.refined},
    }
    if search.unrefined:
        out["unrefined"] = ("a challenger whose screened pick is more than "
                            f"{_NEAR:g} points below the criterion it must reach")
    return out
