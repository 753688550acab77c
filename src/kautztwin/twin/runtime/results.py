"""What a twin run produces: a :class:`TwinState` per sample, events, the :class:`TwinRun`."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from numpy.typing import NDArray

from .config import TwinConfig

__all__ = ["TwinEvent", "TwinRun", "TwinState"]


@dataclass(frozen=True)
class TwinEvent:
    """Something that happened during a run.

    Parameters
    ----------
    kind : str
        ``'phase'``, ``'drift'``, ``'desync'``, ``'resync'``, ``'model-update'``,
        ``'model-rejected'``, ``'model-version'``, ``'controller'``,
        ``'controller-rejected'``, ``'estimator-update'``, ``'estimator-rejected'``,
        ``'pole-retune'`` (a resync's pole re-optimisation handed to a worker; its verdict
        follows as ``'model-update'`` or ``'model-rejected'``) or ``'resume'``.
    k : int
        Sample index.
    t : float
        Sample time, s.
    message : str
        Human-readable text.
    payload : mapping
        JSON-ready details.
    """

    kind: str
    k: int
    t: float
    message: str
    payload: Mapping[str, Any] = field(default_factory=dict, hash=False, compare=False)


@dataclass(frozen=True)
class TwinState:
    """The twin after one sample (what :meth:`~kautztwin.twin.runtime.DigitalTwin.step` returns).

    Parameters
    ----------
    k : int
        Sample index just processed (-1 before the first).
    t : float
        Its time, s.
    phase : str
        ``'identification'``, ``'closed-loop'``, ``'monitoring'`` (no control)
        or ``'done'``.
    y : float
        Measured output as read (NaN for a dropout).
    u : float
        Input applied from this sample on.
    command : float
        Controller command (NaN without control).
    setpoint, reference : float
        Set-point and filtered reference of the controller (NaN without control).
    y_pred, y_pred_static : float
        Monitored predictions of this sample by the updating and the static twin.
    flags : int
        :class:`~kautztwin.twin.SampleFlag` bits of the sample.
    version : int
        Version of the digital model (0 before identification).
    fit, fit_static : float
        Latest rolling fits of the two twins, percent.
    mpc_ms, update_ms : float
        Time of the MPC solve and of the update step, ms.
    events : tuple of str
        Kinds of the events of this sample.
    committed : int
        Samples committed to the history store so far.
    replayed : bool
        Whether the sample was replayed from the store (a resumed run).
    """

    k: int
    t: float
    phase: str
    y: float = math.nan
    u: float = math.nan
    command: float = math.nan
    setpoint: float = math.nan
    reference: float = math.nan
    y_pred: float = math.nan
    y_pred_static: float = math.nan
    flags: int = 0
    version: int = 0
    fit: float = math.nan
    fit_static: float = math.nan
    mpc_ms: float = math.nan
    update_ms: float = math.nan
    events: tuple[str, ...] = ()
    committed: int = 0
    replayed: bool = False


_ARRAYS = ("t", "y", "y_clean", "u", "command", "dither", "setpoint", "reference", "y_pred",
           "y_pred_static", "mpc_ms", "update_ms", "version", "flags", "mpc_ok")


@dataclass(frozen=True, eq=False)
class TwinRun:
    """Record of a run: per-sample arrays, events and bookkeeping (input of the report).

    Parameters
    ----------
    config : TwinConfig
        The run's configuration.
    plant_name : str
        Name of the plant.
    run_id : int
        Run identifier in the history store.
    store : str
        Where the history is (a path, or ``':memory:'``).
    n_done : int
        Samples processed (``config.n_samples`` for a complete run).
    k_closed_loop : int
        First sample under control: right after the identification phase, or for a live
        plant the first sample after it once the samples queued meanwhile are taken in.
    arrays : mapping of str to ndarray
        ``t, y, y_clean`` (NaN where the sample was not usable), ``u, command,
        dither, setpoint, reference, y_pred, y_pred_static, mpc_ms, update_ms``
        (NaN for samples with an accurate-path attempt or without an update),
        ``version, flags, mpc_ok``; each of length ``n_done``.
    events : tuple of TwinEvent
        Everything that happened, in order.
    versions : tuple of dict
        Model versions: ``version, k, provenance, fit_percent, offset, poles``.
    tunings : tuple of dict
        Controller tunings: ``k, accepted, r, reason``.
    counts : mapping
        Sample counters (``total, dropout, outlier, clipped, held, late, ...``)
        and update counters (``attempts, accepted``).
    identification : mapping
        The initial identification: ``fit_percent, poles, continuous_poles, offset,
        n_samples`` (the samples identified), ``k_twin`` (the sample the twin was built
        at: ``n_samples`` unless a live plant's twin was built in the background, then
        also ``tuning_point``, the ``(u_op, y_op)`` of its first controller's tuning)
        and ``elapsed`` (wall seconds from the fit's start to the twin).
    resume : mapping
        ``resumed, resume_k, replayed, replay_mismatches``.
    wall_time : float
        Wall-clock seconds of this process's run (replay included).
    status : str
        ``'finished'`` or ``'running'``.
    """

    config: TwinConfig
    plant_name: str
    run_id: int
    store: str
    n_done: int
    k_closed_loop: int
    arrays: Mapping[str, NDArray[Any]]
    events: tuple[TwinEvent, ...]
    versions: tuple[Mapping[str, Any], ...]
    tunings: tuple[Mapping[str, Any], ...]
    counts: Mapping[str, int]
    identification: Mapping[str, Any]
    resume: Mapping[str, Any]
    wall_time: float
    status: str
