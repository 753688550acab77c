"""Labelled response data of an uncertain system: generation, noise, quantisation, files.

:func:`make_dataset` turns every parameter vector of a
:class:`~kautztwin.datasets.ParametricSystem` into a noisy (white or coloured),
optionally quantised, sampled impulse or step response labelled with the exact
Kautz coefficients of its noise-free impulse response and its true poles.  The
resulting :class:`ResponseDataset` is what the neural coefficient estimator
trains on (measured noisy response in, Kautz coefficients out); it is saved to
and loaded from a plain ``.npz`` file.
"""

from __future__ import annotations

import dataclasses
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from .._validation import check_choice, check_finite, check_nonnegative, check_time
from ..basis import KautzBasis
from ..basis._propagate import continuous_functions
from ..exceptions import DataError, DimensionError, KautzTwinError
from .systems import ParametricSystem, TransferFunction, _readonly, _sort_poles

__all__ = ["ResponseDataset", "make_dataset"]

_KINDS = ("impulse", "step")
_NOISE_KINDS = ("white", "colored")
_CHUNK = 256  # records simulated per batched call
_FILE_FORMAT = "kautztwin.ResponseDataset"
_FILE_VERSION = 1


# =========================================================================== dataset
@dataclass(frozen=True, eq=False)
class ResponseDataset:
    """Noisy sampled responses of an uncertain system with their exact Kautz labels.

    Every array is copied and read-only.  Record ``i`` is the response of the
    system at ``parameters[i]``; ``coefficients[i]`` are the exact coefficients
    of its noise-free impulse response in the basis with poles
    ``basis_poles`` and ``poles[i]`` its true poles.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Sample times in seconds.
    responses : array-like of shape (n, n_samples)
        Measured (noisy, possibly quantised) responses.
    clean : array-like of shape (n, n_samples)
        Noise-free responses.
    coefficients : array-like of shape (n, n_functions)
        Exact Kautz coefficients of each noise-free impulse response.
    poles : array-like of complex, shape (n, order)
        True poles, sorted as :meth:`ParametricSystem.poles` does.
    parameters : array-like of shape (n, n_parameters)
        Parameter vectors.
    parameter_names : sequence of str
        Names of the parameter columns.
    basis_poles : array-like of complex, shape (n_functions,)
        Poles of the (continuous-time) Kautz basis of the labels.
    kind : {'impulse', 'step'}, default='impulse'
        What the responses are.
    noise : float, default=0.0
        Noise standard deviation as a fraction of each record's noise-free peak.
    noise_kind : {'white', 'colored'}, default='white'
        Noise colour.
    color_pole : float, default=0.9
        AR(1) pole of colored noise (stored also for white noise, unused there).
    quantization : float or None, default=None
        Quantisation step of the responses, if any.

    Raises
    ------
    DataError
        On an unknown ``kind``/``noise_kind``, non-finite values or a negative noise.
    DimensionError
        If the array shapes do not agree.

    See Also
    --------
    make_dataset : Builds a dataset from a parametric system.
    """

    t: NDArray[np.float64]
    responses: NDArray[np.float64]
    clean: NDArray[np.float64]
    coefficients: NDArray[np.float64]
    poles: NDArray[np.complex128]
    parameters: NDArray[np.float64]
    parameter_names: tuple[str, ...]
    basis_poles: NDArray[np.complex128]
    kind: str = "impulse"
    noise: float = 0.0
    noise_kind: str = "white"
    color_pole: float = 0.9
    quantization: float | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        check_choice(self.kind, "kind", _KINDS)
        check_choice(self.noise_kind, "noise_kind", _NOISE_KINDS)
        set_(self, "kind", str(self.kind))
        set_(self, "noise_kind", str(self.noise_kind))
        set_(self, "noise", check_nonnegative(self.noise, "noise"))
        set_(self, "color_pole", float(self.color_pole))
        if self.quantization is not None:
            set_(self, "quantization", check_nonnegative(self.quantization, "quantization"))
        set_(self, "parameter_names", tuple(str(n) for n in self.parameter_names))
        t = _readonly(self.t, float)
        if t.ndim != 1:
            raise DimensionError(f"t must be 1-D, got shape {t.shape}")
        n_samples = t.size
        resp = _readonly(self.responses, float)
        if resp.ndim != 2 or resp.shape[1] != n_samples:
            raise DimensionError(
                f"responses must have shape (n, {n_samples}) to match t; got {resp.shape}"
            )
        n = resp.shape[0]
        basis_poles = _readonly(self.basis_poles, complex)
        if basis_poles.ndim != 1:
            raise DimensionError(f"basis_poles must be 1-D, got shape {basis_poles.shape}")
        expected = {
            "clean": ((n, n_samples), float),
            "coefficients": ((n, basis_poles.size), float),
            "parameters": ((n, len(self.parameter_names)), float),
        }
        arrays: dict[str, NDArray] = {"t": t, "responses": resp, "basis_poles": basis_poles}
        for key, (shape, dtype) in expected.items():
            a = _readonly(getattr(self, key), dtype)
            if a.shape != shape:
                raise DimensionError(f"{key} must have shape {shape}; got {a.shape}")
            arrays[key] = a
        poles = _readonly(self.poles, complex)
        if poles.ndim != 2 or poles.shape[0] != n:
            raise DimensionError(f"poles must have shape ({n}, order); got {poles.shape}")
        arrays["poles"] = poles
        for key, a in arrays.items():
            check_finite(a, key)
            set_(self, key, a)

    # ------------------------------------------------------------------ views
    def __len__(self) -> int:
        return int(self.responses.shape[0])

    @property
    def n_samples(self) -> int:
        """Samples per record."""
        return int(self.t.size)

    @property
    def n_functions(self) -> int:
        """Number of Kautz coefficients per record."""
        return int(self.basis_poles.size)

    @property
    def basis(self) -> KautzBasis:
        """The continuous-time Kautz basis of the labels."""
        return KautzBasis(self.basis_poles)

    def subset(self, indices: ArrayLike) -> ResponseDataset:
        """Dataset of the records ``indices`` (in that order).

        Parameters
        ----------
        indices : array-like of int or bool mask

        Returns
        -------
        ResponseDataset
        """
        idx = np.asarray(indices)
        if idx.dtype == bool:
            if idx.shape != (len(self),):
                raise DimensionError(
                    f"a boolean mask must have shape ({len(self)},); got {idx.shape}"
                )
            idx = np.flatnonzero(idx)
        idx = idx.astype(np.intp).ravel()
        if idx.size and (idx.min() < -len(self) or idx.max() >= len(self)):
            raise DataError(f"indices must lie in [0, {len(self)}); got {idx.min()}..{idx.max()}")
        return dataclasses.replace(
            self,
            responses=self.responses[idx],
            clean=self.clean[idx],
            coefficients=self.coefficients[idx],
            poles=self.poles[idx],
            parameters=self.parameters[idx],
        )

    def split(
        self, fraction: float = 0.85, random_state: int | np.random.Generator | None = None
    ) -> tuple[ResponseDataset, ResponseDataset]:
        """Random disjoint split into a training and a validation set.

        Parameters
        ----------
        fraction : float, default=0.85
            Share of the records in the training set (``round(fraction * n)``),
            in ``(0, 1)``; both parts must be non-empty.
        random_state : int, numpy.random.Generator or None, default=None
            Seed of the shuffle.

        Returns
        -------
        train, validation : ResponseDataset
            Records keep their original relative order within each part.

        Raises
        ------
        DataError
            If ``fraction`` is not in ``(0, 1)`` or a part would be empty.
        """
        f = float(fraction)
        if not 0.0 < f < 1.0:
            raise DataError(f"fraction must lie in (0, 1), got {fraction!r}")
        n = len(self)
        n_train = int(round(f * n))
        if n_train < 1 or n_train > n - 1:
            raise DataError(
                f"fraction = {f:g} of {n} records leaves an empty training or validation set"
            )
        perm = np.random.default_rng(random_state).permutation(n)
        return self.subset(np.sort(perm[:n_train])), self.subset(np.sort(perm[n_train:]))

    def allclose(self, other: ResponseDataset, rtol: float = 1e-12, atol: float = 0.0) -> bool:
        """Whether ``other`` has the same metadata and (nearly) the same arrays."""
        if not isinstance(other, ResponseDataset):
            return False
        meta = ("parameter_names", "kind", "noise", "noise_kind", "color_pole", "quantization")
        if any(getattr(self, m) != getattr(other, m) for m in meta):
            return False
        arrays = ("t", "responses", "clean", "coefficients", "poles", "parameters", "basis_poles")
        return all(
            getattr(self, a).shape == getattr(other, a).shape
            and bool(np.allclose(getattr(self, a), getattr(other, a), rtol=rtol, atol=atol))
            for a in arrays
        )

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write the dataset to a compressed ``.npz`` file (plain arrays, no pickle).

        Parameters
        ----------
        path : str or path-like
            File name, used as given (no suffix is appended).

        Returns
        -------
        pathlib.Path
            The file written.
        """
        path = Path(path)
        arrays = {
            "format": np.array(_FILE_FORMAT),
            "version": np.array(_FILE_VERSION),
            "t": self.t,
            "responses": self.responses,
            "clean": self.clean,
            "coefficients": self.coefficients,
            "poles": self.poles,
            "parameters": self.parameters,
            "parameter_names": np.array(self.parameter_names, dtype=str).reshape(-1),
            "basis_poles": self.basis_poles,
            "kind": np.array(self.kind),
            "noise": np.array(self.noise),
            "noise_kind": np.array(self.noise_kind),
            "color_pole": np.array(self.color_pole),
            "quantization": np.array(np.nan if self.quantization is None else self.quantization),
        }
        with path.open("wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> ResponseDataset:
        """Read a dataset written by :meth:`save` (``allow_pickle=False``).

        Parameters
        ----------
        path : str or path-like

        Returns
        -------
        ResponseDataset

        Raises
        ------
        DataError
            If the file is missing, unreadable, not an ``.npz`` dataset file or
            its arrays are inconsistent (one-line message).
        """
        path = Path(path)
        if not path.is_file():
            raise DataError(f"dataset file {str(path)!r} does not exist")
        try:
            npz = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise DataError(f"cannot read dataset file {str(path)!r}: {msg}") from None
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise DataError(f"{str(path)!r} is not a kautztwin ResponseDataset file (.npz)")
        try:
            with npz:
                data = {k: npz[k] for k in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise DataError(f"cannot read dataset file {str(path)!r}: {msg}") from None
        if data.get("format") is None or str(data["format"]) != _FILE_FORMAT:
            raise DataError(f"{str(path)!r} is not a kautztwin ResponseDataset file")
        required = (
            "t", "responses", "clean", "coefficients", "poles", "parameters", "parameter_names",
            "basis_poles", "kind", "noise", "noise_kind", "color_pole", "quantization",
        )  # fmt: skip
        missing = [k for k in required if k not in data]
        if missing:
            raise DataError(
                f"dataset file {str(path)!r} is malformed: missing {', '.join(map(repr, missing))}"
            )
        try:
            q = float(data["quantization"])
            return cls(
                t=data["t"],
                responses=data["responses"],
                clean=data["clean"],
                coefficients=data["coefficients"],
                poles=data["poles"],
                parameters=data["parameters"],
                parameter_names=tuple(str(s) for s in np.atleast_1d(data["parameter_names"])),
                basis_poles=data["basis_poles"],
                kind=str(data["kind"]),
                noise=float(data["noise"]),
                noise_kind=str(data["noise_kind"]),
                color_pole=float(data["color_pole"]),
                quantization=None if math.isnan(q) else q,
            )
        except (KautzTwinError, TypeError, ValueError) as exc:
            raise DataError(f"dataset file {str(path)!r} is malformed: {exc}") from None

    def __repr__(self) -> str:
        return (
            f"ResponseDataset(n={len(self)}, n_samples={self.n_samples}, "
            f"n_functions={self.n_functions}, kind={self.kind!r}, noise={self.noise:g}, "
            f"noise_kind={self.noise_kind!r})"
        )


def _responses(tfs: list[TransferFunction], t: NDArray, kind: str) -> NDArray[np.float64]:
    """Exact impulse or unit-step responses ``C e^{At} B`` (state space, batched)."""
    A, B, C = [], [], []
    for num, den in tfs:
        a, b, c, _ = scipy.signal.tf2ss(num, den)
        A.append(a)
        B.append(b[:, 0])
        C.append(c[0])
    A_, B_, C_ = np.array(A), np.array(B), np.array(C)
    out = np.empty((len(tfs), t.size))
    for start in range(0, len(tfs), _CHUNK):
        s = slice(start, start + _CHUNK)
        F = continuous_functions(A_[s], B_[s], t)  # (b, order, n_samples): e^{At} B
        if kind == "step":  # int_0^t e^{As} B ds = A^{-1} (e^{At} - I) B
            F = np.linalg.solve(A_[s], F - B_[s][:, :, None])
        out[s] = np.einsum("bi,bik->bk", C_[s], F)
    return out


def _noise(
    shape: tuple[int, int], kind: str, color_pole: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Unit-variance noise: white, or stationary AR(1) with lag-1 correlation ``color_pole``."""
    w = rng.standard_normal(shape)
    if kind == "white" or color_pole == 0:
        return w
    a = color_pole
    g = math.sqrt(1.0 - a * a)
    w[:, 0] /= g  # e[0] = w[0] ~ N(0, 1): the filter starts in its stationary state
    return scipy.signal.lfilter([g], [1.0, -a], w, axis=1)


def make_dataset(
    system: ParametricSystem,
    parameters: ArrayLike,
    basis: KautzBasis,
    t: ArrayLike,
    *,
    kind: str = "impulse",
    noise: float = 0.0,
    noise_kind: str = "white",
    color_pole: float = 0.9,
    quantization: float | None = None,
    random_state: int | np.random.Generator | None = None,
) -> ResponseDataset:
    r"""Noisy sampled responses of many parameter vectors, labelled with exact Kautz coefficients.

    For every parameter vector the noise-free impulse or unit-step response is
    computed exactly from a state-space realisation,
    :math:`h(t) = C e^{At} B` and :math:`y(t) = C A^{-1}(e^{At} - I) B`
    (matrix-exponential stepping, no ODE solver); then noise is added and the
    readings are optionally quantised.  The labels are the exact coefficients
    :math:`c_i = \langle h, K_i \rangle` of the noise-free *impulse* response
    from :func:`kautztwin.coefficients_from_system` (a Sylvester equation, no
    quadrature), for both kinds: the step response of the model
    :math:`\sum c_i K_i` is :math:`\sum c_i \int_0^t K_i`, so the same
    coefficients describe both.

    Parameters
    ----------
    system : ParametricSystem
        The nominal model; every row must give a strictly proper stable system.
    parameters : array-like of shape (n, n_parameters)
        Parameter vectors, e.g. from :func:`draw_parameters`.
    basis : KautzBasis
        Continuous-time basis of the labels.
    t : array-like of shape (n_samples,)
        Strictly increasing sample times, ``t[0] >= 0`` (uniform grids are fastest).
    kind : {'impulse', 'step'}, default='impulse'
        Response recorded.
    noise : float, default=0.0
        Noise standard deviation as a fraction of each record's noise-free
        peak :math:`\max_t |y|` (0.1 = 10 %).
    noise_kind : {'white', 'colored'}, default='white'
        White Gaussian noise, or first-order low-pass (AR(1)) filtered white
        noise :math:`e_k = a e_{k-1} + \sqrt{1 - a^2}\, w_k`, started in its
        stationary state, with the same standard deviation.
    color_pole : float, default=0.9
        AR(1) pole :math:`a \in (-1, 1)` of colored noise, per sample; it is
        the lag-1 autocorrelation of the noise.
    quantization : float, optional
        Step to round the noisy readings to (``step * round(y / step)``).
    random_state : int, numpy.random.Generator or None, default=None
        Seed of the noise.

    Returns
    -------
    ResponseDataset

    Raises
    ------
    DataError
        On an unknown ``kind``/``noise_kind``, a negative ``noise``,
        ``|color_pole| >= 1``, a non-positive ``quantization``, a discrete
        basis, ``t[0] < 0``, or a row that gives an unstable or biproper system
        (no redraw here: pass stable rows, e.g. from :func:`draw_parameters`).
    DimensionError
        If ``parameters`` does not have ``n_parameters`` columns.

    See Also
    --------
    draw_parameters : Random parameter vectors.
    factorial_parameters : Full-factorial parameter grid.
    kautztwin.coefficients_from_system : The labels.

    Notes
    -----
    The labels describe the infinite-horizon impulse response; projecting a
    record (:func:`kautztwin.project`) reproduces them only if the record is
    long and fine enough for the response and the basis to have decayed.
    Colored-noise correlation is per sample, so it depends on the grid spacing.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.datasets import draw_parameters, make_dataset, paper_system
    >>> system = paper_system()
    >>> P = draw_parameters(system, 0.1, 8, random_state=0)
    >>> basis = kt.KautzBasis(system.poles())
    >>> t = np.linspace(0.0, 20.0, 901)
    >>> ds = make_dataset(system, P, basis, t, noise=0.05, random_state=1)
    >>> ds.responses.shape, ds.coefficients.shape, ds.poles.shape
    ((8, 901), (8, 4), (8, 4))
    >>> nominal = make_dataset(system, system.nominal, basis, t)
    >>> np.round(nominal.coefficients, 6)
    array([[-0.220971,  0.088388,  0.287262, -0.038273]])
    """
    from ..approx.projection import coefficients_from_system

    check_choice(kind, "kind", _KINDS)
    check_choice(noise_kind, "noise_kind", _NOISE_KINDS)
    noise = check_nonnegative(noise, "noise")
    try:
        color_pole = float(color_pole)
    except (TypeError, ValueError) as exc:
        raise DataError(f"color_pole must be a number in (-1, 1), got {color_pole!r}") from exc
    if not -1.0 < color_pole < 1.0:
        raise DataError(f"color_pole must lie in (-1, 1), got {color_pole}")
    if quantization is not None:
        quantization = check_nonnegative(quantization, "quantization")
        if quantization == 0:
            raise DataError("quantization must be a positive step (or None), got 0")
    if not isinstance(basis, KautzBasis):
        raise DataError(f"basis must be a KautzBasis, got {type(basis).__name__}")
    if basis.is_discrete:
        raise DataError(
            "basis must be continuous-time (dt = 0) for continuous-time systems; "
            f"got dt = {basis.dt:g}"
        )
    t = check_time(t)
    if t[0] < 0:
        raise DataError(
            f"t must start at t[0] >= 0 (responses from rest at 0), got t[0] = {t[0]:g}"
        )
    P = system._matrix(parameters)
    if P.shape[0] == 0:
        raise DataError("parameters holds no rows")

    tfs: list[TransferFunction] = []
    for i, p in enumerate(P):
        try:
            num, den = system.transfer_function(p)
        except DataError as exc:
            raise DataError(f"parameters[{i}]: {exc}") from None
        if num.size >= den.size:
            raise DataError(
                f"parameters[{i}]: {system.name!r} is biproper (deg num = deg den = "
                f"{den.size - 1}); its impulse response has a Dirac at t = 0 and no L2 coefficients"
            )
        tfs.append((num, den))

    clean = _responses(tfs, t, kind)
    coefficients = np.array([coefficients_from_system(basis, tf) for tf in tfs]).reshape(
        len(tfs), basis.n_functions
    )
    poles = np.array([_sort_poles(np.roots(den)) for _, den in tfs], dtype=complex)

    responses = clean.copy()
    if noise > 0:
        rng = np.random.default_rng(random_state)
        scale = noise * np.max(np.abs(clean), axis=1, keepdims=True)
        responses += scale * _noise(clean.shape, noise_kind, color_pole, rng)
    if quantization is not None:
        responses = quantization * np.round(responses / quantization)

    return ResponseDataset(
        t=t,
        responses=responses,
        clean=clean,
        coefficients=coefficients,
        poles=poles,
        parameters=P,
        parameter_names=system.parameter_names,
        basis_poles=basis.poles,
        kind=kind,
        noise=noise,
        noise_kind=noise_kind,
        color_pole=color_pole,
        quantization=quantization,
    )
