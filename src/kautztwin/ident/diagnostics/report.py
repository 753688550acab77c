"""The verdict of an identification: residual tests of both data parts, bands and poles."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_int
from ...exceptions import DataError, NotFittedError
from .bands import (
    FrequencyResponseBand,
    PoleUncertainty,
    StepResponseBand,
    _default_frequencies,
    frequency_response_band,
    pole_uncertainty,
    step_response_band,
)
from .correlation import (
    DEFAULT_MAX_LAG,
    CrossCorrelationTest,
    WhitenessTest,
    _check_alpha,
    cross_correlation_test,
    whiteness_test,
)

if TYPE_CHECKING:
    from ..records import Record
    from ..tfest import TransferFunctionModel

__all__ = ["IdentificationDiagnostics", "ResidualAnalysis", "diagnose"]


# =============================================================================== the report
def _count(n: int, word: str) -> str:
    """``'1 pole'``, ``'2 poles'``."""
    return f"{n} {word}" + ("" if n == 1 else "s")


@dataclass(frozen=True, eq=False)
class ResidualAnalysis:
    """Residual tests of one part of the data (estimation or validation).

    Parameters
    ----------
    part : {'estimation', 'validation'}
        Which samples: ``t < validate_from`` or ``t >= validate_from`` (all samples for
        estimation when nothing is held out).
    whiteness : WhitenessTest
        Autocorrelation test of the residual.
    input_correlation : CrossCorrelationTest or None
        Residual-input test; ``None`` when the input is constant over the part (a step
        record that starts at its step) or varies in too few samples for the lags.
    fit_percent : float or None
        Simulation fit of the part.
    """

    part: str
    whiteness: WhitenessTest
    input_correlation: CrossCorrelationTest | None
    fit_percent: float | None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary.

        Returns
        -------
        dict
        """
        ic = self.input_correlation
        return {"part": self.part, "fit_percent": self.fit_percent,
                "whiteness": self.whiteness.to_dict(),
                "input_correlation": None if ic is None else ic.to_dict()}


@dataclass(frozen=True, eq=False)
class IdentificationDiagnostics:
    """Everything a validation report shows about an identified transfer function.

    Parameters
    ----------
    model : TransferFunctionModel
        The model.
    records : tuple of Record
        The records it was compared with.
    predictions : tuple of ndarray
        Simulated output of each record (MATLAB ``compare``).
    validate_from : float or None
        Start of the validation samples.
    estimation : ResidualAnalysis
        Tests on the estimation samples.
    validation : ResidualAnalysis or None
        Tests on the validation samples, if any.
    bode : FrequencyResponseBand
        Frequency response with confidence bands.
    step : StepResponseBand
        Step response with confidence band.
    poles : PoleUncertainty
        Poles with standard deviations.

    Attributes
    ----------
    decisive : ResidualAnalysis
        The part the verdict rests on: validation when there is one, else estimation.
    """

    model: TransferFunctionModel
    records: tuple[Record, ...]
    predictions: tuple[NDArray[np.float64], ...]
    validate_from: float | None
    estimation: ResidualAnalysis
    validation: ResidualAnalysis | None
    bode: FrequencyResponseBand
    step: StepResponseBand
    poles: PoleUncertainty

    @property
    def decisive(self) -> ResidualAnalysis:
        """Validation tests when there are validation samples, else estimation tests."""
        return self.validation if self.validation is not None else self.estimation

    def verdict(self) -> dict[str, Any]:
        """The one-page verdict as a JSON-ready dict.

        Returns
        -------
        dict
            ``residuals_white`` (bool), ``whiteness_p_value``,
            ``residuals_independent_of_input`` (bool, or None without input variation),
            ``input_p_value``, ``tested_on`` (the part), ``fit_percent``,
            ``validation_fit_percent``, ``parameters`` (name, value, std), ``poles``
            (``re``, ``im``, ``std_re``, ``std_im``), ``gain`` and ``gain_std``, and the
            full test results of both parts under ``estimation`` and ``validation``.
        """
        d = self.decisive
        ic = d.input_correlation
        m = self.model
        values = np.concatenate([m.num, m.den[1:], [m.delay]])[: len(m.parameter_names)]
        return {
            "tested_on": d.part,
            "residuals_white": d.whiteness.white,
            "whiteness_p_value": d.whiteness.p_value,
            "residuals_independent_of_input": None if ic is None else ic.independent,
            "input_p_value": None if ic is None else ic.p_value,
            "alpha": d.whiteness.alpha,
            "fit_percent": m.fit_percent,
            "validation_fit_percent": m.validation_fit_percent,
            "n_poles": m.n_poles, "n_zeros": m.n_zeros, "delay": m.delay,
            "gain": m.gain, "gain_std": m.gain_std,
            "parameters": [{"name": k, "value": float(v), "std": float(s)}
                           for k, v, s in zip(m.parameter_names, values, m.std, strict=True)],
            "poles": self.poles.to_list(),
            "estimation": self.estimation.to_dict(),
            "validation": None if self.validation is None else self.validation.to_dict(),
        }

    def to_markdown(self, figures: Sequence[str] = ()) -> str:
        """The verdict as one page of Markdown (plain text that reads well as it is).

        Parameters
        ----------
        figures : sequence of str, default=()
            File names of the figures to list at the end.

        Returns
        -------
        str
        """
        v = self.verdict()
        m = self.model
        yn = {True: "yes", False: "no",
              None: "n/a (the input does not vary, or too few samples where it does)"}
        lines = ["# Identification report", "",
                 f"model: {_count(m.n_poles, 'pole')}, {_count(m.n_zeros, 'zero')}"
                 + (f", delay {m.delay:.4g} s" if m.delay else "")
                 + f", gain {m.gain:.4g} +- {m.gain_std:.2g}", ""]
        d = self.decisive
        lines.append(f"- residuals white: {yn[v['residuals_white']]} (Ljung-Box p = "
                     f"{d.whiteness.p_value:.3g}, {d.whiteness.dof} lags, {d.part} data; "
                     f"{d.whiteness.n_outside} of {d.whiteness.lags[-1]} lags outside the "
                     f"{100 * (1 - d.whiteness.alpha):.0f} % bound)")
        ic = d.input_correlation
        extra = "" if ic is None else (
            f" (p = {ic.p_value:.3g}, lags {ic.tested_lags[0]}..{ic.tested_lags[-1]}; "
            f"{ic.n_outside} outside the bound)")
        lines.append(f"- residuals independent of input: "
                     f"{yn[v['residuals_independent_of_input']]}{extra}")
        lines.append(f"- fit: estimation {m.fit_percent:.2f} %" + (
            "" if m.validation_fit_percent is None
            else f", validation {m.validation_fit_percent:.2f} %"))
        if self.validation is not None:
            e = self.estimation
            lines.append(f"- on the estimation data: white {yn[e.whiteness.white]} "
                         f"(p = {e.whiteness.p_value:.3g})" + (
                             "" if e.input_correlation is None else
                             f", independent of input {yn[e.input_correlation.independent]} "
                             f"(p = {e.input_correlation.p_value:.3g})"))
        lines += ["", "| parameter | value | std |", "|---|---|---|"]
        lines += [f"| {p['name']} | {p['value']:.6g} | {p['std']:.3g} |"
                  for p in v["parameters"]]
        lines += ["", "| pole | std (re) | std (im) | time constant [s] |", "|---|---|---|---|"]
        for p in v["poles"]:
            z = complex(p["re"], p["im"])
            txt = f"{z.real:.5g}" if z.imag == 0 else f"{z.real:.5g}{z.imag:+.5g}j"
            lines.append(f"| {txt} | {p['std_re']:.3g} | {p['std_im']:.3g} | "
                         f"{-1 / z.real:.4g} |")
        if figures:
            lines += ["", "figures: " + ", ".join(figures)]
        return "\n".join(lines) + "\n"


def _part(records: Sequence[Record], yhat: Sequence[NDArray], masks: Sequence[NDArray],
          name: str, fit: float | None, max_lag: int, alpha: float) -> ResidualAnalysis | None:
    es = [np.asarray(r.y)[k] - yh[k] for r, yh, k in zip(records, yhat, masks, strict=True)
          if k.sum() >= 3]
    us = [np.asarray(r.u)[k] for r, k in zip(records, masks, strict=True) if k.sum() >= 3]
    n = sum(e.size for e in es)
    if n < 8:
        return None
    lag = min(max_lag, max(1, n // 4), max(e.size for e in es) - 2)
    white = whiteness_test(es, max_lag=lag, alpha=alpha)
    varied = [i for i, u in enumerate(us) if np.ptp(u) > 0]
    cross = None
    if sum(es[i].size for i in varied) >= 8:
        try:
            cross = cross_correlation_test([es[i] for i in varied], [us[i] for i in varied],
                                           max_lag=lag, alpha=alpha)
        except DataError:  # the records with input variation are too short for the lags
            cross = None
    return ResidualAnalysis(part=name, whiteness=white, input_correlation=cross,
                            fit_percent=fit)


def diagnose(estimator: Any, records: Any = None, *, max_lag: int = DEFAULT_MAX_LAG,
             alpha: float = 0.05, confidence: float = 0.95, w: ArrayLike | None = None,
             t: ArrayLike | None = None) -> IdentificationDiagnostics:
    """Residual tests, confidence bands and verdict of a fitted transfer-function estimator.

    The residual is the measured minus the simulated output of every record (its offset
    and initial state fitted on the estimation samples, as ``estimator.predict`` does).
    The tests run on the estimation samples and, when the estimator holds data out
    (``validate_from``), on the validation samples; the verdict rests on the validation
    part then, as MATLAB recommends for ``resid``. Sample weights (merged duplicate
    stamps) are ignored by the tests; jittered stamps are taken as a uniform sequence.

    Parameters
    ----------
    estimator : TransferFunctionEstimator
        A fitted estimator.
    records : Record or list of Record, optional
        The records to test; those it was fitted to when omitted.
    max_lag : int, default=25
        Lags of the tests (fewer when a part has under ``4 max_lag`` samples).
    alpha : float, default=0.05
        Significance level of the tests.
    confidence : float, default=0.95
        Level of the Bode and step bands.
    w : array-like, optional
        Frequencies of the Bode band; by default from a decade below the slowest pole to
        the Nyquist frequency :math:`\\pi/\\Delta t` of the records (the data say nothing
        above it).
    t : array-like, optional
        Times of the step band (see :func:`step_response_band`).

    Returns
    -------
    IdentificationDiagnostics

    Raises
    ------
    NotFittedError
        If the estimator is not fitted.
    DataError
        If the model has no covariance, or the residual is too short to test.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import Record, TransferFunctionEstimator, simulate_lti
    >>> from kautztwin.ident.diagnostics import diagnose
    >>> rng = np.random.default_rng(0)
    >>> t = 0.1 * np.arange(600)
    >>> u = np.repeat(rng.standard_normal(60), 10)
    >>> y = simulate_lti(([1.0], [1.0, 1.0]), t, u) + 0.02 * rng.standard_normal(t.size)
    >>> est = TransferFunctionEstimator(n_poles=1, n_zeros=0).fit(Record.from_data(t, u, y))
    >>> v = diagnose(est).verdict()
    >>> v["residuals_white"], v["residuals_independent_of_input"]
    (True, True)
    """
    model = getattr(estimator, "model_", None)
    if model is None:
        raise NotFittedError("the estimator is not fitted yet; call fit(records) first")
    alpha = _check_alpha(alpha)
    check_int(max_lag, "max_lag", 1)
    recs = tuple(estimator.records_ if records is None else estimator._records(records))
    yhat = tuple(estimator.predict(list(recs)))
    T = estimator.validate_from
    if T is None:
        est_masks = [np.ones(r.n_samples, dtype=bool) for r in recs]
        val_masks = None
    else:
        est_masks = [r.t < float(T) for r in recs]
        val_masks = [r.t >= float(T) for r in recs]
    est = _part(recs, yhat, est_masks, "estimation", model.fit_percent, max_lag, alpha)
    if est is None:
        raise DataError("too few estimation samples to test the residual (at least 8 needed)")
    val = None if val_masks is None else _part(recs, yhat, val_masks, "validation",
                                               model.validation_fit_percent, max_lag, alpha)
    if w is None:
        dt = min(float(np.median(np.diff(r.t))) for r in recs)
        w = _default_frequencies(model, w_max=np.pi / dt)
    return IdentificationDiagnostics(
        model=model, records=recs, predictions=yhat,
        validate_from=None if T is None else float(T), estimation=est, validation=val,
        bode=frequency_response_band(model, w, confidence=confidence),
        step=step_response_band(model, t, confidence=confidence),
        poles=pole_uncertainty(model),
    )
