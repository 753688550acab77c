"""Export for deployment: trained estimators as ONNX, linear and Kautz models as FMI 2.0 FMUs.

``fmu`` (:func:`export_fmu`) needs numpy, scipy and a C compiler; ``onnx``
(:func:`export_onnx`) needs torch and ``onnx`` (``pip install 'kautztwin[export]'``),
imported when it is called.
"""

from __future__ import annotations

from .fmu import ExportError, discretize, export_fmu, find_compiler, read_model_file
from .onnx import export_onnx, load_estimator_file

__all__ = [
    "ExportError",
    "discretize",
    "export_fmu",
    "export_onnx",
    "find_compiler",
    "load_estimator_file",
    "read_model_file",
]
