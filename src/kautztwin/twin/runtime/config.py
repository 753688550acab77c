"""Configuration of a twin run: :class:`TwinConfig` (shipped plant profiles), faults, set-points."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from ..._json import to_jsonable
from ..._validation import check_nonnegative
from ...exceptions import DataError
from ..physical import HydraulicPlant, Plant, ReplayPlant, TCLabPlant
from ..prediction import MPCSettings

__all__ = ["FaultConfig", "TwinConfig", "parse_setpoints"]


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


def _config_from_fields(cls: type, values: dict[str, Any]) -> Any:
    """Unpickle a :class:`TwinConfig` (its checks run again)."""
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
    monitor_resync_margin : float
        The monitor's ``resync_margin``: fit points above ``monitor_threshold``
        that a desynchronised twin must reach to resynchronise (0: the
        threshold itself).
    updater : mapping
        Further keyword arguments of :class:`~kautztwin.twin.Updater`
        (``'background'`` among them: see :class:`~kautztwin.twin.runtime.DigitalTwin`;
        ``'max_relative_width'`` defers a DNN update whose confidence band is wider
        than that share of the response).
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
    monitor_resync_margin: float = 0.0
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
        object.__setattr__(self, "monitor_resync_margin",
                           check_nonnegative(self.monitor_resync_margin, "monitor_resync_margin"))
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

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickle by fields (the read-only ``updater`` view as a dict): a process pool's copy."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values["updater"] = dict(self.updater)
        return (_config_from_fields, (type(self), values))

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
        return json.loads(json.dumps(to_jsonable(out), allow_nan=False))

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
                monitor_threshold=95.0, monitor_consecutive=2, monitor_resync_margin=1.0,
                updater={"min_rate": 1.0, "max_iter": 20 if quick else 30,
                         "quadratic_scale": 0.02, "directional_forgetting": True},
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
