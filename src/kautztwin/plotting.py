"""Matplotlib helpers: basis functions, approximations and pole-sensitivity maps.

matplotlib is imported inside the functions only, so ``import kautztwin`` does
not need it.  When no display is available (and neither ``MPLBACKEND`` nor an
earlier ``import matplotlib.pyplot`` chose a backend) the non-interactive Agg
backend is selected.  No function calls ``plt.show()``; every ``plot_*``
function draws into ``ax`` (a new figure when ``ax`` is ``None``) and returns it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from .exceptions import DimensionError

if TYPE_CHECKING:  # pragma: no cover - typing only
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from .basis import KautzBasis

__all__ = [
    "plot_approximation",
    "plot_basis",
    "plot_sensitivity_curve",
    "plot_sensitivity_surface",
    "save_figure",
]


def _has_display() -> bool:
    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def _pyplot() -> Any:
    """Import ``matplotlib.pyplot``, choosing Agg first when there is no display."""
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - matplotlib is a dependency
        raise ImportError("plotting needs matplotlib: pip install matplotlib") from exc
    if "matplotlib.pyplot" not in sys.modules and not os.environ.get("MPLBACKEND"):
        if not _has_display():
            matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _axes(ax: Axes | None) -> Axes:
    if ax is not None:
        return ax
    _, new = _pyplot().subplots()
    return new


def _new_figure(n_panels: int, *, ncols: int = 3, panel_size: tuple[float, float] = (4.6, 3.8)):
    """A figure outside pyplot's registry with ``n_panels`` axes (for files only).

    Returns
    -------
    fig : matplotlib.figure.Figure
    axes : list of Axes
        The first ``n_panels`` axes in reading order; unused grid cells are removed.
    """
    from matplotlib.figure import Figure

    ncols = max(1, min(ncols, n_panels))
    nrows = -(-n_panels // ncols)
    fig = Figure(figsize=(panel_size[0] * ncols, panel_size[1] * nrows), layout="constrained")
    grid = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for extra in grid[n_panels:]:
        extra.remove()
    return fig, list(grid[:n_panels])


def _format_pole(p: complex, pair: bool = False) -> str:
    if pair:
        return f"{p.real:.4g} ± {abs(p.imag):.4g}j"
    if p.imag == 0:
        return f"{p.real:.4g}"
    return f"{p.real:.4g}{p.imag:+.4g}j"


def plot_basis(basis: KautzBasis, t: ArrayLike, ax: Axes | None = None) -> Axes:
    """Plot every function of an orthonormal basis against time (the paper's Figure 2).

    Continuous bases are drawn as curves, discrete ones as sequences with
    markers.  The legend gives each function's pole: a real pole, or the
    complex pair ``Re ± Im j`` that the function belongs to.

    Parameters
    ----------
    basis : KautzBasis
        The basis (a :class:`~kautztwin.LaguerreBasis` works too).
    t : array-like of shape (n_samples,)
        Time instants in seconds (on the grid ``k * dt`` for a discrete basis).
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.

    Returns
    -------
    matplotlib.axes.Axes

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.plotting import plot_basis
    >>> ax = plot_basis(kt.KautzBasis([-1.1, -0.8, -2.1]), np.linspace(0, 10, 200))
    >>> len(ax.get_legend().get_texts())
    3
    >>> import matplotlib.pyplot as plt; plt.close(ax.figure)
    """
    t = np.asarray(t, dtype=float)
    F = basis.evaluate(t)
    ax = _axes(ax)
    poles = np.asarray(basis.poles)
    discrete = basis.dt > 0
    for i, (f, p) in enumerate(zip(F, poles, strict=True)):
        is_pair = p.imag != 0
        label = f"$K_{{{i + 1}}}$, p = {_format_pole(p, pair=is_pair)}"
        if discrete:
            ax.plot(t, f, marker="o", markersize=3, linewidth=0.8, label=label)
        else:
            ax.plot(t, f, linewidth=1.5, label=label)
    ax.axhline(0.0, color="0.6", linewidth=0.6, zorder=0)
    name = type(basis).__name__.replace("Basis", "")
    domain = f"discrete, dt = {basis.dt:g} s" if discrete else "continuous"
    ax.set_title(f"{name} basis: {basis.n_functions} functions, {domain}")
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("$K_i(t)$" if not discrete else "$K_i(k)$")
    ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3)
    return ax


def plot_approximation(
    t: ArrayLike,
    y: ArrayLike,
    yhat: ArrayLike,
    ax: Axes | None = None,
    *,
    label: str = "measured",
    approx_label: str = "Kautz approximant",
    ylabel: str = "response",
    title: str | None = None,
) -> Axes:
    """Plot a measured response and its approximant on the same axes.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Sample times in seconds.
    y : array-like of shape (n_samples,)
        Measured (or reference) response.
    yhat : array-like of shape (n_samples,)
        Model response on the same grid.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.
    label : str, default='measured'
        Legend entry of ``y``.
    approx_label : str, default='Kautz approximant'
        Legend entry of ``yhat``.
    ylabel : str, default='response'
        Label of the y axis.
    title : str, optional
        Axes title.

    Returns
    -------
    matplotlib.axes.Axes

    Raises
    ------
    DimensionError
        If ``t``, ``y`` and ``yhat`` are not 1-D arrays of one length.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.plotting import plot_approximation
    >>> t = np.linspace(0, 5, 50)
    >>> ax = plot_approximation(t, np.exp(-t), np.exp(-1.1 * t))
    >>> [line.get_label() for line in ax.get_lines()]
    ['measured', 'Kautz approximant']
    >>> import matplotlib.pyplot as plt; plt.close(ax.figure)
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    if not (t.ndim == y.ndim == yhat.ndim == 1 and t.size == y.size == yhat.size):
        raise DimensionError(
            "t, y and yhat must be 1-D of one length; "
            f"got shapes {t.shape}, {y.shape}, {yhat.shape}"
        )
    ax = _axes(ax)
    ax.plot(t, y, color="0.35", linewidth=1.0, marker=".", markersize=2.5, label=label)
    ax.plot(t, yhat, color="C3", linewidth=1.8, label=approx_label)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend()
    ax.grid(True, alpha=0.3)
    return ax


def plot_sensitivity_curve(
    values: ArrayLike,
    ise: ArrayLike,
    ax: Axes | None = None,
    *,
    nominal: float | None = None,
    label: str | None = None,
    xlabel: str = "pole location",
    title: str | None = None,
) -> Axes:
    """Plot the ISE against the location of one real pole, on a log scale.

    The minimum is marked with a dot.  Zero ISE values (an exact fit) cannot be
    shown on a log axis and are left out of the curve.

    Parameters
    ----------
    values : array-like of shape (n_values,)
        Pole locations (real; a complex array must have zero imaginary part).
    ise : array-like of shape (n_values,)
        ISE of the best approximation for each location.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.
    nominal : float, optional
        Location to mark with a dashed vertical line (e.g. the basis pole).
    label : str, optional
        Legend entry of the curve.
    xlabel : str, default='pole location'
        Label of the x axis.
    title : str, optional
        Axes title.

    Returns
    -------
    matplotlib.axes.Axes

    Raises
    ------
    DimensionError
        If ``values`` and ``ise`` are not 1-D arrays of one length.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.plotting import plot_sensitivity_curve
    >>> p = np.linspace(-3, -0.2, 30)
    >>> ax = plot_sensitivity_curve(p, 1e-3 + (p + 1) ** 2, nominal=-1.0)
    >>> ax.get_yscale()
    'log'
    >>> import matplotlib.pyplot as plt; plt.close(ax.figure)
    """
    x = np.real(np.asarray(values))
    e = np.asarray(ise, dtype=float)
    if not (x.ndim == e.ndim == 1 and x.size == e.size):
        raise DimensionError(
            f"values and ise must be 1-D of one length; got shapes {x.shape} and {e.shape}"
        )
    ax = _axes(ax)
    finite = np.isfinite(e)
    shown = np.where(finite & (e > 0), e, np.nan)
    ax.plot(x, shown, color="C0", linewidth=1.6, label=label)
    if np.any(finite):
        k = int(np.nanargmin(np.where(finite, e, np.nan)))
        # an exact zero sits at the bottom of the drawn curve
        y_mark = e[k] if e[k] > 0 else np.nanmin(shown) if np.any(np.isfinite(shown)) else np.nan
        if np.isfinite(y_mark):
            ax.plot([x[k]], [y_mark], "o", color="C3", label=f"min {e[k]:.3g} at {x[k]:.4g}")
    if nominal is not None:
        ax.axvline(float(np.real(nominal)), color="0.4", linestyle="--", linewidth=1.0,
                   label=f"basis pole {float(np.real(nominal)):.4g}")
    if np.any(e > 0):
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("ISE")
    if title:
        ax.set_title(title)
    ax.legend(fontsize="small")
    ax.grid(True, which="both", alpha=0.3)
    return ax


def plot_sensitivity_surface(
    real_values: ArrayLike,
    imag_values: ArrayLike,
    ise_2d: ArrayLike,
    ax: Axes | None = None,
    *,
    nominal: complex | None = None,
    levels: int = 30,
    title: str | None = None,
) -> Axes:
    r"""Filled contours of :math:`\log_{10}` ISE over the real and imaginary part of a pole pair.

    The minimum on the grid is marked with a red dot and a colour bar is
    added.  Zero ISE values are floored at the smallest positive value (or
    ``1e-300``) before the logarithm.

    Parameters
    ----------
    real_values : array-like of shape (n_real,)
        Real parts of the pole (x axis).
    imag_values : array-like of shape (n_imag,)
        Positive imaginary parts of the pole (y axis).
    ise_2d : array-like of shape (n_imag, n_real)
        ``ise_2d[i, j]`` is the ISE with the pair at
        ``real_values[j] +- 1j * imag_values[i]`` (matplotlib's ``Z[y, x]`` order,
        which ``re[None, :] + 1j * im[:, None]`` produces).
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when omitted.
    nominal : complex, optional
        Pole location to mark with a cross (e.g. the basis pole).
    levels : int, default=30
        Number of contour levels.
    title : str, optional
        Axes title.

    Returns
    -------
    matplotlib.axes.Axes

    Raises
    ------
    DimensionError
        If the shapes do not match or an axis has fewer than two values.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.plotting import plot_sensitivity_surface
    >>> re, im = np.linspace(-2, -0.1, 20), np.linspace(0.5, 4, 15)
    >>> Z = 1e-4 + (re[None, :] + 0.5) ** 2 + (im[:, None] - 1.9) ** 2
    >>> ax = plot_sensitivity_surface(re, im, Z, nominal=-0.5 + 1.9j)
    >>> ax.get_xlabel()
    'Re p'
    >>> import matplotlib.pyplot as plt; plt.close(ax.figure)
    """
    re = np.real(np.asarray(real_values)).astype(float)
    im = np.real(np.asarray(imag_values)).astype(float)
    Z = np.asarray(ise_2d, dtype=float)
    if re.ndim != 1 or im.ndim != 1 or re.size < 2 or im.size < 2:
        raise DimensionError(
            "real_values and imag_values must be 1-D with at least 2 values each; "
            f"got shapes {re.shape} and {im.shape}"
        )
    if Z.shape != (im.size, re.size):
        raise DimensionError(
            f"ise_2d must have shape (n_imag, n_real) = ({im.size}, {re.size}); got {Z.shape}"
        )
    ax = _axes(ax)
    positive = Z[np.isfinite(Z) & (Z > 0)]
    floor = float(positive.min()) if positive.size else 1e-300
    logZ = np.log10(np.where(np.isfinite(Z), np.maximum(Z, floor), np.nan))
    filled = ax.contourf(re, im, logZ, levels=levels, cmap="viridis")
    ax.figure.colorbar(filled, ax=ax, label="log$_{10}$ ISE")
    if np.any(np.isfinite(Z)):
        i, j = np.unravel_index(int(np.nanargmin(np.where(np.isfinite(Z), Z, np.nan))), Z.shape)
        ax.plot([re[j]], [im[i]], "o", color="C3", markeredgecolor="white",
                label=f"min at {re[j]:.4g} ± {im[i]:.4g}j")
    if nominal is not None:
        nominal = complex(nominal)
        ax.plot([nominal.real], [abs(nominal.imag)], "x", color="white", markersize=8,
                markeredgewidth=2, label=f"basis pole {_format_pole(nominal, pair=True)}")
    ax.set_xlabel("Re p")
    ax.set_ylabel("Im p")
    if title:
        ax.set_title(title)
    ax.legend(fontsize="small", loc="best")
    return ax


def save_figure(fig: Figure | Axes, path: str | os.PathLike[str], *, dpi: int = 150) -> Path:
    """Write a figure to a file; the format follows the extension (PNG by default).

    A figure made by pyplot is closed afterwards, so that scripts and the
    command line do not accumulate open figures.

    Parameters
    ----------
    fig : matplotlib.figure.Figure or matplotlib.axes.Axes
        The figure, or an axes of it.
    path : str or os.PathLike
        Output file; ``.png``, ``.pdf``, ``.svg`` and the other matplotlib formats.
    dpi : int, default=150
        Resolution of raster formats.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    OSError
        If the file cannot be written.
    ValueError
        If matplotlib does not know the format.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from kautztwin.plotting import plot_approximation, save_figure
    >>> t = np.linspace(0, 5, 50)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     ax = plot_approximation(t, np.exp(-t), np.exp(-t))
    ...     out = save_figure(ax, pathlib.Path(tmp) / "a.png")
    ...     out.read_bytes()[:4]
    b'\\x89PNG'
    """
    figure = fig
    while not hasattr(figure, "savefig"):  # Axes or SubFigure: up to the root figure
        figure = figure.figure
    path = Path(path)
    figure.savefig(path, dpi=dpi)
    plt = sys.modules.get("matplotlib.pyplot")
    if plt is not None:
        plt.close(figure)  # a no-op for figures that pyplot does not manage
    return path
