"""Tests of kautztwin.plotting: every helper returns its Axes and files are valid PNGs."""

from __future__ import annotations

import subprocess
import sys

import matplotlib

matplotlib.use("Agg")  # the tests never need a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402

import kautztwin as kt  # noqa: E402
from kautztwin.exceptions import DimensionError  # noqa: E402
from kautztwin.plotting import (  # noqa: E402
    plot_approximation,
    plot_basis,
    plot_sensitivity_curve,
    plot_sensitivity_surface,
    save_figure,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
W = np.sqrt(15.0) / 2.0


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def test_import_kautztwin_does_not_import_matplotlib():
    code = (
        "import sys, kautztwin, kautztwin.plotting, kautztwin.cli.main; "
        "sys.exit('matplotlib' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_plot_basis_draws_one_line_per_function_with_pole_legend():
    basis = kt.KautzBasis([-1.1, -0.8, -2.1])
    t = np.linspace(0, 10, 300)
    ax = plot_basis(basis, t)
    assert isinstance(ax, Axes)
    lines = ax.get_lines()[:3]
    for line, row in zip(lines, basis.evaluate(t), strict=True):
        np.testing.assert_allclose(line.get_ydata(), row, rtol=0, atol=0)
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert labels == ["$K_{1}$, p = -1.1", "$K_{2}$, p = -0.8", "$K_{3}$, p = -2.1"]


def test_plot_basis_labels_complex_pairs():
    ax = plot_basis(kt.KautzBasis([-1, -0.5 + 1j * W, -0.5 - 1j * W]), np.linspace(0, 10, 50))
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert labels[1] == labels[2].replace("K_{3}", "K_{2}") == "$K_{2}$, p = -0.5 ± 1.936j"


def test_plot_basis_into_given_axes_and_discrete_basis():
    fig, ax = plt.subplots()
    basis = kt.KautzBasis([0.8, 0.5 + 0.3j, 0.5 - 0.3j], dt=0.1)
    out = plot_basis(basis, 0.1 * np.arange(30), ax=ax)
    assert out is ax
    assert "discrete" in ax.get_title()
    assert ax.get_lines()[0].get_marker() == "o"


def test_plot_approximation_returns_axes_with_both_signals():
    t = np.linspace(0, 5, 40)
    ax = plot_approximation(t, np.exp(-t), np.exp(-1.1 * t), label="data", title="fit")
    assert isinstance(ax, Axes)
    assert [line.get_label() for line in ax.get_lines()] == ["data", "Kautz approximant"]
    assert ax.get_title() == "fit"


def test_plot_approximation_rejects_mismatched_lengths():
    with pytest.raises(DimensionError, match="one length"):
        plot_approximation(np.arange(5.0), np.zeros(5), np.zeros(4))


def test_plot_sensitivity_curve_log_scale_marks_minimum():
    p = np.linspace(-3, -0.2, 29)
    ise = 1e-3 + (p + 1) ** 2
    ax = plot_sensitivity_curve(p, ise, nominal=-1.0, label="ISE")
    assert isinstance(ax, Axes)
    assert ax.get_yscale() == "log"
    marker = [line for line in ax.get_lines() if line.get_marker() == "o"][0]
    k = int(np.argmin(ise))
    assert marker.get_xdata()[0] == p[k] and marker.get_ydata()[0] == ise[k]


def test_plot_sensitivity_curve_tolerates_exact_zero():
    p = np.array([-2.0, -1.0, -0.5])
    ax = plot_sensitivity_curve(p, np.array([1e-3, 0.0, 1e-2]))
    marker = [line for line in ax.get_lines() if line.get_marker() == "o"][0]
    assert marker.get_xdata()[0] == -1.0  # drawn at the smallest positive value
    assert marker.get_ydata()[0] == 1e-3


def test_plot_sensitivity_curve_rejects_shapes():
    with pytest.raises(DimensionError, match="values and ise"):
        plot_sensitivity_curve(np.arange(3.0), np.ones(4))


def test_plot_sensitivity_surface_marks_minimum_and_adds_colorbar():
    re = np.linspace(-2, -0.1, 21)
    im = np.linspace(0.5, 4, 17)
    Z = 1e-4 + (re[None, :] + 0.5) ** 2 + (im[:, None] - 1.9) ** 2
    Z[0, 0] = 0.0  # an exact zero must not break the log scale
    ax = plot_sensitivity_surface(re, im, Z + 1.0, nominal=-0.5 + 1.9j)
    assert isinstance(ax, Axes)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("Re p", "Im p")
    assert len(ax.figure.axes) == 2  # plot and colour bar
    i, j = np.unravel_index(np.argmin(Z + 1.0), Z.shape)
    best = [line for line in ax.get_lines() if line.get_marker() == "o"][0]
    assert (best.get_xdata()[0], best.get_ydata()[0]) == (re[j], im[i])
    plot_sensitivity_surface(re, im, Z)


def test_plot_sensitivity_surface_rejects_transposed_grid():
    re, im = np.linspace(-2, -0.1, 5), np.linspace(0.5, 4, 4)
    with pytest.raises(DimensionError, match=r"\(n_imag, n_real\) = \(4, 5\)"):
        plot_sensitivity_surface(re, im, np.ones((5, 4)))


def test_save_figure_writes_png_and_closes_pyplot_figure(tmp_path):
    ax = plot_basis(kt.LaguerreBasis(pole=-1.0, n=3), np.linspace(0, 8, 100))
    number = ax.figure.number
    out = save_figure(ax, tmp_path / "basis.png")
    data = out.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 1000
    assert not plt.fignum_exists(number)


def test_save_figure_other_format(tmp_path):
    ax = plot_approximation(np.arange(3.0), np.ones(3), np.ones(3))
    out = save_figure(ax.figure, tmp_path / "a.pdf")
    assert out.read_bytes().startswith(b"%PDF")
