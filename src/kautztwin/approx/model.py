"""The Kautz approximant ``G_N(s) = sum_i c_i K_i(s)`` as an immutable LTI model."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..basis import KautzBasis
from ..basis._blocks import transfer_polynomials
from ..exceptions import DataError, DimensionError

__all__ = ["KautzModel"]


@dataclass(frozen=True, eq=False)
class KautzModel:
    r"""Immutable LTI model :math:`G_N = \sum_i c_i K_i` on an orthonormal basis.

    Its impulse response is :math:`h_N(t) = c^T K(t)` and its state-space
    realisation is ``(A, B, c^T, 0)`` with the basis' network matrices
    (continuous time).  Evaluation is cheap (a matrix product), which is what
    the digital twin needs to swap models live.

    Parameters
    ----------
    basis : KautzBasis
        The orthonormal basis.
    coefficients : array-like of shape (n_functions,)
        Expansion coefficients in the basis' function order.

    Raises
    ------
    DimensionError
        If the number of coefficients differs from ``basis.n_functions``.
    DataError
        If a coefficient is NaN or inf.

    See Also
    --------
    kautztwin.approximate : Build a model from a sampled response.
    kautztwin.coefficients_from_system : Exact coefficients of a known LTI system.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> w = 15**0.5 / 2
    >>> basis = kt.KautzBasis([-1, -3, -0.5 + 1j * w, -0.5 - 1j * w])
    >>> c = [2**0.5 / 8, -3 * 6**0.5 / 32, 5 * 2**0.5 / 32, 2**0.5 / 16]
    >>> model = kt.KautzModel(basis, c)
    >>> num, den = model.transfer_function()
    >>> np.round(num, 10), np.round(den, 10)
    (array([6.]), array([ 1.,  5., 11., 19., 12.]))
    >>> round(model.dc_gain, 10)
    0.5
    """

    basis: KautzBasis
    coefficients: NDArray[np.float64] = field()

    def __post_init__(self) -> None:
        if not isinstance(self.basis, KautzBasis):
            raise DataError(f"basis must be a KautzBasis, got {type(self.basis).__name__}")
        c = np.array(self.coefficients, dtype=float, copy=True)
        if c.shape != (self.basis.n_functions,):
            raise DimensionError(
                f"coefficients has shape {c.shape} but the basis has "
                f"{self.basis.n_functions} functions"
            )
        if not np.all(np.isfinite(c)):
            raise DataError("coefficients contain NaN or inf")
        c.setflags(write=False)
        object.__setattr__(self, "coefficients", c)

    # ------------------------------------------------------------------ responses
    @property
    def n_functions(self) -> int:
        """Number of basis functions (the model order)."""
        return self.basis.n_functions

    @property
    def dt(self) -> float:
        """Sampling period of the basis (0: continuous)."""
        return self.basis.dt

    @property
    def poles(self) -> NDArray[np.complex128]:
        """Model poles: the basis poles."""
        return self.basis.poles

    def impulse(self, t: ArrayLike) -> NDArray[np.float64]:
        """Impulse response :math:`h_N(t) = c^T K(t)` on any time grid.

        Parameters
        ----------
        t : array-like of shape (n_samples,)

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return self.coefficients @ self.basis.evaluate(t)

    def step(self, t: ArrayLike) -> NDArray[np.float64]:
        r"""Unit-step response :math:`y_N(t) = c^T A^{-1}(e^{At} - I)B` on any time grid.

        Parameters
        ----------
        t : array-like of shape (n_samples,)

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        return self.coefficients @ self.basis.step_functions(t)

    @property
    def dc_gain(self) -> float:
        """Static gain :math:`G_N(0)` (continuous) or :math:`G_N(1)` (discrete)."""
        A, B = self.basis.A, self.basis.B
        if self.dt == 0:
            return float(-self.coefficients @ np.linalg.solve(A, B))
        eye = np.eye(self.n_functions)
        # sum_k F(k) = (I - A)^{-1} B; delayed sequences sum to the same
        return float(self.coefficients @ np.linalg.solve(eye - A, B))

    def frequency_response(self, w: ArrayLike) -> NDArray[np.complex128]:
        """Complex frequency response at angular frequencies ``w`` (rad/s).

        Parameters
        ----------
        w : array-like of shape (n_freqs,)

        Returns
        -------
        ndarray of complex, shape (n_freqs,)
        """
        w = np.atleast_1d(np.asarray(w, dtype=float))
        A, B, C, D = self.state_space()
        s = 1j * w if self.dt == 0 else np.exp(1j * w * self.dt)
        eye = np.eye(A.shape[0])
        X = np.linalg.solve(
            s[:, None, None] * eye[None] - A[None], np.broadcast_to(B, (w.size,) + B.shape)
        )
        return (C @ X)[:, 0, 0] + D[0, 0]

    # ------------------------------------------------------------------ conversions
    def state_space(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Realisation ``(A, B, C, D)`` as 2-D arrays (``B`` a column, ``C`` a row).

        Continuous and delayed discrete bases give ``(A, B, c^T, 0)``; undelayed
        discrete bases ``(A, B, c^T A, c^T B)``, whose pulse response starts at ``k = 0``.

        Returns
        -------
        A, B, C, D : ndarray
        """
        A = np.array(self.basis.A)
        B = np.array(self.basis.B)[:, None]
        c = self.coefficients[None, :]
        if self.dt > 0 and not self.basis.delayed:
            return A, B, c @ A, c @ B
        return A, B, c.copy(), np.zeros((1, 1))

    def transfer_function(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Polynomial transfer function ``num / den`` (highest power first).

        The denominator is the product of the basis' pole factors, exact; the
        numerator is built from the basis' product formulas.  Use it for
        reporting; compute with :meth:`state_space` (better conditioned).

        Returns
        -------
        num, den : ndarray
        """
        nums, dens, tails = transfer_polynomials(
            self.basis.block_kinds, self.basis._params, self.dt
        )
        num = np.zeros(1)
        for ci, n_i, tail in zip(self.coefficients, nums, tails, strict=True):
            num = np.polyadd(num, ci * np.polymul(n_i, tail))
        den = np.polymul(dens[-1], tails[-1])
        if self.basis.delayed:
            num = num[:-1] if num.size > 1 else num
        # leading coefficients that are rounding noise (a cancelled highest power) are dropped
        scale = np.max(np.abs(num)) if num.size else 0.0
        keep = np.flatnonzero(np.abs(num) > 1e-13 * scale)
        num = num[keep[0] :] if keep.size else np.zeros(1)
        return num, den

    def to_scipy(self) -> scipy.signal.lti | scipy.signal.dlti:
        """The model as ``scipy.signal.lti`` (or ``dlti`` with ``dt``), state-space form.

        Returns
        -------
        scipy.signal.lti or scipy.signal.dlti
        """
        A, B, C, D = self.state_space()
        if self.dt == 0:
            return scipy.signal.lti(A, B, C, D)
        return scipy.signal.dlti(A, B, C, D, dt=self.dt)

    def to_control(self) -> Any:
        """The model as ``control.TransferFunction`` (needs python-control).

        Returns
        -------
        control.TransferFunction

        Raises
        ------
        ImportError
            If python-control is not installed (``pip install kautztwin[control]``).
        """
        try:
            import control
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "to_control() needs python-control: pip install 'kautztwin[control]'"
            ) from exc
        num, den = self.transfer_function()
        if self.dt == 0:
            return control.tf(num, den)
        return control.tf(num, den, self.dt)

    def with_coefficients(self, coefficients: ArrayLike) -> KautzModel:
        """A new model on the same basis with other coefficients."""
        return KautzModel(self.basis, coefficients)

    def allclose(self, other: KautzModel, rtol: float = 1e-10, atol: float = 1e-12) -> bool:
        """Whether ``other`` has the same basis and (nearly) the same coefficients."""
        return (
            isinstance(other, KautzModel)
            and self.basis.allclose(other.basis, rtol=rtol)
            and bool(np.allclose(self.coefficients, other.coefficients, rtol=rtol, atol=atol))
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: basis (poles, dt) and coefficients."""
        return {**self.basis.to_dict(), "coefficients": self.coefficients.tolist()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> KautzModel:
        """Rebuild a model written by :meth:`to_dict`."""
        poles = [complex(re, im) for re, im in data["poles"]]
        basis = KautzBasis(poles, dt=data.get("dt", 0.0), delayed=data.get("delayed", False))
        return cls(basis, data["coefficients"])
