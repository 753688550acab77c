"""The plant-family file of ``kautztwin train --family FAMILY.toml``: parsing and checks.

A family is a nominal model with parameter tolerances, a noise model and a record
format; everything but the nominal model has a default.  Every key is checked: an
unknown key, a wrong type or a bad value is a one-line :class:`~kautztwin.exceptions.DataError`
naming the key.  The parsed :class:`PlantFamily` compiles to what the training code
already consumes: a :class:`~kautztwin.datasets.ParametricSystem`, an uncertainty per
parameter for :func:`~kautztwin.datasets.draw_parameters`, and the noise options of
:func:`~kautztwin.datasets.make_dataset` (plus the drift, added on top).

Format (``examples/family_5th_order.toml`` is a complete one)::

    [plant]                     # one of: num/den, zeros/poles/gain, model = "FILE.json"
    zeros = [-2.0]
    poles = [-0.8, "-0.45+1.43j", "-0.45-1.43j", "-1.5+2.6j", "-1.5-2.6j"]
    gain = 3.0

    [tolerance]
    default = 0.3               # relative: half-width (uniform) or standard deviation (normal)
    distribution = "uniform"    # or "normal" (truncated to stable systems)
    # pole1 = 0.1               # per pole factor: every parameter of zpk factor 'pole1'
    # pole1_zeta = 0.2          # per parameter, by name (most specific wins)

    [noise]
    level = 0.05                # standard deviation, fraction of each record's peak
    color = "white"             # "white", "ar1" or "drift"
    ar1_pole = 0.9              # lag-1 autocorrelation of "ar1" noise, per sample
    drift = 0.05                # "drift": random walk's std at the record's end (default level)

    [record]
    kind = "impulse"            # or "step"
    t_end = 12.5                # default: 10 / slowest nominal decay rate
    n_samples = 500

    [training]
    n_records = 20000           # simulated training records (85/15 split)
    n_calibration = 1000        # fresh records that calibrate the uncertainty
    n_validation = 200          # fresh records of the validation report (oracle fits)
    random_state = 0
    # max_epochs = 100          # overrides the estimator's default budget

    [estimator]                 # AdaptivePoleEstimator options (defaults: its own)
    # hidden = [256, 256, 256]
    # n_features = 32
    # n_stages = 2
    # pretrain_epochs = 30
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..._validation import check_memory
from ...datasets import ParametricSystem
from ...exceptions import DataError, KautzTwinError

__all__ = ["COLORS", "DISTRIBUTIONS", "PlantFamily"]

#: Noise colours of a family.
COLORS: tuple[str, ...] = ("white", "ar1", "drift")
#: Tolerance distributions of a family.
DISTRIBUTIONS: tuple[str, ...] = ("uniform", "normal")
_T_END_DECAYS = 10.0  # default record length: this many slowest nominal time constants
_ARRAYS_PER_RECORD = 4  # float64 (records x samples) arrays held while training

_NUMBER = (int, float)
_SCHEMA: dict[str, dict[str, type | tuple[type, ...]]] = {
    "plant": {"num": list, "den": list, "zeros": list, "poles": list, "gain": _NUMBER,
              "model": str, "name": str},
    "tolerance": {"default": _NUMBER, "distribution": str},  # plus parameter/factor names
    "noise": {"level": _NUMBER, "color": str, "ar1_pole": _NUMBER, "drift": _NUMBER},
    "record": {"kind": str, "t_end": _NUMBER, "n_samples": int},
    "training": {"n_records": int, "n_calibration": int, "n_validation": int,
                 "random_state": int, "max_epochs": int},
    "estimator": {"hidden": list, "n_features": int, "n_stages": int, "pretrain_epochs": int},
}


def _complex(value: Any, key: str) -> complex:
    if isinstance(value, bool):
        raise DataError(f"{key}: expected a number, got {value!r}")
    if isinstance(value, _NUMBER):
        return complex(value)
    if isinstance(value, str):
        try:
            return complex(value.replace(" ", "").replace("i", "j"))
        except ValueError:
            pass
    if isinstance(value, list) and len(value) == 2 and all(
        isinstance(v, _NUMBER) and not isinstance(v, bool) for v in value
    ):
        return complex(value[0], value[1])
    raise DataError(f"{key}: cannot read {value!r} as a number (e.g. -0.5, '-0.5+1.9j', [re, im])")


def _real_list(values: list[Any], key: str) -> list[float]:
    out = []
    for i, v in enumerate(values):
        if isinstance(v, bool) or not isinstance(v, _NUMBER):
            raise DataError(f"{key}[{i}] must be a number, got {v!r}")
        out.append(float(v))
    return out


def _number(value: Any, key: str, *, low: float, high: float = np.inf,
            low_open: bool = False) -> float:
    v = float(value)
    ok = np.isfinite(v) and (v > low if low_open else v >= low) and v < high
    if not ok:
        lo = f"> {low:g}" if low_open else f">= {low:g}"
        hi = "" if high == np.inf else f" and < {high:g}"
        raise DataError(f"{key} must be {lo}{hi}, got {value!r}")
    return v


def _zpk_from_file(path: Path, base: Path | None) -> tuple[list[complex], list[complex], float]:
    """Zeros, poles and gain of a model file written by ``kautztwin identify --json``."""
    full = path if path.is_absolute() or base is None else base / path
    try:
        data = json.loads(full.read_text())
    except OSError as exc:
        raise DataError(f"plant.model: cannot read {full}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise DataError(f"plant.model: {full} is not JSON: {exc}") from None
    if not isinstance(data, dict) or "num" not in data or "den" not in data:
        raise DataError(
            f"plant.model: {full} has no 'num' and 'den' (write it with "
            "'kautztwin identify ... --json > FILE.json')"
        )
    delay = float(data.get("delay", 0.0) or 0.0)
    if delay > 0:
        raise DataError(
            f"plant.model: the identified model has a dead time of {delay:g} s; families with "
            "a delay are not supported (shift the records by the delay and identify without it)"
        )
    num = np.trim_zeros(np.asarray(_real_list(data["num"], "plant.model num")), "f")
    den = np.asarray(_real_list(data["den"], "plant.model den"))
    if num.size == 0 or den.size < 2 or den[0] == 0:
        raise DataError(f"plant.model: {full} holds a degenerate transfer function")
    return list(np.roots(num)), list(np.roots(den)), float(num[0] / den[0])


def _build_plant(cfg: dict[str, Any], base: Path | None) -> ParametricSystem:
    given = [k for k in ("num", "den", "zeros", "poles", "gain", "model") if k in cfg]
    name = str(cfg.get("name", "family"))
    if not given:
        raise DataError(
            "[plant] is required: give num and den, or poles (zeros, gain), or model = FILE.json"
        )
    try:
        if "model" in cfg:
            extra = [k for k in given if k != "model"]
            if extra:
                raise DataError(f"plant.model takes no other model keys; got {extra}")
            zeros, poles, gain = _zpk_from_file(Path(cfg["model"]), base)
            return ParametricSystem.from_zpk(zeros, poles, gain, name=name)
        if "num" in cfg or "den" in cfg:
            if "num" not in cfg or "den" not in cfg:
                raise DataError("plant.num and plant.den go together")
            extra = [k for k in ("zeros", "poles", "gain") if k in cfg]
            if extra:
                raise DataError(f"plant.num/den cannot be combined with {extra}")
            return ParametricSystem.from_transfer_function(
                _real_list(cfg["num"], "plant.num"), _real_list(cfg["den"], "plant.den"),
                name=name,
            )
        if "poles" not in cfg:
            raise DataError("plant.zeros/gain need plant.poles")
        zeros = [_complex(v, f"plant.zeros[{i}]") for i, v in enumerate(cfg.get("zeros", []))]
        poles = [_complex(v, f"plant.poles[{i}]") for i, v in enumerate(cfg["poles"])]
        gain = float(cfg.get("gain", 1.0))
        if gain == 0 or not np.isfinite(gain):
            raise DataError(f"plant.gain must be a nonzero number, got {cfg.get('gain')!r}")
        return ParametricSystem.from_zpk(zeros, poles, gain, name=name)
    except DataError as exc:
        msg = str(exc)
        raise DataError(msg if msg.startswith("plant") else f"[plant]: {msg}") from None
    except KautzTwinError as exc:
        raise DataError(f"[plant]: {exc}") from None


def _tolerances(cfg: dict[str, Any], system: ParametricSystem) -> dict[str, float]:
    """Relative tolerance per parameter: default, then per factor prefix, then per name."""
    default = _number(cfg.get("default", 0.3), "tolerance.default", low=0.0)
    out = dict.fromkeys(system.parameter_names, default)
    names = set(system.parameter_names)
    prefixes = {n.split("_")[0] for n in names if "_" in n}
    specific: dict[str, float] = {}
    for key, value in cfg.items():
        if key in ("default", "distribution"):
            continue
        if isinstance(value, bool) or not isinstance(value, _NUMBER):
            raise DataError(f"tolerance.{key} must be a number, got {value!r}")
        v = _number(value, f"tolerance.{key}", low=0.0)
        if key in names:
            specific[key] = v
        elif key in prefixes:
            for n in names:
                if n.startswith(key + "_") and n not in specific:
                    out[n] = v
        else:
            valid = sorted(names | prefixes)
            raise DataError(
                f"unknown key tolerance.{key}: the plant's parameters are {', '.join(valid)} "
                "(and 'default', 'distribution')"
            )
    out.update(specific)
    return out


def _estimator_options(cfg: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if "hidden" in cfg:
        h = cfg["hidden"]
        if not h or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in h):
            raise DataError(f"estimator.hidden must be a list of positive integers, got {h!r}")
        out["hidden"] = tuple(int(v) for v in h)
    for key, least in (("n_features", 1), ("n_stages", 1), ("pretrain_epochs", 0)):
        if key in cfg:
            if cfg[key] < least:
                raise DataError(f"estimator.{key} must be at least {least}, got {cfg[key]}")
            out[key] = int(cfg[key])
    return out


@dataclass(frozen=True)
class PlantFamily:
    """A validated plant family: nominal model, tolerances, noise, records, budget.

    Build it with :meth:`from_toml` or :meth:`from_dict` (the module docstring has the
    format and the defaults).

    Parameters
    ----------
    system : ParametricSystem
        The nominal model with named parameters.
    tolerance : dict of str to float
        Relative tolerance per parameter: the half-width (``uniform``) or the
        standard deviation (``normal``) as a share of the nominal value.
    distribution : {'uniform', 'normal'}
        Distribution of each parameter around its nominal value (draws that give
        an unstable system are redrawn).
    noise : float
        Noise standard deviation as a fraction of each record's noise-free peak
        (for ``drift``: of the white part).
    color : {'white', 'ar1', 'drift'}
        White noise; stationary AR(1) noise with lag-1 correlation ``ar1_pole``;
        or white noise plus a random walk from 0 whose standard deviation reaches
        ``drift`` (fraction of the peak) at the record's last sample.
    ar1_pole : float
        AR(1) pole in ``[0, 1)``.
    drift : float
        Size of the drift (``color='drift'`` only).
    kind : {'impulse', 'step'}
        Which response the records are.
    t : ndarray of shape (n_samples,)
        The time grid ``linspace(0, t_end, n_samples)``.
    n_records, n_calibration, n_validation : int
        Training, calibration and validation records.
    random_state : int
        Seed of everything.
    max_epochs : int or None
        Epoch budget of the estimator (``None``: its default).
    estimator : dict
        Constructor options of :class:`~kautztwin.nn.AdaptivePoleEstimator` given in
        ``[estimator]`` (empty: its defaults).
    source : dict
        The parsed file, as read.
    """

    system: ParametricSystem
    tolerance: dict[str, float]
    distribution: str
    noise: float
    color: str
    ar1_pole: float
    drift: float
    kind: str
    t: NDArray[np.float64] = field(repr=False)
    n_records: int
    n_calibration: int
    n_validation: int
    random_state: int
    max_epochs: int | None
    estimator: dict[str, Any] = field(default_factory=dict)
    source: dict[str, Any] = field(repr=False, default_factory=dict)

    @classmethod
    def from_toml(cls, path: str | Path) -> PlantFamily:
        """Read and validate a family file.

        Parameters
        ----------
        path : str or Path
            The TOML file; a ``plant.model`` path in it is relative to the file's folder.

        Returns
        -------
        PlantFamily

        Raises
        ------
        DataError
            Unreadable file, TOML syntax error, unknown key, wrong type or bad value.
        """
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise DataError(f"cannot read the family file {path}: {exc.strerror or exc}") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise DataError(f"{path} is not valid TOML: {exc}") from None
        return cls.from_dict(data, base=path.parent)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, base: str | Path | None = None) -> PlantFamily:
        """Validate a family given as nested dictionaries (the parsed TOML).

        Parameters
        ----------
        data : dict
            Sections ``plant`` (required), ``tolerance``, ``noise``, ``record``, ``training``.
        base : str or Path, optional
            Folder that a relative ``plant.model`` path is read from.

        Returns
        -------
        PlantFamily

        Raises
        ------
        DataError
            Unknown section or key, wrong type or bad value (one line naming the key).

        Examples
        --------
        >>> from kautztwin.nn.family import PlantFamily
        >>> fam = PlantFamily.from_dict({"plant": {"num": [2.0], "den": [1.0, 3.0, 2.0]}})
        >>> fam.system.parameter_names, fam.distribution, fam.color, float(fam.t[-1])
        (('num0', 'den1', 'den2'), 'uniform', 'white', 10.0)
        """
        if not isinstance(data, dict):
            raise DataError("the family must be a table of sections")
        for section, content in data.items():
            if section not in _SCHEMA:
                raise DataError(
                    f"unknown section [{section}] in the family; valid: {', '.join(_SCHEMA)}"
                )
            if not isinstance(content, dict):
                raise DataError(f"[{section}] must be a table of keys")
            for key, value in content.items():
                expected = _SCHEMA[section]
                if key not in expected:
                    if section == "tolerance":
                        continue  # parameter names: checked against the plant
                    raise DataError(
                        f"unknown key {section}.{key} in the family; valid: {', '.join(expected)}"
                    )
                if isinstance(value, bool) or not isinstance(value, expected[key]):
                    raise DataError(
                        f"{section}.{key} has the wrong type ({type(value).__name__})"
                    )
        system = _build_plant(data.get("plant", {}), None if base is None else Path(base))
        tol_cfg = data.get("tolerance", {})
        distribution = tol_cfg.get("distribution", "uniform")
        if distribution not in DISTRIBUTIONS:
            raise DataError(
                f"tolerance.distribution must be 'uniform' or 'normal', got {distribution!r}"
            )
        tolerance = _tolerances(tol_cfg, system)
        noise_cfg = data.get("noise", {})
        level = _number(noise_cfg.get("level", 0.05), "noise.level", low=0.0)
        color = noise_cfg.get("color", "white")
        if color not in COLORS:
            raise DataError(f"noise.color must be 'white', 'ar1' or 'drift', got {color!r}")
        ar1_pole = _number(noise_cfg.get("ar1_pole", 0.9), "noise.ar1_pole", low=0.0, high=1.0)
        drift = _number(noise_cfg.get("drift", level), "noise.drift", low=0.0)
        for key, applies in (("ar1_pole", "ar1"), ("drift", "drift")):
            if key in noise_cfg and color != applies:
                raise DataError(f"noise.{key} applies only to noise.color = '{applies}'")
        rec = data.get("record", {})
        kind = rec.get("kind", "impulse")
        if kind == "io":
            raise DataError(
                "record.kind = 'io' is not supported yet: the estimators read impulse or step "
                "records; use 'impulse' or 'step'"
            )
        if kind not in ("impulse", "step"):
            raise DataError(f"record.kind must be 'impulse' or 'step', got {kind!r}")
        slowest = float(np.min(np.abs(system.poles().real)))
        t_end = _number(rec.get("t_end", _T_END_DECAYS / slowest), "record.t_end",
                        low=0.0, low_open=True)
        n_samples = int(rec.get("n_samples", 500))
        if n_samples < 20:
            raise DataError(f"record.n_samples must be at least 20, got {n_samples}")
        tr = data.get("training", {})
        counts = {}
        for key, default, least in (("n_records", 20000, 10), ("n_calibration", 1000, 10),
                                    ("n_validation", 200, 1)):
            counts[key] = int(tr.get(key, default))
            if counts[key] < least:
                raise DataError(f"training.{key} must be at least {least}, got {counts[key]}")
        seed = int(tr.get("random_state", 0))
        if seed < 0:
            raise DataError(f"training.random_state must be >= 0, got {seed}")
        max_epochs = tr.get("max_epochs")
        if max_epochs is not None and max_epochs < 1:
            raise DataError(f"training.max_epochs must be positive, got {max_epochs}")
        estimator = _estimator_options(data.get("estimator", {}))
        check_memory(
            8.0 * _ARRAYS_PER_RECORD * float(max(counts.values())) * n_samples,
            f"training.n_records = {counts['n_records']} records of record.n_samples = "
            f"{n_samples} samples",
        )
        return cls(
            system=system, tolerance=tolerance, distribution=distribution, noise=level,
            color=color, ar1_pole=ar1_pole, drift=drift if color == "drift" else 0.0,
            kind=kind, t=np.linspace(0.0, t_end, n_samples), random_state=seed,
            max_epochs=None if max_epochs is None else int(max_epochs), estimator=estimator,
            source=data, **counts,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (what the trained model stores as its training data)."""
        return {
            "system": self.system.name,
            "parameter_names": list(self.system.parameter_names),
            "nominal": [float(v) for v in self.system.nominal],
            "nominal_poles": [[float(p.real), float(p.imag)] for p in self.system.poles()],
            "tolerance": dict(self.tolerance),
            "distribution": self.distribution,
            "noise": {"level": self.noise, "color": self.color, "ar1_pole": self.ar1_pole,
                      "drift": self.drift},
            "record": {"kind": self.kind, "t_end": float(self.t[-1]),
                       "n_samples": int(self.t.size)},
            "training": {"n_records": self.n_records, "n_calibration": self.n_calibration,
                         "n_validation": self.n_validation, "random_state": self.random_state,
                         "max_epochs": self.max_epochs},
            "estimator": {k: list(v) if isinstance(v, tuple) else v
                          for k, v in self.estimator.items()},
        }
