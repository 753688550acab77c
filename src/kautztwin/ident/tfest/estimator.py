"""The estimator of the transfer-function package: parameters, order selection, prediction."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..._validation import check_choice
from ...exceptions import DataError, KautzTwinError, NotFittedError
from ..records import MIN_SAMPLES, Record
from ..simulate import INTERSAMPLE
from .integrator import fit_integrating
from .problem import _pooled_fit, _Problem
from .refine import fit_order
from .statistics import nuisance
from .structure import search_structure

__all__ = ["TransferFunctionEstimator"]

_INITIAL_STATE = ("auto", "zero", "estimate")


class TransferFunctionEstimator:
    r"""Estimate a continuous-time transfer function from step, impulse or input/output records.

    The continuous-time counterpart of MATLAB's ``tfest``: chosen numbers of
    poles and zeros (or automatic order selection), an optional input delay,
    several records fitted together (each with its own offset and, for
    input/output records, initial state), exact simulation of sampled inputs,
    stability guaranteed, and parameter covariances.  The method is described
    in the module docstring and ``docs/identification.md``.

    Parameters
    ----------
    n_poles : int or 'auto', default=2
        Number of poles, or ``'auto'`` to search the structure (orders 1 to
        the bound, zeros, delay) by :mod:`~kautztwin.ident.tfest.structure`:
        cheap screening of every order, output-error refinement of the best
        few, chosen by the validation fit when ``validate_from`` leaves
        validation data, else by the fit on held-out data of the estimation
        records (the last third of each record, or each record in turn when
        several records start at rest).
    n_zeros : int, optional
        Number of zeros (at most ``n_poles``); ``n_poles - 1`` when omitted,
        as in ``tfest``.  With ``n_poles='auto'``: searched from 0 to ``n - 1``
        when omitted, else fixed (capped at ``n - 1``).
    delay : bool or float, default=False
        ``False``: no delay.  ``True``: estimate the input delay.  A number:
        a fixed delay in seconds.
    kind : {'io', 'step', 'impulse'}, optional
        What ``(t, u, y)`` tuples passed to :meth:`fit` are.  When given,
        :class:`Record` objects must be of this kind.
    intersample : {'zoh', 'foh'}, default='zoh'
        Input between samples of ``'io'`` records: held (zero-order hold) or
        linearly interpolated (first-order hold).  Step and impulse records are
        ideal steps and impulses either way.
    initial_state : {'auto', 'zero', 'estimate'}, default='auto'
        Whether to estimate each record's initial state (``'auto'``: for
        ``'io'`` records; step and impulse records start at rest).
    offset : bool, default=True
        Estimate one output offset per record.
    validate_from : float, optional
        Samples at ``t >= validate_from`` are held out of the estimation; the
        model is simulated over the whole record and scored on them.
    max_order : int, optional
        Largest order tried by ``n_poles='auto'``.  When omitted, the bound
        the data support: 10, plus one per 100 estimation samples beyond
        1000 (at most 20); either way lowered until the estimation samples
        are three times the parameters.  A pick at the bound warns
        (``ConvergenceWarning``).
    max_iter : int, default=100
        Iteration budget of each refinement (residual evaluations are about
        ``max_iter * (n_params + 1)``).
    tol : float, default=1e-10
        ``ftol``, ``xtol`` and ``gtol`` of the refinement.
    integrator : bool, optional
        A pole at :math:`s = 0` (an integrating plant: a level fed by a flow, a
        position driven by a velocity), fitted as ``G(s)/s`` with ``G`` stable
        (:mod:`~kautztwin.ident.tfest.integrator`; held input/output records
        only).  ``True``: always (``n_poles`` counts the integrator);
        ``False``: never.  ``None`` (default): never for a given ``n_poles``;
        with ``n_poles='auto'`` the integrating structures are searched too
        when the data show a mode slower than the records, and chosen only if
        their criterion is better.  The model then acts on
        ``u - model_.input_level``.
    n_restarts : int, default=0
        Extra refinements from randomly perturbed copies of the best start.
    random_state : int or numpy.random.Generator, optional
        Seed of those perturbations (the only randomness).

    Attributes
    ----------
    model_ : TransferFunctionModel
        The estimated model and its statistics.
    n_poles_, n_zeros_ : int
        The order fitted (chosen, with ``'auto'``).
    records_ : list of Record
        The records the model was fitted to.
    n_evaluations_ : int
        Residual evaluations spent (all starts and orders).
    search_ : dict
        With ``n_poles='auto'``: the bound and its rule, the criterion, the
        number of candidates, the refined structures and the search time.

    See Also
    --------
    kautztwin.optimize_poles : The Kautz-basis pole optimisation used to initialise.
    kautztwin.ident.ARXEstimator : Discrete-time least-squares baseline.
    kautztwin.ident.simulate_lti : Exact simulation of continuous models with sampled inputs.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import Record, TransferFunctionEstimator, step_response
    >>> t = np.linspace(0, 10, 201)
    >>> y = 3.0 + 2.0 * step_response(([2.0], [1.0, 3.0, 2.0]), t)   # offset 3, step 2
    >>> est = TransferFunctionEstimator(n_poles=2, n_zeros=0)
    >>> model = est.fit(Record.step_response(t, y, amplitude=2.0)).model_
    >>> np.round(model.den, 6), round(model.gain, 6), round(model.fit_percent, 3)
    (array([1., 3., 2.]), 1.0, 100.0)
    """

    def __init__(
        self,
        n_poles: int | str = 2,
        n_zeros: int | None = None,
        *,
        delay: bool | float = False,
        kind: str | None = None,
        intersample: str = "zoh",
        initial_state: str = "auto",
        offset: bool = True,
        validate_from: float | None = None,
        max_order: int | None = None,
        max_iter: int = 100,
        tol: float = 1e-10,
        integrator: bool | None = None,
        n_restarts: int = 0,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.n_poles = n_poles
        self.n_zeros = n_zeros
        self.delay = delay
        self.kind = kind
        self.intersample = intersample
        self.initial_state = initial_state
        self.offset = offset
        self.validate_from = validate_from
        self.max_order = max_order
        self.max_iter = max_iter
        self.tol = tol
        self.integrator = integrator
        self.n_restarts = n_restarts
        self.random_state = random_state

    # ------------------------------------------------------------------ sklearn plumbing
    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Constructor parameters (scikit-learn protocol).

        Parameters
        ----------
        deep : bool, default=True
            Unused (no nested estimators).

        Returns
        -------
        dict
        """
        names = ("n_poles", "n_zeros", "delay", "kind", "intersample", "initial_state", "offset",
                 "validate_from", "max_order", "max_iter", "tol", "integrator", "n_restarts",
                 "random_state")
        return {k: getattr(self, k) for k in names}

    def set_params(self, **params: Any) -> TransferFunctionEstimator:
        """Set constructor parameters (scikit-learn protocol).

        Parameters
        ----------
        **params
            New values of constructor parameters.

        Returns
        -------
        self
        """
        valid = self.get_params()
        for k, v in params.items():
            if k not in valid:
                raise ValueError(f"unknown parameter {k!r}; valid: {', '.join(valid)}")
            setattr(self, k, v)
        return self

    def __repr__(self) -> str:
        return f"TransferFunctionEstimator(n_poles={self.n_poles!r}, n_zeros={self.n_zeros!r})"

    # ------------------------------------------------------------------ validation
    def _records(self, records: Any) -> list[Record]:
        if isinstance(records, Record):
            records = [records]
        elif isinstance(records, tuple) and len(records) == 3 and not isinstance(records[0],
                                                                                  Record):
            records = [records]
        if not isinstance(records, Sequence) or len(records) == 0:
            raise DataError("records must be a Record, a (t, u, y) tuple, or a non-empty list "
                            "of them")
        out = []
        for i, r in enumerate(records):
            if isinstance(r, Record):
                if self.kind is not None and r.kind != self.kind:
                    raise DataError(f"records[{i}] is a {r.kind!r} record but kind={self.kind!r}")
                out.append(r)
            elif isinstance(r, (tuple, list)) and len(r) == 3:
                out.append(Record.from_data(*r, kind=self.kind or "io", name=f"record {i}"))
            else:
                raise DataError(f"records[{i}] must be a Record or a (t, u, y) tuple; got "
                                f"{type(r).__name__}")
        return out

    def _check_params(self) -> None:
        check_choice(self.intersample, "intersample", INTERSAMPLE)
        check_choice(self.initial_state, "initial_state", _INITIAL_STATE)
        if isinstance(self.n_poles, str):
            if self.n_poles != "auto":
                raise DataError(f"n_poles must be a positive integer or 'auto'; got "
                                f"{self.n_poles!r}")
            if self.max_order is not None and (
                    not isinstance(self.max_order, (int, np.integer))
                    or isinstance(self.max_order, bool) or self.max_order < 1):
                raise DataError(f"max_order must be an integer >= 1 or None; got "
                                f"{self.max_order!r}")
        elif (not isinstance(self.n_poles, (int, np.integer)) or isinstance(self.n_poles, bool)
              or self.n_poles < 1):
            raise DataError(f"n_poles must be a positive integer or 'auto'; got {self.n_poles!r}")
        if self.n_zeros is not None:
            if (not isinstance(self.n_zeros, (int, np.integer)) or isinstance(self.n_zeros, bool)
                    or self.n_zeros < 0):
                raise DataError(f"n_zeros must be an integer >= 0; got {self.n_zeros!r}")
            if not isinstance(self.n_poles, str) and self.n_zeros > self.n_poles:
                raise DataError(f"n_zeros = {self.n_zeros} exceeds n_poles = {self.n_poles}: "
                                "the model would be improper")
        if not isinstance(self.delay, bool):
            try:
                d = float(self.delay)
            except (TypeError, ValueError):
                raise DataError(f"delay must be True, False or a number >= 0; got "
                                f"{self.delay!r}") from None
            if not (np.isfinite(d) and d >= 0):
                raise DataError(f"delay must be True, False or a number >= 0; got {self.delay!r}")
        if self.validate_from is not None and not np.isfinite(float(self.validate_from)):
            raise DataError(f"validate_from must be a finite time; got {self.validate_from!r}")
        if not isinstance(self.max_iter, (int, np.integer)) or self.max_iter < 1:
            raise DataError(f"max_iter must be an integer >= 1; got {self.max_iter!r}")
        if not (np.isfinite(self.tol) and self.tol > 0):
            raise DataError(f"tol must be > 0; got {self.tol!r}")
        if self.integrator not in (None, True, False):
            raise DataError(f"integrator must be True, False or None; got {self.integrator!r}")

    def _split(self, records: list[Record]) -> tuple[list[Record], list[int]]:
        """Estimation parts of the records (``t < validate_from``) and their indices."""
        if self.validate_from is None:
            return records, list(range(len(records)))
        T = float(self.validate_from)
        est, idx = [], []
        for i, r in enumerate(records):
            mask = r.t < T
            if mask.sum() < MIN_SAMPLES:
                continue
            if r.kind != "io" and not r.start < T:
                continue
            try:
                est.append(r.select(mask))
            except KautzTwinError:
                continue
            idx.append(i)
        if not est:
            raise DataError(
                f"validate_from = {T:g} leaves no record with at least {MIN_SAMPLES} estimation "
                "samples (and its step or impulse) before it"
            )
        return est, idx

    # ------------------------------------------------------------------ fitting
    def fit(self, records: Any) -> TransferFunctionEstimator:
        """Estimate the transfer function from one or many records.

        Parameters
        ----------
        records : Record, (t, u, y) tuple, or list of them
            The experiments, fitted together.  Tuples are read with
            :meth:`Record.from_data` and this estimator's ``kind``.

        Returns
        -------
        self

        Raises
        ------
        DataError
            On invalid parameters, unusable records (NaN, constant input, ...),
            or fewer samples than parameters.
        DimensionError
            On records that are too short.
        """
        self._check_params()
        recs = self._records(records)
        if len({r.kind for r in recs}) > 1 and any(r.kind == "impulse" for r in recs):
            raise DataError("impulse records cannot be mixed with other kinds in one fit")
        if self.initial_state == "estimate":
            for r in recs:
                if r.kind != "io" and r.start is not None and r.start <= r.t[0]:
                    raise DataError(
                        f"record {r.name!r} starts at its {r.kind}: with initial_state="
                        "'estimate' its initial state, offset and gain cannot be told apart "
                        "(the response lies in the span of the free responses); use "
                        "initial_state='zero', or a record that starts before the "
                        f"{r.kind}"
                    )
        est, _ = self._split(recs)
        self.n_evaluations_ = 0
        if self.n_poles == "auto":
            chosen, caught = search_structure(self, recs, est)
        else:
            n = int(self.n_poles)
            m = n - 1 if self.n_zeros is None else int(self.n_zeros)
            if any(r.kind == "impulse" for r in recs) and m >= n:
                raise DataError(f"impulse records need fewer zeros than poles; got n_zeros = {m}, "
                                f"n_poles = {n}")
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                if self.integrator:
                    chosen = fit_integrating(self, recs, est, n, m)
                else:
                    chosen = fit_order(self, recs, est, n, m)
        for w in caught:  # only the chosen order's warnings matter
            warnings.warn(w.message, w.category, stacklevel=2)
        self.model_ = chosen
        self.n_poles_ = chosen.n_poles
        self.n_zeros_ = chosen.n_zeros
        self.records_ = recs
        return self

    # ------------------------------------------------------------------ use
    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise NotFittedError(
                "this TransferFunctionEstimator is not fitted yet; call fit(records) first"
            )

    def predict(self, records: Any) -> list[NDArray[np.float64]]:
        """Simulated output of every record, as MATLAB ``compare`` computes it.

        The model is simulated over each whole record; the record's offset (and
        initial state, where estimated) is fitted to its samples before
        ``validate_from`` when there are enough of them, else to all samples.
        An integrating model acts on ``u - model_.input_level``.

        Parameters
        ----------
        records : Record, (t, u, y) tuple, or list of them

        Returns
        -------
        list of ndarray
            One simulated output per record, on the record's (merged) time grid.
        """
        self._check_fitted()
        recs = self._records(records)
        model = self.model_
        if model.input_level is not None:  # an integrating model acts from its input level
            recs = [dataclasses.replace(r, u_before=float(model.input_level)) for r in recs]
        prob = _Problem(recs, model.n_poles, model.n_zeros, intersample=model.intersample,
                        offset=bool(self.offset), initial_state=self.initial_state)
        b = model.num[::-1].copy()
        out = []
        for r, free in zip(recs, prob.free, strict=True):
            mask = np.ones(r.n_samples, dtype=bool)
            if self.validate_from is not None:
                emask = r.t < float(self.validate_from)
                if emask.sum() >= MIN_SAMPLES:
                    mask = emask
            yh, _ = nuisance(prob, r, free, model.den, model.delay, b, mask)
            out.append(yh)
        return out

    def score(self, records: Any) -> float:
        """Pooled simulation fit percent of :meth:`predict` on ``records`` (all samples).

        Parameters
        ----------
        records : Record, (t, u, y) tuple, or list of them

        Returns
        -------
        float
        """
        recs = self._records(records)
        return float(_pooled_fit([np.asarray(r.y) for r in recs], self.predict(recs),
                                 [np.asarray(r.weights) for r in recs]))

    def simulate(self, t: ArrayLike, u: ArrayLike, *, u_before: float = 0.0
                 ) -> NDArray[np.float64]:
        """Output of the fitted model (no offset) for a sampled input.

        Parameters
        ----------
        t : array-like of shape (n_samples,)
        u : array-like of shape (n_samples,)
        u_before : float, default=0.0
            Input before ``t[0]``.

        Returns
        -------
        ndarray of shape (n_samples,)
        """
        self._check_fitted()
        return self.model_.simulate(t, u, u_before=u_before)
