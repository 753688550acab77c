"""Optimization module of the twin: pole re-optimisation, consolidation, MPC and DNN retuning."""

from __future__ import annotations

from .optimizer import ControllerTuning, EstimatorRetraining, Optimizer, TuningCandidate

__all__ = ["ControllerTuning", "EstimatorRetraining", "Optimizer", "TuningCandidate"]
