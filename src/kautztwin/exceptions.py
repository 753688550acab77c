"""Exception and warning classes of kautztwin.

Every error raised on bad user input derives from :class:`KautzTwinError`, so
callers (and the command-line interface) can catch the whole family at once and
report it in one line.
"""

from __future__ import annotations

__all__ = [
    "ConvergenceWarning",
    "DataError",
    "DimensionError",
    "ExportError",
    "KautzTwinError",
    "NotFittedError",
    "PoleError",
    "StabilityWarning",
    "TwinError",
    "UnstableModelError",
]


class KautzTwinError(Exception):
    """Base class of every error that kautztwin raises on bad input."""


class DimensionError(KautzTwinError, ValueError):
    """An array has the wrong number of dimensions, samples or columns."""


class DataError(KautzTwinError, ValueError):
    """Data are unusable: NaN or inf values, a missing column, an empty file."""


class PoleError(KautzTwinError, ValueError):
    """Basis poles are invalid: unstable, unpaired complex or not finite."""


class UnstableModelError(PoleError):
    """A pole lies outside the stability region (``Re >= 0`` or ``|z| >= 1``)."""


class NotFittedError(KautzTwinError, ValueError, AttributeError):
    """An estimator was used before ``fit`` was called."""


class ExportError(KautzTwinError, RuntimeError):
    """An export cannot be built here: no C compiler, or the compiler failed."""


class TwinError(KautzTwinError, RuntimeError):
    """The twin runtime cannot go on (identification impossible, store of another run, ...)."""


class ConvergenceWarning(UserWarning):
    """An iterative method stopped before it met its tolerance."""


class StabilityWarning(UserWarning):
    """A result is close to the stability boundary."""
