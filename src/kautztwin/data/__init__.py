"""Data: the reference systems of the paper and CSV loading."""

from __future__ import annotations

from .csv import read_columns
from .systems import reference_poles, reference_response, reference_system

__all__ = ["read_columns", "reference_poles", "reference_response", "reference_system"]
