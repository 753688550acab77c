"""Digital twin runtime: the digital model, sample sanitising and the history store."""

from __future__ import annotations

from .digital_model import DigitalModel
from .history import (
    SCHEMA_VERSION,
    Event,
    HistoryError,
    HistoryStore,
    Measurement,
    Measurements,
    MemoryHistory,
    Prediction,
    ResumeState,
    RunInfo,
    SQLiteHistory,
)
from .signals import SampleFlag, SampleSanitizer, SanitizedSample

__all__ = [
    "SCHEMA_VERSION",
    "DigitalModel",
    "Event",
    "HistoryError",
    "HistoryStore",
    "Measurement",
    "Measurements",
    "MemoryHistory",
    "Prediction",
    "ResumeState",
    "RunInfo",
    "SampleFlag",
    "SampleSanitizer",
    "SanitizedSample",
    "SQLiteHistory",
]
