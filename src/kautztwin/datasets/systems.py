"""Parametric uncertain systems: a nominal model with named parameters, and draws around it.

A :class:`ParametricSystem` maps a parameter vector to a stable SISO transfer
function (from physical parameters, zeros/poles/gain or polynomial
coefficients); :func:`paper_system` is the paper's sample system.
:func:`draw_parameters` (uniform, Monte Carlo) and :func:`factorial_parameters`
(full-factorial grid) perturb the parameters around their nominal values,
keeping only stable systems.

Size: the module runs to about 700 lines (:class:`ParametricSystem` to 420) because
the system's three constructors carry full documentation and the draws belong with
the stability check they rely on.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._validation import check_finite, check_int, check_nonnegative
from ..exceptions import DataError, DimensionError, KautzTwinError

__all__ = [
    "ParametricSystem",
    "TransferFunction",
    "draw_parameters",
    "factorial_parameters",
    "paper_system",
]

_IMAG_TOL = 1e-12  # |Im p| <= this * |p| counts as a real root (zpk parsing)
_PAIR_TOL = 1e-8  # relative tolerance when matching a complex root with its conjugate
_MAX_GRID = 10_000_000  # largest factorial grid built

TransferFunction = tuple[NDArray[np.float64], NDArray[np.float64]]


def _readonly(x: ArrayLike, dtype: type) -> NDArray:
    out = np.array(x, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _fmt_vector(names: Sequence[str], values: NDArray) -> str:
    return ", ".join(f"{n}={v:.6g}" for n, v in zip(names, values, strict=True))


def _fmt_complex(p: complex) -> str:
    return f"{p.real:.6g}" if p.imag == 0 else f"{p.real:.6g}{p.imag:+.6g}j"


def _sort_poles(p: NDArray) -> NDArray[np.complex128]:
    """Sort poles by decreasing real part; each pair as ``(p, conj p)`` with ``Im p > 0``."""
    p = np.asarray(p, dtype=complex)
    order = np.lexsort((-p.imag, -np.abs(p.imag), -p.real))
    return p[order]


# =========================================================================== systems
@dataclass(frozen=True, eq=False)
class ParametricSystem:
    r"""A stable SISO transfer function that depends on named parameters.

    The system is described by a *builder*: a function from a parameter vector
    (in the order of ``parameter_names``) to the polynomial coefficients
    ``(num, den)`` of :math:`G(s)`, highest power first (``scipy.signal``
    order).  Every built system is normalised to a monic denominator, must be
    strictly proper or biproper, keep the nominal order, and is checked for
    stability (all poles with :math:`\mathrm{Re}\,p < 0`) by
    :meth:`transfer_function`.  Use the factories :meth:`from_physical`,
    :meth:`from_zpk` and :meth:`from_transfer_function`, or :func:`paper_system`.

    Parameters
    ----------
    name : str
        Short label of the system.
    parameter_names : sequence of str
        Unique parameter names.
    nominal : array-like of shape (n_parameters,)
        Nominal parameter values; the nominal system must be stable.
    builder : callable
        ``builder(p) -> (num, den)`` for a 1-D float parameter vector ``p``.
        Called once per parameter vector (batches are looped).

    Attributes
    ----------
    n_parameters : int
        Number of parameters.
    order : int
        Denominator degree (number of poles) of every built system.

    Raises
    ------
    DataError
        If the names are not unique, the nominal values are not finite or do
        not match the names, or the nominal system is not stable.

    See Also
    --------
    paper_system : The paper's sample system with physical parameters.
    draw_parameters : Uniform random parameter vectors around the nominal.
    make_dataset : Labelled responses of many parameter vectors.

    Examples
    --------
    >>> from kautztwin.datasets import ParametricSystem
    >>> sys = ParametricSystem.from_zpk([], [-1.0, -2.0], 2.0)
    >>> sys.parameter_names
    ('gain', 'pole0_rate', 'pole1_rate')
    >>> sys.transfer_function()
    (array([2.]), array([1., 3., 2.]))
    """

    name: str
    parameter_names: tuple[str, ...]
    nominal: NDArray[np.float64]
    builder: Callable[[NDArray[np.float64]], tuple[ArrayLike, ArrayLike]] = field(repr=False)
    _order: int = field(init=False, repr=False, default=0)

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.parameter_names)
        if any(not n for n in names):
            raise DataError("parameter names must be non-empty strings")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise DataError(
                f"parameter names must be unique; repeated: {', '.join(map(repr, dup))}"
            )
        nominal = np.atleast_1d(np.asarray(self.nominal, dtype=float))
        if nominal.ndim != 1 or nominal.size != len(names):
            raise DataError(
                f"nominal has shape {nominal.shape} but there are {len(names)} parameter names"
            )
        check_finite(nominal, "nominal")
        if not callable(self.builder):
            raise DataError(f"builder must be callable, got {type(self.builder).__name__}")
        object.__setattr__(self, "name", str(self.name))
        object.__setattr__(self, "parameter_names", names)
        object.__setattr__(self, "nominal", _readonly(nominal, float))
        num, den = self._build(nominal, order=None)
        poles = np.roots(den)
        if np.any(poles.real >= 0):
            worst = poles[np.argmax(poles.real)]
            raise DataError(
                f"the nominal system {self.name!r} is not stable: pole {_fmt_complex(worst)} "
                "has Re >= 0"
            )
        object.__setattr__(self, "_order", den.size - 1)

    # ------------------------------------------------------------------ factories
    @classmethod
    def from_physical(
        cls,
        nominal: Mapping[str, float],
        transfer_function: Callable[..., tuple[ArrayLike, ArrayLike]],
        *,
        name: str = "physical",
    ) -> ParametricSystem:
        """System from physical parameters and a function building its transfer function.

        Parameters
        ----------
        nominal : mapping of str to float
            Parameter names and nominal values, in order.
        transfer_function : callable
            Called with the parameters as keyword arguments,
            ``transfer_function(**params) -> (num, den)``.
        name : str, default='physical'
            Label of the system.

        Returns
        -------
        ParametricSystem

        Examples
        --------
        >>> from kautztwin.datasets import ParametricSystem
        >>> sys = ParametricSystem.from_physical(
        ...     {"k": 2.0, "tau": 0.5}, lambda k, tau: ([k], [tau, 1.0]), name="first order")
        >>> sys.transfer_function()
        (array([4.]), array([1., 2.]))
        """
        names = tuple(nominal)
        values = [float(nominal[n]) for n in names]

        def builder(p: NDArray[np.float64]) -> tuple[ArrayLike, ArrayLike]:
            return transfer_function(**{n: float(v) for n, v in zip(names, p, strict=True)})

        return cls(name, names, np.asarray(values), builder)

    @classmethod
    def from_zpk(
        cls, zeros: ArrayLike, poles: ArrayLike, gain: float, *, name: str = "zpk"
    ) -> ParametricSystem:
        r"""System :math:`k \prod (s - z_i) / \prod (s - p_i)` parametrised by rates and damping.

        The parameters are ``'gain'``, then for every zero factor and then every
        pole factor (numbered separately, in order of first appearance): a real
        root ``r`` gives the rate ``-r`` of the factor :math:`(s + \text{rate})`
        (``'pole0_rate'``), a complex pair gives the natural frequency
        :math:`\omega_n = |p|` and damping :math:`\zeta = -\mathrm{Re}\,p/|p|` of
        :math:`s^2 + 2\zeta\omega_n s + \omega_n^2` (``'pole1_wn'``,
        ``'pole1_zeta'``).  A relative perturbation of a rate, a frequency or a
        damping therefore moves the poles the physical way.

        Parameters
        ----------
        zeros : array-like of complex
            Zeros; each complex zero listed together with its conjugate.
        poles : array-like of complex
            Poles, ``Re < 0``; each complex pole listed with its conjugate.
        gain : float
            The factor ``k`` (``scipy.signal.zpk2tf`` convention).
        name : str, default='zpk'
            Label of the system.

        Returns
        -------
        ParametricSystem

        Raises
        ------
        DataError
            If a complex root has no conjugate partner, there are more zeros
            than poles, or a pole has ``Re >= 0``.
        """
        zf = _factors(zeros, "zeros")
        pf = _factors(poles, "poles")
        names: list[str] = ["gain"]
        values: list[float] = [float(gain)]
        for prefix, factors in (("zero", zf), ("pole", pf)):
            for i, f in enumerate(factors):
                if f[0] == "real":
                    names.append(f"{prefix}{i}_rate")
                    values.append(f[1])
                else:
                    names += [f"{prefix}{i}_wn", f"{prefix}{i}_zeta"]
                    values += [f[1], f[2]]
        kinds_z = [f[0] for f in zf]
        kinds_p = [f[0] for f in pf]

        def builder(p: NDArray[np.float64]) -> tuple[ArrayLike, ArrayLike]:
            pos = 1
            polys = []
            for kinds in (kinds_z, kinds_p):
                poly = np.array([1.0])
                for kind in kinds:
                    if kind == "real":
                        poly = np.polymul(poly, [1.0, p[pos]])
                        pos += 1
                    else:
                        wn, zeta = p[pos], p[pos + 1]
                        poly = np.polymul(poly, [1.0, 2.0 * zeta * wn, wn * wn])
                        pos += 2
                polys.append(poly)
            return p[0] * polys[0], polys[1]

        return cls(name, tuple(names), np.asarray(values), builder)

    @classmethod
    def from_transfer_function(
        cls, num: ArrayLike, den: ArrayLike, *, name: str = "tf"
    ) -> ParametricSystem:
        """System parametrised by its polynomial coefficients.

        The denominator is normalised to ``den[0] = 1`` (not a parameter); the
        parameters are ``'num0', 'num1', ...`` and ``'den1', 'den2', ...``,
        numbered by position in the highest-power-first arrays.

        Parameters
        ----------
        num, den : array-like of float
            Coefficients, highest power first; ``len(num) <= len(den)``.
        name : str, default='tf'
            Label of the system.

        Returns
        -------
        ParametricSystem

        Raises
        ------
        DataError
            If the system is improper, ``den[0] = 0`` or the system is unstable.

        Examples
        --------
        >>> from kautztwin.datasets import ParametricSystem
        >>> ParametricSystem.from_transfer_function([4.0], [2.0, 6.0, 4.0]).parameter_names
        ('num0', 'den1', 'den2')
        """
        num = np.trim_zeros(np.atleast_1d(np.asarray(num, dtype=float)), "f")
        den = np.atleast_1d(np.asarray(den, dtype=float))
        if num.size == 0:
            num = np.zeros(1)
        if den.ndim != 1 or num.ndim != 1 or den.size < 2:
            raise DataError("num and den must be 1-D coefficient lists and den of degree >= 1")
        check_finite(num, "num")
        check_finite(den, "den")
        if den[0] == 0:
            raise DataError("den[0] must be nonzero (the leading denominator coefficient)")
        if num.size > den.size:
            raise DataError(
                f"the system is improper: deg num = {num.size - 1} > deg den = {den.size - 1}"
            )
        num, den = num / den[0], den / den[0]
        n_num = num.size
        names = tuple(f"num{i}" for i in range(n_num))
        names += tuple(f"den{i}" for i in range(1, den.size))

        def builder(p: NDArray[np.float64]) -> tuple[ArrayLike, ArrayLike]:
            return p[:n_num], np.concatenate([[1.0], p[n_num:]])

        return cls(name, names, np.concatenate([num, den[1:]]), builder)

    # ------------------------------------------------------------------ properties
    @property
    def n_parameters(self) -> int:
        """Number of parameters."""
        return len(self.parameter_names)

    @property
    def order(self) -> int:
        """Number of poles of every built system."""
        return int(self._order)

    # ------------------------------------------------------------------ building
    def _vector(self, parameters: ArrayLike | None) -> NDArray[np.float64]:
        if parameters is None:
            return np.array(self.nominal)
        p = np.atleast_1d(np.asarray(parameters, dtype=float))
        if p.shape != (self.n_parameters,):
            raise DimensionError(
                f"a parameter vector of {self.name!r} has {self.n_parameters} entries "
                f"({', '.join(self.parameter_names)}); got shape {p.shape}"
            )
        check_finite(p, "parameters")
        return p

    def _matrix(self, parameters: ArrayLike) -> NDArray[np.float64]:
        P = np.asarray(parameters, dtype=float)
        if P.ndim == 1 and P.size == self.n_parameters:
            P = P[None, :]
        if P.ndim != 2 or P.shape[1] != self.n_parameters:
            raise DimensionError(
                f"parameters must have shape (n, {self.n_parameters}) for {self.name!r} "
                f"({', '.join(self.parameter_names)}); got shape {P.shape}"
            )
        check_finite(P, "parameters")
        return P

    def _build(self, p: NDArray, order: int | None) -> TransferFunction:
        """Call the builder and normalise; no stability check."""
        num, den = self.builder(np.array(p, dtype=float))
        num = np.trim_zeros(np.atleast_1d(np.asarray(num, dtype=float)), "f")
        den = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), "f")
        if num.size == 0:
            num = np.zeros(1)
        if num.ndim != 1 or den.ndim != 1 or den.size < 2:
            raise DataError(
                f"{self.name!r} built a denominator of degree < 1 or non-1-D coefficients at "
                f"({_fmt_vector(self.parameter_names, p)})"
            )
        at = _fmt_vector(self.parameter_names, p)
        if not (np.all(np.isfinite(num)) and np.all(np.isfinite(den))):
            raise DataError(f"{self.name!r} built non-finite coefficients at ({at})")
        if order is not None and den.size - 1 != order:
            raise DataError(
                f"{self.name!r} has order {den.size - 1} at ({at}) "
                f"but order {order} at the nominal parameters"
            )
        if num.size > den.size:
            raise DataError(
                f"{self.name!r} is improper at ({_fmt_vector(self.parameter_names, p)}): "
                f"deg num = {num.size - 1} > deg den = {den.size - 1}"
            )
        return num / den[0], den / den[0]

    def transfer_function(self, parameters: ArrayLike | None = None) -> TransferFunction:
        """Transfer function at one parameter vector (the nominal one by default).

        Parameters
        ----------
        parameters : array-like of shape (n_parameters,), optional
            Parameter values in the order of ``parameter_names``.

        Returns
        -------
        num, den : ndarray of float
            Coefficients, highest power first, ``den[0] = 1``.

        Raises
        ------
        DataError
            If the system is not stable (a pole with ``Re >= 0``) at these
            parameters, or cannot be built there.
        DimensionError
            If ``parameters`` has the wrong length.
        """
        p = self._vector(parameters)
        num, den = self._build(p, self.order)
        poles = np.roots(den)
        if np.any(poles.real >= 0):
            worst = poles[np.argmax(poles.real)]
            raise DataError(
                f"{self.name!r} is not stable at ({_fmt_vector(self.parameter_names, p)}): "
                f"pole {_fmt_complex(worst)} has Re >= 0"
            )
        return num, den

    def transfer_functions(self, parameters: ArrayLike) -> list[TransferFunction]:
        """Transfer functions of many parameter vectors (looped over the rows).

        Parameters
        ----------
        parameters : array-like of shape (n, n_parameters)

        Returns
        -------
        list of (num, den)

        Raises
        ------
        DataError
            If any row gives an unstable system.
        """
        return [self.transfer_function(p) for p in self._matrix(parameters)]

    def poles(self, parameters: ArrayLike | None = None) -> NDArray[np.complex128]:
        """Poles at one or many parameter vectors, sorted consistently.

        Sorted by decreasing real part (dominant pole first); each complex pair
        as ``(p, conj(p))`` with ``Im p > 0`` first.

        Parameters
        ----------
        parameters : array-like of shape (n_parameters,) or (n, n_parameters), optional
            Default: the nominal vector.

        Returns
        -------
        ndarray of complex, shape (order,) or (n, order)

        Examples
        --------
        >>> from kautztwin.datasets import paper_system
        >>> paper_system().poles().round(4)
        array([-0.5+1.9365j, -0.5-1.9365j, -1. +0.j    , -3. +0.j    ])
        """
        if parameters is None or np.ndim(parameters) == 1:
            return _sort_poles(np.roots(self.transfer_function(parameters)[1]))
        rows = self._matrix(parameters)
        return np.array(
            [_sort_poles(np.roots(self.transfer_function(p)[1])) for p in rows], dtype=complex
        ).reshape(rows.shape[0], self.order)

    def is_stable(self, parameters: ArrayLike) -> NDArray[np.bool_]:
        """Whether each parameter vector gives a stable system of the nominal order.

        Parameters
        ----------
        parameters : array-like of shape (n, n_parameters)

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        rows = self._matrix(parameters)
        out = np.zeros(rows.shape[0], dtype=bool)
        for i, p in enumerate(rows):
            try:
                _, den = self._build(p, self.order)
            except KautzTwinError:
                continue
            out[i] = bool(np.all(np.roots(den).real < 0))
        return out

    def __repr__(self) -> str:
        return (
            f"ParametricSystem({self.name!r}, order={self.order}, "
            f"{_fmt_vector(self.parameter_names, self.nominal)})"
        )


def _factors(roots: ArrayLike, what: str) -> list[tuple]:
    """Real roots and conjugate pairs as ``('real', rate)`` / ``('pair', wn, zeta)``."""
    try:
        r = np.atleast_1d(np.asarray(roots, dtype=complex))
    except (TypeError, ValueError) as exc:
        raise DataError(f"{what} must be numbers, got {roots!r}") from exc
    if r.ndim != 1:
        raise DataError(f"{what} must be a 1-D list, got shape {r.shape}")
    for i, x in enumerate(r):
        if not np.isfinite(x):
            raise DataError(f"{what}[{i}] = {x} is not finite")
    used = np.zeros(r.size, dtype=bool)
    out: list[tuple] = []
    for i, x in enumerate(r):
        if used[i]:
            continue
        used[i] = True
        if abs(x.imag) <= _IMAG_TOL * abs(x):
            out.append(("real", float(-x.real)))
            continue
        tol = _PAIR_TOL * max(abs(x), 1e-300)
        mates = [j for j in range(r.size) if not used[j] and abs(r[j] - np.conj(x)) <= tol]
        if not mates:
            raise DataError(
                f"{what}[{i}] = {_fmt_complex(x)} has no conjugate partner; list both members "
                "of every complex pair"
            )
        used[mates[0]] = True
        wn = float(abs(x))
        out.append(("pair", wn, float(-x.real / wn)))
    return out


def _paper_transfer_function(
    k: float, a: float, b: float, wn: float, zeta: float
) -> tuple[ArrayLike, ArrayLike]:
    den = np.polymul(np.polymul([1.0, a], [1.0, b]), [1.0, 2.0 * zeta * wn, wn * wn])
    return np.array([k]), den


def paper_system() -> ParametricSystem:
    r"""The paper's sample system with physical parameters.

    .. math:: G(s) = \frac{k}{(s + a)(s + b)(s^2 + 2\zeta\omega_n s + \omega_n^2)}

    with nominal ``k = 6, a = 1, b = 3, wn = 2, zeta = 0.25``, i.e.
    ``6 / ((s+1)(s+3)(s^2+s+4))``, poles ``-1, -3, -1/2 +- j sqrt(15)/2``.

    Returns
    -------
    ParametricSystem
        Parameters ``('k', 'a', 'b', 'wn', 'zeta')``.

    See Also
    --------
    kautztwin.data.reference_system : The nominal system as a scipy transfer function.

    Examples
    --------
    >>> from kautztwin.datasets import paper_system
    >>> num, den = paper_system().transfer_function()
    >>> num, den
    (array([6.]), array([ 1.,  5., 11., 19., 12.]))
    """
    return ParametricSystem.from_physical(
        {"k": 6.0, "a": 1.0, "b": 3.0, "wn": 2.0, "zeta": 0.25},
        _paper_transfer_function,
        name="paper",
    )


# =========================================================================== parameter draws
def _uncertainty_vector(
    system: ParametricSystem, uncertainty: float | Mapping[str, float]
) -> NDArray[np.float64]:
    if isinstance(uncertainty, Mapping):
        unknown = [k for k in uncertainty if k not in system.parameter_names]
        if unknown:
            raise DataError(
                f"unknown parameter name(s) {', '.join(map(repr, unknown))} for {system.name!r}; "
                f"valid names: {', '.join(map(repr, system.parameter_names))}"
            )
        return np.array(
            [
                check_nonnegative(uncertainty.get(n, 0.0), f"uncertainty[{n!r}]")
                for n in system.parameter_names
            ]
        )
    u = check_nonnegative(uncertainty, "uncertainty")
    return np.full(system.n_parameters, u)


def draw_parameters(
    system: ParametricSystem,
    uncertainty: float | Mapping[str, float],
    n: int,
    random_state: int | np.random.Generator | None = None,
    *,
    max_tries: int = 100,
) -> NDArray[np.float64]:
    r"""Random parameter vectors, each parameter uniform within a relative band.

    Parameter ``j`` is drawn independently and uniformly from
    :math:`\theta_j^0 (1 + u_j [-1, 1])`.  A vector that gives an unstable
    system (possible when :math:`u_j \ge 1` or for polynomial-coefficient
    parameters) is **redrawn**, up to ``max_tries`` draws per vector, so the
    result is uniform on the stable part of the box.

    Parameters
    ----------
    system : ParametricSystem
        The nominal model.
    uncertainty : float or mapping of str to float
        Relative half-width :math:`u \ge 0` (0.1 = +-10 %) for every
        parameter, or per parameter name (names left out are held at nominal).
    n : int
        Number of vectors, ``>= 1``.
    random_state : int, numpy.random.Generator or None, default=None
        Seed or generator.
    max_tries : int, default=100
        Most draws per vector before giving up.

    Returns
    -------
    ndarray of shape (n, n_parameters)

    Raises
    ------
    DataError
        On an unknown parameter name (the message lists the valid ones), a
        negative or non-finite uncertainty, or when some vector is still
        unstable after ``max_tries`` draws.

    See Also
    --------
    factorial_parameters : The deterministic full-factorial grid.

    Examples
    --------
    >>> from kautztwin.datasets import draw_parameters, paper_system
    >>> P = draw_parameters(paper_system(), {"k": 0.1, "zeta": 0.2}, 5, random_state=0)
    >>> P.shape
    (5, 5)
    >>> bool(((P[:, 0] >= 5.4) & (P[:, 0] <= 6.6)).all())
    True
    """
    u = _uncertainty_vector(system, uncertainty)
    n = check_int(n, "n", 1)
    max_tries = check_int(max_tries, "max_tries", 1)
    rng = np.random.default_rng(random_state)
    nominal = np.asarray(system.nominal)

    def draw(m: int) -> NDArray[np.float64]:
        return nominal * (1.0 + u * rng.uniform(-1.0, 1.0, size=(m, nominal.size)))

    P = draw(int(n))
    bad = np.flatnonzero(~system.is_stable(P))
    tries = 1
    while bad.size and tries < max_tries:
        P[bad] = draw(bad.size)
        bad = bad[~system.is_stable(P[bad])]
        tries += 1
    if bad.size:
        wide = [repr(nm) for nm, uj in zip(system.parameter_names, u, strict=True) if uj >= 1]
        hint = f" (u >= 1 lets {', '.join(wide)} change sign)" if wide else ""
        raise DataError(
            f"{bad.size} of {n} parameter vectors of {system.name!r} were still unstable after "
            f"{max_tries} draws each; reduce the uncertainty{hint} or raise max_tries"
        )
    return P


def factorial_parameters(
    system: ParametricSystem, uncertainty: float | Mapping[str, float], levels: int = 3
) -> NDArray[np.float64]:
    r"""Full-factorial grid of parameter vectors around the nominal.

    Parameter ``j`` takes ``levels`` values evenly spaced in
    :math:`\theta_j^0 [1 - u_j, 1 + u_j]` (``levels=3`` gives
    :math:`-u, 0, +u`); a parameter whose band is a single point (``u_j = 0``
    or nominal 0) takes only its nominal value.  The rows enumerate every
    combination, the first parameter varying slowest.

    Parameters
    ----------
    system : ParametricSystem
    uncertainty : float or mapping of str to float
        As in :func:`draw_parameters`.
    levels : int, default=3
        Levels per uncertain parameter, ``>= 2``.

    Returns
    -------
    ndarray of shape (levels ** n_uncertain, n_parameters)

    Raises
    ------
    DataError
        On an unknown parameter name, a negative uncertainty, ``levels < 2``,
        a grid of more than 10**7 points, or a grid point that gives an
        unstable system (no redraw: the grid is deterministic).

    Examples
    --------
    >>> from kautztwin.datasets import factorial_parameters, paper_system
    >>> factorial_parameters(paper_system(), {"a": 0.5}, levels=3)[:, 1]
    array([0.5, 1. , 1.5])
    """
    u = _uncertainty_vector(system, uncertainty)
    levels = check_int(levels, "levels", 2)
    nominal = np.asarray(system.nominal)
    varied = (u > 0) & (nominal != 0)
    size = int(levels) ** int(varied.sum())
    if size > _MAX_GRID:
        raise DataError(
            f"the factorial grid would have {levels}**{int(varied.sum())} = {size} points "
            f"(limit {_MAX_GRID}); use fewer levels or draw_parameters()"
        )
    offsets = np.linspace(-1.0, 1.0, int(levels))
    axes = [
        nominal[j] * (1.0 + u[j] * offsets) if varied[j] else nominal[j : j + 1]
        for j in range(nominal.size)
    ]
    P = np.array(list(itertools.product(*axes)), dtype=float).reshape(size, nominal.size)
    stable = system.is_stable(P)
    if not stable.all():
        i = int(np.argmin(stable))
        raise DataError(
            f"factorial grid point {i} of {system.name!r} "
            f"({_fmt_vector(system.parameter_names, P[i])}) gives an unstable system; "
            f"{int((~stable).sum())} of {size} points are unstable: reduce the uncertainty"
        )
    return P
