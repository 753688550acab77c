"""Estimators for any plant family: ``kautztwin train --family FAMILY.toml``.

A family file gives the nominal model (a transfer function, poles/zeros/gain, or a
model identified by ``kautztwin identify``), parameter tolerances (uniform or normal,
per parameter or per pole factor), the noise level and colour (white, AR(1), drift),
the record kind and length, and the budget; everything but the nominal model has a
default.  Modules, one job each:

- :mod:`~kautztwin.nn.family.spec`: the file format and its checks (:class:`PlantFamily`);
- :mod:`~kautztwin.nn.family.records`: parameter draws, noise colours, data sets;
- :mod:`~kautztwin.nn.family.train`: training, calibration and the validation report.
"""

from __future__ import annotations

from .records import draw_family_parameters, drift_noise, family_dataset
from .spec import COLORS, DISTRIBUTIONS, PlantFamily
from .train import COVERAGE_LEVELS, train_family, validation_report, write_family_model

__all__ = [
    "COLORS",
    "COVERAGE_LEVELS",
    "DISTRIBUTIONS",
    "PlantFamily",
    "draw_family_parameters",
    "drift_noise",
    "family_dataset",
    "train_family",
    "validation_report",
    "write_family_model",
]
