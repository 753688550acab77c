"""Pole studies: ISE sensitivity maps and automatic pole optimisation (variable projection).

The paper chooses the basis poles by hand and shows (its Figure 3) how the
approximation error depends on them.  Here both are automatic and vectorised:

* :func:`pole_sensitivity` evaluates the ISE of the best approximation for a
  whole grid of candidate pole locations at once (batched Sylvester equations
  for a known system, batched basis evaluation and least squares for data);
* :func:`optimize_poles` chooses the poles that minimise the ISE of one or many
  records by variable projection: for given poles the coefficients are the
  linear least-squares solution, so only the poles are searched, by bounded
  nonlinear least squares in stable coordinates (log-rates), so every iterate
  is a stable basis.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from .._quadrature import least_squares_weights
from .._validation import check_records, check_time
from ..basis import KautzBasis
from ..basis._blocks import PAIR, REAL, continuous_matrices, parse_poles
from ..basis._propagate import continuous_functions, uniform_step
from ..exceptions import ConvergenceWarning, DataError, PoleError
from ..metrics import fit_percent, ise
from ._system import as_state_space
from .model import KautzModel

__all__ = ["PoleOptimization", "optimize_poles", "pole_sensitivity", "real_restart_poles"]

_CHUNK = 2048  # bases per batch: bounds memory at about CHUNK * N * n_samples floats


# --------------------------------------------------------------------------- batched ISE
def _design_batch(kinds: tuple[str, ...], params: NDArray, t: NDArray, kind: str) -> NDArray:
    """Basis impulse (or step) responses for a batch of pole sets, shape (b, N, n)."""
    A, B = continuous_matrices(kinds, params)
    K = continuous_functions(A, B, t)
    if kind == "impulse":
        return K
    return np.linalg.solve(A, K - B[:, :, None])


def _ise_data_batch(
    kinds: tuple[str, ...], params: NDArray, t: NDArray, h: NDArray, kind: str
) -> NDArray[np.float64]:
    """Weighted least-squares ISE on the grid of every record, summed, per basis."""
    w = least_squares_weights(t)
    H = np.atleast_2d(h)  # (r, n)
    energy = float(np.sum(H**2 @ w))
    out = np.empty(params.shape[0])
    for start in range(0, params.shape[0], _CHUNK):
        P = _design_batch(kinds, params[start : start + _CHUNK], t, kind)  # (b, N, n)
        G = np.einsum("bin,n,bjn->bij", P, w, P)
        rhs = np.einsum("bin,n,rn->bir", P, w, H)
        c = np.linalg.solve(G, rhs)
        out[start : start + _CHUNK] = energy - np.einsum("bir,bir->b", rhs, c)
    return np.maximum(out, 0.0)


def _ise_system_batch(kinds: tuple[str, ...], params: NDArray, system: Any) -> NDArray[np.float64]:
    """Exact ISE ``||h||^2 - ||c||^2`` per basis, with batched Sylvester equations."""
    ss = as_state_space(system)
    if ss.dt != 0:
        raise DataError("pole_sensitivity takes continuous-time systems only")
    import scipy.linalg

    energy = float(
        ss.C @ scipy.linalg.solve_continuous_lyapunov(ss.A, -np.outer(ss.B, ss.B)) @ ss.C
    )
    n_h = ss.A.shape[0]
    out = np.empty(params.shape[0])
    for start in range(0, params.shape[0], _CHUNK):
        A, B = continuous_matrices(kinds, params[start : start + _CHUNK])
        b, N, _ = A.shape
        # vec(A X + X Ah^T) = (I kron A + Ah kron I) vec X  (column-major vec)
        M = np.einsum("ij,bkl->bikjl", np.eye(n_h), A).reshape(b, n_h * N, n_h * N)
        M = M + np.kron(ss.A, np.eye(N))[None]
        rhs = -(B[:, :, None] * ss.B[None, None, :]).transpose(0, 2, 1).reshape(b, n_h * N)
        X = np.linalg.solve(M, rhs[:, :, None])[:, :, 0].reshape(b, n_h, N).transpose(0, 2, 1)
        c = X @ ss.C
        out[start : start + _CHUNK] = energy - np.sum(c**2, axis=1)
    return np.maximum(out, 0.0)


def _block_of_index(poles: NDArray, index: int, kinds: tuple[str, ...], params: NDArray) -> int:
    """Block that holds ``poles[index]`` (a pair's block holds both members)."""
    if not -poles.size <= index < poles.size:
        raise PoleError(f"index {index} is out of range for {poles.size} poles")
    target = poles[index]
    col = 0
    for j, kind in enumerate(kinds):
        if kind == REAL:
            if target.imag == 0 and np.isclose(-target.real, params[col], rtol=1e-12, atol=0):
                return j
            col += 1
        else:
            if np.isclose(-target.real, params[col], rtol=1e-12) and np.isclose(
                abs(target.imag), params[col + 1], rtol=1e-8
            ):
                return j
            col += 2
    raise PoleError(f"poles[{index}] was not found in the basis")  # pragma: no cover


def pole_sensitivity(
    poles: ArrayLike,
    index: int,
    values: ArrayLike,
    *,
    system: Any = None,
    t: ArrayLike | None = None,
    h: ArrayLike | None = None,
    kind: str = "impulse",
) -> NDArray[np.float64]:
    """ISE of the best approximation as one basis pole moves (the paper's Figure 3).

    ``poles[index]`` (and, for a complex pole, its conjugate) is replaced by
    each entry of ``values`` while the other poles stay; for each candidate the
    coefficients are optimal and the ISE is returned.  All candidates are
    computed in vectorised batches, so a 100 x 100 map takes about a second.

    Parameters
    ----------
    poles : array-like of complex
        Continuous-time basis pole locations (``Re < 0``, pairs complete).
    index : int
        Which pole moves.
    values : array-like, any shape
        Candidate locations.  For a real pole: negative reals.  For a complex
        pole: complex locations (the member with ``Im > 0``; its conjugate
        moves with it), e.g. a 2-D grid ``re[None, :] + 1j * im[:, None]``.
    system : scipy.signal.lti, (num, den) or (A, B, C, D), optional
        Known system: exact ISE via Sylvester and Lyapunov equations.
    t, h : array-like, optional
        Sampled data instead of ``system``: the grid and one or many records;
        the ISE is that of the weighted least-squares fit on the grid (summed
        over records).
    kind : {'impulse', 'step'}, default='impulse'
        What the records ``h`` are.

    Returns
    -------
    ndarray of the shape of ``values``

    Raises
    ------
    PoleError
        If a candidate is unstable, or a real pole is given complex candidates.
    DataError
        If neither or both of ``system`` and ``(t, h)`` are given.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.data import reference_poles, reference_system
    >>> ise = kt.pole_sensitivity(reference_poles(), 0, [-0.5, -1.0, -2.0],
    ...                           system=reference_system())
    >>> bool(ise[1] < 1e-12 < ise[0])
    True
    """
    if (system is None) == (t is None or h is None):
        raise DataError("give either system=... or both t=... and h=...")
    kinds, params = parse_poles(poles, 0.0)
    p = np.atleast_1d(np.asarray(poles, dtype=complex))
    block = _block_of_index(p, index, kinds, params)
    col = sum(1 if k == REAL else 2 for k in kinds[:block])
    vals = np.asarray(values, dtype=complex)
    flat = vals.reshape(-1)
    if np.any(~np.isfinite(flat)):
        raise PoleError("values contain NaN or inf")
    if np.any(flat.real >= 0):
        raise PoleError("every candidate location must have Re < 0 (a stable pole)")
    batch = np.repeat(params[None, :], flat.size, axis=0)
    if kinds[block] == REAL:
        if np.any(flat.imag != 0):
            raise PoleError(f"poles[{index}] is real; its candidates must be real too")
        batch[:, col] = -flat.real
    else:
        if np.any(flat.imag == 0):
            raise PoleError(f"poles[{index}] is complex; its candidates need Im != 0")
        batch[:, col] = -flat.real
        batch[:, col + 1] = np.abs(flat.imag)
    if system is not None:
        out = _ise_system_batch(kinds, batch, system)
    else:
        if kind not in ("impulse", "step"):
            raise DataError(f"kind must be 'impulse' or 'step', got {kind!r}")
        tt = check_time(t)
        out = _ise_data_batch(kinds, batch, tt, check_records(h, tt.size), kind)
    return out.reshape(vals.shape)


# --------------------------------------------------------------------------- optimisation
@dataclass(frozen=True, eq=False)
class PoleOptimization:
    """Result of :func:`optimize_poles`.

    Parameters
    ----------
    basis : KautzBasis
        Basis with the optimised poles.
    coefficients : ndarray of shape (n_functions,) or (n_records, n_functions)
        Least-squares coefficients of each record in ``basis``.
    initial_basis : KautzBasis
        The starting basis of the best run.
    kind : {'impulse', 'step'}
        What the records were.
    ise : float or ndarray of shape (n_records,)
        ISE of each record on its grid (Simpson quadrature of the error).
    fit_percent : float or ndarray of shape (n_records,)
        Fit percent of each record (MATLAB ``compare`` definition).
    n_evaluations : int
        Residual evaluations over all starts.
    success : bool
        Whether the best run met its tolerance.
    message : str
        The solver's message for the best run.
    """

    basis: KautzBasis
    coefficients: NDArray[np.float64]
    initial_basis: KautzBasis
    kind: str
    ise: float | NDArray[np.float64]
    fit_percent: float | NDArray[np.float64]
    n_evaluations: int
    success: bool
    message: str

    @property
    def model(self) -> KautzModel:
        """The fitted model (one-record fits only)."""
        if self.coefficients.ndim != 1:
            raise DataError("model is defined for a one-record fit; use models() for many records")
        return KautzModel(self.basis, self.coefficients)

    def models(self) -> list[KautzModel]:
        """One model per record (all on the shared optimised basis)."""
        return [KautzModel(self.basis, c) for c in np.atleast_2d(self.coefficients)]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary."""

        def _num(x: Any) -> Any:
            return x.tolist() if isinstance(x, np.ndarray) else float(x)

        return {
            "coefficients": self.coefficients.tolist(),
            "poles": [[float(p.real), float(p.imag)] for p in self.basis.poles],
            "initial_poles": [[float(p.real), float(p.imag)] for p in self.initial_basis.poles],
            "kind": self.kind,
            "ise": _num(self.ise),
            "fit_percent": _num(self.fit_percent),
            "n_evaluations": self.n_evaluations,
            "success": self.success,
            "message": self.message,
        }


class _Problem:
    """Variable-projection residual for a fixed block structure."""

    def __init__(self, kinds: tuple[str, ...], t: NDArray, H: NDArray, kind: str) -> None:
        self.kinds = kinds
        self.t = t
        self.kind = kind
        self.sw = np.sqrt(least_squares_weights(t))
        self.rhs = (H * self.sw).T  # (n, r)
        self.n_eval = 0

    def params(self, x: NDArray) -> NDArray:
        out = np.empty_like(x)
        col = 0
        for kind in self.kinds:
            out[col] = np.exp(x[col])
            if kind == PAIR:
                out[col + 1] = x[col + 1]
                col += 2
            else:
                col += 1
        return out

    def solve(self, x: NDArray) -> tuple[NDArray, NDArray]:
        self.n_eval += 1
        M = (_design_batch(self.kinds, self.params(x)[None], self.t, self.kind)[0] * self.sw).T
        c, *_ = np.linalg.lstsq(M, self.rhs, rcond=None)
        return c, self.rhs - M @ c

    def residual(self, x: NDArray) -> NDArray:
        return self.solve(x)[1].ravel()


def _to_x(kinds: tuple[str, ...], params: NDArray) -> NDArray:
    x = np.array(params, dtype=float)
    col = 0
    for kind in kinds:
        x[col] = np.log(params[col])
        col += 2 if kind == PAIR else 1
    return x


def _bounds(kinds: tuple[str, ...], t: NDArray) -> tuple[NDArray, NDArray]:
    span = t[-1] - t[0]
    dmin = float(np.min(np.diff(t)))
    rate_lo, rate_hi = 0.01 / span, 10.0 / dmin
    lo, hi = [], []
    for kind in kinds:
        lo.append(np.log(rate_lo))
        hi.append(np.log(rate_hi))
        if kind == PAIR:
            lo.append(0.0)
            hi.append(np.pi / dmin)
    return np.array(lo), np.array(hi)


def _prony_start(t: NDArray, H: NDArray, n: int, kind: str) -> tuple[tuple[str, ...], NDArray]:
    """Initial poles from linear prediction (Prony) on the (mean) impulse response."""
    step = uniform_step(t)
    if step is None:  # resample for the initial guess only
        tu = np.linspace(t[0], t[-1], t.size)
        H = np.array([np.interp(tu, t, row) for row in H])
        step = float(tu[1] - tu[0])
    sig = np.mean(H, axis=0)
    m = sig.size
    if m <= 2 * n + 1:
        raise DataError(f"{t.size} samples are too few to place {n} poles")
    rows = np.array([sig[k - n : k][::-1] for k in range(n, m)])
    if kind == "step":
        # a step response is a constant plus the modes: linear prediction with an offset term
        # (differencing the record instead would amplify its noise)
        rows = np.hstack([rows, np.ones((rows.shape[0], 1))])
    coef, *_ = np.linalg.lstsq(rows, sig[n:], rcond=None)
    a = coef[:n]
    z = np.roots(np.concatenate([[1.0], -a]))
    kinds: list[str] = []
    params: list[float] = []
    for zi in z:
        if abs(zi.imag) > 1e-9 * max(1.0, abs(zi)) and zi.imag < 0:
            continue
        mag = max(abs(zi), 1e-12)
        rate = -np.log(mag) / step
        if abs(zi.imag) > 1e-9 * max(1.0, abs(zi)):
            kinds.append(PAIR)
            params += [rate, abs(np.angle(zi)) / step]
        else:
            kinds.append(REAL)
            params.append(rate)
    return tuple(kinds), np.asarray(params)


def _candidate_starts(
    t: NDArray, H: NDArray, n: int, kind: str
) -> list[tuple[tuple[str, ...], NDArray]]:
    """A few starting structures: Prony's, all-real spread, and complex pairs."""
    sig = np.abs(np.mean(H, axis=0))
    if kind == "step":
        sig = np.abs(np.gradient(np.mean(H, axis=0), t))
    weight = np.sum(sig)
    centre = float(np.sum(t * sig) / weight - t[0]) if weight > 0 else (t[-1] - t[0]) / 4
    p0 = 1.0 / max(centre, (t[-1] - t[0]) / t.size)
    starts = []
    try:
        starts.append(_prony_start(t, H, n, kind))
    except (np.linalg.LinAlgError, DataError):
        pass
    spread = p0 * 2.0 ** (np.arange(n) - (n - 1) / 2)
    starts.append(((REAL,) * n, spread))
    if n >= 2:
        kinds = (PAIR,) * (n // 2) + ((REAL,) if n % 2 else ())
        params: list[float] = []
        for k in range(n // 2):
            params += [p0, p0 * (k + 1)]
        if n % 2:
            params.append(p0)
        starts.append((kinds, np.asarray(params)))
    return starts


def optimize_poles(
    t: ArrayLike,
    h: ArrayLike,
    init: int | ArrayLike | KautzBasis,
    *,
    kind: str = "impulse",
    max_iter: int = 100,
    tol: float = 1e-10,
    restart_collapsed: bool = False,
) -> PoleOptimization:
    r"""Choose basis poles that minimise the approximation error of one or many records.

    Variable projection: for fixed poles the coefficients of every record are
    the linear least-squares solution (weighted by Simpson's rule on the grid), so the error is a
    function of the poles alone; it is minimised by bounded nonlinear least
    squares (``scipy.optimize.least_squares``, trust-region reflective) over
    log-rates and imaginary parts, so every iterate is a stable basis.  All
    records share the poles and have their own coefficients.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Strictly increasing sample times.
    h : array-like of shape (n_samples,) or (n_records, n_samples)
        Impulse responses, or unit-step responses from rest.
    init : int, array-like of complex, or KautzBasis
        Starting poles (their real/pair structure is kept), or the number of
        basis functions: then several structures are tried (poles from Prony's
        linear prediction, spread real poles, complex pairs) and the best is kept.
    kind : {'impulse', 'step'}, default='impulse'
        What the records are.
    max_iter : int, default=100
        Iteration budget per start (residual evaluations are about
        ``max_iter * (n_params + 1)``).
    tol : float, default=1e-10
        ``ftol``, ``xtol`` and ``gtol`` of the solver.
    restart_collapsed : bool, default=False
        When the search stops at its budget without converging and a complex pair
        has collapsed onto the real axis (``|Im p| <= 0.05 |Re p|``: the optimum
        wants two equal real poles, which the pair parametrisation reaches only
        slowly), search once more from two real poles in its place and keep the
        better result (its ``n_evaluations`` counts both searches).  The
        command-line ``approx --optimize-poles`` turns this on.

    Returns
    -------
    PoleOptimization

    Raises
    ------
    DataError
        Bad data (NaN, lengths, non-increasing time, too few samples).
    PoleError
        Bad initial poles.

    Notes
    -----
    Rates are bounded to :math:`[0.01/T, 10/\Delta_{min}]` and imaginary parts
    to :math:`[0, \pi/\Delta_{min}]` (``T`` the record length): slower poles
    cannot be told apart on the record, faster ones not between two samples.

    Examples
    --------
    >>> import kautztwin as kt
    >>> from kautztwin.data import reference_response
    >>> t, h = reference_response(kind="impulse")
    >>> res = kt.optimize_poles(t, h, [-1.3, -3.9, -0.65 + 2.52j, -0.65 - 2.52j])
    >>> bool(res.fit_percent > 99.99)
    True
    """
    res = _search(t, h, init, kind, max_iter, tol)
    if not restart_collapsed or res.success:
        return res
    start = real_restart_poles(res.basis.poles)
    if start is None:
        return res
    again = _search(t, h, start, kind, max_iter, tol)
    if np.sum(again.ise) <= np.sum(res.ise) * (1 + 1e-9):
        return replace(again, n_evaluations=res.n_evaluations + again.n_evaluations,
                       initial_basis=res.initial_basis)
    return res


#: a complex pair with |Im p| at most this share of |Re p| is collapsing onto the real axis
COLLAPSING_PAIR = 0.05


def real_restart_poles(poles: ArrayLike) -> list[complex] | None:
    """Starting poles with every collapsing complex pair split into two real poles.

    Parameters
    ----------
    poles : array-like of complex
        Poles of a basis (conjugate pairs adjacent, as :attr:`KautzBasis.poles` lists them).

    Returns
    -------
    list of complex or None
        The poles with each pair whose ``|Im p| <= COLLAPSING_PAIR * |Re p|`` replaced by
        the two real poles ``Re p * (1 -+ COLLAPSING_PAIR)``; None when no pair collapses.

    Examples
    --------
    >>> real_restart_poles([-1 + 0.01j, -1 - 0.01j, -3])
    [(-1.05+0j), (-0.95+0j), (-3+0j)]
    >>> real_restart_poles([-1 + 1j, -1 - 1j]) is None
    True
    """
    out: list[complex] = []
    changed = False
    for p in np.asarray(poles, dtype=complex):
        if p.imag != 0 and abs(p.imag) <= COLLAPSING_PAIR * abs(p.real):
            out.append(complex(p.real * (1.0 + np.sign(p.imag) * COLLAPSING_PAIR)))
            changed = True
        else:
            out.append(complex(p))
    return out if changed else None


def _search(
    t: ArrayLike, h: ArrayLike, init: int | ArrayLike | KautzBasis, kind: str, max_iter: int,
    tol: float,
) -> PoleOptimization:
    """One variable-projection search of :func:`optimize_poles` (no restart)."""
    if kind not in ("impulse", "step"):
        raise DataError(f"kind must be 'impulse' or 'step', got {kind!r}")
    t = check_time(t, min_samples=5)
    h = check_records(h, t.size)
    H = np.atleast_2d(h)
    if isinstance(init, KautzBasis):
        if init.is_discrete:
            raise PoleError("optimize_poles works with continuous-time bases only")
        starts = [(init.block_kinds, np.array(init._params))]
    elif isinstance(init, (int, np.integer)) and not isinstance(init, bool):
        if init < 1:
            raise PoleError(f"the number of functions must be >= 1, got {init}")
        if 2 * init >= t.size:
            raise DataError(f"{t.size} samples are too few to place {init} poles")
        starts = _candidate_starts(t, H, int(init), kind)
    else:
        starts = [parse_poles(init, 0.0)]

    best = None
    total_eval = 0
    for kinds, params in starts:
        prob = _Problem(kinds, t, H, kind)
        lo, hi = _bounds(kinds, t)
        x0 = np.clip(_to_x(kinds, params), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
        sol = scipy.optimize.least_squares(
            prob.residual,
            x0,
            bounds=(lo, hi),
            method="trf",
            x_scale="jac",
            ftol=tol,
            xtol=tol,
            gtol=tol,
            max_nfev=max_iter * (x0.size + 1),
        )
        total_eval += prob.n_eval
        if best is None or sol.cost < best[0].cost:
            best = (sol, prob, kinds, params)
    sol, prob, kinds, params = best
    lo, hi = _bounds(kinds, t)
    at_bound = np.isclose(sol.x, lo, rtol=0, atol=1e-6) & (lo != 0)
    if np.any(at_bound):
        warnings.warn(
            "a basis pole ended at the slowest allowed rate (0.01 / record length): the record "
            "is too short to resolve it and it mimics an offset or drift; try fewer poles",
            ConvergenceWarning,
            stacklevel=3,
        )
    c, _ = prob.solve(sol.x)
    basis = KautzBasis._from_blocks(kinds, prob.params(sol.x))
    initial = KautzBasis._from_blocks(kinds, np.clip(params, np.exp(_bounds(kinds, t)[0][0]), None))
    C = c.T  # (r, N)
    P = basis.evaluate(t) if kind == "impulse" else basis.step_functions(t)
    Yhat = C @ P
    ise_r = np.asarray(ise(t, H, Yhat))
    fit_r = np.asarray(fit_percent(H, Yhat))
    single = h.ndim == 1
    return PoleOptimization(
        basis=basis,
        coefficients=C[0] if single else C,
        initial_basis=initial,
        kind=kind,
        ise=float(ise_r[0]) if single else ise_r,
        fit_percent=float(fit_r[0]) if single else fit_r,
        n_evaluations=total_eval,
        success=bool(sol.success),
        message=str(sol.message),
    )
