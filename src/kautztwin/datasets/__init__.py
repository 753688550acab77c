"""Uncertain systems: parametric nominal models, parameter draws and labelled response data.

A :class:`ParametricSystem` maps a parameter vector to a stable SISO transfer
function.  :func:`draw_parameters` (uniform, Monte Carlo) and
:func:`factorial_parameters` (full-factorial grid) perturb the parameters
around their nominal values, and :func:`make_dataset` turns every parameter
vector into a noisy sampled impulse or step response labelled with the exact
Kautz coefficients of its noise-free impulse response and its true poles.  The
resulting :class:`ResponseDataset` is what the neural coefficient estimator
trains on (measured noisy response in, Kautz coefficients out).

Modules: :mod:`~kautztwin.datasets.systems` (parametric systems and parameter
draws) and :mod:`~kautztwin.datasets.labelled` (labelled data generation, noise
models, quantisation, save/load).
"""

from __future__ import annotations

from .labelled import ResponseDataset, make_dataset
from .systems import ParametricSystem, draw_parameters, factorial_parameters, paper_system

__all__ = [
    "ParametricSystem",
    "ResponseDataset",
    "draw_parameters",
    "factorial_parameters",
    "make_dataset",
    "paper_system",
]
