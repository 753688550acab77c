r"""Optimization module of the digital twin: offline re-tuning of the model and the controller.

The update module (:class:`~kautztwin.twin.Updater`) keeps the twin
synchronised sample by sample.  When it asks for more - a drift has been
learnt (a ``'resync'`` event) or a new model version was accepted - the
runtime hands the work to the :class:`Optimizer`, which

* **re-optimises the basis poles** on the twin's recent behaviour: the live
  fast-path model (which has followed the plant through the drift) is
  compressed into a model of the original order with
  :func:`kautztwin.optimize_poles` on its step response, and the candidate is
  validated on held-out recent measurements by the updater before it
  replaces the running model (:meth:`Optimizer.retune_model`);
* **consolidates the fast path** into a new model version when its live
  coefficients predict recent data clearly better than the current version
  (:meth:`Optimizer.consolidate`);
* **retunes the MPC weights** for a model version by small closed-loop
  simulations on the model itself and on gain-perturbed copies, and
  validates the winner (zero constraint violations, all solves successful,
  settled within the horizon, bounded overshoot) before the controller is
  rebuilt (:meth:`Optimizer.tune_controller`).
* **retrains the neural estimator** on data around the new operating point:
  labelled records of the uncertain system around the current model are
  simulated, the estimator is fine-tuned on them from its trained weights,
  and the candidate replaces the running estimator only if it fits fresh
  held-out records better (:meth:`Optimizer.retrain_estimator`).

The controller design it tunes is :class:`~kautztwin.twin.prediction.MPCSettings`
(:func:`~kautztwin.twin.prediction.build_mpc` builds the problem).

Size: over 600 lines because :class:`Optimizer` carries the four validated
re-tunings above, each with its numpydoc docstring and acceptance rules, and the
estimator retraining needs its model conversions beside it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..._validation import check_int
from ...approx.model import KautzModel
from ...basis import KautzBasis
from ...datasets import ParametricSystem, ResponseDataset, draw_parameters, make_dataset
from ...exceptions import DataError
from ...metrics import fit_percent, fit_percent_or_nan
from ...mpc import simulate_closed_loop
from ..digital import discretize_model
from ..prediction.settings import MPCSettings, _number_or_inf, build_mpc
from ..update import ModelUpdate, RecursiveKautzEstimator, Updater

__all__ = [
    "ControllerTuning",
    "EstimatorRetraining",
    "Optimizer",
    "TuningCandidate",
]


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class TuningCandidate:
    """One weight tried by :meth:`Optimizer.tune_controller`.

    Parameters
    ----------
    r : float
        Increment weight.
    score : float
        Mean normalised IAE over the simulated plants (lower is better; inf if invalid).
    valid : bool
        Whether every validation check passed.
    violations : int
        Constraint violations over all simulations.
    overshoot : float
        Overshoot of the nominal simulation, fraction of the step.
    final_error : float
        Final tracking error of the nominal simulation, fraction of the step.
    reason : str
        Why it is invalid ('' when valid).
    """

    r: float
    score: float
    valid: bool
    violations: int
    overshoot: float
    final_error: float
    reason: str = ""


@dataclass(frozen=True)
class ControllerTuning:
    """Outcome of :meth:`Optimizer.tune_controller`.

    Parameters
    ----------
    accepted : bool
        Whether a candidate passed the validation (the controller may be rebuilt).
    settings : MPCSettings
        The chosen design (the input design when nothing was accepted).
    candidates : tuple of TuningCandidate
        Every weight tried.
    reason : str
        Summary in words.
    elapsed : float
        Wall-clock seconds.
    """

    accepted: bool
    settings: MPCSettings
    candidates: tuple[TuningCandidate, ...] = field(default=())
    reason: str = ""
    elapsed: float = 0.0

    def payload(self) -> dict[str, Any]:
        """JSON-ready summary (for the history store).

        Returns
        -------
        dict
        """
        return {
            "accepted": self.accepted, "r": self.settings.r, "reason": self.reason,
            "elapsed": self.elapsed,
            "candidates": [
                {"r": c.r, "score": c.score if math.isfinite(c.score) else None,
                 "valid": c.valid, "reason": c.reason}
                for c in self.candidates
            ],
        }


@dataclass(frozen=True, eq=False)
class EstimatorRetraining:
    """Outcome of :meth:`Optimizer.retrain_estimator`.

    Parameters
    ----------
    accepted : bool
        Whether the fine-tuned candidate passed the validation (it may replace
        the running estimator).
    estimator : object
        The estimator to run: the candidate when accepted, else the input one.
    candidate : object
        The fine-tuned estimator (a new object; the input one is unchanged).
    fit_old, fit_new : float
        Mean fit percent, on the held-out records, of the noise-free responses
        of the models predicted by the input estimator and by the candidate.
    reason : str
        Summary in words.
    elapsed : float
        Wall-clock seconds of the whole call (data, fine-tuning, validation).
    train_seconds : float
        Wall-clock seconds of the fine-tuning alone.
    n_train, n_validation : int
        Records simulated for the fine-tuning and for the validation.
    """

    accepted: bool
    estimator: Any
    candidate: Any
    fit_old: float
    fit_new: float
    reason: str = ""
    elapsed: float = 0.0
    train_seconds: float = 0.0
    n_train: int = 0
    n_validation: int = 0

    @property
    def gain(self) -> float:
        """Fit points gained by the candidate, ``fit_new - fit_old``."""
        return self.fit_new - self.fit_old

    def payload(self) -> dict[str, Any]:
        """JSON-ready summary (for the history store).

        Returns
        -------
        dict
        """

        def clean(v: float) -> float | None:
            return v if math.isfinite(v) else None

        return {
            "accepted": self.accepted, "fit_old": clean(self.fit_old),
            "fit_new": clean(self.fit_new), "reason": self.reason, "elapsed": self.elapsed,
            "train_seconds": self.train_seconds, "n_train": self.n_train,
            "n_validation": self.n_validation,
        }


# --------------------------------------------------------------------------- optimizer
class Optimizer:
    r"""Offline re-tuning for the twin: basis poles, model consolidation, MPC weights.

    Parameters
    ----------
    weight_factors : sequence of float, default=(0.2, 1.0, 5.0)
        Multiples of the configured increment weight tried by
        :meth:`tune_controller`.
    gain_margins : sequence of float, default=(1.0, 0.75, 1.35)
        Gain factors of the plants each candidate is simulated on (1 is the
        model itself; the others stand for a drifted plant).
    n_settle : int or None, default=None
        Samples of each tuning simulation; ``2 * horizon`` when omitted.
    max_overshoot : float, default=0.25
        Largest overshoot on the nominal model, fraction of the step.
    max_final_error : float, default=0.05
        Largest error at the end of the nominal simulation, fraction of the step.
    min_gain : float, default=1.0
        Fit percent by which the live fast-path model must beat the current
        version in :meth:`consolidate`.
    validation_samples : int, default=300
        Recent samples on which :meth:`consolidate` compares the two models.
    max_step_samples : int, default=2000
        Longest virtual step test of :meth:`retune_model`.
    retune_poles : bool, default=True
        Run the pole re-optimisation in :meth:`retune_model`.

    See Also
    --------
    kautztwin.twin.Updater.update_from_step_test : Validates a pole re-optimisation.
    kautztwin.optimize_poles : The pole optimisation.
    kautztwin.twin.prediction.build_mpc : The controller that is tuned.
    kautztwin.nn.CoefficientEstimator.fine_tune : The estimator retraining.

    Notes
    -----
    **Weight tuning.**  For each candidate weight :math:`r` the MPC is built
    on the model in deviation coordinates around the current operating point
    and a set-point step of the size the run uses is simulated in closed loop
    (:func:`kautztwin.mpc.simulate_closed_loop`) on the model and on copies
    with their gain scaled by ``gain_margins``.  The score is the mean IAE
    normalised by the step; a candidate is valid when no simulation breaks a
    limit or fails a solve and the nominal response overshoots by at most
    ``max_overshoot`` and ends within ``max_final_error`` of the set-point.
    The valid candidate with the lowest score wins.

    **Estimator retraining.**  :meth:`retrain_estimator` fine-tunes a neural
    estimator on records simulated around the current model and accepts the
    candidate only if its predicted models fit fresh held-out records (the
    noise-free responses) better than the running estimator's by ``margin``
    fit points.

    Examples
    --------
    >>> import kautztwin as kt
    >>> from kautztwin.twin.optimization import Optimizer
    >>> from kautztwin.twin.prediction import MPCSettings
    >>> model = kt.KautzModel(kt.KautzBasis([0.9], dt=0.1, delayed=True), [1.0])
    >>> s = MPCSettings(30, 0.7, 3, 0.1, u_min=-1.0, u_max=1.0, du_max=0.5)
    >>> tuning = Optimizer().tune_controller(model, s, step=0.5)
    >>> tuning.accepted, len(tuning.candidates)
    (True, 3)
    """

    def __init__(
        self,
        *,
        weight_factors: ArrayLike = (0.2, 1.0, 5.0),
        gain_margins: ArrayLike = (1.0, 0.75, 1.35),
        n_settle: int | None = None,
        max_overshoot: float = 0.25,
        max_final_error: float = 0.05,
        min_gain: float = 1.0,
        validation_samples: int = 300,
        max_step_samples: int = 2000,
        retune_poles: bool = True,
    ) -> None:
        self.weight_factors = tuple(float(f) for f in np.atleast_1d(weight_factors))
        self.gain_margins = tuple(float(g) for g in np.atleast_1d(gain_margins))
        if not self.weight_factors or any(not f > 0 for f in self.weight_factors):
            raise DataError(f"weight_factors must be positive numbers, got {weight_factors!r}")
        if not self.gain_margins or any(not g > 0 for g in self.gain_margins):
            raise DataError(f"gain_margins must be positive numbers, got {gain_margins!r}")
        self.n_settle = n_settle
        self.max_overshoot = float(max_overshoot)
        self.max_final_error = float(max_final_error)
        self.min_gain = float(min_gain)
        self.validation_samples = int(validation_samples)
        self.max_step_samples = int(max_step_samples)
        self.retune_poles = bool(retune_poles)

    # ------------------------------------------------------------------ controller
    def tune_controller(
        self,
        model: KautzModel,
        settings: MPCSettings,
        *,
        step: float,
        u_op: float | None = None,
        y_op: float = 0.0,
    ) -> ControllerTuning:
        """Retune the increment weight by closed-loop simulation and validate the winner.

        Parameters
        ----------
        model : KautzModel
            The model version the controller will run on (delayed discrete basis).
        settings : MPCSettings
            The design; its ``r`` is the base of ``weight_factors``.
        step : float
            Set-point step to simulate (output units, nonzero).
        u_op : float, optional
            Current command: the limits are taken relative to it (mid-range when omitted).
        y_op : float, default=0.0
            Current output (for the output limits).

        Returns
        -------
        ControllerTuning
        """
        start = time.perf_counter()
        step = _number_or_inf(step, "step")
        if step == 0:
            raise DataError("step must be nonzero")
        lim = settings.controller_limits()
        if u_op is None:
            u_op = 0.5 * (lim["u_min"] + lim["u_max"])
        u_op = float(np.clip(u_op, lim["u_min"], lim["u_max"]))
        n = int(self.n_settle) if self.n_settle is not None else 2 * settings.horizon
        candidates = []
        for f in self.weight_factors:
            cand = settings.with_weight(settings.r * f)
            candidates.append(self._evaluate(model, cand, step, u_op, float(y_op), n))
        valid = [c for c in candidates if c.valid]
        elapsed = time.perf_counter() - start
        if not valid:
            reasons = "; ".join(f"r={c.r:g}: {c.reason}" for c in candidates)
            return ControllerTuning(
                False, settings, tuple(candidates), f"no weight passed the validation ({reasons})",
                elapsed,
            )
        best = min(valid, key=lambda c: c.score)
        return ControllerTuning(
            True, settings.with_weight(best.r), tuple(candidates),
            f"r = {best.r:g} (normalised IAE {best.score:.3g}, overshoot "
            f"{100 * best.overshoot:.1f} %) of {len(valid)}/{len(candidates)} valid weights",
            elapsed,
        )

    def _evaluate(
        self, model: KautzModel, settings: MPCSettings, step: float, u_op: float, y_op: float,
        n: int,
    ) -> TuningCandidate:
        try:
            problem = build_mpc(model, settings, u_shift=u_op, y_shift=y_op)
        except (DataError, ValueError, np.linalg.LinAlgError) as exc:
            return TuningCandidate(settings.r, math.inf, False, 0, math.nan, math.nan, str(exc))
        dt = model.dt
        scores, violations, failed = [], 0, 0
        overshoot = final = math.nan
        for g in self.gain_margins:
            plant = model if g == 1.0 else KautzModel(model.basis, model.coefficients * g)
            res = simulate_closed_loop(plant, problem, np.full(n, step), u0=0.0)
            violations += res.violations
            failed += res.n_failed
            y = np.asarray(res.y, dtype=float)
            scores.append(float(np.sum(np.abs(y[1:] - step))) * dt / abs(step))
            if g == 1.0:
                overshoot = max(0.0, float(np.max(y * np.sign(step))) / abs(step) - 1.0)
                final = abs(float(y[-1]) - step) / abs(step)
        reason = ""
        if violations:
            reason = f"{violations} constraint violations"
        elif failed:
            reason = f"{failed} failed solves"
        elif overshoot > self.max_overshoot:
            reason = f"overshoot {100 * overshoot:.1f} % > {100 * self.max_overshoot:g} %"
        elif final > self.max_final_error:
            reason = f"final error {100 * final:.1f} % of the step"
        ok = not reason
        return TuningCandidate(
            settings.r, float(np.mean(scores)) if ok else math.inf, ok, violations, overshoot,
            final, reason,
        )

    # ------------------------------------------------------------------ model
    def retune_model(self, updater: Updater) -> ModelUpdate | None:
        """Re-optimise the basis poles on the twin's recent behaviour (validated).

        The live fast-path model of ``updater`` (which has followed the plant)
        runs a virtual step test from rest; :func:`kautztwin.optimize_poles`
        fits a model of the current order to it, starting from the current
        poles, and :meth:`Updater.update_from_step_test` validates the
        candidate on held-out recent measurements before it replaces the
        running model; the fast path then continues from the live model on the
        new poles (``from_live``).

        Parameters
        ----------
        updater : Updater
            The twin's update module.

        Returns
        -------
        ModelUpdate or None
            The attempt (``None`` when pole re-optimisation is switched off).
        """
        if not self.retune_poles:
            return None
        est = updater.estimator_
        basis = est.basis_
        rates = -np.log(np.maximum(np.abs(basis.poles), 1e-12)) / updater.dt
        slowest = float(np.min(rates)) if rates.size else 1.0
        n = int(np.clip(8.0 / (slowest * updater.dt), 50, self.max_step_samples))
        u0 = updater.input_offset
        y = est.simulate(np.full(n, u0 + 1.0), linear=True)  # the linear part's step
        try:
            return updater.update_from_step_test(y, amplitude=1.0, u0=u0, y0=est.offset_,
                                                 from_live=True)
        except (DataError, ValueError, np.linalg.LinAlgError):
            return None

    def consolidate(
        self,
        updater: Updater,
        current: KautzModel,
        current_offset: float,
        u: ArrayLike,
        y: ArrayLike,
    ) -> tuple[bool, float, float]:
        """Whether the live fast-path model predicts recent data better than the current version.

        Both models are simulated from rest over the recent input history
        ``u`` (the early part settles their filters) and compared on the last
        ``validation_samples`` finite outputs.

        Parameters
        ----------
        updater : Updater
            The twin's update module (its live model and offset).
        current : KautzModel
            The current version's model (delayed discrete basis).
        current_offset : float
            Its output offset.
        u, y : array-like of shape (n_samples,)
            Recent applied inputs and measured outputs (NaN where not usable).

        Returns
        -------
        better : bool
            The live model's fit exceeds the current one's by ``min_gain``.
        fit_live, fit_current : float
            Fit percent of each on the validation samples.
        """
        u = np.asarray(u, dtype=float)
        y = np.asarray(y, dtype=float)
        n_val = min(self.validation_samples, u.size // 2)
        if n_val < 20 or not np.all(np.isfinite(u)):
            return False, math.nan, math.nan
        est = updater.estimator_
        u0 = updater.input_offset
        live = est.simulate(u, linear=True)  # what a version would hold
        cur = RecursiveKautzEstimator(
            current.basis, dt=updater.dt, coef_init=current.coefficients,
            offset_init=current_offset, input_offset=u0,
        ).simulate(u)
        yy = y[-n_val:]
        f_live = fit_percent_or_nan(yy, live[-n_val:])
        f_cur = fit_percent_or_nan(yy, cur[-n_val:])
        better = math.isfinite(f_live) and (
            not math.isfinite(f_cur) or f_live > f_cur + self.min_gain
        )
        return better, f_live, f_cur

    # ------------------------------------------------------------------ estimator
    def retrain_estimator(
        self,
        estimator: Any,
        model: KautzModel,
        *,
        uncertainty: float | Mapping[str, float] = 0.2,
        n_records: int = 500,
        n_validation: int = 200,
        noise: float = 0.05,
        margin: float = 0.5,
        random_state: int = 0,
        config: Any = None,
    ) -> EstimatorRetraining:
        r"""Fine-tune the neural estimator around the current model, and validate it.

        1. The uncertain system around ``model``:
           :meth:`ParametricSystem.from_zpk <kautztwin.datasets.ParametricSystem.from_zpk>`
           of its zeros, poles and gain (parameters ``'gain'``, ``'zero<i>_rate'``,
           ``'pole<i>_rate'``, ``'pole<i>_wn'``, ``'pole<i>_zeta'``).  A discrete
           model on a delayed basis (the twin's model versions) is first
           converted to the continuous model whose zero-order-hold
           discretisation it is.
        2. ``n_records`` parameter vectors within ``uncertainty``
           (:func:`~kautztwin.datasets.draw_parameters`) and their noisy
           responses on the estimator's grid ``t_``, of its ``kind_``, labelled
           in the basis of the model's poles
           (:func:`~kautztwin.datasets.make_dataset`).
        3. ``estimator.fine_tune(data, config=config, random_state=random_state)``
           gives the candidate (a new estimator; the input one is unchanged).
        4. Validation on ``n_validation`` fresh records (independent draws and
           noise): the mean fit percent of the noise-free responses by the
           models each estimator predicts (``predict_models``).  The candidate
           is accepted only if it beats the running estimator by more than
           ``margin`` points.

        Parameters
        ----------
        estimator : CoefficientEstimator or AdaptivePoleEstimator
            The fitted estimator the twin runs (any object with ``fine_tune``,
            ``predict_models``, ``t_`` and ``kind_``).
        model : KautzModel
            The current model: continuous, or discrete on a delayed basis.
        uncertainty : float or mapping of str to float, default=0.2
            Relative half-width of the parameter distribution, for every
            parameter or per parameter name (see step 1).
        n_records : int, default=500
            Training records simulated, ``>= 2`` (split into training and
            validation parts by the fine-tuning).
        n_validation : int, default=200
            Held-out records of the acceptance test, ``>= 1``.
        noise : float, default=0.05
            Noise standard deviation as a fraction of each record's peak.
        margin : float, default=0.5
            Fit points by which the candidate must beat the running estimator.
        random_state : int, default=0
            Seed of the data and of the fine-tuning.
        config : TrainingConfig, mapping or None, default=None
            Options of the fine-tuning run (see ``estimator.fine_tune``).

        Returns
        -------
        EstimatorRetraining

        Raises
        ------
        DataError
            If the estimator cannot be fine-tuned, ``model`` is not a
            :class:`~kautztwin.KautzModel` with a continuous-time equivalent
            and a nonzero transfer function, or an option is invalid.

        See Also
        --------
        kautztwin.nn.CoefficientEstimator.fine_tune : The fine-tuning of the paper's estimator.
        kautztwin.nn.AdaptivePoleEstimator.fine_tune : The fine-tuning of the adaptive one.
        kautztwin.twin.Updater.update_from_step_test : Where the twin uses the estimator.

        Notes
        -----
        The acceptance test compares models, not coefficients, so an old
        estimator on the old basis and a candidate on the new one are judged
        alike, by the fit of the noise-free response :math:`h` of every
        held-out record,

        .. math:: \mathrm{fit} = 100\,(1 - \|h - \hat h\| / \|h - \bar h\|).

        The held-out records come from the same distribution as the training
        records; the test shows that the candidate is better around the new
        operating point, not that it is still good around the old one.
        """
        start = time.perf_counter()
        for name in ("fine_tune", "predict_models"):
            if not callable(getattr(estimator, name, None)):
                raise DataError(
                    f"estimator must have a {name}() method (a kautztwin.nn estimator), got "
                    f"{type(estimator).__name__}"
                )
        if not hasattr(estimator, "t_") or not hasattr(estimator, "kind_"):
            raise DataError("estimator must be fitted (it has no time grid t_ or kind_)")
        n_records = _integer_at_least(n_records, "n_records", 2)
        n_validation = _integer_at_least(n_validation, "n_validation", 1)
        margin = _number_or_inf(margin, "margin")
        if not math.isfinite(margin):
            raise DataError(f"margin must be a finite number, got {margin}")
        seed = _integer_at_least(random_state, "random_state", 0)
        cont = _continuous_model(model)
        system = _model_system(cont)
        t = np.asarray(estimator.t_, dtype=float)
        kind = str(estimator.kind_)
        draw_train, noise_train, draw_val, noise_val = (
            np.random.default_rng(s) for s in np.random.SeedSequence([seed, 7]).spawn(4)
        )

        def records(n: int, draws: np.random.Generator, rng: np.random.Generator):
            P = draw_parameters(system, uncertainty, n, random_state=draws)
            return make_dataset(
                system, P, cont.basis, t, kind=kind, noise=noise, random_state=rng
            )

        train = records(n_records, draw_train, noise_train)
        held_out = records(n_validation, draw_val, noise_val)
        tic = time.perf_counter()
        candidate = estimator.fine_tune(train, config=config, random_state=seed)
        train_seconds = time.perf_counter() - tic
        fit_old = _mean_fit(estimator, held_out)
        fit_new = _mean_fit(candidate, held_out)
        accepted = math.isfinite(fit_new) and (
            not math.isfinite(fit_old) or fit_new > fit_old + margin
        )
        summary = (
            f"mean held-out fit {fit_new:.2f} % (candidate) vs {fit_old:.2f} % (running) "
            f"on {n_validation} records"
        )
        reason = (
            f"accepted: {summary}"
            if accepted
            else f"rejected: {summary}; the candidate must gain more than {margin:g} points"
        )
        return EstimatorRetraining(
            accepted, candidate if accepted else estimator, candidate, fit_old, fit_new, reason,
            time.perf_counter() - start, train_seconds, n_records, n_validation,
        )

    def __repr__(self) -> str:
        return (
            f"Optimizer(weight_factors={self.weight_factors}, gain_margins={self.gain_margins}, "
            f"retune_poles={self.retune_poles})"
        )


def _integer_at_least(value: Any, name: str, low: int) -> int:
    """:func:`~kautztwin._validation.check_int`, worded ``an integer >= low`` for every ``low``."""
    try:
        return check_int(value, name, low)
    except DataError:
        raise DataError(f"{name} must be an integer >= {low}, got {value!r}") from None


def _continuous_model(model: Any) -> KautzModel:
    """The model itself if continuous, else the continuous model whose ZOH discretisation it is.

    The discretisation (:func:`~kautztwin.twin.digital.discretize_model`) is
    linear in the coefficients, so the continuous coefficients solve one
    ``N x N`` system on the basis with poles ``log(xi) / dt``.
    """
    if not isinstance(model, KautzModel):
        raise DataError(f"model must be a KautzModel, got {type(model).__name__}")
    if model.dt == 0:
        return model
    if not model.basis.delayed:
        raise DataError(
            "model is on an undelayed discrete basis (a direct feedthrough); pass a continuous "
            "model or one on a delayed basis"
        )
    dt = model.dt
    poles = []
    for i, xi in enumerate(model.poles):
        if abs(xi.imag) <= 1e-12 * max(1.0, abs(xi)):
            if xi.real <= 0:
                raise DataError(
                    f"model pole {i} = {xi.real:g} has no continuous-time equivalent (a "
                    "discrete pole at 0 or on the negative real axis)"
                )
            poles.append(complex(math.log(xi.real) / dt))
        else:
            poles.append(complex(np.log(xi)) / dt)
    basis = KautzBasis(poles)
    n = model.n_functions
    columns = [discretize_model(KautzModel(basis, e), dt) for e in np.eye(n)]
    if not columns[0].basis.allclose(model.basis, rtol=1e-8, atol=1e-12):
        raise DataError(
            "model's discrete basis is not the zero-order-hold image of a continuous Kautz "
            "basis; pass the continuous model"
        )
    M = np.column_stack([m.coefficients for m in columns])
    return KautzModel(basis, np.linalg.solve(M, model.coefficients))


def _model_system(model: KautzModel) -> ParametricSystem:
    """The continuous model as a :class:`ParametricSystem` of its zeros, poles and gain."""
    num, den = model.transfer_function()
    if not np.any(num):
        raise DataError("model has a zero transfer function; there is nothing to retrain on")
    zeros = np.roots(num) if num.size > 1 else np.empty(0)
    return ParametricSystem.from_zpk(zeros, model.poles, float(num[0] / den[0]), name="model")


def _mean_fit(estimator: Any, data: ResponseDataset) -> float:
    """Mean fit percent of the noise-free responses by the estimator's predicted models."""
    models = estimator.predict_models(data.responses, t=data.t)
    response = "impulse" if data.kind == "impulse" else "step"
    yhat = np.array([getattr(m, response)(data.t) for m in models])
    if not np.all(np.isfinite(yhat)):
        return math.nan
    return float(np.mean(fit_percent(data.clean, yhat)))
