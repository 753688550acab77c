"""Prediction module of the twin: the MPC design and the controller run on the current model."""

from __future__ import annotations

from .controller import MPCController
from .settings import MPCSettings, build_mpc

__all__ = ["MPCController", "MPCSettings", "build_mpc"]
