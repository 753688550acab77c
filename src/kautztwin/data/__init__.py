"""Data: the reference systems of the paper and CSV loading."""

from __future__ import annotations

from .systems import reference_poles, reference_response, reference_system

__all__ = ["reference_poles", "reference_response", "reference_system"]
