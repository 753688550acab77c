r"""Digital twin runtime: plant, update, prediction/control, optimization and history in one loop.

:class:`DigitalTwin` composes the five modules of the twin through small
:class:`typing.Protocol` interfaces:

1. the **physical system** (:class:`~kautztwin.twin.Plant`: the hydraulic drive,
   the TCLab emulator or board, or a replayed record);
2. the **digital model** (:class:`~kautztwin.twin.DigitalModel`: the current
   Kautz model, versioned, with its provenance);
3. the **update module** (:class:`TwinUpdater`, by default
   :class:`~kautztwin.twin.Updater`: recursive least squares on Kautz filters,
   synchronisation monitor, re-identification);
4. the **prediction module** (:class:`TwinController`/:class:`TwinPredictor`:
   :class:`MPCController`, a constrained Laguerre MPC built once per model
   version and re-solved every sample, and the twin's what-if prediction);
5. the **optimization module** (:class:`TwinOptimizer`, by default
   :class:`~kautztwin.twin.optimize.Optimizer`: pole re-optimisation, model
   consolidation and MPC weight retuning, each validated before it replaces
   the running version);

and the **history store** (:class:`~kautztwin.twin.HistoryStore`, SQLite by
default) in which every sample is committed.

A run is a deterministic function of its :class:`TwinConfig` and the plant:
an open-loop identification phase (binary excitation around the operating
point, then :func:`~kautztwin.twin.identify_output_error`), then closed-loop
MPC tracking of the set-point schedule while the twin updates itself.  Each
:meth:`DigitalTwin.step` returns a new immutable :class:`TwinState`.  A run
that is killed resumes from its store: the committed samples are replayed
through the same code (the plant re-simulated with the stored inputs and
checked against the stored outputs), so the twin, the controller and the
plant continue exactly where the committed history ends and no committed
sample is lost or repeated.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import asdict, dataclass, field, replace
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..approx.model import KautzModel
from ..exceptions import DataError, KautzTwinError
from ..mpc import MPCProblem, MPCResult
from .digital_model import DigitalModel
from .history import HistoryStore, SQLiteHistory
from .optimize import ControllerTuning, EstimatorRetraining, MPCSettings, Optimizer, build_mpc
from .plants import Clock, HydraulicPlant, Plant, Reading, ReplayPlant, TCLabPlant
from .signals import SampleFlag, SampleSanitizer
from .update import (
    ModelUpdate,
    SyncEvent,
    SyncMonitor,
    Updater,
    UpdateResult,
    identify_output_error,
)

__all__ = [
    "DigitalTwin",
    "FaultConfig",
    "MPCController",
    "TwinConfig",
    "TwinController",
    "TwinError",
    "TwinEvent",
    "TwinOptimizer",
    "TwinPredictor",
    "TwinRun",
    "TwinState",
    "TwinUpdater",
    "make_plant",
    "parse_setpoints",
]

PHASES = ("identification", "closed-loop", "monitoring", "done")


class TwinError(KautzTwinError, RuntimeError):
    """The twin runtime cannot go on (identification impossible, store of another run, ...)."""


# --------------------------------------------------------------------------- protocols
@runtime_checkable
class TwinUpdater(Protocol):
    """Update module: keeps the digital model synchronised, one sample at a time.

    :class:`~kautztwin.twin.Updater` implements it.
    """

    digital_model: DigitalModel
    input_offset: float

    def step(self, u: Any, y: Any, t: Any = None) -> UpdateResult:
        """Process one sample ``(u(k), y(k))`` (see :meth:`Updater.step`)."""
        ...

    def predict(self, u: ArrayLike) -> NDArray[np.float64]:
        """Predict the output for planned inputs from the current state."""
        ...


@runtime_checkable
class TwinPredictor(Protocol):
    """Prediction module, what-if part: the response of the twin to a planned input."""

    def what_if(self, u_plan: ArrayLike) -> NDArray[np.float64]:
        """Predicted outputs of the next samples for the planned inputs ``u_plan``."""
        ...


@runtime_checkable
class TwinController(Protocol):
    """Prediction module, control part: receding-horizon MPC on the current model.

    :class:`MPCController` implements it.
    """

    def rebuild(
        self, model: KautzModel, settings: MPCSettings, v_history: ArrayLike,
        d_history: ArrayLike,
    ) -> None:
        """Build the controller for a (new) model version, once."""
        ...

    def solve(self, y: float, reference: float, v_prev: float) -> MPCResult:
        """Solve for the current sample (fast, re-solved every sample)."""
        ...

    def advance(self, v: float, d: float) -> None:
        """Advance the controller's model state with the applied command and dither."""
        ...


@runtime_checkable
class TwinOptimizer(Protocol):
    """Optimization module: offline re-tuning; :class:`~kautztwin.twin.optimize.Optimizer`."""

    def tune_controller(
        self, model: KautzModel, settings: MPCSettings, *, step: float, u_op: float | None = None,
        y_op: float = 0.0,
    ) -> ControllerTuning:
        """Retune the MPC weights for a model version and validate them."""
        ...

    def retune_model(self, updater: Updater) -> ModelUpdate | None:
        """Re-optimise the basis poles on recent behaviour (validated by the updater)."""
        ...

    def consolidate(
        self, updater: Updater, current: KautzModel, current_offset: float, u: ArrayLike,
        y: ArrayLike,
    ) -> tuple[bool, float, float]:
        """Whether the live fast-path model beats the current version on recent data."""
        ...

    def retrain_estimator(self, estimator: Any, model: KautzModel) -> EstimatorRetraining:
        """Fine-tune the DNN estimator around a new model version and validate it."""
        ...


# --------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class FaultConfig:
    """Sensor faults injected after the identification phase (deterministic, seeded).

    Parameters
    ----------
    dropout : float, default=0.0
        Probability per sample that the output reads NaN.
    outlier : float, default=0.0
        Probability per sample of a gross error of ``outlier_size`` (random sign).
    late : float, default=0.0
        Probability per sample that the reading arrives late: it carries the
        previous sample's timestamp (never two in a row).
    outlier_size : float, default=0.0
        Size of an outlier in output units; the plant profile's default when 0.

    Raises
    ------
    DataError
        If a probability is outside ``[0, 1)`` or the size is negative.

    Examples
    --------
    >>> from kautztwin.twin.runtime import FaultConfig
    >>> FaultConfig.parse("dropout=0.01,outlier=0.005,late=0.002")
    FaultConfig(dropout=0.01, outlier=0.005, late=0.002, outlier_size=0.0)
    """

    dropout: float = 0.0
    outlier: float = 0.0
    late: float = 0.0
    outlier_size: float = 0.0

    def __post_init__(self) -> None:
        for name in ("dropout", "outlier", "late"):
            v = float(getattr(self, name))
            if not 0.0 <= v < 1.0:
                raise DataError(f"faults: {name} must be a probability in [0, 1), got {v}")
            object.__setattr__(self, name, v)
        size = float(self.outlier_size)
        if not (math.isfinite(size) and size >= 0):
            raise DataError(f"faults: outlier_size must be >= 0, got {size}")
        object.__setattr__(self, "outlier_size", size)

    @property
    def any(self) -> bool:
        """Whether any fault is injected."""
        return bool(self.dropout or self.outlier or self.late)

    @classmethod
    def parse(cls, text: str) -> FaultConfig:
        """Read ``"dropout=P,outlier=P,late=P,size=S"`` (any subset, any order).

        Parameters
        ----------
        text : str

        Returns
        -------
        FaultConfig

        Raises
        ------
        DataError
            On an unknown key or a value that is not a number.
        """
        keys = {"dropout": "dropout", "outlier": "outlier", "late": "late",
                "size": "outlier_size", "outlier_size": "outlier_size"}
        values: dict[str, float] = {}
        for part in (p.strip() for p in str(text).split(",")):
            if not part:
                continue
            key, sep, value = part.partition("=")
            key = key.strip().lower()
            if not sep or key not in keys:
                raise DataError(
                    f"faults: cannot read {part!r}; write e.g. dropout=0.01,outlier=0.005,"
                    "late=0.005,size=40"
                )
            try:
                values[keys[key]] = float(value)
            except ValueError:
                raise DataError(f"faults: {key} must be a number, got {value!r}") from None
        return cls(**values)


@dataclass(frozen=True)
class TwinConfig:
    r"""Everything that defines a twin run (stored with the run; resuming needs the same).

    Use :meth:`for_plant` for the tuned profiles of the shipped plants.

    Parameters
    ----------
    plant : str
        Profile name (``'hydraulic'``, ``'tclab'``, ``'replay'`` or another label).
    dt : float
        Sampling period of the plant, s.
    duration : float
        Length of the run, s (``round(duration / dt)`` samples).
    ident_duration : float
        Open-loop identification phase at the start, s.
    operating_input : float
        Input at which the plant rests at ``t = 0`` (the models' input offset).
    ident_level, ident_amplitude : float
        Identification input: ``ident_level`` plus binary steps of
        ``+-ident_amplitude``.
    ident_hold : (int, int)
        Range of the hold times of the binary steps, samples.
    n_poles : int
        Order of the identified model.
    min_rate : float or None
        Slowest pole rate of the identification, 1/s (see
        :func:`~kautztwin.twin.identify_output_error`).
    setpoints : tuple of (float, float)
        Set-point schedule as ``(time, value)`` pairs (value from that time on).
    reference_tau : float
        Time constant of the first-order reference filter that smooths the
        set-point steps, s (0: none).
    dither, dither_hold : float, (int, int)
        Excitation dither added to the MPC command (binary, these hold times)
        so that the twin stays identifiable in closed loop; the controller
        does not react to it (its predicted response is removed from the
        feedback).
    mpc : MPCSettings or None
        Controller design and plant limits; ``None`` for a plant without
        control (a replay).
    forgetting : float
        Forgetting factor of the fast path.
    extra_pole_factor : float
        An extra fast-path pole at this multiple of the slowest identified
        rate (0: none).
    monitor_window, monitor_stride, monitor_threshold, monitor_consecutive
        :class:`~kautztwin.twin.SyncMonitor` settings (the rolling fit).
    updater : mapping
        Further keyword arguments of :class:`~kautztwin.twin.Updater`
        (``'background'`` among them: see :class:`DigitalTwin`).
    sanitizer_threshold, sanitizer_window, sensor_scale : float, int, float
        :class:`~kautztwin.twin.SampleSanitizer` settings (``sensor_scale`` is
        its ``min_scale``).
    recovery_window : float
        Documented recovery window after each drift event, s (metrics only).
    drift_events : tuple of float
        Start times of the plant's drift events, s (metrics and plots only).
    faults : FaultConfig
        Injected sensor faults.
    static_twin : bool
        Run the static twin (updates disabled) on the same samples for comparison.
    retune : bool
        Run the optimization module.
    commit_every : int
        Samples per history transaction.
    seed : int
        Seed of the excitation, the dither and the faults.
    quick : bool
        Whether this is a quick profile (informational).
    """

    plant: str
    dt: float
    duration: float
    ident_duration: float
    operating_input: float
    ident_level: float
    ident_amplitude: float
    ident_hold: tuple[int, int]
    n_poles: int
    min_rate: float | None
    setpoints: tuple[tuple[float, float], ...]
    reference_tau: float
    dither: float
    dither_hold: tuple[int, int]
    mpc: MPCSettings | None
    forgetting: float
    extra_pole_factor: float
    monitor_window: int
    monitor_stride: int
    monitor_threshold: float
    monitor_consecutive: int
    updater: Mapping[str, Any] = field(default_factory=dict)
    sanitizer_threshold: float = 8.0
    sanitizer_window: int = 100
    sensor_scale: float = 0.0
    recovery_window: float = 15.0
    drift_events: tuple[float, ...] = ()
    faults: FaultConfig = field(default_factory=FaultConfig)
    static_twin: bool = True
    retune: bool = True
    commit_every: int = 50
    seed: int = 0
    quick: bool = False

    def __post_init__(self) -> None:
        for name in ("dt", "duration", "ident_duration"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise DataError(f"{name} must be a positive number of seconds, got {v}")
            object.__setattr__(self, name, v)
        if self.ident_duration >= self.duration:
            raise DataError(
                f"duration = {self.duration:g} s must exceed the identification phase of "
                f"{self.ident_duration:g} s"
            )
        n_id = self.n_ident
        if n_id < 10 * (self.n_poles + 1):
            raise DataError(
                f"the identification phase has {n_id} samples; {10 * (self.n_poles + 1)} are "
                f"needed for {self.n_poles} poles"
            )
        object.__setattr__(self, "ident_hold", tuple(int(h) for h in self.ident_hold))
        object.__setattr__(self, "dither_hold", tuple(int(h) for h in self.dither_hold))
        for name in ("ident_hold", "dither_hold"):
            lo, hi = getattr(self, name)
            if not 1 <= lo < hi:
                raise DataError(f"{name} must be (low, high) samples with 1 <= low < high")
        sp = tuple((float(t), float(v)) for t, v in self.setpoints)
        if any(not (math.isfinite(t) and math.isfinite(v)) for t, v in sp):
            raise DataError("setpoints must be finite (time, value) pairs")
        object.__setattr__(self, "setpoints", tuple(sorted(sp)))
        if self.mpc is not None:
            if not sp:
                raise DataError("a controlled plant needs at least one set-point")
            lo, hi = self.mpc.y_min, self.mpc.y_max
            for _, v in sp:
                if not lo <= v <= hi:
                    raise DataError(
                        f"set-point {v:g} lies outside the output limits [{lo:g}, {hi:g}] of "
                        f"the {self.plant} plant"
                    )
        if not 0 < self.forgetting <= 1:
            raise DataError(f"forgetting must lie in (0, 1], got {self.forgetting}")
        if self.commit_every < 1:
            raise DataError(f"commit_every must be >= 1, got {self.commit_every}")
        object.__setattr__(self, "updater", MappingProxyType(dict(self.updater)))
        object.__setattr__(self, "drift_events", tuple(float(e) for e in self.drift_events))

    # ------------------------------------------------------------------ derived
    @property
    def n_samples(self) -> int:
        """Number of samples of the run."""
        return int(round(self.duration / self.dt))

    @property
    def n_ident(self) -> int:
        """Samples of the identification phase."""
        return int(round(self.ident_duration / self.dt))

    @property
    def controlled(self) -> bool:
        """Whether the twin controls the plant (``mpc`` is set)."""
        return self.mpc is not None

    def setpoint(self, t: float) -> float:
        """The set-point in force at time ``t`` (the first value before the first time).

        Parameters
        ----------
        t : float

        Returns
        -------
        float
        """
        if not self.setpoints:
            return math.nan
        value = self.setpoints[0][1]
        for ti, v in self.setpoints:
            if ti <= t + 1e-9 * self.dt:
                value = v
        return value

    def tuning_step(self) -> float:
        """Set-point step used to tune the MPC weights: the largest step of the schedule.

        Returns
        -------
        float
        """
        values = [v for _, v in self.setpoints]
        steps = [abs(b - a) for a, b in zip(values[:-1], values[1:], strict=False)]
        step = max(steps, default=0.0)
        if step > 0:
            return step
        return max(0.05 * abs(values[0]), 1e-3) if values else 1.0

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (stored as the run configuration).

        Returns
        -------
        dict
        """
        out = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if isinstance(v, MPCSettings):
                v = v.to_dict()
            elif isinstance(v, FaultConfig):
                v = asdict(v)
            elif isinstance(v, Mapping):
                v = dict(v)
            out[name] = v
        return json.loads(json.dumps(_json_ready(out), allow_nan=False))

    # ------------------------------------------------------------------ profiles
    @classmethod
    def for_plant(
        cls,
        plant: str | Plant,
        *,
        duration: float | None = None,
        setpoints: str | Sequence[float] | Sequence[tuple[float, float]] | None = None,
        quick: bool = False,
        seed: int = 0,
        faults: FaultConfig | str | None = None,
        drift_events: Sequence[float] = (),
        **overrides: Any,
    ) -> TwinConfig:
        """The tuned profile of a shipped plant, with optional changes.

        Parameters
        ----------
        plant : {'hydraulic', 'tclab'} or Plant
            Profile name, or a plant (a :class:`~kautztwin.twin.ReplayPlant`
            gets the generic monitoring profile, sized to its record).
        duration : float, optional
            Run length, s; the profile's default (shorter with ``quick``) when omitted.
        setpoints : str, sequence of float or of (time, value), optional
            Set-points: values at equal intervals over the closed-loop phase,
            or ``(time, value)`` pairs (see :func:`parse_setpoints`).
        quick : bool, default=False
            The quick profile: a shorter run and identification phase.
        seed : int, default=0
            Seed of the excitation, dither and faults.
        faults : FaultConfig or str, optional
            Injected sensor faults.
        drift_events : sequence of float, default=()
            Start times of drift events (for the metrics).
        **overrides
            Any other :class:`TwinConfig` field.

        Returns
        -------
        TwinConfig

        Raises
        ------
        DataError
            On an unknown profile or invalid values.

        Examples
        --------
        >>> from kautztwin.twin.runtime import TwinConfig
        >>> cfg = TwinConfig.for_plant("hydraulic", quick=True)
        >>> cfg.dt, cfg.duration, cfg.n_ident, [v for _, v in cfg.setpoints]
        (0.02, 40.0, 400, [97.0, 103.0, 100.0])
        """
        if isinstance(faults, str):
            faults = FaultConfig.parse(faults)
        if not drift_events and not isinstance(plant, str):
            drift_events = tuple(getattr(plant, "drift_events", ()))
        faults = faults if faults is not None else FaultConfig()
        name = plant if isinstance(plant, str) else _plant_kind(plant)
        if name == "hydraulic":
            dt = plant.dt if not isinstance(plant, str) else 0.02
            dur = float(duration) if duration is not None else (40.0 if quick else 90.0)
            ident = min(8.0 if quick else 20.0, 0.4 * dur)
            base: dict[str, Any] = dict(
                plant="hydraulic", dt=dt, duration=dur, ident_duration=ident,
                operating_input=0.5, ident_level=0.5, ident_amplitude=0.02, ident_hold=(5, 25),
                n_poles=3, min_rate=1.0, reference_tau=3.0, dither=0.02, dither_hold=(5, 25),
                mpc=MPCSettings(75, 0.85, 6, 1e5, u_min=0.3, u_max=0.7, du_max=0.05,
                                y_min=70.0, y_max=130.0, dither=0.02),
                forgetting=0.98, extra_pole_factor=0.5, monitor_window=150, monitor_stride=25,
                monitor_threshold=95.0, monitor_consecutive=2,
                updater={"min_rate": 1.0, "max_iter": 20 if quick else 30},
                sensor_scale=1.0, recovery_window=15.0, commit_every=50,
            )
            default_sp: Any = (97.0, 103.0, 100.0)
            outlier = 40.0
        elif name == "tclab":
            dt = plant.dt if not isinstance(plant, str) else 1.0
            dur = float(duration) if duration is not None else (1800.0 if quick else 3600.0)
            ident = min(600.0 if quick else 900.0, 0.5 * dur)
            base = dict(
                plant="tclab", dt=dt, duration=dur, ident_duration=ident, operating_input=0.0,
                ident_level=40.0, ident_amplitude=10.0, ident_hold=(30, 120), n_poles=2,
                min_rate=None, reference_tau=30.0, dither=5.0, dither_hold=(30, 120),
                mpc=MPCSettings(300, 0.97, 6, 1.0, u_min=0.0, u_max=100.0, du_max=20.0,
                                y_max=60.0, dither=5.0, sparse_every=10),
                forgetting=0.998, extra_pole_factor=0.5, monitor_window=600, monitor_stride=50,
                monitor_threshold=90.0, monitor_consecutive=2,
                updater={"reid_samples": 900, "min_reid_samples": 450, "reid_every": 150,
                         "burn_in": 600, "buffer_size": 2000},
                sensor_scale=1.0, sanitizer_window=30, recovery_window=0.0, commit_every=10,
            )
            default_sp = (50.0, 40.0, 45.0)
            outlier = 20.0
        elif name == "replay" and isinstance(plant, ReplayPlant):
            dt = plant.dt
            n_rec = plant.n_samples
            dur = min(float(duration), (n_rec - 1) * dt) if duration is not None else (
                (n_rec - 1) * dt)
            ident = max(0.3 * dur, 100 * dt)
            u_id = plant.u[: int(round(ident / dt))]
            u_fin = u_id[np.isfinite(u_id)]
            y_fin = plant.y[np.isfinite(plant.y)]
            spread = float(np.ptp(y_fin)) if y_fin.size else 1.0
            base = dict(
                plant="replay", dt=dt, duration=dur, ident_duration=ident,
                operating_input=float(np.median(u_fin)) if u_fin.size else 0.0, ident_level=0.0,
                ident_amplitude=0.0, ident_hold=(5, 25), n_poles=3, min_rate=None,
                reference_tau=0.0, dither=0.0, dither_hold=(5, 25), mpc=None, forgetting=0.99,
                extra_pole_factor=0.5, monitor_window=150, monitor_stride=25,
                monitor_threshold=95.0, monitor_consecutive=2, updater={},
                sensor_scale=0.01 * spread, recovery_window=0.0, commit_every=50,
            )
            default_sp = ()
            outlier = 5.0 * spread
        else:
            raise DataError(
                f"unknown plant profile {name!r}; use 'hydraulic', 'tclab' or a ReplayPlant"
            )
        if faults.any and faults.outlier_size == 0:
            faults = replace(faults, outlier_size=outlier)
        base.update(seed=int(seed), quick=bool(quick), faults=faults,
                    drift_events=tuple(drift_events))
        base.update(overrides)
        t_cl = float(base["ident_duration"])
        if base["mpc"] is not None:
            spec = default_sp if setpoints is None else setpoints
            base["setpoints"] = parse_setpoints(spec, start=t_cl, end=float(base["duration"]))
        else:
            base.setdefault("setpoints", ())
        return cls(**base)


def _plant_kind(plant: Any) -> str:
    if isinstance(plant, HydraulicPlant):
        return "hydraulic"
    if isinstance(plant, TCLabPlant):
        return "tclab"
    if isinstance(plant, ReplayPlant):
        return "replay"
    return type(plant).__name__


def _json_ready(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_ready(obj.tolist())
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        x = float(obj)
        return x if math.isfinite(x) else None
    return obj


def parse_setpoints(
    spec: str | Sequence[float] | Sequence[tuple[float, float]], *, start: float, end: float
) -> tuple[tuple[float, float], ...]:
    """Read a set-point schedule.

    Parameters
    ----------
    spec : str or sequence
        ``"v1,v2,v3"`` (or a sequence of numbers): the values at equal
        intervals over ``[start, end)``; ``"t1:v1,t2:v2"`` (or ``(t, v)``
        pairs): value ``v_i`` from time ``t_i`` on.
    start, end : float
        Start and end of the closed-loop phase, s.

    Returns
    -------
    tuple of (float, float)
        ``(time, value)`` pairs, sorted by time.

    Raises
    ------
    DataError
        If the text mixes the two forms, holds something that is not a number,
        or is empty.

    Examples
    --------
    >>> from kautztwin.twin.runtime import parse_setpoints
    >>> parse_setpoints("97,103,100", start=20.0, end=80.0)
    ((20.0, 97.0), (40.0, 103.0), (60.0, 100.0))
    >>> parse_setpoints("0:45,600:50", start=300.0, end=1200.0)
    ((0.0, 45.0), (600.0, 50.0))
    """
    if isinstance(spec, str):
        parts = [p.strip() for p in spec.split(",") if p.strip()]
        if not parts:
            raise DataError("setpoints: the schedule is empty")
        pairs = [":" in p for p in parts]
        if any(pairs) and not all(pairs):
            raise DataError(
                f"setpoints: write either values (97,103,100) or time:value pairs "
                f"(20:97,40:103), not both; got {spec!r}"
            )
        try:
            if all(pairs):
                items: list[Any] = [tuple(float(x) for x in p.split(":", 1)) for p in parts]
            else:
                items = [float(p) for p in parts]
        except ValueError:
            raise DataError(f"setpoints: cannot read {spec!r} as numbers") from None
    else:
        items = list(spec)
        if not items:
            raise DataError("setpoints: the schedule is empty")
    if all(isinstance(i, tuple | list) for i in items):
        out = tuple(sorted((float(t), float(v)) for t, v in items))
    else:
        values = [float(v) for v in items]
        step = (float(end) - float(start)) / len(values)
        out = tuple((float(start) + i * step, v) for i, v in enumerate(values))
    if any(not (math.isfinite(t) and math.isfinite(v)) for t, v in out):
        raise DataError("setpoints: times and values must be finite")
    return out


def make_plant(
    spec: str,
    *,
    drift: float = 0.0,
    drift_events: Sequence[float] = (),
    seed: int = 0,
    noise: float | None = None,
) -> Plant:
    """Build a plant from its command-line name.

    Parameters
    ----------
    spec : str
        ``'hydraulic'``, ``'tclab'`` (the emulator) or ``'replay:FILE'``.
    drift : float, default=0.0
        Hydraulic only: total relative drift of the dominant pole over ``drift_events``.
    drift_events : sequence of float, default=()
        Hydraulic only: start times of the drift steps, s.
    seed : int, default=0
        Seed of the sensor noise.
    noise : float, optional
        Sensor noise (plant default when omitted: 0.01 rad/s, tclab's 0.043 °C).

    Returns
    -------
    Plant

    Raises
    ------
    DataError
        On an unknown name, a drift for another plant, or an unreadable record.
    """
    kind, _, arg = spec.partition(":")
    kind = kind.strip().lower()
    if kind != "hydraulic" and drift:
        raise DataError(f"drift applies to the hydraulic plant only, not to {spec!r}")
    if kind == "hydraulic":
        kwargs: dict[str, Any] = dict(dt=0.02, noise=0.01 if noise is None else noise,
                                      random_state=seed + 1)
        if drift:
            if not drift_events:
                raise DataError("a drift needs at least one event time")
            return HydraulicPlant.with_pole_drift(
                drift, events=tuple(drift_events), ramp_time=2.0, base_temperature=20.0, **kwargs
            )
        return HydraulicPlant(temperature=20.0, **kwargs)
    if kind == "tclab":
        kwargs = {} if noise is None else {"noise": noise}
        return TCLabPlant(dt=1.0, random_state=seed, **kwargs)
    if kind == "replay":
        if not arg:
            raise DataError("replay needs a file: --plant replay:FILE.csv")
        return ReplayPlant.from_csv(arg)
    raise DataError(f"unknown plant {spec!r}; use hydraulic, tclab or replay:FILE")


# --------------------------------------------------------------------------- records
@dataclass(frozen=True)
class TwinEvent:
    """Something that happened during a run.

    Parameters
    ----------
    kind : str
        ``'phase'``, ``'drift'``, ``'desync'``, ``'resync'``, ``'model-update'``,
        ``'model-rejected'``, ``'model-version'``, ``'controller'``,
        ``'controller-rejected'``, ``'estimator-update'``, ``'estimator-rejected'`` or
        ``'resume'``.
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
    """The twin after one sample (what :meth:`DigitalTwin.step` returns).

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
        First sample after the identification phase.
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
        The initial identification: ``fit_percent, poles, offset, elapsed``.
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


# --------------------------------------------------------------------------- controller
def _filter_states(
    A: NDArray, B: NDArray, w: NDArray, n_keep: int = 2
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Last two states ``x(n), x(n-1)`` of ``x(k+1) = A x(k) + B w(k)`` from rest."""
    x = np.zeros(A.shape[0])
    prev = x.copy()
    for wk in w.tolist():
        prev = x
        x = A @ x + B * wk
    return x, prev


@dataclass(frozen=True, eq=False)
class _PreparedController:
    """An MPC problem and its filter states after the first ``n`` samples of the histories."""

    model: KautzModel
    settings: MPCSettings
    problem: MPCProblem
    A: NDArray[np.float64]
    B: NDArray[np.float64]
    c: NDArray[np.float64]
    xv: NDArray[np.float64]
    xv_prev: NDArray[np.float64]
    xd: NDArray[np.float64]
    n: int


def _prepare_controller(
    model: KautzModel, settings: MPCSettings, v_history: ArrayLike, d_history: ArrayLike,
    input_offset: float,
) -> _PreparedController:
    """Build the problem and the filter states (a pure function: it also runs in the worker)."""
    problem = build_mpc(model, settings)
    A = np.array(model.basis.A)
    B = np.array(model.basis.B)
    c = np.array(model.coefficients)
    v = np.asarray(v_history, dtype=float) - input_offset
    d = np.asarray(d_history, dtype=float)
    xv, xv_prev = _filter_states(A, B, v)
    xd, _ = _filter_states(A, B, d)
    return _PreparedController(model, settings, problem, A, B, c, xv, xv_prev, xd, int(v.size))


class MPCController:
    r"""The twin's prediction/control module: Laguerre MPC on the current model version.

    The MPC problem is built once per model version (:meth:`rebuild`) and
    re-solved every sample (:meth:`solve`).  The controller runs its own copy
    of the model's filter state, split into the part driven by its command
    ``v`` and the part driven by the excitation dither ``d``:

    .. math::

        x(k) = x_v(k) + x_d(k),\qquad
        \text{MPC state} = \big[x_v(k) - x_v(k-1);\ y(k) - c^T x_d(k)\big],

    so the controller tracks with the dither's predicted response removed
    from the feedback and does not fight the excitation.

    Parameters
    ----------
    input_offset : float, default=0.0
        The models' input operating point :math:`u_0`.

    Attributes
    ----------
    model : KautzModel or None
        The model the controller runs on.
    settings : MPCSettings or None
        Its design.
    problem : MPCProblem or None
        The built problem.
    n_builds : int
        Times the problem was built.

    Examples
    --------
    >>> import numpy as np
    >>> import kautztwin as kt
    >>> from kautztwin.twin.optimize import MPCSettings
    >>> from kautztwin.twin.runtime import MPCController
    >>> model = kt.KautzModel(kt.KautzBasis([0.9], dt=0.1, delayed=True), [1.0])
    >>> ctl = MPCController()
    >>> ctl.rebuild(model, MPCSettings(30, 0.7, 3, 0.1, u_min=-1, u_max=1, du_max=0.5),
    ...             np.zeros(10), np.zeros(10))
    >>> res = ctl.solve(0.0, 1.0, 0.0)
    >>> res.success, 0.0 < res.u_next <= 0.5
    (True, True)
    """

    def __init__(self, *, input_offset: float = 0.0) -> None:
        self.input_offset = float(input_offset)
        self.model: KautzModel | None = None
        self.settings: MPCSettings | None = None
        self.problem: MPCProblem | None = None
        self.n_builds = 0

    def rebuild(
        self, model: KautzModel, settings: MPCSettings, v_history: ArrayLike,
        d_history: ArrayLike,
    ) -> None:
        """Build the problem for ``model`` and rebuild the filter states from the histories.

        Parameters
        ----------
        model : KautzModel
            The model version (delayed discrete basis).
        settings : MPCSettings
            The design.
        v_history, d_history : array-like of shape (n_samples,)
            Commands and dither applied so far (the plant at rest at the
            input offset before them).
        """
        self._install(_prepare_controller(model, settings, v_history, d_history,
                                          self.input_offset))

    def _install(
        self, prepared: _PreparedController, v_since: ArrayLike = (), d_since: ArrayLike = ()
    ) -> None:
        """Run on a prepared controller, advanced over the samples applied since it was prepared.

        The advance repeats the operations of :func:`_filter_states`, so the
        states equal those of a :meth:`rebuild` on the whole history, bit for bit.
        """
        self.problem = prepared.problem
        self.model = prepared.model
        self.settings = prepared.settings
        self._A, self._B, self._c = prepared.A, prepared.B, prepared.c
        self._xv, self._xv_prev, self._xd = prepared.xv, prepared.xv_prev, prepared.xd
        for v, d in zip(np.asarray(v_since, dtype=float).tolist(),
                        np.asarray(d_since, dtype=float).tolist(), strict=True):
            self.advance(v, d)
        self.n_builds += 1

    def solve(self, y: float, reference: float, v_prev: float) -> MPCResult:
        """Solve the MPC for the current sample.

        Parameters
        ----------
        y : float
            Output feedback (measured, or the twin's prediction for a bad sample).
        reference : float
            Reference (filtered set-point).
        v_prev : float
            Previous command.

        Returns
        -------
        MPCResult
        """
        if self.problem is None:
            raise TwinError("the controller has no model yet; call rebuild() first")
        y_eff = float(y) - float(self._c @ self._xd)
        x = np.concatenate([self._xv - self._xv_prev, [y_eff]])
        return self.problem.solve(x, reference, u_prev=v_prev)

    def advance(self, v: float, d: float) -> None:
        """Advance the filter states with the command and dither applied over this period.

        Parameters
        ----------
        v, d : float
        """
        self._xv_prev = self._xv
        self._xv = self._A @ self._xv + self._B * (float(v) - self.input_offset)
        self._xd = self._A @ self._xd + self._B * float(d)

    def __repr__(self) -> str:
        n = None if self.model is None else self.model.n_functions
        return f"MPCController(n_functions={n}, builds={self.n_builds})"


# --------------------------------------------------------------------------- background jobs
_Prepared = tuple[KautzModel, MPCSettings, _PreparedController | DataError]


@dataclass(frozen=True, eq=False)
class _TuningOutcome:
    """A weight retuning and the controllers built for what the main thread will run."""

    tuning: ControllerTuning
    prepared: tuple[_Prepared, ...]


@dataclass(eq=False)
class _OptimizationJob:
    """The optimisation of one model version in the worker: interim controller, tuning, retraining.

    A part is ``None`` before the job is submitted and again once it is
    applied (or discarded).
    """

    version: int
    k: int
    t: float
    model: KautzModel
    initial: bool
    u_op: float
    y_op: float
    tune: bool
    estimator: Any
    interim: Future[_PreparedController] | None = None
    tuning: Future[_TuningOutcome] | None = None
    retraining: Future[EstimatorRetraining] | None = None
    submitted: bool = False


def _tune_in_worker(
    optimizer: TwinOptimizer, model: KautzModel, mpc: MPCSettings, step: float, u_op: float,
    y_op: float, initial: bool, current: MPCSettings,
    fallback: tuple[KautzModel, MPCSettings] | None, v_history: NDArray, d_history: NDArray,
    input_offset: float, interim: Future[_PreparedController] | None,
) -> _TuningOutcome:
    """Retune the weights, then build the controller the outcome asks for (worker thread).

    Reads its arguments only (immutable models and settings, copied
    histories): the rules of :meth:`DigitalTwin._apply_tuning` decide which
    controller runs next - the model with the tuned (or, for the first
    version, the running) weights, or the last validated controller when
    the tuning or the build fails - and it is built here, so that the main
    thread only advances it over the samples since.
    """
    tuning = optimizer.tune_controller(model, mpc, step=step, u_op=u_op, y_op=y_op)
    prepared: list[_Prepared] = []

    def prepare(m: KautzModel, s: MPCSettings) -> bool:
        try:
            p: _PreparedController | DataError = _prepare_controller(
                m, s, v_history, d_history, input_offset)
        except DataError as exc:
            p = exc
        prepared.append((m, s, p))
        return not isinstance(p, DataError)

    rebuild = tuning.accepted or initial
    ok = True
    if rebuild:
        settings = tuning.settings if tuning.accepted else current
        # the main thread already runs (model, current): built there (first version) or interim
        running = initial or (interim is not None and not interim.cancelled()
                              and interim.exception() is None)
        if not (running and settings == current):
            ok = prepare(model, settings)
    if (not rebuild or not ok) and fallback is not None:
        prepare(*fallback)
    return _TuningOutcome(tuning, tuple(prepared))


# --------------------------------------------------------------------------- helpers
def _binary(rng: np.random.Generator, n: int, amp: float, hold: tuple[int, int]) -> NDArray:
    """Random binary signal: +-amp, switching sign after each random hold time."""
    out: list[float] = []
    sign = float(rng.choice([-1.0, 1.0]))
    while len(out) < n:
        out += [amp * sign] * int(rng.integers(hold[0], hold[1]))
        sign = -sign
    return np.asarray(out[:n], dtype=float)


def _open_history(history: Any) -> tuple[HistoryStore, str, bool]:
    """``(store, where, owned)`` from a store, a path or None (an in-memory SQLite)."""
    if history is None:
        return SQLiteHistory(":memory:"), ":memory:", True
    if isinstance(history, str | os.PathLike):
        return SQLiteHistory(history), os.fspath(history), True
    if isinstance(history, HistoryStore):
        where = getattr(history, "path", type(history).__name__)
        return history, str(where), False
    raise DataError(
        f"history must be a HistoryStore, a path or None, got {type(history).__name__}"
    )


def _same(a: float, b: float, tol: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return abs(a - b) <= tol * max(1.0, abs(a), abs(b))


# --------------------------------------------------------------------------- the twin
class DigitalTwin:
    r"""The digital twin runtime: identify, then control, update, optimise and record.

    Parameters
    ----------
    plant : Plant
        The physical system.
    config : TwinConfig, optional
        The run; :meth:`TwinConfig.for_plant` of the plant when omitted.
    history : HistoryStore, str, os.PathLike or None, default=None
        The history store: a store, the path of a SQLite file (durable; a
        killed run resumes from it), or ``None`` for an in-memory SQLite database.
    clock : Clock, optional
        Pacing of the loop; as fast as possible when omitted.  A real-time
        clock waits for each sample's time (``speedup`` plant seconds per
        wall-clock second) and counts late ticks (its ``tolerance``).
    optimizer : TwinOptimizer, optional
        The optimization module; :class:`~kautztwin.twin.optimize.Optimizer`
        when omitted.
    background : bool or None, default=None
        Run the update module's re-identification in a worker thread, off
        the sampling path (``Updater(background=True)``), and the
        optimization module's work on each new model version (MPC weight
        retuning, estimator retraining) in a second one (see Notes).  ``None`` takes
        ``config.updater['background']`` when set, else turns it on only
        with a real-time ``clock``: there a synchronous attempt (tens of
        milliseconds to seconds) would make samples late, while a run as fast
        as possible gains nothing and stays reproducible only when
        synchronous (the sample at which a background candidate takes over
        depends on wall-clock time).  The replay of a resumed run is always
        synchronous.  :meth:`close` stops the workers.
    estimator : object, optional
        A trained DNN estimator (``kautztwin.nn.CoefficientEstimator`` or
        ``AdaptivePoleEstimator``, or any object with ``predict_models`` and
        ``fine_tune``) for the update module's step-test fast path
        (:meth:`Updater.update_from_step_test`).  With ``config.retune``, each
        new model version asks the optimizer to fine-tune it around the new
        operating point (:meth:`Optimizer.retrain_estimator`); a validated
        candidate replaces it (events ``'estimator-update'`` /
        ``'estimator-rejected'``).  It must have as many basis functions as the
        twin's models.

    Raises
    ------
    DataError
        If the configuration does not fit the plant (another ``dt``), or
        ``background`` is not a bool or ``None``.

    Attributes
    ----------
    updater : Updater or None
        The update module (after the identification phase).
    static : Updater or None
        The static twin (updates disabled), when ``config.static_twin``.
    controller : MPCController
        The prediction/control module.
    optimizer : TwinOptimizer
        The optimization module.
    background : bool
        Whether the update module re-identifies, and the optimization module
        retunes, in the background (resolved).
    history : HistoryStore
        The store.
    run_id : int or None
        The run in the store (after :meth:`start`).
    state : TwinState
        The latest state.

    See Also
    --------
    TwinConfig.for_plant : Tuned profiles of the shipped plants.
    kautztwin.twin.report.write_report : ``metrics.json``, ``report.md`` and plots.

    Notes
    -----
    **One sample** ``k`` (closed loop): read ``y(k)`` (with injected faults);
    sanitise it (a dropout, outlier or late sample is flagged, the controller
    then uses the twin's prediction instead); solve the MPC on the current
    model version for the command ``v(k)`` and apply ``u(k) = v(k) + d(k)``
    (a late sample holds the last input); update the twin and the static
    twin with ``(u(k), y(k))``; act on the update module's events (a
    ``'resync'`` asks the optimizer to re-optimise the poles or consolidate
    the fast path; a new model version is retuned and validated before the
    controller is rebuilt on it); step the plant; commit the sample (every
    ``commit_every`` samples in one transaction).

    **Resume.**  :meth:`start` with ``resume=True`` looks for an unfinished
    run with the same configuration in the store.  Its committed samples are
    replayed through the same code - the plant re-simulated with the stored
    inputs (a real board just continues), the stored outputs used and
    compared - so the run continues after the last committed sample with
    every component in the state it had, and nothing is stored twice.

    **Optimization in background mode.**  The step that produces a new
    model version stores it and queues one job for the optimization worker
    (a thread), then returns.  The worker builds the MPC on the new model
    with the running weights (the next step switches to it), then retunes
    the weights (:meth:`~kautztwin.twin.optimize.Optimizer.tune_controller`)
    and builds the controller the outcome asks for, then retrains the
    estimator, if any.  Every :meth:`step` applies what has finished with
    the rules, events and log entries of the synchronous path (a rejected
    tuning returns to the last validated controller, the one the
    synchronous path keeps); the tuning records and event payloads add
    ``k_submitted``, the sample at which the version appeared.  The worker
    reads immutable models and settings and copies of the command
    histories only, and never the history store; the controller it builds
    is advanced over the samples since with the operations of a rebuild, so
    it equals a rebuild on the whole history bit for bit.  At most one job
    is in flight: a newer version makes it stale, its unapplied parts are
    logged as ``'controller-rejected'`` / ``'estimator-rejected'`` ("discarded
    ...: version N superseded it"), and the newest version's job starts when
    the worker is free.  The first version's tuning runs there too: the
    first controller uses the configured weights until it comes in.

    Examples
    --------
    >>> from kautztwin.twin import HydraulicPlant
    >>> from kautztwin.twin.runtime import DigitalTwin, TwinConfig
    >>> plant = HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1)
    >>> cfg = TwinConfig.for_plant(plant, duration=12.0, quick=True, static_twin=False)
    >>> run = DigitalTwin(plant, cfg).run(progress=False)
    >>> run.n_done, run.status, int(run.arrays["version"][-1]) >= 1
    (600, 'finished', True)
    """

    def __init__(
        self,
        plant: Plant,
        config: TwinConfig | None = None,
        *,
        history: HistoryStore | str | os.PathLike[str] | None = None,
        clock: Clock | None = None,
        optimizer: TwinOptimizer | None = None,
        background: bool | None = None,
        estimator: Any = None,
    ) -> None:
        self.plant = plant
        self.estimator = estimator
        self.config = config if config is not None else TwinConfig.for_plant(plant)
        if abs(self.config.dt - float(plant.dt)) > 1e-9 * plant.dt:
            raise DataError(
                f"the configuration has dt = {self.config.dt:g} s but the plant samples at "
                f"{plant.dt:g} s"
            )
        self.history, self.store, self._owns_history = _open_history(history)
        self.clock = clock if clock is not None else Clock()
        if background is None:
            background = self.config.updater.get("background", self.clock.realtime)
        if not isinstance(background, bool | np.bool_):
            raise DataError(f"background must be True, False or None, got {background!r}")
        self.background = bool(background)
        self.optimizer: TwinOptimizer = optimizer if optimizer is not None else Optimizer()
        cfg = self.config
        self.controller = MPCController(input_offset=cfg.operating_input)
        self.updater: Updater | None = None
        self.static: Updater | None = None
        self.run_id: int | None = None
        self.state = TwinState(-1, math.nan, "identification")
        self._started = False
        self._opt_executor: ThreadPoolExecutor | None = None
        self._opt_job: _OptimizationJob | None = None
        self._opt_next: _OptimizationJob | None = None
        self._opt_waiting: list[Future[Any]] = []
        self._ctl_validated: tuple[KautzModel, MPCSettings] | None = None

    # ------------------------------------------------------------------ properties
    @property
    def digital_model(self) -> DigitalModel | None:
        """The current model version (``None`` before identification)."""
        return None if self.updater is None else self.updater.digital_model

    @property
    def k(self) -> int:
        """Index of the next sample."""
        return self._k if self._started else 0

    @property
    def done(self) -> bool:
        """Whether every sample of the run was processed."""
        return self._started and self._k >= self.config.n_samples

    @property
    def optimizing(self) -> bool:
        """Whether a background optimization job is in flight or waits for the worker."""
        return self._opt_job is not None or self._opt_next is not None

    def wait_optimization(self, timeout: float | None = None) -> bool:
        """Block until the worker has finished the optimization job in flight.

        The next :meth:`step` applies its results (and submits a queued job).

        Parameters
        ----------
        timeout : float, optional
            Most seconds to wait (no limit when omitted).

        Returns
        -------
        bool
            Whether no computation is outstanding any more.
        """
        job = self._opt_job
        futures = [f for f in (job.interim, job.tuning, job.retraining) if f is not None] if (
            job is not None) else []
        futures += self._opt_waiting
        if not futures:
            return True
        _, not_done = wait_futures(futures, timeout=timeout)
        return not not_done

    def what_if(self, u_plan: ArrayLike) -> NDArray[np.float64]:
        """Predict the plant's response to a planned input from the twin's current state.

        Parameters
        ----------
        u_plan : array-like of shape (n_steps,)
            Inputs of the next samples.

        Returns
        -------
        ndarray of shape (n_steps,)
            Predicted outputs of the same samples (the live model of the update module).

        Raises
        ------
        TwinError
            Before the identification phase has ended.
        """
        if self.updater is None:
            raise TwinError("the twin has no model yet (identification phase)")
        return self.updater.predict(np.asarray(u_plan, dtype=float))

    # ------------------------------------------------------------------ setup
    def start(self, *, resume: bool = True) -> TwinState:
        """Open the run: a new one, or resume an unfinished one with the same configuration.

        Parameters
        ----------
        resume : bool, default=True
            Look for an unfinished run with this configuration in the store
            and continue it after its last committed sample.

        Returns
        -------
        TwinState
            The state before the next sample (after the replay when resumed).

        Raises
        ------
        TwinError
            If the store's committed samples are not a contiguous prefix.
        """
        if self._started:
            raise TwinError("the run has already been started")
        cfg = self.config
        n = cfg.n_samples
        self._wall0 = time.perf_counter()
        self._arr: dict[str, NDArray[Any]] = {}
        for name in _ARRAYS:
            dtype = np.int64 if name in ("version", "flags") else float
            fill = 0 if dtype is np.int64 else math.nan
            self._arr[name] = np.full(n, fill, dtype=dtype)
        self._arr["mpc_ok"] = np.ones(n)
        rng = np.random.default_rng(cfg.seed)
        self._u_ident = cfg.ident_level + _binary(rng, cfg.n_ident, cfg.ident_amplitude,
                                                  cfg.ident_hold)
        self._d = _binary(rng, n, cfg.dither, cfg.dither_hold) if cfg.dither > 0 else np.zeros(n)
        self._faults = self._fault_plan(n)
        self._sanitizer = self._make_sanitizer()
        self._events: list[TwinEvent] = []
        self._versions: list[dict[str, Any]] = []
        self._tunings: list[dict[str, Any]] = []
        self._ident_info: dict[str, Any] = {}
        self._pending: list[tuple[int, float, float, float, int]] = []
        self._committed = 0
        self._k = 0
        self._k_cl = cfg.n_ident
        self._v_prev = cfg.operating_input
        self._d_prev = 0.0
        self._u_prev = cfg.operating_input
        self._ref = math.nan
        self._late_ticks = 0
        self._mpc_failures = 0
        self._drift_logged: set[float] = set()
        self._replay_rows: Any = None
        self._replay_mismatch = 0
        self._resume_k = 0
        self._stored_events: set[tuple[str, int | None]] = set()
        self._stored_versions: set[int] = set()
        self._version = 0
        self._version_offset: dict[int, float] = {}
        run_id, resumed = self._open_run(resume)
        self.run_id = run_id
        self._reading = self.plant.reset()
        self._t_offset = 0.0
        self._replayable = not getattr(self.plant, "connected", False)
        self._started = True
        self.clock.start()
        self._clock_t0 = 0.0
        if resumed is not None:
            self._resume_k = resumed
            while self._k < resumed:
                self.step()
            if not self._replayable and self._k < cfg.n_samples:
                # a real plant cannot be rewound: it continues from where it is now
                self._reading = self.plant.reset()
                self._t_offset = self._k * cfg.dt
            self._replay_rows = None
            if self.updater is not None:  # the replay ran synchronously
                self.updater.background = self.background
            self.clock.start()
            self._clock_t0 = self._k * cfg.dt
        return self.state

    def _open_run(self, resume: bool) -> tuple[int, int | None]:
        cfg_dict = {"twin": self.config.to_dict(), "plant": self.plant.name}
        if resume:
            for info in reversed(self.history.runs()):
                if info.status == "finished" or info.config != cfg_dict:
                    continue
                state = self.history.resume(info.run_id)
                rows = self.history.measurements(info.run_id)
                k = np.asarray(rows.k)
                if not np.array_equal(k, np.arange(k.size)):
                    raise TwinError(
                        f"run {info.run_id} in {self.store} has non-contiguous samples; "
                        "it cannot be resumed"
                    )
                self._replay_rows = rows
                self._committed = int(k.size)
                self._stored_events = {
                    (e.kind, e.k) for e in self.history.events(info.run_id)
                }
                self._stored_versions = {
                    v.version for v in self.history.model_versions(info.run_id)
                }
                self._event("resume", state.next_k, math.nan,
                            f"resumed after sample {state.last_k} ({state.n_samples} committed "
                            f"samples, previous status {state.previous_status!r})",
                            {"last_k": state.last_k, "n_samples": state.n_samples},
                            store=False)
                return info.run_id, int(k.size)
        run_id = self.history.start_run(cfg_dict)
        return run_id, None

    def _make_sanitizer(self) -> SampleSanitizer:
        cfg = self.config
        return SampleSanitizer(
            threshold=cfg.sanitizer_threshold, window=cfg.sanitizer_window,
            min_scale=cfg.sensor_scale,
        )

    def _fault_plan(self, n: int) -> dict[str, NDArray]:
        f = self.config.faults
        rng = np.random.default_rng([self.config.seed, 7919])
        a, b, c, s = rng.random(n), rng.random(n), rng.random(n), rng.random(n)
        active = np.arange(n) >= self.config.n_ident
        drop = active & (a < f.dropout)
        out = active & (b < f.outlier) & ~drop
        late = active & (c < f.late) & ~drop & ~out
        late[1:] &= ~late[:-1]
        return {"dropout": drop, "outlier": out, "late": late,
                "sign": np.where(s < 0.5, -1.0, 1.0)}

    # ------------------------------------------------------------------ events
    def _event(
        self, kind: str, k: int, t: float, message: str, payload: Mapping[str, Any] | None = None,
        *, store: bool = True,
    ) -> None:
        ev = TwinEvent(kind, int(k), float(t), message, dict(payload or {}))
        self._events.append(ev)
        if store and (kind, int(k)) not in self._stored_events and self.run_id is not None:
            self.history.log_event(
                self.run_id, kind, message, k=int(k), t=None if math.isnan(t) else float(t),
                payload=_json_ready(dict(payload or {})),
            )

    def _store_version(self, dm: DigitalModel, k: int, t: float, offset: float) -> None:
        self._version_offset[dm.version] = float(offset)
        poles = [[float(p.real), float(p.imag)] for p in dm.model.poles]
        rec = {"version": dm.version, "k": int(k), "t": float(t), "provenance": dm.provenance,
               "fit_percent": dm.fit_percent, "offset": float(offset),
               "n_functions": dm.model.n_functions, "poles": poles}
        self._versions.append(rec)
        if dm.version not in self._stored_versions and self.run_id is not None:
            self.history.add_model_version(self.run_id, dm, k=int(k))
            self._stored_versions.add(dm.version)
        self._event("model-version", k, t,
                    f"model version {dm.version} ({dm.provenance})", rec)

    # ------------------------------------------------------------------ one sample
    def step(self) -> TwinState:
        """Process the next sample and return the new state.

        Returns
        -------
        TwinState

        Raises
        ------
        TwinError
            If the run was not started or is complete.
        """
        if not self._started:
            raise TwinError("call start() (or run()) first")
        cfg = self.config
        k = self._k
        if k >= cfg.n_samples:
            raise TwinError(f"the run is complete ({cfg.n_samples} samples)")
        replay = self._replay_rows is not None and k < self._resume_k
        reading = self._reading
        t_k = reading.t + self._t_offset
        y_raw = float(reading.y)
        fp = self._faults
        if fp["dropout"][k]:
            y_raw = math.nan
        elif fp["outlier"][k]:
            y_raw += fp["sign"][k] * cfg.faults.outlier_size
        if fp["late"][k]:
            t_k -= cfg.dt
        if replay:
            row = self._replay_rows
            assert row is not None
            t_s, y_s = float(row.t[k]), float(row.y[k])
            if not (_same(t_s, t_k, 1e-9) and _same(y_s, y_raw, 1e-9)):
                self._replay_mismatch += 1
            t_k, y_raw = t_s, y_s
        events: list[str] = []
        n_ev = len(self._events)
        for e in getattr(self.plant, "drift_events", ()):
            if t_k >= e and e not in self._drift_logged:
                self._drift_logged.add(e)
                self._event("drift", k, t_k, f"plant drift event at {e:g} s", {"t_event": e})
        s = self._sanitizer.process(y_raw, t_k)
        late = bool(s.flags & SampleFlag.LATE and s.flags & SampleFlag.HELD)
        clean = not (s.flags & (SampleFlag.HELD | SampleFlag.OUTLIER))
        a = self._arr
        a["t"][k], a["y"][k], a["flags"][k] = t_k, y_raw, int(s.flags)
        a["y_clean"][k] = y_raw if clean else math.nan
        if self._opt_job is not None or self._opt_next is not None:
            self._poll_optimization(k, t_k)  # background: apply what the worker has finished

        mpc_ms = math.nan
        v = d = math.nan
        # ---------------------------------------------------------- input
        if k < self._k_cl:
            phase = "identification"
            u = self._recorded_input(k) if not cfg.controlled else float(self._u_ident[k])
            v, d = u, 0.0
        elif not cfg.controlled:
            phase = "monitoring"
            u = self._recorded_input(k)
            v, d = u, 0.0
        else:
            phase = "closed-loop"
            if k == self._k_cl:
                self._begin_twin(k, t_k)
            assert self.updater is not None
            y_fb = y_raw if clean else self.updater.estimator_.predict()
            if math.isnan(self._ref):
                self._ref = y_fb
            sp = cfg.setpoint(t_k)
            if cfg.reference_tau > 0:
                alpha = 1.0 - math.exp(-cfg.dt / cfg.reference_tau)
                self._ref += alpha * (sp - self._ref)
            else:
                self._ref = sp
            a["setpoint"][k], a["reference"][k] = sp, self._ref
            if late:
                v, d = self._v_prev, self._d_prev
            else:
                res = self.controller.solve(y_fb, self._ref, self._v_prev)
                mpc_ms = 1e3 * res.solve_time
                a["mpc_ok"][k] = float(res.success)
                if not res.success:
                    self._mpc_failures += 1
                v, d = float(res.u_next), float(self._d[k])
            mpc = cfg.mpc
            assert mpc is not None
            u = float(np.clip(v + d, mpc.u_min, mpc.u_max))
            self.controller.advance(v, d)
        if k == self._k_cl and not cfg.controlled:
            self._begin_twin(k, t_k)
        if replay:
            u_s = float(self._replay_rows.u[k])  # type: ignore[union-attr]
            if not _same(u_s, u, 1e-9):
                self._replay_mismatch += 1
            u = u_s
        a["u"][k], a["command"][k], a["dither"][k], a["mpc_ms"][k] = u, v, d, mpc_ms
        self._v_prev, self._d_prev, self._u_prev = v, d, u

        # ---------------------------------------------------------- update
        upd_ms = math.nan
        fit = fit_s = math.nan
        if self.updater is not None and k >= self._k_cl:
            r = self.updater.step(u, y_raw, t_k)
            a["y_pred"][k] = r.y_pred_frozen
            if r.model_update is None:
                upd_ms = 1e3 * r.elapsed
            fit = self.updater.monitor.fit
            self._after_update(k, t_k, r)
            if self.static is not None:
                rs = self.static.step(u, y_raw, t_k)
                a["y_pred_static"][k] = rs.y_pred_frozen
                fit_s = self.static.monitor.fit
        a["update_ms"][k] = upd_ms
        a["version"][k] = self._version

        # ---------------------------------------------------------- plant, store
        if replay and not self._replayable:
            rows = self._replay_rows
            if k + 1 < len(rows.k):
                self._reading = Reading(float(rows.t[k + 1]), float(rows.y[k + 1]))
        elif k + 1 < cfg.n_samples:
            self._reading = self._plant_step(u)
            if not replay:
                late_s = self.clock.wait_until(self._reading.t + self._t_offset - self._clock_t0)
                if self.clock.realtime and late_s > self.clock.tolerance:
                    self._late_ticks += 1
        if not replay:
            self._pending.append((k, t_k, u, y_raw, int(s.flags)))
            if len(self._pending) >= cfg.commit_every or k + 1 == cfg.n_samples:
                self._flush()
        self._k = k + 1
        events = [e.kind for e in self._events[n_ev:]]
        self.state = TwinState(
            k, t_k, phase, y_raw, u, v if cfg.controlled else math.nan,
            a["setpoint"][k], a["reference"][k], a["y_pred"][k], a["y_pred_static"][k],
            int(s.flags), self._version, fit, fit_s, mpc_ms, upd_ms, tuple(events),
            self._committed, replay,
        )
        return self.state

    def _recorded_input(self, k: int) -> float:
        u = getattr(self.plant, "u", None)
        if u is not None and k < len(u):
            value = float(u[k])
            return value if math.isfinite(value) else self._u_prev
        return float(self._u_ident[k]) if k < self._u_ident.size else self._u_prev

    def _plant_step(self, u: float) -> Reading:
        if isinstance(self.plant, ReplayPlant):
            return self.plant.step(None)
        return self.plant.step(u)

    def _flush(self) -> None:
        if self._pending and self.run_id is not None:
            self.history.append_measurements(self.run_id, self._pending)
            self._committed += len(self._pending)
            self._pending = []

    # ------------------------------------------------------------------ identification
    def _begin_twin(self, k: int, t: float) -> None:
        """End of the identification phase: identify, build the twins and the controller."""
        cfg = self.config
        a = self._arr
        start = time.perf_counter()
        u_id = a["u"][:k].copy()
        y_id = a["y_clean"][:k].copy()
        try:
            fit = identify_output_error(
                u_id, y_id, cfg.n_poles, dt=cfg.dt, input_offset=cfg.operating_input,
                min_rate=cfg.min_rate,
            )
        except (DataError, ValueError) as exc:
            raise TwinError(f"the initial identification failed: {exc}") from exc
        rates = np.log(np.maximum(np.abs(fit.model.poles), 1e-12)) / cfg.dt
        slowest = float(np.max(rates))
        extra = [cfg.extra_pole_factor * slowest] if cfg.extra_pole_factor > 0 else None
        kw = dict(cfg.updater)
        kw.setdefault("min_rate", cfg.min_rate if cfg.min_rate is not None else -0.5 * slowest)
        # a resumed run replays its committed samples synchronously (as fast as possible)
        replaying = self._replay_rows is not None and k < self._resume_k
        kw["background"] = self.background and not replaying
        if self.estimator is not None:
            kw["estimator"] = self.estimator
        self.updater = Updater.from_fit(
            fit, dt=cfg.dt, forgetting=cfg.forgetting, extra_poles=extra,
            monitor=self._make_monitor(), sanitizer=self._make_sanitizer(), **kw,
        )
        if cfg.static_twin:
            self.static = Updater.from_fit(
                fit, dt=cfg.dt, fast_update=False, reidentify=False,
                monitor=self._make_monitor(), sanitizer=self._make_sanitizer(),
                **{key: val for key, val in kw.items() if key in ("buffer_size", "burn_in",
                                                                   "reid_samples")},
            )
        for j in range(k):  # the twins catch up on the identification samples
            r = self.updater.step(a["u"][j], a["y"][j], a["t"][j])
            a["y_pred"][j] = r.y_pred_frozen
            if self.static is not None:
                rs = self.static.step(a["u"][j], a["y"][j], a["t"][j])
                a["y_pred_static"][j] = rs.y_pred_frozen
        self._ident_info = {
            "fit_percent": fit.fit_percent, "offset": fit.offset,
            "poles": [[float(p.real), float(p.imag)] for p in fit.model.poles],
            "continuous_poles": [float(r) for r in np.sort(rates)],
            "n_samples": int(k), "elapsed": time.perf_counter() - start,
        }
        self._event("phase", k, t, f"identified the initial model: fit {fit.fit_percent:.2f} %",
                    self._ident_info)
        dm = self.updater.digital_model
        self._version = dm.version
        self._store_version(dm, k, t, self.updater.offset)
        if cfg.controlled and self._offloaded(k):
            # the first controller runs on the configured weights until the tuning ends
            assert cfg.mpc is not None
            self._rebuild_controller(dm.model, cfg.mpc, k)
            self._offload(dm, k, t, initial=True)
            self._event("phase", k, t, "closed loop: MPC tracking with twin updates", {})
        elif cfg.controlled:
            self._retune_controller(k, t, initial=True)
            self._event("phase", k, t, "closed loop: MPC tracking with twin updates", {})
        else:
            self._event("phase", k, t, "monitoring: the twin follows the recorded plant", {})

    def _make_monitor(self) -> SyncMonitor:
        cfg = self.config
        return SyncMonitor(window=cfg.monitor_window, stride=cfg.monitor_stride,
                           threshold=cfg.monitor_threshold, n_consecutive=cfg.monitor_consecutive)

    # ------------------------------------------------------------------ optimisation
    def _after_update(self, k: int, t: float, r: UpdateResult) -> None:
        cfg = self.config
        upd = self.updater
        assert upd is not None
        if r.model_update is not None:
            self._log_model_update(r.model_update, k, t)
        resync = False
        for ev in r.events:
            self._log_sync(ev, k, t)
            resync |= ev.kind == "resync"
        if resync and cfg.retune and k >= self._k_cl:
            mu = self.optimizer.retune_model(upd)
            if mu is not None:
                self._log_model_update(mu, k, t, kind="pole re-optimisation")
            if (mu is None or not mu.accepted) and upd.digital_model.version == self._version:
                current = upd.digital_model.model
                offset = self._version_offset.get(self._version, upd.offset)
                better, f_live, f_cur = self.optimizer.consolidate(
                    upd, current, offset, self._arr["u"][: k + 1], self._arr["y_clean"][: k + 1]
                )
                payload = {"fit_live": f_live, "fit_current": f_cur}
                if better:
                    upd.snapshot("rls-consolidation")
                    self._event("model-update", k, t,
                                f"consolidated the fast path: fit {f_live:.2f} % vs the "
                                f"current version's {f_cur:.2f} %", payload)
                else:
                    self._event("model-rejected", k, t,
                                f"kept the current version: fast path {f_live:.2f} % vs "
                                f"{f_cur:.2f} %", payload)
        dm = upd.digital_model
        if dm.version != self._version:
            self._version = dm.version
            self._store_version(dm, k, t, upd.offset)
            if self._offloaded(k):
                self._offload(dm, k, t)
                return
            if cfg.retune and upd.dnn is not None:
                self._retrain_estimator(dm, k, t)
            if cfg.controlled and cfg.retune:
                self._retune_controller(k, t)
            elif cfg.controlled:
                self._rebuild_or_keep(dm.model, self.controller.settings or cfg.mpc, k, t,
                                      {"k": int(k), "t": float(t), "version": dm.version})

    def _retrain_estimator(self, dm: DigitalModel, k: int, t: float) -> None:
        """Fine-tune the DNN around the new version; keep the old one unless the new one wins."""
        upd = self.updater
        assert upd is not None
        try:
            rt: EstimatorRetraining | KautzTwinError = self.optimizer.retrain_estimator(
                upd.dnn, dm.model)
        except KautzTwinError as exc:  # e.g. the estimator has another number of functions
            rt = exc
        self._apply_retraining(rt, dm.version, k, t)

    def _apply_retraining(
        self, rt: EstimatorRetraining | KautzTwinError, version: int, k: int, t: float,
        extra: Mapping[str, Any] | None = None,
    ) -> None:
        """Log a retraining (or why there is none) and run on an accepted candidate."""
        upd = self.updater
        assert upd is not None
        if isinstance(rt, KautzTwinError):
            self._event("estimator-rejected", k, t, f"estimator not retrained: {rt}",
                        {**(extra or {})})
            return
        self._event("estimator-update" if rt.accepted else "estimator-rejected", k, t,
                    f"estimator retraining for version {version}: {rt.reason}",
                    {**rt.payload(), **(extra or {})})
        if rt.accepted:
            upd.dnn = rt.estimator
            self.estimator = rt.estimator

    def _log_model_update(self, mu: ModelUpdate, k: int, t: float, kind: str = "") -> None:
        what = kind or mu.kind
        payload = {key: val for key, val in mu.payload().items() if key != "model"}
        self._event("model-update" if mu.accepted else "model-rejected", k, t,
                    f"{what}: {mu.reason}", payload)

    def _log_sync(self, ev: SyncEvent, k: int, t: float) -> None:
        self._event(ev.kind, k, t, ev.message, ev.payload())

    def _tuning_point(self, k: int) -> tuple[KautzModel, int, float, float]:
        """``(model, version, u_op, y_op)``: where the weight retuning of sample ``k`` starts."""
        upd = self.updater
        assert upd is not None
        y_op = float(self._arr["y_clean"][k]) if math.isfinite(self._arr["y_clean"][k]) else (
            float(upd.estimator_.predict()))
        return upd.digital_model.model, upd.digital_model.version, self._v_prev, y_op

    def _retune_controller(self, k: int, t: float, *, initial: bool = False) -> None:
        cfg = self.config
        assert self.updater is not None and cfg.mpc is not None
        model, version, u_op, y_op = self._tuning_point(k)
        tuning = self.optimizer.tune_controller(
            model, cfg.mpc, step=cfg.tuning_step(), u_op=u_op, y_op=y_op
        )
        self._apply_tuning(tuning, model, version, k, t, initial=initial)

    def _apply_tuning(
        self, tuning: ControllerTuning, model: KautzModel, version: int, k: int, t: float, *,
        initial: bool, prepared: Sequence[_Prepared] | None = None,
        extra: Mapping[str, Any] | None = None,
    ) -> None:
        """Rebuild the controller on a validated tuning, or keep the running one.

        ``prepared`` (background mode): the controllers the worker built for
        the outcome; without it the controller is built here.
        """
        cfg = self.config
        rec = {"k": int(k), "t": float(t), "version": version, **tuning.payload(),
               **(extra or {})}
        self._tunings.append(rec)
        if tuning.accepted or initial or self.controller.problem is None:
            settings = tuning.settings if tuning.accepted else (self.controller.settings or cfg.mpc)
            if not self._rebuild_or_keep(model, settings, k, t, rec, prepared):
                self._restore_validated(k, prepared)
                return
            self._event("controller", k, t,
                        f"MPC rebuilt on version {version}: {tuning.reason}", rec)
        else:
            self._restore_validated(k, prepared)
            self._event("controller-rejected", k, t,
                        f"kept the controller: {tuning.reason}", rec)

    def _rebuild_or_keep(
        self, model: KautzModel, settings: MPCSettings, k: int, t: float, rec: dict[str, Any],
        prepared: Sequence[_Prepared] | None = None,
    ) -> bool:
        """Rebuild on a new version; keep the running controller if its QP cannot be set up.

        A model version that passed validation can still give a QP that the
        solver refuses (e.g. DAQP's setup on a nearly input-independent
        output row); the loop must not stop for it.  Only the first build
        (no controller yet) raises.
        """
        if self.controller.problem is None:
            self._build(model, settings, k, prepared)
            self._ctl_validated = (model, settings)
            return True
        try:
            self._build(model, settings, k, prepared)
        except DataError as exc:
            self._event("controller-rejected", k, t,
                        f"kept the controller: the MPC on version {rec.get('version')} cannot "
                        f"be set up ({exc})", rec)
            return False
        self._ctl_validated = (model, settings)
        return True

    def _build(
        self, model: KautzModel, settings: MPCSettings, k: int,
        prepared: Sequence[_Prepared] | None,
    ) -> None:
        """Run the controller on ``(model, settings)``: built here, or prepared by the worker."""
        if prepared is not None:
            ctl = self.controller
            if ctl.model is model and ctl.settings == settings:
                return  # the interim controller of this version already runs it
            for m, s, p in prepared:
                if m is model and s == settings:
                    if isinstance(p, DataError):
                        raise p
                    self._install(p, k)
                    return
        self._rebuild_controller(model, settings, k)

    def _restore_validated(self, k: int, prepared: Sequence[_Prepared] | None) -> None:
        """Background mode: back to the last validated controller after the interim one.

        Synchronously the running controller is always the validated one.
        """
        if prepared is None or self._ctl_validated is None:
            return
        model, settings = self._ctl_validated
        try:
            self._build(model, settings, k, prepared)
        except DataError:  # pragma: no cover - it was built before
            pass

    def _history_length(self, k: int) -> int:
        """Samples of the command history that the controller state covers at sample ``k``."""
        a = self._arr
        if k >= self._k_cl and a["command"][k] == a["command"][k]:  # this sample's command is in
            return k + 1
        return k

    def _rebuild_controller(self, model: KautzModel, settings: MPCSettings, k: int) -> None:
        """Build the controller; the histories end with the sample being processed."""
        a = self._arr
        n = self._history_length(k)
        self.controller.rebuild(model, settings, a["command"][:n], a["dither"][:n])

    def _install(self, prepared: _PreparedController, k: int) -> None:
        """Run on a controller the worker prepared, advanced to sample ``k``."""
        a = self._arr
        n = self._history_length(k)
        self.controller._install(prepared, a["command"][prepared.n:n], a["dither"][prepared.n:n])

    # ------------------------------------------------------------------ optimisation, background
    def _offloaded(self, k: int) -> bool:
        """Whether a new version's optimisation runs in the worker (background, not replaying)."""
        replaying = self._replay_rows is not None and k < self._resume_k
        return self.background and self.config.retune and not replaying

    def _offload(self, dm: DigitalModel, k: int, t: float, *, initial: bool = False) -> None:
        """Queue the optimisation of a new version for the worker; it supersedes older ones."""
        cfg = self.config
        upd = self.updater
        assert upd is not None
        reason = f"version {dm.version} superseded it"
        if self._opt_job is not None:
            self._discard(self._opt_job, reason, k, t)
            self._opt_job = None
        if self._opt_next is not None:
            self._discard(self._opt_next, reason, k, t)
            self._opt_next = None
        estimator = None if initial else upd.dnn
        if not cfg.controlled and estimator is None:
            return
        model, version, u_op, y_op = self._tuning_point(k)
        self._opt_next = _OptimizationJob(version, k, t, model, initial, u_op, y_op,
                                          cfg.controlled, estimator)
        self._submit_next(k)

    def _discard(self, job: _OptimizationJob, reason: str, k: int, t: float) -> None:
        """Drop a stale job: log the parts not applied yet, cancel what has not started."""
        when = (f"submitted at sample {job.k}" if job.submitted
                else f"queued at sample {job.k}, not started")
        payload = {"version": job.version, "k_submitted": job.k, "discarded": reason}
        if job.tune and (job.tuning is not None or not job.submitted):
            self._event("controller-rejected", k, t,
                        f"discarded the MPC retuning for version {job.version} ({when}): "
                        f"{reason}", payload)
        if job.estimator is not None and (job.retraining is not None or not job.submitted):
            self._event("estimator-rejected", k, t,
                        f"discarded the estimator retraining for version {job.version} "
                        f"({when}): {reason}", payload)
        for fut in (job.interim, job.tuning, job.retraining):
            if fut is not None and not fut.cancel() and not fut.done():
                self._opt_waiting.append(fut)  # running: the next job waits for it
        job.interim = job.tuning = job.retraining = None

    def _submit_next(self, k: int) -> None:
        """Submit the queued job once the worker is free (one job in flight at most)."""
        job = self._opt_next
        if job is None or self._opt_job is not None:
            return
        self._opt_waiting = [f for f in self._opt_waiting if not f.done()]
        if self._opt_waiting:
            return
        self._opt_next = None
        cfg = self.config
        a = self._arr
        n = self._history_length(k)
        # the worker gets copies and immutable objects only
        v, d = a["command"][:n].copy(), a["dither"][:n].copy()
        if self._opt_executor is None:
            self._opt_executor = ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="kautztwin-optimize"
            )
        ex = self._opt_executor
        offset = self.controller.input_offset
        if job.tune:
            assert cfg.mpc is not None
            current = self.controller.settings or cfg.mpc
            if not job.initial:  # the new model with the running weights, until the tuning ends
                job.interim = ex.submit(_prepare_controller, job.model, current, v, d, offset)
            job.tuning = ex.submit(
                _tune_in_worker, self.optimizer, job.model, cfg.mpc, cfg.tuning_step(), job.u_op,
                job.y_op, job.initial, current, self._ctl_validated, v, d, offset, job.interim,
            )
        if job.estimator is not None:
            job.retraining = ex.submit(self.optimizer.retrain_estimator, job.estimator, job.model)
        job.submitted = True
        self._opt_job = job

    def _poll_optimization(self, k: int, t: float) -> None:
        """Apply what the worker has finished, in the order of the synchronous path."""
        job = self._opt_job
        if job is not None and job.version != self._version:  # pragma: no cover - defensive
            self._discard(job, f"version {self._version} superseded it", k, t)
            self._opt_job = job = None
        if job is not None:
            extra = {"k_submitted": job.k}
            if job.interim is not None and job.interim.done():
                fut, job.interim = job.interim, None
                try:
                    self._install(fut.result(), k)
                except DataError:  # keep the running one; the tuning's rebuild reports it
                    pass
            if job.interim is None and job.tuning is not None and job.tuning.done():
                fut_t, job.tuning = job.tuning, None
                out = fut_t.result()
                self._apply_tuning(out.tuning, job.model, job.version, k, t,
                                   initial=job.initial, prepared=out.prepared, extra=extra)
            if job.tuning is None and job.retraining is not None and job.retraining.done():
                fut_r, job.retraining = job.retraining, None
                try:
                    rt: EstimatorRetraining | KautzTwinError = fut_r.result()
                except KautzTwinError as exc:
                    rt = exc
                self._apply_retraining(rt, job.version, k, t, extra)
            if job.interim is None and job.tuning is None and job.retraining is None:
                self._opt_job = None
        self._submit_next(k)

    # ------------------------------------------------------------------ the loop
    def run(
        self, duration: float | None = None, *, resume: bool = True, progress: bool | None = None
    ) -> TwinRun:
        """Run (or resume) to the end and return the record.

        Parameters
        ----------
        duration : float, optional
            Override the configured duration, s.
        resume : bool, default=True
            Resume an unfinished run with the same configuration from the store.
        progress : bool or None, default=None
            Live progress display (tqdm on stderr): ``None`` shows it only on a
            terminal.

        Returns
        -------
        TwinRun
        """
        if duration is not None and not self._started:
            self.config = replace(self.config, duration=float(duration))
        if not self._started:
            self.start(resume=resume)
        bar = self._progress(progress)
        try:
            every = max(1, self.config.n_samples // 200)
            while self._k < self.config.n_samples:
                st = self.step()
                if bar is not None and (st.k % every == 0 or self._k == self.config.n_samples):
                    bar.update(self._k - bar.n)
                    bar.set_postfix_str(self._postfix(st), refresh=False)
        finally:
            if bar is not None:
                bar.close()
        return self.finish()

    def _progress(self, progress: bool | None) -> Any:
        if progress is False:
            return None
        from tqdm.auto import tqdm

        return tqdm(
            total=self.config.n_samples, initial=self._k, unit="sample",
            desc=f"twin {self.config.plant}", disable=None if progress is None else False,
            dynamic_ncols=True, leave=True,
        )

    def _postfix(self, st: TwinState) -> str:
        fit = "-" if math.isnan(st.fit) else f"{st.fit:.1f}%"
        return f"t={st.t:.1f}s {st.phase} v{st.version} fit={fit}"

    def finish(self, status: str | None = None) -> TwinRun:
        """Commit what is pending, mark the run and return its record.

        Parameters
        ----------
        status : str, optional
            Final status; ``'finished'`` when every sample was processed,
            else the run stays ``'running'`` (resumable).

        Returns
        -------
        TwinRun
        """
        if not self._started:
            raise TwinError("call start() (or run()) first")
        self._flush()
        complete = self._k >= self.config.n_samples
        final = status if status is not None else ("finished" if complete else "running")
        if final != "running" and self.run_id is not None:
            self.history.finish_run(self.run_id, final)
        return self.result(final)

    def result(self, status: str = "running") -> TwinRun:
        """The record of the samples processed so far.

        Parameters
        ----------
        status : str, default='running'

        Returns
        -------
        TwinRun
        """
        n = self._k
        arrays = {}
        for name, arr in self._arr.items():
            view = arr[:n].copy()
            view.setflags(write=False)
            arrays[name] = view
        counts = dict(self._sanitizer.counts)
        counts.update(late_ticks=self._late_ticks, mpc_failures=self._mpc_failures)
        if self.updater is not None:
            uc = self.updater.counts
            counts.update(reidentification_attempts=uc["attempts"],
                          reidentifications_accepted=uc["accepted"])
        return TwinRun(
            config=self.config, plant_name=self.plant.name, run_id=int(self.run_id or 0),
            store=self.store, n_done=n, k_closed_loop=self._k_cl,
            arrays=MappingProxyType(arrays), events=tuple(self._events),
            versions=tuple(MappingProxyType(v) for v in self._versions),
            tunings=tuple(MappingProxyType(v) for v in self._tunings),
            counts=MappingProxyType(counts), identification=MappingProxyType(self._ident_info),
            resume=MappingProxyType({
                "resumed": self._resume_k > 0, "resume_k": self._resume_k,
                "replayed": self._resume_k, "replay_mismatches": self._replay_mismatch,
            }),
            wall_time=time.perf_counter() - self._wall0, status=status,
        )

    def close(self) -> None:
        """Stop the workers, close the plant and the store if the twin opened it.

        A background re-identification still running is cancelled (its
        result is dropped); so is a background optimization job: what has
        not started is cancelled, a running part (a weight retuning, an
        estimator retraining) cannot be interrupted and is waited for, and
        the worker thread is joined.  Call :meth:`finish` first to commit
        the run.
        """
        for upd in (self.updater, self.static):
            if upd is not None:
                upd.close()
        for job in (self._opt_job, self._opt_next):
            for fut in (job.interim, job.tuning, job.retraining) if job is not None else ():
                if fut is not None:
                    fut.cancel()
        self._opt_job = self._opt_next = None
        self._opt_waiting = []
        if self._opt_executor is not None:
            self._opt_executor.shutdown(wait=True, cancel_futures=True)
            self._opt_executor = None
        self.plant.close()
        if self._owns_history:
            self.history.close()

    def __enter__(self) -> DigitalTwin:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"DigitalTwin(plant={self.plant.name!r}, k={self.k}/{self.config.n_samples}, "
            f"version={self._version if self._started else 0}, store={self.store!r})"
        )

