r"""The multi-input multi-output discrete Kautz model and its python-control / scipy interop.

Output :math:`i` of the model is

.. math::

    \hat y_i(k) = y_{0,i} + \sum_{j=1}^{m} c_{ij}^T x_{ij}(k) + D_{ij}\,(u_j(k) - u_{0,j}),
    \qquad x_{ij}(k+1) = A_i x_{ij}(k) + B_i (u_j(k) - u_{0,j}),

one delayed discrete Kautz network :math:`(A_i, B_i)` per input.  With *shared* poles every
output uses the same network, so the state is one filter bank per input and the
coefficients form matrices :math:`C_j = [c_{1j}, \dots, c_{pj}]^T`; with *per-output* poles
each output has its own network and its own filter banks.

Size: :class:`MIMOKautzModel` runs past 400 lines, about two thirds of them numpydoc; its
methods (simulation, frequency response, realisation, conversions both ways, JSON) are the
API of one value object and read together.  The parsing of foreign system descriptions
lives in ``_convert.py``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from ..._json import to_jsonable
from ..._validation import check_finite
from ...approx.projection import coefficients_from_system
from ...basis import KautzBasis
from ...exceptions import DataError, DimensionError
from ..kautz_oe import filter_states
from ._convert import merged_eigenvalues, system_matrices

__all__ = ["MIMOKautzModel", "load_mimo_model"]


def _as_2d(x: ArrayLike, name: str, n_columns: int | None = None) -> NDArray[np.float64]:
    """A signal as a float array of shape (n_samples, n_columns); 1-D means one column."""
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise DimensionError(f"{name} must be 1-D or 2-D (n_samples, n_channels), got {a.shape}")
    if n_columns is not None and a.shape[1] != n_columns:
        raise DimensionError(
            f"{name} has {a.shape[1]} column(s) but the model has {n_columns}"
        )
    check_finite(a, name)
    return a


@dataclass(frozen=True, eq=False)
class MIMOKautzModel:
    r"""Immutable discrete MIMO Kautz model: one filter bank per input, coefficient matrices.

    Parameters
    ----------
    bases : KautzBasis or sequence of KautzBasis
        Delayed discrete bases.  One basis: shared poles (every output uses it).  A
        sequence of ``n_outputs`` bases: per-output poles.
    coefficients : array-like of shape (n_outputs, n_inputs, n_functions), or a sequence
        One ``(n_inputs, n_functions_i)`` array per output; ``coefficients[i][j]`` is
        :math:`c_{ij}`, the weights of input ``j``'s filter bank in output ``i``.
    input_offset : array-like of shape (n_inputs,), optional
        Operating point :math:`u_0` the filters are driven from (zeros when omitted).
    output_offset : array-like of shape (n_outputs,), optional
        Output level :math:`y_0` at rest (zeros when omitted).
    feedthrough : array-like of shape (n_outputs, n_inputs), optional
        Direct term :math:`D` (zeros when omitted; identification fits none).

    Attributes
    ----------
    n_inputs, n_outputs : int
        Channel counts.
    dt : float
        Sampling period, s.
    shared : bool
        Whether every output uses the same poles.
    poles : ndarray of complex
        The shared poles; per-output models list every output's poles, concatenated.

    Raises
    ------
    DataError
        If a basis is not a delayed discrete basis, the bases differ in ``dt``, or a value
        is not finite.
    DimensionError
        If the coefficient, offset or feedthrough shapes do not match.

    See Also
    --------
    identify_mimo : Fit such a model to input/output data.
    MIMOKautzEstimator : The estimator with order and structure selection.

    Notes
    -----
    :meth:`state_space` realises the deviations :math:`y - y_0` from :math:`u - u_0` with
    ``n_inputs * n_functions`` states (shared) or ``n_inputs * sum_i n_functions_i``
    (per output): not minimal in general, but exact.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin import KautzBasis
    >>> from kautztwin.ident.mimo import MIMOKautzModel
    >>> basis = KautzBasis([0.9, 0.5], dt=1.0, delayed=True)
    >>> model = MIMOKautzModel(basis, np.arange(8.0).reshape(2, 2, 2))
    >>> model.n_outputs, model.n_inputs, model.state_space()[0].shape
    (2, 2, (4, 4))
    >>> model.simulate(np.ones((3, 2))).shape
    (3, 2)
    """

    bases: tuple[KautzBasis, ...]
    coefficients: tuple[NDArray[np.float64], ...]
    input_offset: NDArray[np.float64] | None = None
    output_offset: NDArray[np.float64] | None = None
    feedthrough: NDArray[np.float64] | None = field(default=None)

    def __post_init__(self) -> None:
        bases = (self.bases,) if isinstance(self.bases, KautzBasis) else tuple(self.bases)
        if not bases or not all(isinstance(b, KautzBasis) for b in bases):
            raise DataError("bases must be a KautzBasis or a non-empty sequence of them")
        for b in bases:
            if not (b.is_discrete and b.delayed):
                raise DataError("MIMO Kautz models need delayed discrete bases (dt > 0, delayed)")
        if len({b.dt for b in bases}) != 1:
            raise DataError("the bases must share one sampling period")
        coef = self.coefficients
        if isinstance(coef, np.ndarray) or not isinstance(coef, Sequence) or (
            len(coef) and np.ndim(coef[0]) < 2
        ):
            arr = np.asarray(coef, dtype=float)
            if arr.ndim != 3:
                raise DimensionError(
                    "coefficients must have shape (n_outputs, n_inputs, n_functions), got "
                    f"{arr.shape}"
                )
            coef = list(arr)
        coefs = tuple(np.array(c, dtype=float, copy=True) for c in coef)
        n_out = len(coefs)
        if len(bases) == 1:
            bases = bases * n_out
        if len(bases) != n_out:
            raise DimensionError(f"{len(bases)} bases for {n_out} outputs")
        n_in = coefs[0].shape[0] if coefs and coefs[0].ndim == 2 else 0
        for i, (c, b) in enumerate(zip(coefs, bases, strict=True)):
            if c.shape != (n_in, b.n_functions) or n_in == 0:
                raise DimensionError(
                    f"coefficients[{i}] has shape {c.shape}; expected ({max(n_in, 1)}, "
                    f"{b.n_functions}) (n_inputs, n_functions of its basis)"
                )
            check_finite(c, f"coefficients[{i}]")
            c.setflags(write=False)
        object.__setattr__(self, "bases", bases)
        object.__setattr__(self, "coefficients", coefs)
        for name, shape in (
            ("input_offset", (n_in,)), ("output_offset", (n_out,)), ("feedthrough", (n_out, n_in))
        ):
            value = getattr(self, name)
            a = np.zeros(shape) if value is None else np.array(value, dtype=float, copy=True)
            if a.shape != shape:
                raise DimensionError(f"{name} has shape {a.shape}; expected {shape}")
            check_finite(a, name)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    # ------------------------------------------------------------------ shape
    @property
    def n_inputs(self) -> int:
        """Number of inputs."""
        return int(self.coefficients[0].shape[0])

    @property
    def n_outputs(self) -> int:
        """Number of outputs."""
        return len(self.coefficients)

    @property
    def dt(self) -> float:
        """Sampling period, s."""
        return self.bases[0].dt

    @property
    def shared(self) -> bool:
        """Whether all outputs use one set of poles."""
        first = self.bases[0]
        return all(b is first or b.allclose(first, rtol=0.0) for b in self.bases[1:])

    @property
    def poles(self) -> NDArray[np.complex128]:
        """Shared poles, or every output's poles concatenated (per-output models)."""
        if self.shared:
            return np.array(self.bases[0].poles)
        return np.concatenate([b.poles for b in self.bases])

    @property
    def n_states(self) -> int:
        """Number of states of :meth:`state_space`."""
        if self.shared:
            return self.n_inputs * self.bases[0].n_functions
        return self.n_inputs * sum(b.n_functions for b in self.bases)

    # ------------------------------------------------------------------ responses
    def simulate(self, u: ArrayLike, x0: ArrayLike | None = None) -> NDArray[np.float64]:
        """Free-run simulation from a state (rest, ``x0 = 0``, when omitted).

        Parameters
        ----------
        u : array-like of shape (n_samples, n_inputs)
            Input; 1-D for a single-input model.
        x0 : array-like of shape (n_states,), optional
            Initial state of :meth:`state_space`'s realisation.

        Returns
        -------
        ndarray of shape (n_samples, n_outputs)
            1-D when the model has one input, one output and ``u`` is 1-D.

        Raises
        ------
        DimensionError
            If ``u`` or ``x0`` has the wrong shape.
        DataError
            If ``u`` is not finite.
        """
        u_in = np.asarray(u)
        v = _as_2d(u, "u", self.n_inputs) - self.input_offset
        n_per = self._states_per_output()
        x0s = None
        if x0 is not None:
            x0a = np.asarray(x0, dtype=float).reshape(-1)
            if x0a.size != self.n_states:
                raise DimensionError(f"x0 has {x0a.size} values; the model has {self.n_states}")
            check_finite(x0a, "x0")
            x0s = x0a
        out = np.empty((v.shape[0], self.n_outputs))
        cache: dict[int, list[NDArray]] = {}
        for i, (b, c) in enumerate(zip(self.bases, self.coefficients, strict=True)):
            key = 0 if self.shared else i
            if key not in cache:
                n_f = b.n_functions
                start = 0 if self.shared else sum(n_per[:i])
                cache[key] = [
                    filter_states(
                        b, v[:, j],
                        None if x0s is None else x0s[start + j * n_f: start + (j + 1) * n_f],
                    )[:-1]
                    for j in range(self.n_inputs)
                ]
            X = cache[key]
            out[:, i] = sum(X[j] @ c[j] for j in range(self.n_inputs))
        out += v @ self.feedthrough.T + self.output_offset
        if u_in.ndim == 1 and self.n_outputs == 1:
            return out[:, 0]
        return out

    def frequency_response(self, w: ArrayLike) -> NDArray[np.complex128]:
        """Frequency response matrix at angular frequencies ``w`` (rad/s), ``z = exp(j w dt)``.

        Parameters
        ----------
        w : array-like of shape (n_freqs,)

        Returns
        -------
        ndarray of complex, shape (n_freqs, n_outputs, n_inputs)
        """
        w = np.atleast_1d(np.asarray(w, dtype=float))
        z = np.exp(1j * w * self.dt)
        out = np.empty((w.size, self.n_outputs, self.n_inputs), dtype=complex)
        for i, (b, c) in enumerate(zip(self.bases, self.coefficients, strict=True)):
            eye = np.eye(b.n_functions)
            Phi = np.linalg.solve(
                z[:, None, None] * eye[None] - np.asarray(b.A)[None],
                np.broadcast_to(np.asarray(b.B)[:, None], (w.size, b.n_functions, 1)),
            )[:, :, 0]  # (n_freqs, n_functions)
            out[:, i, :] = Phi @ c.T
        return out + self.feedthrough[None]

    @property
    def dc_gain(self) -> NDArray[np.float64]:
        """Static gain matrix :math:`G(1)`, shape (n_outputs, n_inputs)."""
        return self.frequency_response([0.0])[0].real

    # ------------------------------------------------------------------ conversions
    def _states_per_output(self) -> list[int]:
        return [self.n_inputs * b.n_functions for b in self.bases]

    def state_space(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Realisation ``(A, B, C, D)`` of the deviations ``y - y0`` from ``u - u0``.

        Returns
        -------
        A : ndarray of shape (n_states, n_states)
        B : ndarray of shape (n_states, n_inputs)
        C : ndarray of shape (n_outputs, n_states)
        D : ndarray of shape (n_outputs, n_inputs)
        """
        m = self.n_inputs
        groups = [self.bases[0]] if self.shared else list(self.bases)
        A = scipy.linalg.block_diag(*[np.kron(np.eye(m), np.asarray(b.A)) for b in groups])
        B = np.vstack([np.kron(np.eye(m), np.asarray(b.B)[:, None]) for b in groups])
        C = np.zeros((self.n_outputs, A.shape[0]))
        start = 0
        for i, c in enumerate(self.coefficients):
            C[i, start: start + c.size] = c.reshape(-1)
            if not self.shared:
                start += c.size
        return A, B, C, np.array(self.feedthrough)

    def to_scipy(self) -> scipy.signal.StateSpace:
        """The model as a discrete ``scipy.signal.StateSpace`` (deviation variables).

        Returns
        -------
        scipy.signal.StateSpace
        """
        return scipy.signal.StateSpace(*self.state_space(), dt=self.dt)

    def to_control(self) -> Any:
        """The model as a discrete ``control.StateSpace`` (needs python-control).

        Returns
        -------
        control.StateSpace

        Raises
        ------
        ImportError
            If python-control is not installed (``pip install 'kautztwin[control]'``).
        """
        try:
            import control
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "to_control() needs python-control: pip install 'kautztwin[control]'"
            ) from exc
        return control.ss(*self.state_space(), self.dt)

    @classmethod
    def from_state_space(
        cls,
        system: Any,
        *,
        dt: float | None = None,
        poles: ArrayLike | None = None,
        input_offset: ArrayLike | None = None,
        output_offset: ArrayLike | None = None,
    ) -> MIMOKautzModel:
        """Shared-pole Kautz model of a stable LTI system (scipy, python-control or matrices).

        With ``poles`` omitted the basis poles are the eigenvalues of the system's ``A``
        (rounding-split repeated eigenvalues merged), and the model reproduces the system
        exactly.  With ``poles`` the coefficients are the orthogonal projection of every
        channel's pulse response (exact when the system's poles are among them).

        Parameters
        ----------
        system : scipy.signal StateSpace/dlti/lti, control.StateSpace/TransferFunction, or
            a tuple ``(A, B, C, D[, dt])`` (a 4-tuple is continuous time).
        dt : float, optional
            Sampling period for a continuous system, discretised with a zero-order hold;
            must match a discrete system's own period when both are given.
        poles : array-like of complex, optional
            Discrete basis poles (``|p| < 1``).
        input_offset, output_offset : array-like, optional
            Operating point of the returned model.

        Returns
        -------
        MIMOKautzModel

        Raises
        ------
        DataError
            If the system is unstable, continuous without ``dt``, or ``dt`` disagrees.
        """
        A, B, C, D, sys_dt = system_matrices(system)
        if sys_dt == 0:
            if dt is None:
                raise DataError(
                    "the system is continuous-time: pass dt to discretise it (zero-order hold)"
                )
            if not (np.isfinite(dt) and dt > 0):
                raise DataError(f"dt must be a positive sampling period, got {dt!r}")
            A, B, C, D, _ = scipy.signal.cont2discrete((A, B, C, D), float(dt), method="zoh")
            sys_dt = float(dt)
        elif dt is not None and not np.isclose(float(dt), sys_dt, rtol=1e-12, atol=0.0):
            raise DataError(f"dt = {dt} disagrees with the system's sampling period {sys_dt}")
        eig = np.linalg.eigvals(A) if A.size else np.zeros(0)
        if np.any(np.abs(eig) >= 1):
            raise DataError(
                f"the system is not stable: |eig(A)| reaches {np.max(np.abs(eig)):.6g} >= 1"
            )
        p = merged_eigenvalues(A) if poles is None else np.asarray(poles, dtype=complex)
        if p.size == 0:
            raise DataError("the system has no states; give poles to build a basis")
        basis = KautzBasis(p, dt=sys_dt, delayed=True)
        coef = np.empty((C.shape[0], B.shape[1], basis.n_functions))
        for i in range(C.shape[0]):
            for j in range(B.shape[1]):
                coef[i, j] = coefficients_from_system(
                    basis, (A, B[:, j : j + 1], C[i : i + 1], np.zeros((1, 1)), sys_dt)
                )
        return cls(basis, coef, input_offset, output_offset, D)

    # ------------------------------------------------------------------ persistence
    def allclose(self, other: MIMOKautzModel, rtol: float = 1e-10, atol: float = 1e-12) -> bool:
        """Whether ``other`` has the same bases and (nearly) the same coefficients and offsets.

        Parameters
        ----------
        other : MIMOKautzModel
        rtol, atol : float
            Tolerances of ``numpy.allclose``.

        Returns
        -------
        bool
        """
        if not isinstance(other, MIMOKautzModel) or other.n_outputs != self.n_outputs:
            return False
        if other.n_inputs != self.n_inputs:
            return False
        return all(
            a.allclose(b, rtol=rtol) for a, b in zip(self.bases, other.bases, strict=True)
        ) and all(
            np.allclose(x, y, rtol=rtol, atol=atol)
            for x, y in zip(
                (*self.coefficients, self.input_offset, self.output_offset, self.feedthrough),
                (*other.coefficients, other.input_offset, other.output_offset,
                 other.feedthrough),
                strict=True,
            )
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (inverse: :meth:`from_dict`).

        Returns
        -------
        dict
            ``type``, ``dt``, ``shared``, ``poles`` (one ``[[re, im], ...]`` list per output),
            ``coefficients`` (per output, ``n_inputs`` lists), the offsets and ``feedthrough``.
        """
        return {
            "type": "MIMOKautzModel",
            "dt": self.dt,
            "shared": self.shared,
            "poles": [[[float(p.real), float(p.imag)] for p in b.poles] for b in self.bases],
            "coefficients": [c.tolist() for c in self.coefficients],
            "input_offset": self.input_offset.tolist(),
            "output_offset": self.output_offset.tolist(),
            "feedthrough": self.feedthrough.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MIMOKautzModel:
        """Rebuild a model from :meth:`to_dict`'s dictionary.

        Parameters
        ----------
        data : dict

        Returns
        -------
        MIMOKautzModel

        Raises
        ------
        DataError
            If ``data`` is not such a dictionary.
        """
        try:
            if data.get("type") != "MIMOKautzModel":
                raise DataError(f"not a MIMO Kautz model dictionary (type {data.get('type')!r})")
            dt = float(data["dt"])
            bases = [
                KautzBasis([complex(re, im) for re, im in poles], dt=dt, delayed=True)
                for poles in data["poles"]
            ]
            if data.get("shared"):
                bases = bases[:1]
            return cls(
                bases, [np.asarray(c, dtype=float) for c in data["coefficients"]],
                data["input_offset"], data["output_offset"], data["feedthrough"],
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            if isinstance(exc, DataError | DimensionError):
                raise
            raise DataError(f"not a MIMO Kautz model dictionary: {exc}") from None

    def save(self, path: str | Path) -> None:
        """Write the model as JSON (:func:`load_mimo_model` reads it back).

        Parameters
        ----------
        path : str or Path
        """
        Path(path).write_text(json.dumps(to_jsonable(self.to_dict()), indent=1))

    def __repr__(self) -> str:
        kind = "shared" if self.shared else "per-output"
        return (
            f"MIMOKautzModel({self.n_outputs}x{self.n_inputs}, {kind} poles, "
            f"{self.n_states} states, dt={self.dt:g})"
        )


def load_mimo_model(path: str | Path) -> MIMOKautzModel:
    """Read a model written by :meth:`MIMOKautzModel.save`.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    MIMOKautzModel

    Raises
    ------
    DataError
        If the file cannot be read or holds no such model.
    """
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot read a MIMO Kautz model from {path}: {exc}") from None
    if not isinstance(data, dict):
        raise DataError(f"{path} holds no MIMO Kautz model")
    return MIMOKautzModel.from_dict(data)
