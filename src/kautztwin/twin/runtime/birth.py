"""A live plant's twin built without stalling the sample loop: the excitation goes on meanwhile.

At the end of the identification phase (sample ``n_ident``) the twin is born:
its first model is identified (:func:`~kautztwin.twin.runtime.twins.identify_initial`),
the twins are built and stepped through the samples so far
(:func:`~kautztwin.twin.runtime.twins.catch_up`) and the first controller is
tuned.  On a simulated or replayed plant, and without background workers,
this happens at once in the sample loop.  A live plant (an OPC UA or MQTT
link) does not wait for it: it goes on sampling at its own pace.  A loop
stalled by that work (0.2 to 0.5 s at 10x real time, 110 to 270 samples) left
the plant at one held input, parked at the excitation's centre
``ident_level``.  The model was identified on the excitation's two levels and
the drive is nonlinear: measured against the OPC UA plant server at x10, its
steady state at the centre lay 0.065 to 0.075 rad/s above the model's in 28
runs of 28 (sensor noise 0.01), and the prediction error over the closed
loop's first 150 samples was 0.037 to 0.064 rad/s against about 0.03 later.

:class:`BackgroundBirth` builds the twin of such a plant while the loop goes
on with the excitation - a continuation of the binary signal, seeded apart
from the run's other signals (:func:`~.excitation.continued_excitation`) - in
three steps, none of which blocks the loop for more than a slice:

1. the identification of the first ``n_ident`` samples, in a worker (the
   update module's kind: a ``forkserver`` child process for a live link);
2. the twins, built on the fit, stepped through the samples so far
   :data:`CATCH_UP_SLICE` samples per loop sample (they adapt on the
   continuation's samples too: the plant was excited);
3. the first controller's weight tuning, in the same worker meanwhile, at
   the operating point ``(ident_level, y)`` of the sample the fit arrived at.

The twin is born on the first sample at which the twins have caught up and
the tuning has arrived (it waits for the fit after ``n_ident`` samples of
continuation).  A resumed run replays its stored samples and builds the
twin at the sample where the stored run did, tuned at the stored operating
point, so the replay gives the same twin and controller.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import Future
from typing import Any

from numpy.typing import NDArray

from ..update.worker import fit_from_portable, portable_fit, preload_in_workers, single_worker
from .config import TwinConfig
from .excitation import continued_excitation
from .protocols import TwinError
from .twins import catch_up, identify_initial, make_twins

__all__ = ["CATCH_UP_SLICE", "BackgroundBirth"]

preload_in_workers(__name__)

#: samples of history the twins being built step through per sample of the loop
CATCH_UP_SLICE = 40


def _identify_portable(config: TwinConfig, u: NDArray, y: NDArray) -> tuple[Any, ...]:
    """:func:`identify_initial` in a worker process, its fit as plain, picklable values."""
    return portable_fit(identify_initial(config, u, y))


def _tune(optimizer: Any, model: Any, config: TwinConfig, u_op: float, y_op: float) -> Any:
    """The first controller's weight tuning (what the worker runs)."""
    return optimizer.tune_controller(model, config.mpc, step=config.tuning_step(), u_op=u_op,
                                     y_op=y_op)


def _started() -> bool:
    """A no-op job: the worker has started (a process: forked from the ``forkserver``)."""
    return True


class BackgroundBirth:
    """A live run's twin in the making: fit and tuning in a worker, the catch-up in slices.

    Parameters
    ----------
    config : TwinConfig
        The run (its excitation, ``n_ident`` and MPC settings).
    kind : {'thread', 'process'}
        Where the fit and the tuning run (see
        :func:`~kautztwin.twin.update.worker.single_worker`).

    Attributes
    ----------
    twins : tuple or None
        ``(updater, static, rates)`` of :func:`~.twins.make_twins`, once built.
    fit : OutputErrorFit or None
        The identification, once it has arrived.
    tuning_point : tuple of float or None
        ``(u_op, y_op)`` of the first controller's tuning, once submitted.

    Notes
    -----
    The worker starts at once (a process needs about a second): the
    identification phase gives it ``ident_duration`` of plant time.
    """

    def __init__(self, config: TwinConfig, kind: str) -> None:
        self.config = config
        self.kind = kind
        self._executor = single_worker(kind, "kautztwin-birth")
        self._executor.submit(_started)
        self._fit: Future[Any] | None = None
        self._tuning: Future[Any] | None = None
        self._inputs = continued_excitation(config)
        self._t0 = time.perf_counter()
        self._next = 0  # the next sample the twins step through
        self.fit: Any = None
        self.twins: tuple[Any, Any, Any] | None = None
        self.tuning_point: tuple[float, float] | None = None

    @property
    def submitted(self) -> bool:
        """Whether the fit has been submitted."""
        return self._fit is not None

    @property
    def started_at(self) -> float:
        """``time.perf_counter()`` when the fit was submitted."""
        return self._t0

    def submit(self, u: NDArray, y: NDArray) -> None:
        """Submit the fit of the identification samples ``u, y`` (copied: the loop goes on).

        Parameters
        ----------
        u, y : ndarray of shape (n_ident,)
            Inputs and sanitised outputs (NaN where unusable).
        """
        self._t0 = time.perf_counter()
        fn = _identify_portable if self.kind == "process" else identify_initial
        self._fit = self._executor.submit(fn, self.config, u.copy(), y.copy())

    def input(self, j: int) -> float:
        """The plant's input ``j`` samples after the identification phase, until the twin is born.

        Parameters
        ----------
        j : int
            Samples since ``n_ident`` (``0 <= j``).

        Returns
        -------
        float
            The continued excitation (its last value after ``n_ident`` samples).
        """
        return float(self._inputs[min(j, self._inputs.size - 1)])

    def fit_due(self, j: int) -> bool:
        """Whether the fit has arrived, or must be waited for (``j >= n_ident`` samples since).

        Parameters
        ----------
        j : int
            Samples since ``n_ident``.

        Returns
        -------
        bool
        """
        assert self._fit is not None, "submit the fit first"
        return self._fit.done() or j >= self.config.n_ident

    def take_fit(self) -> Any:
        """The fit (waiting for it), or ``None`` when the worker failed.

        ``None``: a killed or broken child process; the caller identifies in
        the loop instead.

        Returns
        -------
        OutputErrorFit or None

        Raises
        ------
        TwinError
            If the identification itself failed.
        """
        assert self._fit is not None, "submit the fit first"
        try:
            value = self._fit.result()
        except TwinError:
            raise
        except Exception:  # noqa: BLE001 - a broken worker: the loop fits instead
            return None
        return fit_from_portable(value) if self.kind == "process" else value

    def conceive(self, fit: Any, twins: tuple[Any, Any, Any], optimizer: Any,
                 tuning_point: tuple[float, float] | None) -> None:
        """Take the fit and the twins built on it; submit the first controller's tuning.

        Parameters
        ----------
        fit : OutputErrorFit
            The identification.
        twins : tuple
            ``(updater, static, rates)`` of :func:`~.twins.make_twins`, not stepped yet.
        optimizer : object
            The optimization module (its ``tune_controller``); picklable for a process.
        tuning_point : tuple of float or None
            ``(u_op, y_op)`` of the tuning; ``None``: no controller (nothing to tune).
        """
        self.fit, self.twins = fit, twins
        self.tuning_point = tuning_point
        if tuning_point is not None:
            model = twins[0].digital_model.model
            self._tuning = self._executor.submit(_tune, optimizer, model, self.config,
                                                 *tuning_point)

    def catch_up(self, arrays: dict[str, NDArray[Any]], k: int) -> bool:
        """Step the twins through the next slice of the samples before ``k``; caught up?

        Parameters
        ----------
        arrays : dict of ndarray
            The run's per-sample arrays (``u``, ``y``, ``t``; their predictions are stored).
        k : int
            The current sample (not stepped here: the twin is born at it).

        Returns
        -------
        bool
            Whether the twins have stepped through every sample before ``k``.
        """
        assert self.twins is not None, "conceive the twins first"
        stop = min(k, self._next + CATCH_UP_SLICE)
        updater, static, _ = self.twins
        catch_up(updater, static, arrays, stop, start=self._next)
        self._next = stop
        return stop == k

    def grow(self, arrays: dict[str, NDArray[Any]], k: int, *, optimizer: Any,
             estimator: Any = None) -> bool:
        """One loop sample's step of the twin's making; whether it can be born at ``k``.

        Submits the fit at the first call; once the fit has arrived (or is
        due: :meth:`fit_due`) builds the twins on it (:func:`~.twins.make_twins`,
        background workers; a failed worker's fit is made here) and submits the
        first tuning at ``(ident_level, y(k - 1))`` (:meth:`conceive`); then
        steps the twins through a slice of the history (:meth:`catch_up`).

        Parameters
        ----------
        arrays : dict of ndarray
            The run's per-sample arrays (``u``, ``y_clean``, ``y``, ``t``, predictions).
        k : int
            The current sample (``>= n_ident``).
        optimizer : object
            The optimization module (its ``tune_controller``).
        estimator : object, optional
            The update module's DNN estimator.

        Returns
        -------
        bool
            Whether the twins have caught up and the tuning has arrived (or is
            due: ``2 n_ident`` samples after the identification phase).
        """
        cfg = self.config
        n_id = cfg.n_ident
        a = arrays
        if not self.submitted:
            self.submit(a["u"][:n_id], a["y_clean"][:n_id])
        if self.twins is None:
            if not self.fit_due(k - n_id):
                return False
            fit = self.take_fit()
            if fit is None:  # a broken worker: identify here
                fit = identify_initial(cfg, a["u"][:n_id].copy(), a["y_clean"][:n_id].copy())
            twins = make_twins(fit, cfg, background=True, estimator=estimator)
            y_op = a["y_clean"][k - 1]
            y_op = float(y_op) if math.isfinite(y_op) else float(fit.offset)
            self.conceive(fit, twins, optimizer, (float(cfg.ident_level), y_op))
        caught_up = self.catch_up(a, k)
        return caught_up and (self.tuning()[0] or k - n_id >= 2 * n_id)

    def tuning(self, wait: bool = False) -> tuple[bool, Any]:
        """``(ready, tuning)``: the first controller's tuning once it has arrived.

        ``tuning`` is ``None`` when there is nothing to tune or the worker
        failed (the caller then tunes in the loop).

        Parameters
        ----------
        wait : bool, default=False
            Wait for it.

        Returns
        -------
        tuple
        """
        f = self._tuning
        if f is None:
            return True, None
        if not wait and not f.done():
            return False, None
        try:
            return True, f.result()
        except Exception:  # noqa: BLE001 - a broken worker: the loop tunes instead
            return True, None

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the work submitted so far has finished; whether it has.

        Parameters
        ----------
        timeout : float, optional
            Most seconds to wait.

        Returns
        -------
        bool
        """
        for f in (self._fit, self._tuning):
            if f is None:
                continue
            try:
                f.exception(timeout)
            except TimeoutError:
                return False
        return True

    def close(self) -> None:
        """Stop the worker (work still running is abandoned)."""
        self._executor.shutdown(wait=False, cancel_futures=True)
