r"""Linear or nonlinear? The model class of ``kautztwin identify``'s default, by held-out fit.

:func:`choose_model_class` decides whether a nonlinear Kautz model validates clearly better
than the linear model already identified, on held-out blocks of the estimation record only.
It is built to cost little where the answer is "linear":

1. **Linear reference.**  The linear pick's poles (discretised, with its input delay in whole
   samples) define a linear Kautz output-error model whose coefficients are refitted by least
   squares on each fold's training samples (milliseconds); its held-out errors stand for the
   linear class.
2. **Screen** (a few seconds): one nonlinear candidate on the same folds, a Hammerstein
   model with a small MLP input map and 2 poles, trained briefly (100 iterations: its
   held-out fits on the benchmark data were within 1 point of 1 500 iterations).  Without
   torch the screen is a Kautz-Volterra series of degree 2 fitted by variable projection,
   its poles started from the linear pick's dominant poles as well as from an ARX fit
   (and nothing is refined).  Cheaper screens were tried and rejected:
   polynomial and tanh-basis Hammerstein / Wiener models fitted by variable projection
   extrapolate badly into held-out operating points and lost to the linear reference on
   the cascaded tanks; a polynomial NARX beats ARX in one-step prediction on none of the
   nonlinear benchmark plants.
3. **Refinement** (only when the screen's held-out error is below the linear reference's):
   Hammerstein and Wiener-Hammerstein models with MLP maps and 2 poles, fully trained, on
   the same folds (tens of seconds to minutes; the cost falls on nonlinear data only).

Decision (a one-standard-error rule between classes): the nonlinear class is chosen only if
the chosen nonlinear candidate's mean held-out squared error plus one standard error of its
fold errors is still below the linear reference's mean held-out error, so a nonlinear model
has to beat the linear one by more than the fold-to-fold noise.  Among the nonlinear
candidates the smallest one within one standard error of the best is kept (as in
:func:`~kautztwin.ident.nonlinear.identify_nonlinear`); its fold (and seed) models are
averaged.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..._validation import check_int, check_number
from ...exceptions import DataError, DimensionError
from ...metrics import fit_percent
from .filters import filter_bank_states, raw_from_poles, require_torch
from .model import NonlinearKautzEnsemble, check_signal
from .selection import (
    NonlinearFit,
    _candidate,
    _folds,
    _n_parameters,
    _one_standard_error,
)
from .training import TorchOptions

__all__ = ["ModelClassChoice", "choose_model_class", "dominant_poles"]

#: screen candidate with torch: (structure, map, degree, poles), trained with SCREEN_OPTIONS
SCREEN = (("hammerstein", "mlp", 2, 2),)
#: screen candidate without torch (variable projection)
SCREEN_NO_TORCH = (("volterra", "poly", 2, 2),)
#: brief training of the screen
SCREEN_OPTIONS = {"max_iter": 100, "patience": 30}
#: refinement candidates (torch, full training)
REFINE = (("hammerstein", "mlp", 2, 2), ("wiener-hammerstein", "mlp", 2, 2))
#: numerical resolution of the comparison: held-out MSE differences below this share of the
#: output variance are ties (a noise-free linear record fits both classes to rounding)
RESOLUTION = 1e-9
#: pole radius range of the linear reference (discretised continuous poles)
_R_MIN, _R_MAX = 1e-6, 0.999


@dataclass(frozen=True, eq=False)
class ModelClassChoice:
    """Result of :func:`choose_model_class`.

    Parameters
    ----------
    model_class : {'linear', 'nonlinear'}
        The class chosen.
    reason : str
        One sentence: the held-out fits that decided it.
    nonlinear : NonlinearFit or None
        The best nonlinear candidate's averaged fold models (``None`` if none was fitted).
    linear_cv_fit_percent : float
        Out-of-fold simulation fit of the linear reference, percent.
    candidates : list of dict
        Every candidate: class, structure, map, degree, n_poles, n_parameters, stage
        ('linear', 'screen', 'refine'), cv_fit_percent, cv_fold_mse, seconds, chosen.
    stages : list of str
        Stages that ran.
    seconds : float
        Wall-clock time of the choice.
    """

    model_class: str
    reason: str
    nonlinear: NonlinearFit | None
    linear_cv_fit_percent: float
    candidates: list[dict[str, Any]] = field(default_factory=list)
    stages: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (without the nonlinear model's parameters)."""
        return {"model_class": self.model_class, "reason": self.reason,
                "linear_cv_fit_percent": self.linear_cv_fit_percent,
                "candidates": self.candidates, "stages": self.stages,
                "seconds": self.seconds}


def dominant_poles(poles: ArrayLike, n_poles: int) -> np.ndarray:
    """The ``n_poles`` discrete poles nearest the unit circle, conjugate pairs kept together.

    Parameters
    ----------
    poles : array-like of complex
        Discrete poles (complex ones with their conjugates).
    n_poles : int
        How many to keep.

    Returns
    -------
    ndarray of complex
        At most ``n_poles`` poles by decreasing radius; a pair that would not fit is skipped.

    Examples
    --------
    >>> dominant_poles([0.5, 0.9j, -0.9j, 0.95], 3)
    array([0.95+0.j , 0.  +0.9j, 0.  -0.9j])
    """
    p = np.asarray(poles, dtype=complex).ravel()
    upper = sorted((z for z in p if z.imag >= -1e-12), key=lambda z: -abs(z))
    out: list[complex] = []
    for z in upper:
        block = [complex(z.real)] if abs(z.imag) <= 1e-12 else [z, z.conjugate()]
        if len(out) + len(block) <= n_poles:
            out += block
    return np.asarray(out, dtype=complex)


def _discrete(poles_s: np.ndarray, dt: float) -> np.ndarray:
    """Continuous poles to discrete ones ``exp(p dt)``, radii clipped into the disc."""
    z = np.exp(np.asarray(poles_s, dtype=complex) * dt)
    r = np.abs(z)
    z = np.where(r < _R_MIN, _R_MIN, z)
    return np.where(np.abs(z) > _R_MAX, z / np.abs(z) * _R_MAX, z)


def _linear_reference(us: np.ndarray, ys: np.ndarray, poles: np.ndarray, delay: int,
                      folds: list[np.ndarray]) -> tuple[float, list[float]]:
    """Out-of-fold fit and fold errors of a linear Kautz model on fixed poles (delayed input)."""
    ud = np.concatenate([np.full(delay, us[0]), us[: us.size - delay]]) if delay else us
    X = filter_bank_states(poles, ud, ud[0])
    Phi = np.column_stack([np.ones(us.size), X])
    oof = np.zeros_like(ys)
    for held in folds:
        A = Phi[~held]
        k = A.shape[1]
        scale = math.sqrt(1e-10 * max(float(np.trace(A.T @ A)) / k, 1e-300))
        theta, *_ = np.linalg.lstsq(np.vstack([A, scale * np.eye(k)]),
                                    np.concatenate([ys[~held], np.zeros(k)]), rcond=None)
        oof[held] = Phi[held] @ theta
    fold_mse = [float(np.mean((ys[h] - oof[h]) ** 2)) for h in folds]
    return float(fit_percent(ys, oof)), fold_mse


def _torch_available() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def _mean_se(fold_mse: list[float]) -> tuple[float, float]:
    e = np.asarray(fold_mse, dtype=float)
    m = float(np.mean(e))
    se = float(np.std(e, ddof=1) / math.sqrt(e.size)) if e.size > 1 else 0.0
    return m, se if math.isfinite(se) else math.inf


def choose_model_class(
    u: ArrayLike,
    y: ArrayLike,
    linear_poles: ArrayLike,
    *,
    dt: float = 1.0,
    delay: float = 0.0,
    n_folds: int = 6,
    n_seeds: int = 2,
    refine: bool | None = None,
    options: TorchOptions | None = None,
    max_iter: int = 100,
    random_state: int = 0,
) -> ModelClassChoice:
    r"""Choose between a linear model and a nonlinear Kautz model by block cross-validation.

    Parameters
    ----------
    u, y : array-like of shape (n_samples,)
        Estimation record (one input, one output), finite.
    linear_poles : array-like of complex
        Continuous-time poles of the linear model already identified on ``u, y``
        (the linear reference's poles and a warm start of the nonlinear candidates).
    dt : float, default=1.0
        Sampling period in seconds.
    delay : float, default=0.0
        Input delay of the linear model in seconds (the reference uses it rounded to
        whole samples).
    n_folds : int, default=6
        Contiguous cross-validation blocks (at least 2).
    n_seeds : int, default=2
        Seeds of a chosen MLP candidate (the selection uses one).
    refine : bool or None, default=None
        Use the MLP candidates (screen and refinement): ``None`` when torch is installed,
        ``False`` never (the screen is then the Volterra series and nothing is refined),
        ``True`` always (``ImportError`` without torch).
    options : TorchOptions, optional
        Training options of the MLP candidates.
    max_iter : int, default=100
        Iterations of the variable-projection searches.
    random_state : int, default=0
        Seeds the MLP candidates.

    Returns
    -------
    ModelClassChoice

    Raises
    ------
    DimensionError
        If ``u`` and ``y`` are not 1-D of one length.
    DataError
        If a signal is not finite, the input or output is constant, or the record is too
        short for ``n_folds`` blocks.

    See Also
    --------
    identify_nonlinear : The nonlinear structures and their cross-validation.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.nonlinear import filter_bank_states
    >>> rng = np.random.default_rng(0)
    >>> u = np.repeat(rng.uniform(-1, 1, 60), 10)
    >>> x = filter_bank_states([0.9], u, u[0])[:, 0]
    >>> y_lin = x + 0.02 * rng.normal(size=600)
    >>> choose_model_class(u, y_lin, [np.log(0.9)], refine=False).model_class
    'linear'
    >>> ch = choose_model_class(u, x + 0.8 * x**2, [np.log(0.9)], refine=False)
    >>> ch.model_class, ch.nonlinear.structure
    ('nonlinear', 'volterra')
    """
    t0 = time.perf_counter()
    u = check_signal(u, "u")
    y = check_signal(y, "y")
    if u.size != y.size:
        raise DimensionError(f"u and y must have one length, got {u.size} and {y.size} samples")
    dt = check_number(dt, "dt")
    n_folds = check_int(n_folds, "n_folds", 2)
    n_seeds = check_int(n_seeds, "n_seeds", 1)
    u_scale, y_scale = float(np.std(u)), float(np.std(y))
    if u_scale <= 1e-12 * max(1.0, float(np.abs(u).max())):
        raise DataError("u is constant: a constant input carries no information on the dynamics")
    if y_scale == 0:
        raise DataError("y is constant: nothing to fit")
    if u.size // n_folds < 10:
        raise DataError(f"{u.size} samples are too few for {n_folds} folds of 10 samples")
    zpoles = _discrete(np.asarray(linear_poles, dtype=complex).ravel(), dt)
    raw_from_poles(zpoles)  # validates
    n_delay = min(max(int(round(check_number(delay, "delay") / dt)), 0), u.size // 4)
    stats = (float(np.mean(u)), u_scale, float(np.mean(y)), y_scale)
    us, ys = (u - stats[0]) / stats[1], (y - stats[2]) / stats[3]
    folds = _folds(u.size, n_folds)
    options = options or TorchOptions()

    t1 = time.perf_counter()
    lin_fit, lin_mse = _linear_reference(us, ys, zpoles, n_delay, folds)
    table: list[dict[str, Any]] = [{
        "class": "linear", "structure": "linear", "map": "linear", "degree": 1,
        "n_poles": int(zpoles.size), "n_parameters": int(zpoles.size) + 1, "stage": "linear",
        "cv_fit_percent": lin_fit, "cv_fold_mse": lin_mse,
        "seconds": time.perf_counter() - t1}]
    fitted: list[list[Any] | None] = [None]
    stages = ["linear", "screen"]

    def run(cands: tuple[tuple[str, str, int, int], ...], stage: str,
            opts: TorchOptions) -> None:
        for structure, mk, degree, k in cands:
            t2 = time.perf_counter()
            warm = dominant_poles(zpoles, k)
            init = warm if warm.size == k else None
            best: tuple[list[Any], float, list[float]] | None = None
            starts = [None, init] if (init is not None and mk != "mlp") else [None]
            for start in starts:  # ARX/grid start, and the linear pick's dominant poles
                res = _candidate(structure, mk, degree, k, us, ys, folds, [random_state],
                                 stats, dt, opts, max_iter, start)
                if best is None or np.mean(res[2]) < np.mean(best[2]):
                    best = res
            assert best is not None
            models, score, fold_mse = best
            table.append({
                "class": "nonlinear", "structure": structure, "map": mk, "degree": degree,
                "n_poles": k, "n_parameters": _n_parameters(structure, mk, degree, k, options),
                "stage": stage, "cv_fit_percent": score, "cv_fold_mse": fold_mse,
                "seconds": time.perf_counter() - t2})
            fitted.append(models)

    use_torch = refine is True or (refine is None and _torch_available())
    if use_torch:
        require_torch()
        quick = replace(options, **{k: min(v, getattr(options, k))
                                    for k, v in SCREEN_OPTIONS.items()})
        run(SCREEN, "screen", quick)
    else:
        run(SCREEN_NO_TORCH, "screen", options)
    lin_mean = _mean_se(lin_mse)[0] - RESOLUTION
    nl_rows = list(range(1, len(table)))
    if use_torch and np.mean(table[1]["cv_fold_mse"]) < lin_mean:
        stages.append("refine")
        run(REFINE, "refine", options)
        nl_rows = list(range(2, len(table)))  # the screen model is a draft of the first
    pick = nl_rows[_one_standard_error([table[i] for i in nl_rows])]
    m, se = _mean_se(table[pick]["cv_fold_mse"])
    if not m + se < lin_mean:
        pick = None
    keep = nl_rows[_one_standard_error([table[i] for i in nl_rows])] if pick is None else pick
    for i, row in enumerate(table):
        row["chosen"] = i == (0 if pick is None else pick)
    row = table[keep]
    models = fitted[keep]
    assert models is not None
    if row["map"] == "mlp" and n_seeds > 1 and pick is not None:
        more, *_ = _candidate(row["structure"], "mlp", row["degree"], row["n_poles"], us, ys,
                              folds, [random_state + s for s in range(1, n_seeds)], stats, dt,
                              options, max_iter, None)
        models = models + more
    ens = NonlinearKautzEnsemble(tuple(models))
    fit = float(fit_percent(y, ens.simulate(u)))
    ens = NonlinearKautzEnsemble(ens.members, fit)
    nl_fit = NonlinearFit(ens, row["structure"], row["map"], row["n_poles"],
                          row["cv_fit_percent"], fit,
                          [r for r in table if r["class"] == "nonlinear"],
                          time.perf_counter() - t0)
    m, se = _mean_se(row["cv_fold_mse"])
    name = f"{row['structure']} ({row['map']}, {row['n_poles']} poles)"
    if pick is None:
        reason = (f"linear: held-out fit {lin_fit:.1f} %; the best nonlinear candidate, "
                  f"{name}, {row['cv_fit_percent']:.1f} %, is not better by more than one "
                  f"standard error (held-out MSE {m:.4g} + {se:.2g} vs {lin_mean:.4g})")
    else:
        reason = (f"nonlinear: {name} held-out fit {row['cv_fit_percent']:.1f} % vs linear "
                  f"{lin_fit:.1f} % (held-out MSE {m:.4g} + one standard error {se:.2g} "
                  f"< {lin_mean:.4g})")
    return ModelClassChoice("linear" if pick is None else "nonlinear", reason, nl_fit, lin_fit,
                            table, stages, time.perf_counter() - t0)
