"""The training specification of ``kautztwin train --config SPEC.toml``.

A spec names the nominal model, its uncertainty, the noise, the time grid, the
basis (fixed poles or ``adaptive``), the preset and the budget.  Every key is
checked: an unknown key, a wrong type or an out-of-range value is a one-line
:class:`~kautztwin.exceptions.DataError` naming the key.

Example::

    [system]
    model = "paper"                    # or "tf" (num, den) or "zpk" (zeros, poles, gain)

    [uncertainty]
    default = 0.5                      # relative, every parameter
    # k = 0.2                          # per parameter, by name

    [noise]
    level = 0.1                        # std as a fraction of each record's peak
    kind = "white"                     # or "colored"

    [grid]
    t_end = 20.0
    n_samples = 900
    response = "impulse"               # or "step"

    [basis]
    poles = "nominal"                  # the nominal model's poles, a list, or "adaptive"

    [training]
    preset = "default"                 # or "paper"
    n_records = 50
    random_state = 0
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._validation import check_memory
from ..datasets import ParametricSystem, paper_system
from ..exceptions import DataError

__all__ = ["TrainSpec"]

#: float64 arrays of (records x samples) that training holds at once: the noisy and the
#: noise-free responses, and the network's scaled copy of the inputs with its gradients
_ARRAYS_PER_RECORD = 4

_SCHEMA: dict[str, dict[str, type | tuple[type, ...]]] = {
    "system": {
        "model": str,
        "num": list,
        "den": list,
        "zeros": list,
        "poles": list,
        "gain": (int, float),
        "name": str,
    },
    "uncertainty": {},  # parameter names, checked against the system
    "noise": {
        "level": (int, float),
        "kind": str,
        "color_pole": (int, float),
        "quantization": (int, float),
    },
    "grid": {"t_end": (int, float), "n_samples": int, "response": str},
    "basis": {"poles": (str, list)},
    "training": {
        "preset": str,
        "n_records": int,
        "random_state": int,
        "per_coefficient": bool,
        "max_epochs": int,
        "n_test": int,
    },
}


def _parse_complex(value: Any, key: str) -> complex:
    if isinstance(value, bool):
        raise DataError(f"{key}: expected a number, got {value!r}")
    if isinstance(value, (int, float)):
        return complex(value)
    if isinstance(value, str):
        try:
            return complex(value.replace(" ", "").replace("i", "j"))
        except ValueError:
            pass
    if (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        return complex(value[0], value[1])
    raise DataError(f"{key}: cannot read {value!r} as a number ('-0.5+1.9j' or [re, im])")


@dataclass(frozen=True)
class TrainSpec:
    """A validated training specification (see the module docstring for the format).

    Parameters
    ----------
    system : ParametricSystem
        Nominal model with named parameters.
    uncertainty : dict of str to float
        Relative uncertainty per parameter name.
    noise : float
        Noise standard deviation as a fraction of each record's peak.
    noise_kind : {'white', 'colored'}
    color_pole : float
        AR(1) pole of coloured noise.
    quantization : float or None
        Reading resolution.
    t : ndarray
        The time grid ``linspace(0, t_end, n_samples)``.
    kind : {'impulse', 'step'}
        Which response the records are.
    basis_poles : ndarray of complex or None
        Fixed basis poles; ``None`` for an adaptive basis.
    preset : {'default', 'paper'}
    n_records : int
        Training records (split 85/15 into training and validation).
    n_test : int
        Fresh test records for the summary.
    random_state : int
    per_coefficient : bool
        One network per coefficient (the paper) or one multi-output network.
    max_epochs : int or None
        Overrides the preset's epoch budget.
    """

    system: ParametricSystem
    uncertainty: dict[str, float]
    noise: float
    noise_kind: str
    color_pole: float
    quantization: float | None
    t: NDArray[np.float64] = field(repr=False)
    kind: str
    basis_poles: NDArray[np.complex128] | None
    preset: str
    n_records: int
    n_test: int
    random_state: int
    per_coefficient: bool
    max_epochs: int | None

    @property
    def adaptive(self) -> bool:
        """Whether the basis poles are predicted per record (adaptive estimator)."""
        return self.basis_poles is None

    @classmethod
    def from_toml(cls, path: str | Path) -> TrainSpec:
        """Read and validate a TOML spec file.

        Parameters
        ----------
        path : str or Path

        Returns
        -------
        TrainSpec

        Raises
        ------
        DataError
            Missing or unreadable file, TOML syntax error, unknown key, wrong type or value.
        """
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise DataError(f"cannot read the spec {path}: {exc.strerror or exc}") from exc
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise DataError(f"{path} is not valid TOML: {exc}") from exc
        return cls.from_dict(data)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainSpec:
        """Validate a spec given as nested dictionaries (the parsed TOML)."""
        for section, content in data.items():
            if section not in _SCHEMA:
                raise DataError(
                    f"unknown section [{section}] in the spec; valid: {', '.join(_SCHEMA)}"
                )
            if not isinstance(content, dict):
                raise DataError(f"[{section}] must be a table of keys")
            for key, value in content.items():
                if section == "uncertainty":
                    continue
                expected = _SCHEMA[section]
                if key not in expected:
                    raise DataError(
                        f"unknown key {section}.{key} in the spec; valid: {', '.join(expected)}"
                    )
                if isinstance(value, bool) and expected[key] is not bool:
                    raise DataError(f"{section}.{key} must not be a boolean")
                if not isinstance(value, expected[key]):
                    raise DataError(f"{section}.{key} has the wrong type ({type(value).__name__})")
        sys_cfg = data.get("system", {})
        system = _build_system(sys_cfg)
        unc_cfg = dict(data.get("uncertainty", {}))
        default = unc_cfg.pop("default", 0.0)
        uncertainty = {}
        for name in system.parameter_names:
            uncertainty[name] = _nonnegative(unc_cfg.pop(name, default), f"uncertainty.{name}")
        if unc_cfg:
            raise DataError(
                f"unknown parameter(s) {', '.join(sorted(unc_cfg))} in [uncertainty]; "
                f"the system has {', '.join(system.parameter_names)} (and 'default')"
            )
        noise_cfg = data.get("noise", {})
        noise_kind = noise_cfg.get("kind", "white")
        if noise_kind not in ("white", "colored"):
            raise DataError(f"noise.kind must be 'white' or 'colored', got {noise_kind!r}")
        color_pole = float(noise_cfg.get("color_pole", 0.9))
        if not 0 <= color_pole < 1:
            raise DataError(f"noise.color_pole must lie in [0, 1), got {color_pole}")
        quant = noise_cfg.get("quantization")
        if quant is not None and not quant > 0:
            raise DataError(f"noise.quantization must be positive, got {quant}")
        grid = data.get("grid", {})
        t_end = float(grid.get("t_end", 20.0))
        n_samples = int(grid.get("n_samples", 900))
        if not (np.isfinite(t_end) and t_end > 0):
            raise DataError(f"grid.t_end must be positive, got {t_end}")
        if n_samples < 10:
            raise DataError(f"grid.n_samples must be at least 10, got {n_samples}")
        kind = grid.get("response", "impulse")
        if kind not in ("impulse", "step"):
            raise DataError(f"grid.response must be 'impulse' or 'step', got {kind!r}")
        poles_cfg = data.get("basis", {}).get("poles", "nominal")
        if poles_cfg == "adaptive":
            basis_poles = None
        elif poles_cfg == "nominal":
            basis_poles = system.poles()
        elif isinstance(poles_cfg, list):
            basis_poles = np.array(
                [_parse_complex(v, f"basis.poles[{i}]") for i, v in enumerate(poles_cfg)]
            )
        else:
            raise DataError(
                f"basis.poles must be 'nominal', 'adaptive' or a list, got {poles_cfg!r}"
            )
        tr = data.get("training", {})
        preset = tr.get("preset", "default")
        if preset not in ("default", "paper"):
            raise DataError(f"training.preset must be 'default' or 'paper', got {preset!r}")
        n_records = int(tr.get("n_records", 50))
        n_test = int(tr.get("n_test", 200))
        if n_records < 10:
            raise DataError(f"training.n_records must be at least 10, got {n_records}")
        if n_test < 1:
            raise DataError(f"training.n_test must be positive, got {n_test}")
        check_memory(
            8.0 * _ARRAYS_PER_RECORD * float(n_records + n_test) * float(n_samples),
            f"training.n_records = {n_records} (+ training.n_test = {n_test}) records of "
            f"grid.n_samples = {n_samples} samples",
        )
        max_epochs = tr.get("max_epochs")
        if max_epochs is not None and max_epochs < 1:
            raise DataError(f"training.max_epochs must be positive, got {max_epochs}")
        return cls(
            system=system,
            uncertainty=uncertainty,
            noise=_nonnegative(noise_cfg.get("level", 0.0), "noise.level"),
            noise_kind=noise_kind,
            color_pole=color_pole,
            quantization=None if quant is None else float(quant),
            t=np.linspace(0.0, t_end, n_samples),
            kind=kind,
            basis_poles=basis_poles,
            preset=preset,
            n_records=n_records,
            n_test=n_test,
            random_state=int(tr.get("random_state", 0)),
            per_coefficient=bool(tr.get("per_coefficient", True)),
            max_epochs=None if max_epochs is None else int(max_epochs),
        )


def _nonnegative(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DataError(f"{key} must be a number, got {value!r}")
    if not (np.isfinite(value) and value >= 0):
        raise DataError(f"{key} must be a finite number >= 0, got {value}")
    return float(value)


def _build_system(cfg: dict[str, Any]) -> ParametricSystem:
    model = cfg.get("model", "paper")
    name = cfg.get("name", model)
    if model == "paper":
        extra = set(cfg) - {"model"}
        if extra:
            raise DataError(f"system.model = 'paper' takes no other keys; got {sorted(extra)}")
        return paper_system()
    if model == "tf":
        if "num" not in cfg or "den" not in cfg:
            raise DataError("system.model = 'tf' needs system.num and system.den")
        num = [_real(v, "system.num") for v in cfg["num"]]
        den = [_real(v, "system.den") for v in cfg["den"]]
        return ParametricSystem.from_transfer_function(num, den, name=name)
    if model == "zpk":
        if "poles" not in cfg:
            raise DataError("system.model = 'zpk' needs system.poles (and zeros, gain)")
        zeros = [_parse_complex(v, "system.zeros") for v in cfg.get("zeros", [])]
        poles = [_parse_complex(v, "system.poles") for v in cfg["poles"]]
        return ParametricSystem.from_zpk(zeros, poles, float(cfg.get("gain", 1.0)), name=name)
    raise DataError(f"system.model must be 'paper', 'tf' or 'zpk', got {model!r}")


def _real(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DataError(f"{key} must hold numbers, got {value!r}")
    return float(value)
