r"""Nonlinear Kautz identification with structure/order selection by block cross-validation.

:func:`identify_nonlinear` is the one entry point: it fits Wiener, Hammerstein,
Wiener-Hammerstein or Kautz-Volterra models, or (``model='auto'``) chooses among them and
among pole counts, and returns the average of the fold models.

Block cross-validation: the estimation record is cut into ``n_folds`` contiguous blocks.
Each fold model simulates the *whole* record (the input is known everywhere) but is fitted to
the outputs outside its block only; its block scores it (and stops its training early).  The
concatenated held-out simulations give one out-of-fold fit per candidate.  The structure and
order are chosen by the one-standard-error rule: the candidate with the fewest parameters
whose mean held-out error is within one standard error (over the folds) of the best one's,
so a bigger model has to beat a smaller one by more than the fold-to-fold noise.  (A tail
hold-out would score only the end of the record, which on real plants often holds operating
points never seen before.)  The chosen
candidate's fold models (over ``n_seeds`` seeds for the MLP structures) are averaged:
single models of these small data sets vary by several fit points, their average does not.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_choice, check_int
from ...exceptions import DataError, DimensionError
from ...metrics import fit_percent
from .filters import raw_from_poles, require_torch
from .model import NonlinearKautzEnsemble, check_signal
from .starts import start_poles
from .training import TorchOptions, fit_torch
from .varpro import fit_varpro

__all__ = ["NonlinearFit", "identify_nonlinear"]

MODELS = ("wiener", "hammerstein", "wiener-hammerstein", "volterra", "auto")
#: candidates of model='auto': (structure, map)
AUTO_CANDIDATES = (("hammerstein", "mlp"), ("wiener-hammerstein", "mlp"), ("wiener", "mlp"),
                   ("volterra", "poly"))


@dataclass(frozen=True, eq=False)
class NonlinearFit:
    """Result of :func:`identify_nonlinear`.

    Parameters
    ----------
    model : NonlinearKautzEnsemble
        The average of the chosen candidate's fold (and seed) models; its ``simulate``
        gives the free-run output.
    structure : str
        Chosen structure.
    map : {'mlp', 'poly'}
        Kind of static map.
    n_poles : int
        Chosen number of poles.
    cv_fit_percent : float
        Out-of-fold simulation fit of the chosen candidate on the estimation record, percent.
    fit_percent : float
        Simulation fit of the averaged model on the estimation record, percent.
    candidates : list of dict
        Every candidate tried: structure, map, n_poles, n_parameters, cv_fit_percent,
        cv_fold_mse (held-out mean squared error per fold, standardised output), seconds,
        chosen.
    seconds : float
        Wall-clock time of the whole identification.
    """

    model: NonlinearKautzEnsemble
    structure: str
    map: str
    n_poles: int
    cv_fit_percent: float
    fit_percent: float
    candidates: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    def simulate(self, u: ArrayLike, level: float | None = None) -> NDArray[np.float64]:
        """Free-run simulation of the averaged model (:meth:`NonlinearKautzEnsemble.simulate`)."""
        return self.model.simulate(u, level)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary with the model."""
        return {"structure": self.structure, "map": self.map, "n_poles": self.n_poles,
                "cv_fit_percent": self.cv_fit_percent, "fit_percent": self.fit_percent,
                "candidates": self.candidates, "seconds": self.seconds,
                "model": self.model.to_dict()}


def _folds(n: int, n_folds: int) -> list[NDArray]:
    edges = np.linspace(0, n, n_folds + 1).round().astype(int)
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        m = np.zeros(n, dtype=bool)
        m[a:b] = True
        out.append(m)
    return out


def _fit_one(structure: str, map_kind: str, degree: int, n_poles: int, us: NDArray,
             ys: NDArray, train: NDArray, val: NDArray, stats: tuple[float, ...], dt: float,
             seed: int, options: TorchOptions, max_iter: int,
             init: NDArray | None = None) -> tuple[Any, float]:
    """One model on one fold: (model, held-out mse)."""
    start = start_poles(us, ys, n_poles, train) if init is None else init
    kinds, raw0 = raw_from_poles(start)
    level0 = float(us[0])
    if map_kind in ("poly", "tanh"):
        res = fit_varpro(structure, degree, kinds, raw0, us, ys, train, val, level0=level0,
                         stats=stats, dt=dt, max_iter=max_iter,
                         n_centres=degree if map_kind == "tanh" else 0)
        return res.model, res.val_mse
    res = fit_torch(structure, kinds, raw0, us, ys, train, val, level0=level0, stats=stats,
                    dt=dt, seed=seed, options=options)
    return res.model, res.val_mse


def _candidate(structure: str, map_kind: str, degree: int, n_poles: int, us: NDArray,
               ys: NDArray, folds: list[NDArray], seeds: list[int], stats: tuple[float, ...],
               dt: float, options: TorchOptions, max_iter: int,
               init: NDArray | None = None) -> tuple[list[Any], float, list[float]]:
    """Fold models of one candidate over the seeds, its out-of-fold fit (percent) and the
    mean squared out-of-fold error of each fold (standardised output)."""
    models = []
    oof = np.zeros((len(seeds), ys.size))
    for s, seed in enumerate(seeds):
        for k, held in enumerate(folds):
            train = ~held if len(folds) > 1 else held
            val = held if len(folds) > 1 else np.zeros_like(held)
            model, _ = _fit_one(structure, map_kind, degree, n_poles, us, ys, train, val, stats,
                                dt, seed + 1000 * k, options, max_iter, init)
            models.append(model)
            sim = (model.simulate(stats[0] + stats[1] * us) - stats[2]) / stats[3]
            oof[s, held] = sim[held]
    oof_mean = oof.mean(axis=0)
    score = float(fit_percent(ys, oof_mean)) if len(folds) > 1 else math.nan
    fold_mse = [float(np.mean((ys[h] - oof_mean[h]) ** 2)) for h in folds]
    fold_mse = [m if math.isfinite(m) else math.inf for m in fold_mse]
    return models, score if math.isfinite(score) else -math.inf, fold_mse


def identify_nonlinear(
    u: ArrayLike,
    y: ArrayLike,
    *,
    model: str = "auto",
    n_poles: int | list[int] | str = "auto",
    map: str = "mlp",
    degree: int = 2,
    dt: float = 1.0,
    n_folds: int = 6,
    n_seeds: int = 2,
    options: TorchOptions | None = None,
    max_iter: int = 100,
    random_state: int = 0,
    init_poles: ArrayLike | None = None,
) -> NonlinearFit:
    r"""Identify a nonlinear Kautz model from one input/output record (free-run simulation).

    Parameters
    ----------
    u, y : array-like of shape (n_samples,)
        Estimation record, finite, equal lengths.
    model : {'auto', 'wiener', 'hammerstein', 'wiener-hammerstein', 'volterra'}, default='auto'
        Structure; ``'auto'`` chooses among Hammerstein, Wiener-Hammerstein and Wiener (MLP
        maps) and Kautz-Volterra (``degree``) by block cross-validation (the smallest
        candidate within one standard error of the best).
    n_poles : int, list of int or 'auto', default='auto'
        Poles of the Kautz bank; a list (or ``'auto'``: ``[2, 4]``) is searched by
        cross-validation.
    map : {'mlp', 'poly', 'tanh'}, default='mlp'
        Static map of Wiener / Hammerstein: a small MLP (trained in torch) or a polynomial of
        ``degree`` (variable projection, no torch); ``'tanh'`` (Hammerstein only, variable
        projection): ``degree`` fixed tanh functions of the input centred at its quantiles
        drive the bank beside ``u``.  Volterra is always polynomial, Wiener-Hammerstein
        always MLP.
    degree : int, default=2
        Polynomial degree (with ``map='tanh'``: the number of tanh functions).
    dt : float, default=1.0
        Sampling period (stored in the model).
    n_folds : int, default=6
        Contiguous cross-validation blocks (``1``: one model on all samples, no selection).
    n_seeds : int, default=2
        Seeds of the MLP models of the chosen candidate (the selection uses one).
    options : TorchOptions, optional
        Training options of the MLP models.
    max_iter : int, default=100
        Iterations of the variable-projection search.
    random_state : int, default=0
        Seeds everything (deterministic for a given value).
    init_poles : array-like of complex, optional
        Starting discrete poles (their count replaces ``n_poles``); by default each fold
        starts from the best of an ARX fit and a small grid of pairs (linear output error).

    Returns
    -------
    NonlinearFit

    Raises
    ------
    DimensionError
        If ``u`` and ``y`` are not 1-D of one length.
    DataError
        If a signal holds NaN/inf, the input is constant, or the record is too short for
        the order and folds asked.
    ImportError
        If an MLP structure is asked and torch is not installed.

    See Also
    --------
    NonlinearKautzEnsemble.with_fitted_level : The initial state of a new record from its
        first outputs.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident.nonlinear import filter_bank_states, identify_nonlinear
    >>> rng = np.random.default_rng(0)
    >>> u = rng.normal(size=300)
    >>> x = filter_bank_states([0.7], u)[:, 0]
    >>> fit = identify_nonlinear(u, x + 0.2 * x**2, model="volterra", n_poles=1, n_folds=1)
    >>> bool(fit.fit_percent > 99.99), np.round(fit.model.members[0].poles.real, 6)
    (True, array([0.7]))
    """
    t0 = time.perf_counter()
    u = check_signal(u, "u")
    y = check_signal(y, "y")
    if u.size != y.size:
        raise DimensionError(f"u and y must have one length, got {u.size} and {y.size} samples")
    model = check_choice(model, "model", MODELS)
    map_kind = check_choice(map, "map", ("mlp", "poly", "tanh"))
    if map_kind == "tanh" and model not in ("hammerstein", "auto"):
        raise DataError(f"map='tanh' is an input map: it needs model='hammerstein', "
                        f"got {model!r}")
    degree = check_int(degree, "degree", 1)
    n_folds = check_int(n_folds, "n_folds", 1)
    n_seeds = check_int(n_seeds, "n_seeds", 1)
    if isinstance(n_poles, str):
        if n_poles != "auto":
            raise DataError(
                f"n_poles must be a positive integer, a list or 'auto', got {n_poles!r}")
        orders = [2, 4]
    elif isinstance(n_poles, int | np.integer):
        orders = [check_int(n_poles, "n_poles", 1)]
    else:
        orders = [check_int(k, "n_poles", 1) for k in n_poles]
        if not orders:
            raise DataError("n_poles is an empty list")
    init = None
    if init_poles is not None:
        init = np.asarray(init_poles, dtype=complex).ravel()
        raw_from_poles(init)  # validates
        orders = [init.size]
    u_scale, y_scale = float(np.std(u)), float(np.std(y))
    if u_scale <= 1e-12 * max(1.0, float(np.abs(u).max())):
        raise DataError("u is constant: a constant input carries no information on the dynamics")
    if y_scale == 0:
        raise DataError("y is constant: nothing to fit")
    if model == "auto":
        cands = [c for c in AUTO_CANDIDATES]
    elif model == "volterra":
        cands = [("volterra", "poly")]
    elif model == "wiener-hammerstein":
        cands = [("wiener-hammerstein", "mlp")]
    else:
        cands = [(model, map_kind)]
    n_block = u.size // n_folds
    n_train = u.size - n_block if n_folds > 1 else u.size
    if n_block < 2 * max(orders) + 1:
        raise DataError(f"{u.size} samples are too few for {n_folds} folds of at least "
                        f"{2 * max(orders) + 1} samples ({max(orders)} poles)")
    sizes = {(s, m, k): _n_parameters(s, m, degree, k, options) for s, m in cands for k in orders}
    runs = [(s, m, k) for s, m in cands for k in orders if n_train > sizes[(s, m, k)]]
    if not runs:
        n_min = min(sizes.values())
        raise DataError(
            f"{u.size} samples are too few for {min(orders)} poles and {n_min} parameters "
            f"with {n_folds} folds (need more than {n_min} samples to fit on)"
        )
    if any(m == "mlp" for _, m, _ in runs):
        require_torch()
    options = options or TorchOptions()
    stats = (float(np.mean(u)), u_scale, float(np.mean(y)), y_scale)
    us, ys = (u - stats[0]) / stats[1], (y - stats[2]) / stats[3]
    folds = _folds(u.size, n_folds)
    table: list[dict[str, Any]] = []
    fitted = []
    for structure, mk, k in runs:
        t1 = time.perf_counter()
        models, score, fold_mse = _candidate(structure, mk, degree, k, us, ys, folds,
                                             [random_state], stats, dt, options, max_iter, init)
        table.append({"structure": structure, "map": mk, "n_poles": k,
                      "n_parameters": sizes[(structure, mk, k)], "cv_fit_percent": score,
                      "cv_fold_mse": fold_mse, "seconds": time.perf_counter() - t1})
        fitted.append(models)
    pick = _one_standard_error(table)
    for i, row in enumerate(table):
        row["chosen"] = i == pick
    structure, mk, k = table[pick]["structure"], table[pick]["map"], table[pick]["n_poles"]
    models, score = fitted[pick], table[pick]["cv_fit_percent"]
    if mk == "mlp" and n_seeds > 1:
        more, *_ = _candidate(structure, mk, degree, k, us, ys, folds,
                                  [random_state + s for s in range(1, n_seeds)], stats, dt,
                                  options, max_iter, init)
        models = models + more
    ens = NonlinearKautzEnsemble(tuple(models))
    fit = float(fit_percent(y, ens.simulate(u)))
    ens = NonlinearKautzEnsemble(ens.members, fit)
    return NonlinearFit(ens, structure, mk, k, score, fit, table, time.perf_counter() - t0)


def _one_standard_error(table: list[dict[str, Any]]) -> int:
    """Index of the smallest candidate whose CV error is within one standard error of the best.

    The errors are the per-fold out-of-fold mean squared errors; the standard error is that of
    the best candidate's mean over the folds (Breiman's one-standard-error rule).  Ties in size
    go to the better CV fit.  With one fold (no CV) the only candidate is returned.
    """
    means = [float(np.mean(r["cv_fold_mse"])) for r in table]
    best = int(np.argmin(means))
    errs = np.asarray(table[best]["cv_fold_mse"])
    se = float(np.std(errs, ddof=1) / math.sqrt(errs.size)) if errs.size > 1 else 0.0
    if not math.isfinite(se):
        se = 0.0
    ok = [i for i, m in enumerate(means) if m <= means[best] + se]
    return min(ok, key=lambda i: (table[i]["n_parameters"], -table[i]["cv_fit_percent"]))


def _n_parameters(structure: str, map_kind: str, degree: int, n_poles: int,
                  options: TorchOptions | None) -> int:
    """Number of parameters of one candidate (for the too-short-record check)."""
    o = options or TorchOptions()
    if structure == "volterra":
        return n_poles + 1 + math.comb(n_poles + degree, degree)
    if map_kind == "tanh":  # degree tanh channels beside u
        return n_poles + 1 + 1 + (degree + 1) * n_poles
    if map_kind == "poly":
        if structure == "hammerstein":
            return n_poles + 1 + 1 + degree * n_poles
        return 2 * n_poles + 1 + degree + 1
    n_ch = 1 + (o.n_input_channels if structure != "wiener" else 0)
    n = n_poles + 1
    if structure != "wiener":
        n += 3 * o.n_input_hidden + o.n_input_channels * (o.n_input_hidden + 1)
    if structure == "hammerstein":
        return n + n_ch * n_poles + 1
    return n + o.n_hidden * (n_ch * n_poles + 2) + 1
