"""Figures and files of an identification report: residual tests, compare, Bode and step bands.

The numbers come from :mod:`kautztwin.ident.diagnostics`; this module only draws them
(matplotlib, imported inside the functions) and writes the report folder
(:func:`write_report`). Every ``plot_*`` function draws into ``ax`` (a new figure when it
is ``None``), returns the axes and never calls ``plt.show()``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._json import to_jsonable
from .diagnostics.report import _count

if TYPE_CHECKING:  # pragma: no cover - typing only
    from matplotlib.axes import Axes

    from .diagnostics import (
        CrossCorrelationTest,
        FrequencyResponseBand,
        IdentificationDiagnostics,
        StepResponseBand,
        WhitenessTest,
    )

__all__ = [
    "REPORT_FILES",
    "plot_bode_band",
    "plot_input_correlation",
    "plot_residual_autocorrelation",
    "plot_step_band",
    "write_report",
]

#: the files :func:`write_report` writes, in the order the verdict lists them
REPORT_FILES = ("report.md", "report.json", "compare.png", "residuals.png", "bode.png",
                "step.png")

_YES_NO = {True: "yes", False: "no"}


def _axes(ax: Axes | None) -> Axes:
    from .. import plotting

    return plotting._axes(ax)


def _correlation_panel(ax: Axes, lags: Any, r: Any, bound: float, colour: str) -> None:
    ax.axhspan(-bound, bound, color="C0", alpha=0.12, lw=0,
               label=f"confidence bound ±{bound:.3g}")
    ax.vlines(lags, 0.0, r, color=colour, lw=1.4)
    ax.plot(lags, r, "o", color=colour, ms=3.5)
    ax.axhline(0.0, color="0.5", lw=0.6)
    ax.grid(True, alpha=0.3)


def plot_residual_autocorrelation(test: WhitenessTest, ax: Axes | None = None, *,
                                  title: str | None = None) -> Axes:
    """Residual autocorrelation with its confidence bound (MATLAB ``resid``, upper panel).

    Parameters
    ----------
    test : WhitenessTest
        Result of :func:`~kautztwin.ident.diagnostics.whiteness_test`.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.
    title : str, optional
        Axes title; by default the verdict and the Ljung-Box p-value.

    Returns
    -------
    matplotlib.axes.Axes

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.diagnostics import whiteness_test
    >>> from kautztwin.ident.diagnostics_plots import plot_residual_autocorrelation
    >>> ax = plot_residual_autocorrelation(whiteness_test(np.random.default_rng(0).normal(
    ...     size=300)))
    >>> ax.get_xlabel()
    'lag k [samples]'
    >>> import matplotlib.pyplot as plt; plt.close(ax.figure)
    """
    ax = _axes(ax)
    _correlation_panel(ax, test.lags[1:], test.autocorrelation[1:], test.bound, "C3")
    ax.set_xlabel("lag k [samples]")
    ax.set_ylabel("$r_e(k)$")
    ax.set_title(title or f"residual autocorrelation: white {_YES_NO[test.white]} "
                 f"(Ljung-Box p = {test.p_value:.3g})", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    return ax


def plot_input_correlation(test: CrossCorrelationTest, ax: Axes | None = None, *,
                           title: str | None = None) -> Axes:
    """Residual-input cross-correlation with its bound (MATLAB ``resid``, lower panel).

    Parameters
    ----------
    test : CrossCorrelationTest
        Result of :func:`~kautztwin.ident.diagnostics.cross_correlation_test`.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.
    title : str, optional
        Axes title; by default the verdict and the p-value.

    Returns
    -------
    matplotlib.axes.Axes
    """
    ax = _axes(ax)
    _correlation_panel(ax, test.lags, test.cross_correlation, test.bound, "C2")
    if test.tested_lags[0] >= 0:
        ax.axvspan(test.lags[0] - 0.5, -0.5, color="0.5", alpha=0.08, lw=0,
                   label="not tested (feedback)")
    ax.set_xlabel("lag k [samples] (k > 0: input leads)")
    ax.set_ylabel("$r_{eu}(k)$")
    ax.set_title(title or f"residual vs input: independent {_YES_NO[test.independent]} "
                 f"(p = {test.p_value:.3g})", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    return ax


def plot_bode_band(band: FrequencyResponseBand, ax: tuple[Axes, Axes] | None = None,
                   ) -> tuple[Axes, Axes]:
    """Bode magnitude (dB) and phase (degrees) with their confidence bands.

    Parameters
    ----------
    band : FrequencyResponseBand
        Result of :func:`~kautztwin.ident.diagnostics.frequency_response_band`.
    ax : (Axes, Axes), optional
        Magnitude and phase axes; a new figure with two stacked panels when omitted.

    Returns
    -------
    (matplotlib.axes.Axes, matplotlib.axes.Axes)
        Magnitude and phase axes.
    """
    if ax is None:
        from .. import plotting

        _, axes = plotting._pyplot().subplots(2, 1, sharex=True, figsize=(6.4, 5.2),
                                               layout="constrained")
        ax = (axes[0], axes[1])
    mag_ax, ph_ax = ax
    level = f"{100 * band.confidence:g} % band"

    def db(x: Any) -> Any:
        return 20 * np.log10(np.maximum(x, np.finfo(float).tiny))

    # a band wider than the value itself reaches |G| = 0 (-inf dB): the axes follow the
    # model's curve, and the band is cut where it leaves them
    mag = db(band.magnitude)
    lo, hi = float(np.min(mag)), float(np.max(mag))
    mag_ax.fill_between(band.w, np.maximum(db(band.magnitude_lower), lo - 40),
                        np.minimum(db(band.magnitude_upper), hi + 40),
                        color="C0", alpha=0.25, lw=0, label=level)
    mag_ax.semilogx(band.w, mag, color="C0", lw=1.6, label="model")
    mag_ax.set_ylim(lo - 20 - 0.05 * (hi - lo), hi + 10 + 0.05 * (hi - lo))
    mag_ax.set_ylabel("magnitude [dB]")
    mag_ax.legend(fontsize=8, loc="lower left")
    deg = 180 / np.pi
    ph = deg * band.phase
    plo, phi = float(np.min(ph)), float(np.max(ph))
    ph_ax.fill_between(band.w, np.maximum(deg * band.phase_lower, plo - 360),
                       np.minimum(deg * band.phase_upper, phi + 360), color="C0",
                       alpha=0.25, lw=0)
    ph_ax.semilogx(band.w, ph, color="C0", lw=1.6)
    ph_ax.set_ylim(plo - 45 - 0.05 * (phi - plo), phi + 45 + 0.05 * (phi - plo))
    ph_ax.set_ylabel("phase [deg]")
    ph_ax.set_xlabel("ω [rad/s]")
    for a in (mag_ax, ph_ax):
        a.grid(True, which="both", alpha=0.3)
    return mag_ax, ph_ax


def plot_step_band(band: StepResponseBand, ax: Axes | None = None) -> Axes:
    """Unit-step response with its confidence band.

    Parameters
    ----------
    band : StepResponseBand
        Result of :func:`~kautztwin.ident.diagnostics.step_response_band`.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.

    Returns
    -------
    matplotlib.axes.Axes
    """
    ax = _axes(ax)
    ax.fill_between(band.t, band.lower, band.upper, color="C0", alpha=0.25, lw=0,
                    label=f"{100 * band.confidence:g} % band")
    ax.plot(band.t, band.y, color="C0", lw=1.6, label="model")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("unit-step response")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    return ax


def _compare_figure(diag: IdentificationDiagnostics, output_name: str) -> Any:
    from .. import plotting

    recs = diag.records
    fig, axes = plotting._new_figure(len(recs), ncols=1, panel_size=(8.0, 2.8))
    T = diag.validate_from
    per = diag.model.fit_percent_per_record
    for k, (ax, r, yh) in enumerate(zip(axes, recs, diag.predictions, strict=True)):
        title = f"record {k + 1}: {r.name}"
        if T is None and k < len(per):
            title += f"  (fit {per[k]:.2f} %)"
        plotting.plot_approximation(r.t, r.y, yh, ax, approx_label="simulated model",
                                    ylabel=output_name, title=title)
        if T is not None and r.t[-1] >= T:
            ax.axvspan(max(T, r.t[0]), r.t[-1], color="C1", alpha=0.08, label="validation")
            ax.legend(fontsize=8)
        ax.title.set_fontsize(9)
    m = diag.model
    head = f"fit: estimation {m.fit_percent:.2f} %"
    if m.validation_fit_percent is not None:
        head += f", validation {m.validation_fit_percent:.2f} %"
    fig.suptitle(head, fontsize=10)
    return fig


def _residual_figure(diag: IdentificationDiagnostics) -> Any:
    from .. import plotting

    parts = [p for p in (diag.estimation, diag.validation) if p is not None]
    fig, axes = plotting._new_figure(2 * len(parts), ncols=2, panel_size=(5.0, 3.0))
    for i, part in enumerate(parts):
        plot_residual_autocorrelation(part.whiteness, axes[2 * i])
        axes[2 * i].set_title(f"{part.part}: " + axes[2 * i].get_title(), fontsize=9)
        ic = part.input_correlation
        if ic is None:
            axes[2 * i + 1].text(0.5, 0.5, "input constant: no cross-correlation test",
                                 ha="center", va="center", transform=axes[2 * i + 1].transAxes)
            axes[2 * i + 1].set_axis_off()
        else:
            plot_input_correlation(ic, axes[2 * i + 1])
            axes[2 * i + 1].set_title(f"{part.part}: " + axes[2 * i + 1].get_title(),
                                      fontsize=9)
    return fig


def write_report(diag: IdentificationDiagnostics, directory: str | os.PathLike[str], *,
                 output_name: str = "y", dpi: int = 100) -> dict[str, Path]:
    """Write an identification report folder: verdict (Markdown and JSON) and four figures.

    Files: ``report.md`` (the one-page verdict), ``report.json`` (the same as data, with
    the full test results), ``compare.png`` (measured and simulated output of every
    record), ``residuals.png`` (autocorrelation and input cross-correlation of the
    residual with their bounds, estimation and validation data), ``bode.png`` and
    ``step.png`` (with confidence bands). The folder is made when missing.

    Parameters
    ----------
    diag : IdentificationDiagnostics
        Result of :func:`~kautztwin.ident.diagnostics.diagnose`.
    directory : str or os.PathLike
        The report folder.
    output_name : str, default='y'
        Label of the output axis in ``compare.png``.
    dpi : int, default=100
        Resolution of the figures.

    Returns
    -------
    dict of str to pathlib.Path
        Each file name in :data:`REPORT_FILES` and the path written.

    Raises
    ------
    OSError
        If the folder cannot be made or written.
    """
    from .. import plotting

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in REPORT_FILES}
    figures = [name for name in REPORT_FILES if name.endswith(".png")]
    paths["report.md"].write_text(diag.to_markdown(figures), encoding="utf-8")
    paths["report.json"].write_text(
        json.dumps(to_jsonable(diag.verdict()), indent=2, allow_nan=False) + "\n",
        encoding="utf-8")
    plotting.save_figure(_compare_figure(diag, output_name), paths["compare.png"], dpi=dpi)
    plotting.save_figure(_residual_figure(diag), paths["residuals.png"], dpi=dpi)
    fig, axes = plotting._new_figure(2, ncols=1, panel_size=(6.4, 2.6))
    axes[0].sharex(axes[1])
    plot_bode_band(diag.bode, (axes[0], axes[1]))
    m = diag.model
    axes[0].set_title(f"Bode: {_count(m.n_poles, 'pole')}, {_count(m.n_zeros, 'zero')}"
                      + (f", delay {m.delay:.3g} s" if m.delay else ""), fontsize=9)
    plotting.save_figure(fig, paths["bode.png"], dpi=dpi)
    fig, axes = plotting._new_figure(1, ncols=1, panel_size=(6.4, 3.4))
    plot_step_band(diag.step, axes[0])
    axes[0].set_title(f"step response: gain {m.gain:.4g} ± {m.gain_std:.2g}", fontsize=9)
    plotting.save_figure(fig, paths["step.png"], dpi=dpi)
    return paths
