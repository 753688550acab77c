"""End-to-end workflows: training specs, the paper's reproductions."""

from __future__ import annotations

from .spec import TrainSpec

__all__ = ["TrainSpec"]
