"""Orthonormal Kautz (Takenaka-Malmquist) and Laguerre bases.

See ``docs/method.md`` and kautz-math.md sections 1-3 for the formulas.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from .._validation import check_dt, check_finite, check_memory
from ..exceptions import DimensionError, PoleError
from ._blocks import (
    PAIR,
    block_poles,
    block_sizes,
    continuous_matrices,
    discrete_matrices,
    parse_poles,
    transfer_polynomials,
)
from ._propagate import continuous_functions, discrete_functions, sample_indices

__all__ = ["KautzBasis", "LaguerreBasis"]


#: float64 arrays of n x n that building a basis of n functions holds at once (the network
#: matrix as built and its read-only copy, plus a temporary)
_MATRICES_PER_BASIS = 3


def _check_basis_size(n: int) -> None:
    """Refuse, before allocating, a basis whose n x n network matrix does not fit in memory."""
    check_memory(
        8.0 * _MATRICES_PER_BASIS * float(n) ** 2,
        f"a basis of {n} functions (its {n} x {n} network matrix)",
    )


def _readonly(x: NDArray) -> NDArray:
    x = np.array(x, copy=True)
    x.setflags(write=False)
    return x


def _rebuild_basis(cls: type, kinds: tuple[str, ...], params: NDArray, dt: float,
                   delayed: bool) -> KautzBasis:
    """Unpickle a :class:`KautzBasis` (or subclass) from its block kinds and parameters."""
    obj = cls.__new__(cls)
    obj._init(tuple(kinds), np.asarray(params, dtype=float), float(dt), bool(delayed))
    return obj


class KautzBasis:
    r"""Orthonormal Kautz basis with any mix of real poles and complex pairs.

    The basis is the general Takenaka-Malmquist construction in real form: a
    real pole contributes one function, a complex-conjugate pair two, and every
    block is multiplied by the all-pass factors of the blocks before it.
    Laguerre (one repeated real pole) is the special case
    :class:`LaguerreBasis`.  The functions are realised exactly as the network
    :math:`\dot F = A F,\ F(0) = B` (continuous) or
    :math:`F(k+1) = A F(k),\ F(0) = B` (discrete), with ``A + A^T + B B^T = 0``
    (continuous) or ``A A^T + B B^T = I`` (discrete), so the Gram matrix is the
    identity by construction.

    The object is immutable: its arrays are read-only and a different pole set
    is a new basis (:meth:`with_poles`).

    Parameters
    ----------
    poles : array-like of complex
        Pole *locations*: ``Re(p) < 0`` in continuous time, ``|p| < 1`` in
        discrete time.  Each complex pole is listed together with its conjugate
        (anywhere in the list); a pair's block sits at the position of its first
        member.  The number of functions is ``len(poles)``.  Repeated poles are
        allowed.
    dt : float, default=0.0
        ``0`` for a continuous-time basis (functions of ``t``); a positive
        sampling period for a discrete-time basis, orthonormal in
        :math:`\ell_2` on the grid ``t = k dt``.
    delayed : bool, default=False
        Discrete bases only: ``False`` gives the sequences ``F(k) = A^k B`` that
        start at ``k = 0``; ``True`` the delayed ones (``F(0) = 0``), whose
        z-transform is ``(zI - A)^{-1} B``.

    Attributes
    ----------
    poles : ndarray of complex, shape (n_functions,)
        Pole locations in block order, each pair as ``(p, conj(p))`` with ``Im p > 0``.
    n_functions : int
        Number of basis functions, ``len(poles)``.
    dt : float
        Sampling period (``0`` for continuous time).

    Raises
    ------
    PoleError
        If a pole is not finite or a complex pole has no conjugate partner.
    UnstableModelError
        If a pole lies outside the stability region.

    See Also
    --------
    LaguerreBasis : One repeated real pole.
    kautztwin.project : Coefficients of a sampled response in this basis.

    Notes
    -----
    Continuous time (kautz-math.md 1.3), block all-pass factors
    :math:`\mathcal A_j(s) = (s - p_j)/(s + p_j)` or
    :math:`(s^2 - b_j s + c_j)/(s^2 + b_j s + c_j)` and
    :math:`G_j = \prod_{m<j}\mathcal A_m`:

    .. math::

        K(s) = \frac{\sqrt{2 p_j}}{s + p_j} G_j(s),\qquad
        K^{(1)}(s) = \frac{\sqrt{2 b_j}\, s}{s^2 + b_j s + c_j} G_j(s),\qquad
        K^{(2)}(s) = \frac{\sqrt{2 b_j c_j}}{s^2 + b_j s + c_j} G_j(s).

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> basis = kt.KautzBasis([-1, -3, -0.5 + 1.9365j, -0.5 - 1.9365j])
    >>> basis.n_functions
    4
    >>> K = basis.evaluate(np.linspace(0, 20, 900))
    >>> K.shape
    (4, 900)
    >>> bool(np.allclose(basis.gram(), np.eye(4), atol=1e-12))
    True
    """

    __slots__ = ("_A", "_B", "_delayed", "_dt", "_kinds", "_params", "_poles")

    def __init__(self, poles: ArrayLike, *, dt: float = 0.0, delayed: bool = False) -> None:
        dt = check_dt(dt)
        kinds, params = parse_poles(poles, dt)
        self._init(kinds, params, dt, bool(delayed))

    def _init(self, kinds: tuple[str, ...], params: NDArray, dt: float, delayed: bool) -> None:
        if delayed and dt == 0:
            raise PoleError("delayed=True applies to discrete-time bases (dt > 0) only")
        object.__setattr__(self, "_kinds", kinds)
        object.__setattr__(self, "_params", _readonly(params))
        object.__setattr__(self, "_dt", dt)
        object.__setattr__(self, "_delayed", delayed)
        _check_basis_size(sum(1 if kind != PAIR else 2 for kind in kinds))
        build = continuous_matrices if dt == 0 else discrete_matrices
        A, B = build(kinds, params[None, :])
        object.__setattr__(self, "_A", _readonly(A[0]))
        object.__setattr__(self, "_B", _readonly(B[0]))
        object.__setattr__(self, "_poles", _readonly(block_poles(kinds, params, dt)))

    @classmethod
    def _from_blocks(
        cls, kinds: tuple[str, ...], params: NDArray, dt: float = 0.0, delayed: bool = False
    ) -> KautzBasis:
        """Build a basis straight from block kinds and parameters (no parsing)."""
        obj = KautzBasis.__new__(KautzBasis)
        obj._init(tuple(kinds), np.asarray(params, dtype=float), float(dt), delayed)
        return obj

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(
            f"{type(self).__name__} is immutable; use with_poles() for a new basis"
        )

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickle by block kinds and parameters: the copy is built as the original was."""
        return (_rebuild_basis, (type(self), self._kinds, np.array(self._params), self._dt,
                                 self._delayed))

    # ------------------------------------------------------------------ properties
    @property
    def poles(self) -> NDArray[np.complex128]:
        """Pole locations in block order (read-only)."""
        return self._poles

    @property
    def dt(self) -> float:
        """Sampling period; ``0`` for continuous time."""
        return self._dt

    @property
    def is_discrete(self) -> bool:
        """Whether the basis is a discrete-time one (``dt > 0``)."""
        return self._dt > 0

    @property
    def delayed(self) -> bool:
        """Whether the discrete sequences are the delayed ones (``F(0) = 0``)."""
        return self._delayed

    @property
    def n_functions(self) -> int:
        """Number of basis functions."""
        return int(self._B.size)

    @property
    def block_kinds(self) -> tuple[str, ...]:
        """Kind of each block, ``'real'`` or ``'pair'``, in order."""
        return self._kinds

    @property
    def A(self) -> NDArray[np.float64]:  # noqa: N802 - the documented matrix name
        """State matrix of the network realisation (read-only)."""
        return self._A

    @property
    def B(self) -> NDArray[np.float64]:  # noqa: N802 - the documented matrix name
        """Initial state ``F(0)`` of the network realisation (read-only)."""
        return self._B

    # ------------------------------------------------------------------ methods
    def state_space(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Return the network realisation ``(A, B)``.

        Returns
        -------
        A : ndarray of shape (n_functions, n_functions)
            Continuous: ``dF/dt = A F``; discrete: ``F(k+1) = A F(k)``.
        B : ndarray of shape (n_functions,)
            ``F(0) = B``.

        Examples
        --------
        >>> import kautztwin as kt
        >>> A, B = kt.LaguerreBasis(pole=-1, n=3).state_space()
        >>> A
        array([[-1.,  0.,  0.],
               [-2., -1.,  0.],
               [-2., -2., -1.]])
        """
        return np.array(self._A), np.array(self._B)

    def evaluate(self, t: ArrayLike) -> NDArray[np.float64]:
        """Evaluate the basis functions on a time grid.

        Continuous bases use exact matrix-exponential stepping (any grid, uniform
        or not; functions are zero for ``t < 0``).  Discrete bases need ``t`` on
        the grid ``k * dt`` and return the sequences there.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Time instants in seconds.

        Returns
        -------
        ndarray of shape (n_functions, n_samples)
            Row ``i`` holds function ``i``.

        Raises
        ------
        DataError
            If ``t`` is not finite, or (discrete) not on the sampling grid.
        """
        t = self._check_t(t)
        if self._dt == 0:
            return continuous_functions(self._A[None], self._B[None], t)[0]
        k = sample_indices(t, self._dt)
        if self._delayed:
            out = np.zeros((self.n_functions, t.size))
            pos = k > 0
            if pos.any():
                out[:, pos] = discrete_functions(self._A[None], self._B[None], k[pos] - 1)[0]
            return out
        return discrete_functions(self._A[None], self._B[None], k)[0]

    def step_functions(self, t: ArrayLike) -> NDArray[np.float64]:
        r"""Evaluate the step responses of the basis functions.

        Continuous: :math:`S(t) = \int_0^t K = A^{-1}(e^{At} - I) B`; discrete:
        the running sum :math:`\sum_{j \le k} F(j)`, i.e.
        :math:`(A - I)^{-1}(A^{k+1} - I) B` (undelayed).

        Parameters
        ----------
        t : array-like of shape (n_samples,)
            Time instants in seconds.

        Returns
        -------
        ndarray of shape (n_functions, n_samples)
        """
        t = self._check_t(t)
        K = self.evaluate(t)
        if self._dt == 0:
            S = np.linalg.solve(self._A, K - self._B[:, None])
            S[:, t < 0] = 0.0
            return S
        # undelayed: sum_{j<=k} A^j B = (A - I)^{-1} (A F(k) - B)
        # delayed:   sum_{1<=j<=k} A^{j-1} B, the same formula with F(k) = A^{k-1} B (k >= 1)
        S = np.linalg.solve(self._A - np.eye(self.n_functions), self._A @ K - self._B[:, None])
        if self._delayed:
            S[:, sample_indices(t, self._dt) == 0] = 0.0
        return S

    def gram(self) -> NDArray[np.float64]:
        r"""Analytic Gram matrix from the Lyapunov (or Stein) equation.

        Solves :math:`AP + PA^T + BB^T = 0` (continuous) or
        :math:`APA^T - P + BB^T = 0` (discrete); ``P`` is the matrix of inner
        products :math:`\langle K_i, K_k \rangle` and equals the identity to
        rounding.

        Returns
        -------
        ndarray of shape (n_functions, n_functions)
        """
        BBt = np.outer(self._B, self._B)
        if self._dt == 0:
            return scipy.linalg.solve_continuous_lyapunov(self._A, -BBt)
        return scipy.linalg.solve_discrete_lyapunov(self._A, BBt)

    def transfer_functions(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """Transfer function of every basis function, from the product formula.

        Continuous bases give :math:`K_i(s)`; discrete ones the z-transform of
        the sequence (undelayed: :math:`z\\,\\phi_i(z)`; delayed: :math:`\\phi_i(z)`).
        The formulas are evaluated independently of ``(A, B)``.

        Returns
        -------
        list of (num, den)
            Polynomial coefficients, highest power first (``scipy.signal`` order).

        Examples
        --------
        >>> import kautztwin as kt
        >>> num, den = kt.LaguerreBasis(pole=-2, n=2).transfer_functions()[1]
        >>> num, den
        (array([ 2., -4.]), array([1., 4., 4.]))
        """
        nums, dens, _ = transfer_polynomials(self._kinds, self._params, self._dt)
        if self._delayed:
            nums = [n[:-1] for n in nums]  # every undelayed numerator ends in a factor z
        return [
            (np.asarray(n, float), np.asarray(d, float)) for n, d in zip(nums, dens, strict=True)
        ]

    def denominator(self) -> NDArray[np.float64]:
        """Common denominator :math:`d_\\pi` of all basis functions (highest power first)."""
        den = np.array([1.0])
        for p in self._poles:
            den = np.polymul(den, [1.0, -p])
        return np.real_if_close(den).astype(float)

    def discretize(self, dt: float) -> KautzBasis:
        """Matched discrete basis with poles ``exp(p * dt)`` (kautz-math.md 3.3).

        Samples of any system whose poles are among this basis' poles lie
        exactly in the span of the returned (undelayed) discrete basis.

        Parameters
        ----------
        dt : float
            Sampling period, ``> 0``.

        Returns
        -------
        KautzBasis
        """
        if self._dt != 0:
            raise PoleError("discretize() applies to continuous-time bases only")
        dt = check_dt(dt)
        if dt == 0:
            raise PoleError("dt must be positive to discretize a basis")
        return KautzBasis(np.exp(self._poles * dt), dt=dt)

    def with_poles(self, poles: ArrayLike) -> KautzBasis:
        """Return a new basis of the same time domain with other poles."""
        return KautzBasis(poles, dt=self._dt, delayed=self._delayed)

    def allclose(self, other: KautzBasis, rtol: float = 1e-10, atol: float = 0.0) -> bool:
        """Whether ``other`` has the same time domain, block structure and nearly the same poles."""
        return (
            isinstance(other, KautzBasis)
            and self._dt == other._dt
            and self._delayed == other._delayed
            and self._kinds == other._kinds
            and bool(np.allclose(self._params, other._params, rtol=rtol, atol=atol))
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: poles as ``[re, im]`` pairs, ``dt``, ``delayed``."""
        return {
            "poles": [[float(p.real), float(p.imag)] for p in self._poles],
            "dt": self._dt,
            "delayed": self._delayed,
        }

    def _check_t(self, t: ArrayLike) -> NDArray[np.float64]:
        t = np.asarray(t, dtype=float)
        if t.ndim != 1:
            raise DimensionError(f"t must be 1-D, got an array of shape {t.shape}")
        check_finite(t, "t")
        return t

    def __repr__(self) -> str:
        poles = ", ".join(
            f"{p.real:.6g}" if p.imag == 0 else f"{p.real:.6g}{p.imag:+.6g}j" for p in self._poles
        )
        extra = (
            ""
            if self._dt == 0
            else f", dt={self._dt:g}" + (", delayed=True" if self._delayed else "")
        )
        return f"{type(self).__name__}([{poles}]{extra})"

    def _block_slices(self) -> list[slice]:
        """Row slices of the functions of each block."""
        starts = np.concatenate([[0], np.cumsum(block_sizes(self._kinds))])
        return [slice(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:], strict=True)]

    @property
    def n_pairs(self) -> int:
        """Number of complex-conjugate pairs."""
        return sum(k == PAIR for k in self._kinds)


class LaguerreBasis(KautzBasis):
    r"""Orthonormal Laguerre basis: ``n`` functions of one repeated real pole.

    Continuous time: :math:`L_i(s) = \frac{\sqrt{2a}}{s+a}\big(\frac{s-a}{s+a}\big)^{i-1}`
    with ``pole = -a``; discrete time: Wang's form with ``|pole| < 1``
    (``pole = 0`` gives pure delays).

    Parameters
    ----------
    pole : float
        Pole location, ``< 0`` (continuous) or in ``(-1, 1)`` (discrete).
    n : int
        Number of functions, ``>= 1``.
    dt : float, default=0.0
        ``0`` for continuous time, else the sampling period.
    delayed : bool, default=False
        Discrete bases only; see :class:`KautzBasis`.

    Attributes
    ----------
    pole : float
        The repeated pole location.

    See Also
    --------
    KautzBasis : The general construction this specialises.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> basis = kt.LaguerreBasis(pole=-1.0, n=4)
    >>> np.round(basis.evaluate([1.0])[:, 0], 6)
    array([ 0.52026, -0.52026, -0.52026, -0.17342])
    """

    __slots__ = ()

    def __init__(self, pole: float, n: int, *, dt: float = 0.0, delayed: bool = False) -> None:
        if isinstance(pole, complex) and pole.imag != 0:
            raise PoleError(f"a Laguerre pole must be real, got {pole}")
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PoleError(f"n must be a positive integer, got {n!r}")
        _check_basis_size(int(n))
        super().__init__([float(np.real(pole))] * int(n), dt=dt, delayed=delayed)

    @property
    def pole(self) -> float:
        """The repeated pole location."""
        return float(self._poles[0].real)

    def __repr__(self) -> str:
        extra = "" if self._dt == 0 else f", dt={self._dt:g}"
        return f"LaguerreBasis(pole={self.pole:g}, n={self.n_functions}{extra})"
