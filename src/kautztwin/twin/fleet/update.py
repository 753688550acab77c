r"""The update module of a fleet: recursive least squares as arrays, re-identification per asset.

:class:`FleetUpdater` is :class:`~kautztwin.twin.Updater` (synchronous
accurate path, no DNN estimator) for ``n_assets`` twins of one structure:
the fast path (:class:`~kautztwin.twin.update.RecursiveKautzEstimator`'s
recursion with forgetting - exponential or directional - trace clamp and symmetrisation,
and its quadratic input channel when the twins have one), the frozen
prediction judged by the monitor, the buffer of recent samples and the
recovery policy run as ``(n_assets, ...)`` array operations.  The accurate
path is the updater's: the same window (:meth:`_prepare`), the same fit
(``_fit_window`` of :mod:`kautztwin.twin.update.worker`, in a
:class:`concurrent.futures` pool for all the assets due at one sample) and
the same validation on held-out samples (:meth:`_judge`).

With a trained neural estimator (``estimator``, e.g.
:class:`~kautztwin.nn.AdaptivePoleEstimator`) the attempts due at a sample
take the fast path of :meth:`Updater.update_from_step_test
<kautztwin.twin.Updater.update_from_step_test>` instead of the output-error
fits: every due asset's live model runs a virtual step test on the
estimator's grid (:meth:`FleetUpdater.step_records`, one array recursion for
all of them), the estimator is called **once** on all these records
(``predict_models``), and each candidate is judged on the asset's held-out
samples as a re-identified one is.

Memory: the inputs of the buffer of recent samples can come from the caller
(``inputs``: the fleet derives them from its command history and the seeded
dither), so that only the outputs are buffered.

Size: :class:`FleetUpdater` passes 400 lines because it holds the whole update
module of N twins - the fast path, the buffer, the recovery policy and both
accurate paths (output-error fits and the DNN) - over one set of arrays that
all of them read and write; split, the state would be shared across classes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...approx.model import KautzModel
from ...basis import KautzBasis
from ...exceptions import DataError
from ...ident.kautz_oe import continuous_poles, filter_states
from ...metrics import fit_percent_or_nan
from ..digital import DigitalModel, discretize_model
from ..update import Updater
from ..update.judging import candidate_verdict
from ..update.worker import _ReidJob
from .assets import reid_job, unpack_fit
from .sync import FleetMonitor

__all__ = ["FleetUpdater", "ReidOutcome", "estimator_grid"]


@dataclass(frozen=True)
class ReidOutcome:
    """One re-identification attempt of one asset.

    Parameters
    ----------
    asset : int
    k : int
        The updater's sample counter when it was decided.
    accepted : bool
    reason : str
    fit_candidate, fit_current : float
        Held-out fits, percent (NaN when the attempt was refused for too few samples).
    version : int
        The asset's model version afterwards.
    """

    asset: int
    k: int
    accepted: bool
    reason: str
    fit_candidate: float
    fit_current: float
    version: int


def estimator_grid(est: Any, dt: float) -> NDArray[np.intp]:
    """The twin samples of a neural estimator's grid, or a one-line error why it cannot serve.

    Parameters
    ----------
    est : object
        A fitted estimator with ``predict_models``, ``t_`` and ``kind_ == 'step'``.
    dt : float
        The twins' sampling period, s.

    Returns
    -------
    ndarray of int
        ``t_ / dt`` (every grid time must be a sample ``k * dt``, ``k >= 0``).

    Raises
    ------
    DataError
        If ``est`` is not such an estimator or its grid is off the samples.
    """
    if not callable(getattr(est, "predict_models", None)) or not hasattr(est, "t_"):
        raise DataError("estimator must be a fitted neural estimator with predict_models "
                        f"and a time grid t_, got {type(est).__name__}")
    if getattr(est, "kind_", "step") != "step":
        raise DataError(f"the fleet's estimator must be trained on step responses, got "
                        f"kind {est.kind_!r}")
    t = np.asarray(est.t_, dtype=float).reshape(-1)
    idx = np.rint(t / dt).astype(np.intp)
    if t.size == 0 or idx.min() < 0 or not np.allclose(idx * dt, t, rtol=1e-9, atol=1e-9 * dt):
        raise DataError(f"the estimator's grid t_ must be samples of the twin's dt = {dt:g} s "
                        "(k * dt, k >= 0)")
    return idx


class FleetUpdater:
    """Fast path, monitor and recovery policy of ``n_assets`` twins.

    Built from one :class:`~kautztwin.twin.Updater` per asset (their initial
    models, offsets, extra poles and settings; every asset must have the same
    number of basis functions and the same settings).

    Parameters
    ----------
    updaters : sequence of Updater
        The assets' freshly built updaters (not stepped yet).
    monitor : FleetMonitor
        The fleet's monitor.
    map_fn : callable, optional
        ``map_fn(function, jobs) -> results`` for the re-identification fits
        (a pool's ``map``); the built-in ``map`` when omitted.
    inputs : callable, optional
        ``inputs(i, first, stop) -> ndarray``: asset ``i``'s inputs of samples
        ``first .. stop - 1`` (the values given to :meth:`step`).  With it
        only the outputs are buffered (half the buffer's memory).
    inputs_span : int or None, default=0
        How many of the latest samples ``inputs`` can give (``None``: all of
        them); it is used only when that covers the buffer.
    estimator : object, optional
        A trained neural estimator with ``predict_models(records, t=...)``,
        ``t_``, ``kind_ == 'step'`` and ``n_functions_`` (an
        :class:`~kautztwin.nn.AdaptivePoleEstimator`): the due attempts use it,
        one call for all the assets due at a sample, instead of the
        output-error fits (see the module notes).

    Attributes
    ----------
    digital_models : list of DigitalModel
        Each asset's current version.
    counts : dict of str to ndarray
        ``attempts`` and ``accepted`` per asset.
    """

    def __init__(
        self, updaters: Sequence[Updater], monitor: FleetMonitor,
        map_fn: Callable[..., Any] | None = None, *,
        inputs: Callable[[int, int, int], NDArray[np.float64]] | None = None,
        inputs_span: int | None = 0, estimator: Any = None,
    ) -> None:
        u0 = updaters[0]
        N = len(updaters)
        est0 = u0.estimator_
        n = est0.basis_.n_functions
        self.n_assets, self.n = N, n
        self.dt = u0.dt
        self.input_offset = u0.input_offset
        self.delta = u0.delta
        self.lam = float(est0.forgetting)
        self.max_trace = float(est0.max_trace)
        # the quadratic input channel's bank follows the offset: theta = [c; d; c_q]
        self.scale = est0.quadratic_scale
        self.directional = bool(est0.directional)
        self.q0 = n + 1
        p = est0.parameters_.size
        self.n_params = p
        self.horizon = u0.horizon
        self.fast_update = u0.fast_update
        self.reidentify_enabled = u0.reidentify_enabled
        for name in ("reid_samples", "min_reid_samples", "reid_every", "max_attempts", "burn_in",
                     "validation_fraction", "min_improvement", "min_candidate_fit", "min_rate",
                     "max_iter"):
            setattr(self, name, getattr(u0, name))
        self.theta = np.zeros((N, p))
        self.P = np.zeros((N, p, p))
        self.R: NDArray[np.float64] | None = np.zeros((N, p, p)) if self.directional else None
        # directional now (exponential from a desync to the next version or the resync)
        self.dir_on = np.full(N, self.directional)
        # monitored samples left before a new regime's first own window (-1: none; see
        # enter_new_regime)
        self.regime_left = np.full(N, -1, dtype=np.int64)
        self.phi = np.zeros((N, p))
        self.A = np.zeros((N, n, n))
        self.B = np.zeros((N, n))
        self.wide_basis: list[KautzBasis] = []
        self.extra_poles = [u.extra_poles for u in updaters]
        self.digital_models: list[DigitalModel] = []
        self.core_n = np.zeros(N, dtype=np.int64)
        for i, u in enumerate(updaters):
            est = u.estimator_
            if est.basis_.n_functions != n or not est.fit_offset:
                raise ValueError("every asset's twin needs the same number of basis functions")
            if (est.quadratic_scale != self.scale or bool(est.directional) != self.directional
                    or float(est.forgetting) != self.lam):
                raise ValueError("every asset's fast path needs the same settings")
            self.theta[i] = est.parameters_
            self.P[i] = est.covariance_
            if self.R is not None:
                self.R[i] = np.linalg.inv(self.P[i])
            state = est.state_
            self.phi[i, :n] = state[:n]
            self.phi[i, n] = 1.0
            self.phi[i, self.q0:] = state[n:]
            self.A[i] = np.array(est.basis_.A)
            self.B[i] = np.array(est.basis_.B).reshape(-1)
            self.wide_basis.append(est.basis_)
            self.digital_models.append(u.digital_model)
            self.core_n[i] = u.n_core_functions
        self.n_updates = np.zeros(N, dtype=np.int64)
        self.theta_frozen = self.theta.copy()
        self.monitor = monitor
        self.L = self.reid_samples + self.burn_in
        covers = inputs_span is None or int(inputs_span) >= self.L
        self._inputs = inputs if inputs is not None and covers else None
        self.buf_u: NDArray[np.float64] | None = (
            np.zeros((N, self.L)) if self._inputs is None else None)
        self.buf_y = np.zeros((N, self.L))
        self.buf_n = 0  # samples in the buffers (the same for every asset)
        self.buf_pos = 0  # where the next one goes
        self.k = 0
        self.rec_on = np.zeros(N, dtype=bool)
        self.rec_change = np.zeros(N, dtype=np.int64)
        self.rec_next = np.zeros(N, dtype=np.int64)
        self.rec_attempts = np.zeros(N, dtype=np.int64)
        self.model_k = np.zeros(N, dtype=np.int64)
        self.counts = {"attempts": np.zeros(N, dtype=np.int64),
                       "accepted": np.zeros(N, dtype=np.int64)}
        self.map_fn = map_fn if map_fn is not None else map
        self.reid_seconds = 0.0  # wall time of the accurate path so far
        self.estimator = estimator
        self._grid: NDArray[np.intp] | None = None
        if estimator is not None:
            self._grid = self._check_estimator(estimator)

    def _check_estimator(self, est: Any) -> NDArray[np.intp]:
        """The sample indices of the estimator's grid (raises if it cannot serve the fleet)."""
        idx = estimator_grid(est, self.dt)
        widths = {len(e) for e in self.extra_poles}
        n_est = int(getattr(est, "n_functions_", self.n - min(widths)))
        if any(n_est + w != self.n for w in widths):
            raise DataError(f"the estimator has {n_est} basis functions but the twins' models "
                            f"have {self.n - max(widths)}")
        return idx

    # ------------------------------------------------------------------ the fast path
    def predict(self) -> NDArray[np.float64]:
        """A-priori predictions ``theta . phi`` of the current sample, every asset."""
        return np.einsum("bi,bi->b", self.theta, self.phi)

    def step(
        self, u: NDArray, y: NDArray, clean: NDArray[np.bool_]
    ) -> tuple[NDArray, NDArray, list[ReidOutcome], NDArray, NDArray, NDArray]:
        """One sample of every asset (the :meth:`Updater.step` of each).

        Parameters
        ----------
        u : ndarray of shape (n_assets,)
            Inputs applied at this sample.
        y : ndarray of shape (n_assets,)
            Measured outputs.
        clean : ndarray of bool
            Samples the sanitiser passed (the others only advance the filters).

        Returns
        -------
        y_pred_frozen : ndarray
            The monitored predictions.
        y_pred : ndarray
            The a-priori predictions with the live parameters.
        outcomes : list of ReidOutcome
            Re-identification attempts decided at this sample.
        evaluated, desync, resync : ndarray of int
            Monitor results (see :meth:`FleetMonitor.update`).
        """
        n = self.n
        th, phi = self.theta, self.phi
        y_pred = np.einsum("bi,bi->b", th, phi)
        y_frozen = np.einsum("bi,bi->b", self.theta_frozen, phi)
        yv = np.where(clean, y, np.nan)
        upd = clean & ~np.isnan(y) if self.fast_update else np.zeros_like(clean)
        rows = np.flatnonzero(upd)
        if rows.size:
            self._correct(rows, y[rows] - y_pred[rows])
        v = u - self.input_offset
        phi[:, :n] = np.einsum("bij,bj->bi", self.A, phi[:, :n]) + self.B * v[:, None]
        if self.scale is not None:
            q0 = self.q0
            phi[:, q0:] = np.einsum("bij,bj->bi", self.A, phi[:, q0:]) + self.B * (
                v * v / self.scale)[:, None]
        # the ring buffer of recent samples
        if self.buf_u is not None:
            self.buf_u[:, self.buf_pos] = u
        self.buf_y[:, self.buf_pos] = yv
        self.buf_pos = (self.buf_pos + 1) % self.L
        self.buf_n = min(self.buf_n + 1, self.L)
        ev, desync, resync, _ = self.monitor.update(y, y_frozen, clean)
        if self.directional:
            self._regime_check(clean, y, y_frozen, ev)
            self.regime_left[desync] = -1  # a recovery owns the forgetting now
        self._set_directional(desync, False)
        self._set_directional(resync, True)
        before = self.k
        self.k += 1
        if self.k // self.horizon != before // self.horizon:
            self.theta_frozen = self.theta.copy()
        # events: a resync ends a recovery, a desync starts one
        self.rec_on[resync] = False
        if self.reidentify_enabled and desync.size:
            start = desync[~self.rec_on[desync]]
            mon = self.monitor
            first_bad_end = self.k - (mon.n_consecutive - 1) * mon.stride
            change = np.maximum(np.maximum(first_bad_end - mon.window // 2, self.model_k[start]),
                                0)
            self.rec_on[start] = True
            self.rec_change[start] = change
            self.rec_next[start] = change + self.min_reid_samples
            self.rec_attempts[start] = 0
        due = np.flatnonzero(self.rec_on & (self.k >= self.rec_next))
        t0 = time.perf_counter()
        outcomes = self.reidentify(due) if due.size else []
        self.reid_seconds += time.perf_counter() - t0
        if due.size:
            self.rec_attempts[due] += 1
            self.rec_next[due] = self.k + self.reid_every
            self.rec_on[due[self.rec_attempts[due] >= self.max_attempts]] = False
        return y_frozen, y_pred, outcomes, ev, desync, resync

    def _correct(self, rows: NDArray[np.intp], err: NDArray[np.float64]) -> None:
        """The measurement update of the assets ``rows`` (as ``RecursiveKautzEstimator.update``)."""
        th, phi = self.theta, self.phi
        Pr, ph = self.P[rows], phi[rows]
        lam = self.lam
        dr = self.dir_on[rows]  # these forget along phi, then take a plain update
        Rn = None
        if dr.any():
            Rn = self.R[rows]
            Rphi = np.einsum("bij,bj->bi", Rn, ph)
            r = np.einsum("bi,bi->b", ph, Rphi)
            fo = dr & (r > 0) & np.isfinite(r) if lam < 1.0 else np.zeros(rows.size, dtype=bool)
            rs = np.where(fo, r, 1.0)
            Rn = Rn - (np.where(fo, (1.0 - lam) / rs, 0.0)[:, None, None]
                       * Rphi[:, :, None] * Rphi[:, None, :])
            Pr = Pr + (np.where(fo, (1.0 - lam) / (lam * rs), 0.0)[:, None, None]
                       * ph[:, :, None] * ph[:, None, :])
        Pphi = np.einsum("bij,bj->bi", Pr, ph)
        denom = np.where(dr, 1.0, lam) + np.einsum("bi,bi->b", ph, Pphi)
        ok = (denom > 0) & np.isfinite(denom)
        g = Pphi / np.where(ok, denom, 1.0)[:, None]
        th[rows] = np.where(ok[:, None], th[rows] + g * err[:, None], th[rows])
        Pn = Pr - g[:, :, None] * Pphi[:, None, :]
        if lam < 1.0 and not dr.all():
            Pn[~dr] /= lam
        if Rn is not None:
            Rn = Rn + ph[:, :, None] * ph[:, None, :]
        self.n_updates[rows] += ok
        sym = ok & (self.n_updates[rows] % 64 == 0)
        if sym.any():
            Ps = Pn[sym]
            Pn[sym] = (Ps + np.swapaxes(Ps, 1, 2)) * 0.5
            again = sym & dr
            if again.any():  # R the inverse of P again
                Rn[again] = np.linalg.inv(Pn[again])
        tr = np.trace(Pn, axis1=1, axis2=2)
        clamp = tr > self.max_trace
        Pn[clamp] *= (self.max_trace / tr[clamp])[:, None, None]
        reset = ~ok | (~clamp & ~(tr > 0))
        Pn[reset] = self.delta * np.eye(self.n_params)
        self.P[rows] = Pn
        if Rn is not None:
            Rn[clamp] *= (tr[clamp] / self.max_trace)[:, None, None]
            Rn[reset] = np.eye(self.n_params) / self.delta
            self.R[rows[dr]] = Rn[dr]

    def enter_new_regime(self) -> None:
        """Every asset enters a new regime: the closed loop's start.

        As :meth:`Updater.enter_new_regime <kautztwin.twin.update.Updater.enter_new_regime>`:
        exponential forgetting until a window of the regime's own samples fits at the
        resync level, a desync or a new model version.
        """
        if self.directional:
            self._set_directional(np.arange(self.regime_left.size), False)
            self.regime_left[:] = self.monitor.window

    def _regime_check(self, clean: NDArray[np.bool_], y: NDArray[np.float64],
                      y_frozen: NDArray[np.float64], evaluated: NDArray[np.intp]) -> None:
        """Count a new regime's monitored samples; end it where a window of them fits.

        The assets whose window of the regime's own samples fits at the resync level
        go back to directional forgetting.
        """
        pending = self.regime_left >= 0
        if not pending.any():
            return
        monitored = clean & np.isfinite(y) & np.isfinite(y_frozen)  # the pairs it took
        count = pending & monitored & (self.regime_left > 0)  # 0: waiting for a good window
        self.regime_left[count] -= 1
        mon = self.monitor
        e = evaluated[pending[evaluated] & (self.regime_left[evaluated] <= 0)]
        back = e[mon.in_sync[e] & (mon.fit[e] >= mon.threshold + mon.resync_margin)]
        self.regime_left[back] = -1
        self._set_directional(back, True)

    def _set_directional(self, assets: NDArray[np.intp], on: bool) -> None:
        """Directional (``on``) or exponential forgetting for ``assets`` from now on."""
        if not self.directional or assets.size == 0:
            return
        switch = assets[self.dir_on[assets] != on]
        self.dir_on[switch] = on
        if on and switch.size:
            self.R[switch] = np.linalg.inv(self.P[switch])

    # ------------------------------------------------------------------ the accurate path
    def _prepare(self, i: int) -> _ReidJob | ReidOutcome:
        """The window of asset ``i``'s attempt (as :meth:`Updater._prepare`), or its refusal."""
        self.counts["attempts"][i] += 1
        size = self.buf_n
        n_samples = self.reid_samples
        if self.rec_on[i]:
            n_samples = min(n_samples, self.k - int(self.rec_change[i]))
        n_w = min(int(n_samples), size)
        h0 = max(0, size - n_w - self.burn_in)
        u_all, y_all = self.buffer(i)
        u, y = u_all[h0:], y_all[h0:]
        w0 = u.size - n_w
        n_val = int(self.validation_fraction * n_w)
        n_est = u.size - n_val
        n_par = int(self.core_n[i]) + 1
        usable = int(np.isfinite(y[w0:n_est]).sum())
        if n_val < 10 or usable < 4 * n_par or np.isfinite(y[n_est:]).sum() < 10:
            return ReidOutcome(
                i, self.k, False,
                f"too few samples: {usable} usable for estimation, {n_val} for validation",
                math.nan, math.nan, self.digital_models[i].version)
        u.setflags(write=False)
        y.setflags(write=False)
        poles = continuous_poles(self.wide_basis[i])[: int(self.core_n[i])]
        return _ReidJob(u=u, y=y, w0=w0, n_est=n_est, n_val=n_val, poles=poles, dt=self.dt,
                        input_offset=self.input_offset, min_rate=self.min_rate,
                        max_iter=self.max_iter, k=self.k)

    def buffer(self, i: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Asset ``i``'s buffered inputs and outputs in time order (copies; NaN: unused sample).

        Parameters
        ----------
        i : int

        Returns
        -------
        u, y : ndarray of shape (n_buffered,)
        """
        if self.buf_n < self.L:
            y = self.buf_y[i, : self.buf_n].copy()
            u = None if self.buf_u is None else self.buf_u[i, : self.buf_n].copy()
        else:
            p = self.buf_pos
            y = np.concatenate([self.buf_y[i, p:], self.buf_y[i, :p]])
            u = None if self.buf_u is None else np.concatenate(
                [self.buf_u[i, p:], self.buf_u[i, :p]])
        if u is None:
            assert self._inputs is not None
            u = np.array(self._inputs(i, self.k - self.buf_n, self.k), dtype=float)
        return u, y

    def reidentify(self, assets: NDArray[np.intp]) -> list[ReidOutcome]:
        """Re-identification attempts of ``assets`` now: fits in the pool, judged here.

        Parameters
        ----------
        assets : ndarray of int

        Returns
        -------
        list of ReidOutcome
        """
        if self.estimator is not None:
            return self.dnn_update(assets)
        out: list[ReidOutcome] = []
        jobs: list[tuple[int, _ReidJob]] = []
        for i in assets.tolist():
            job = self._prepare(i)
            if isinstance(job, ReidOutcome):
                out.append(job)
            else:
                jobs.append((i, job))
        results = list(self.map_fn(reid_job, [j for _, j in jobs]))
        for (i, job), res in zip(jobs, results, strict=True):
            assert res is not None
            fit = unpack_fit(res)
            out.append(self._judge(i, fit.model, fit.offset, job.u, job.y, job.n_val))
        out.sort(key=lambda o: o.asset)
        return out

    # ------------------------------------------------------------------ the DNN fast path
    def step_records(self, assets: NDArray[np.intp]) -> NDArray[np.float64]:
        """Unit step responses of the assets' live models on the estimator's grid.

        The virtual step test of :meth:`Optimizer.retune_model
        <kautztwin.twin.Optimizer.retune_model>` for many assets at once: each
        live fast-path model (filters ``A, B``, coefficients ``theta``, without
        the output offset) from rest, a unit step applied at sample 0.

        Parameters
        ----------
        assets : ndarray of int

        Returns
        -------
        ndarray of shape (len(assets), n_grid)
            The responses at the samples of the estimator's grid ``t_ / dt``.
        """
        if self._grid is None:
            raise DataError("the fleet's update module has no estimator")
        idx = np.asarray(assets, dtype=np.intp)
        n = self.n
        A, B, c = self.A[idx], self.B[idx], self.theta[idx, :n]
        x = np.zeros((idx.size, n))
        last = int(self._grid.max())
        resp = np.empty((idx.size, last + 1))
        for j in range(last + 1):
            resp[:, j] = np.einsum("bi,bi->b", c, x)
            x = np.einsum("bij,bj->bi", A, x) + B
        return resp[:, self._grid]

    def dnn_update(self, assets: NDArray[np.intp]) -> list[ReidOutcome]:
        """Attempts of ``assets`` now from the estimator: one call for all, each judged.

        The windows are those of :meth:`Updater.update_from_step_test
        <kautztwin.twin.Updater.update_from_step_test>` (the last
        ``reid_samples`` buffered samples, their final ``validation_fraction``
        held out); an asset with too few held-out samples is refused.  The
        records of the others (:meth:`step_records`) go to the estimator's
        ``predict_models`` in **one** call; each candidate (continuous poles,
        discretised at ``dt``, the live offset) is then judged as a
        re-identified one.

        Parameters
        ----------
        assets : ndarray of int

        Returns
        -------
        list of ReidOutcome
        """
        out: list[ReidOutcome] = []
        ready: list[tuple[int, NDArray, NDArray, int]] = []
        for i in np.asarray(assets, dtype=np.intp).tolist():
            self.counts["attempts"][i] += 1
            u_all, y_all = self.buffer(i)
            n_w = min(self.reid_samples, u_all.size)
            n_val = int(self.validation_fraction * n_w)
            if n_val < 10 or np.isfinite(y_all[-n_val:]).sum() < 10:
                out.append(ReidOutcome(i, self.k, False, f"too few samples: {n_val} held out",
                                       math.nan, math.nan, self.digital_models[i].version))
                continue
            h0 = max(0, u_all.size - n_w - self.burn_in)
            ready.append((i, u_all[h0:], y_all[h0:], n_val))
        if ready:
            rows = np.array([r[0] for r in ready], dtype=np.intp)
            records = self.step_records(rows)
            models = self.estimator.predict_models(records, t=self.estimator.t_)
            for (i, u, y, n_val), model in zip(ready, models, strict=True):
                try:
                    md = discretize_model(model, self.dt)
                except (DataError, ValueError, np.linalg.LinAlgError) as exc:
                    out.append(ReidOutcome(i, self.k, False, f"the estimate cannot be "
                                           f"discretised: {exc}", math.nan, math.nan,
                                           self.digital_models[i].version))
                    continue
                out.append(self._judge(i, md, float(self.theta[i, self.n]), u, y, n_val,
                                       kind="dnn-update"))
        out.sort(key=lambda o: o.asset)
        return out

    def _widen(self, i: int, model: KautzModel) -> KautzModel:
        extra = self.extra_poles[i]
        if extra.size == 0:
            return model
        poles = np.concatenate([model.basis.poles, np.exp(extra * self.dt)])
        basis = KautzBasis(poles, dt=self.dt, delayed=True)
        return KautzModel(basis, np.concatenate([model.coefficients, np.zeros(extra.size)]))

    def _judge(self, i: int, model: KautzModel, offset: float, u: NDArray, y: NDArray,
               n_val: int, kind: str = "reidentification") -> ReidOutcome:
        """Validate asset ``i``'s candidate on the held-out samples (as :meth:`Updater._judge`)."""
        n = self.n
        v = u - self.input_offset
        Xc = filter_states(model.basis, v)
        yc = Xc[:-1] @ model.coefficients + offset
        ym = filter_states(self.wide_basis[i], v)[:-1] @ self.theta[i, :n].copy() + float(
            self.theta[i, n])
        w = None if self.scale is None else v * v / self.scale  # the quadratic bank's input
        if w is not None:
            ym = ym + filter_states(self.wide_basis[i], w)[:-1] @ (
                self.theta[i, self.q0:].copy())
        sl = slice(u.size - n_val, u.size)
        fit_c, fit_m = fit_percent_or_nan(y[sl], yc[sl]), fit_percent_or_nan(y[sl], ym[sl])
        accepted, reason = candidate_verdict(fit_c, fit_m, n_val,
                                             min_improvement=self.min_improvement,
                                             min_candidate_fit=self.min_candidate_fit)
        if not accepted:
            return ReidOutcome(i, self.k, False, reason, fit_c, fit_m,
                               self.digital_models[i].version)
        dm = self.digital_models[i].with_update(model, kind, fit_c)
        self.digital_models[i] = dm
        self.core_n[i] = model.n_functions
        state = Xc[-1]
        wide = self._widen(i, model)
        if wide is not model:
            state = filter_states(wide.basis, u - self.input_offset)[-1]
        md = discretize_model(wide, self.dt)
        if md.n_functions != n:
            raise ValueError(f"asset {i}: the re-identified model changed the basis size")
        self.wide_basis[i] = md.basis
        self.A[i] = np.array(md.basis.A)
        self.B[i] = np.array(md.basis.B).reshape(-1)
        self.theta[i, :n] = np.array(md.coefficients)
        self.theta[i, n] = float(offset)
        self.P[i] = self.delta * np.eye(self.n_params)
        if self.R is not None:
            self.R[i] = np.eye(self.n_params) / self.delta
            self.dir_on[i] = True
            self.regime_left[i] = -1
        self.phi[i, :n] = state
        self.phi[i, n] = 1.0
        if w is not None:  # the quadratic channel restarts on the window's input
            self.theta[i, self.q0:] = 0.0
            self.phi[i, self.q0:] = filter_states(md.basis, w)[-1]
        self.n_updates[i] = 0
        self.theta_frozen[i] = self.theta[i]
        self.monitor.clear_window(i)
        self.model_k[i] = self.k
        self.counts["accepted"][i] += 1
        return ReidOutcome(i, self.k, True, reason, fit_c, fit_m, dm.version)

    @property
    def offsets(self) -> NDArray[np.float64]:
        """Current output offsets ``d`` of every asset."""
        return self.theta[:, self.n].copy()

    @property
    def nbytes(self) -> int:
        """Bytes held in the arrays (the monitor's not included)."""
        return int(sum(a.nbytes for a in (
            self.theta, self.P, *(() if self.R is None else (self.R,)), self.phi, self.A,
            self.B, self.theta_frozen,
            *(() if self.buf_u is None else (self.buf_u,)), self.buf_y, self.n_updates,
            self.rec_on, self.rec_change, self.rec_next,
            self.rec_attempts, self.model_k, self.core_n, self.dir_on, self.regime_left)))
