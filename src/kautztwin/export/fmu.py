"""FMI 2.0 co-simulation FMUs of identified linear and Kautz models, compiled from generated C.

A model (a :class:`~kautztwin.ident.TransferFunctionModel` from ``kautztwin identify``, a
:class:`~kautztwin.KautzModel` from ``kautztwin approx``, continuous or discrete) becomes
the exact zero-order-hold recursion at the FMU's fixed step :math:`h`:

.. math::

    x_{k+1} = \\Phi x_k + \\Gamma_a u_{k-d-1} + \\Gamma_b u_{k-d},\\qquad
    \\Phi = e^{Ah},\\ \\Gamma_b = \\Gamma(h - \\theta),\\
    \\Gamma_a = e^{A(h-\\theta)}\\Gamma(\\theta),\\
    \\Gamma(s) = \\int_0^{s} e^{Ar}\\,dr\\,B,

for an input delay :math:`\\tau = d h + \\theta` (:math:`0 \\le \\theta < h`).  A
co-simulation master holds the input constant over each communication step, so this
recursion is the model's exact response at the step points, with no integrator error; the
matrices are computed once, in double precision, when the FMU is built.  A discrete model
is stepped at its own sampling period.

:func:`export_fmu` writes the C source (:mod:`kautztwin.export._fmi_c`), compiles it with
the local C compiler into ``binaries/<platform>/<id>.so`` and zips it with
``modelDescription.xml`` and ``sources/<id>.c``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg
import scipy.signal

from ..approx import KautzModel
from ..exceptions import DataError, ExportError, KautzTwinError
from ..ident import TransferFunctionModel
from ._fmi_c import DiscreteRealisation, c_source, model_description, new_guid

__all__ = [
    "ExportError",
    "discretize",
    "export_fmu",
    "find_compiler",
    "read_model_file",
]

#: relative tolerance below which a delay's fractional step is taken as none
_DELAY_RTOL = 1e-9


# --------------------------------------------------------------------------- model files
def read_model_file(path: str | Path) -> TransferFunctionModel | KautzModel:
    """Read a linear model from the JSON that ``kautztwin identify/approx --json`` print.

    ``identify --json`` gives ``num``, ``den``, ``delay`` and ``intersample`` (a
    :class:`~kautztwin.ident.TransferFunctionModel`); ``approx --json`` and
    :meth:`KautzModel.to_dict <kautztwin.KautzModel.to_dict>` give ``poles`` and
    ``coefficients`` (and ``dt``, ``delayed`` for discrete bases).

    Parameters
    ----------
    path : str or path-like
        The JSON file.

    Returns
    -------
    TransferFunctionModel or KautzModel

    Raises
    ------
    DataError
        If the file is missing, is not JSON, or holds neither kind of model (or an
        invalid one).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model file {str(path)!r} does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise DataError(f"cannot read model file {str(path)!r} as JSON: {msg}") from None
    if not isinstance(data, dict):
        raise DataError(f"model file {str(path)!r} holds no JSON object")
    try:
        if "num" in data and "den" in data:
            return TransferFunctionModel(
                num=data["num"],
                den=data["den"],
                delay=float(data.get("delay", 0.0) or 0.0),
                intersample=str(data.get("intersample", "zoh")),
            )
        if "poles" in data and "coefficients" in data:
            return KautzModel.from_dict(data)
    except KautzTwinError as exc:
        raise DataError(f"model file {str(path)!r} holds an invalid model: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise DataError(f"model file {str(path)!r} is malformed: {msg}") from None
    raise DataError(
        f"model file {str(path)!r} is not a linear model: expected the JSON of "
        "'kautztwin identify --json' (num, den) or 'kautztwin approx --json' (poles, "
        "coefficients)"
    )


# --------------------------------------------------------------------------- discretisation
def _continuous(model: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """``(A, B, C, D, dt, delay)`` of a supported model (``dt = 0``: continuous)."""
    if isinstance(model, TransferFunctionModel):
        A, B, C, D = scipy.signal.tf2ss(model.num, model.den)
        return A, B[:, 0], C[0], float(D[0, 0]), 0.0, float(model.delay)
    if isinstance(model, KautzModel):
        A, B, C, D = model.state_space()
        return A, B[:, 0], C[0], float(D[0, 0]), float(model.dt), 0.0
    raise DataError(
        "an FMU can be built from a TransferFunctionModel or a KautzModel; got "
        f"{type(model).__name__}"
    )


def _gamma(A: np.ndarray, B: np.ndarray, s: float) -> np.ndarray:
    r""":math:`\int_0^s e^{Ar}\,dr\,B`, from the exponential of the augmented matrix."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A
    M[:n, n] = B
    return scipy.linalg.expm(M * s)[:n, n]


def discretize(model: Any, step: float | None = None) -> DiscreteRealisation:
    r"""The exact zero-order-hold recursion of a model at the step ``step``.

    Parameters
    ----------
    model : TransferFunctionModel or KautzModel
        Continuous (any step) or discrete (its own sampling period).
    step : float, optional
        The FMU's step :math:`h` in seconds.  Required for continuous models;
        for discrete ones it defaults to (and must equal) the sampling period.

    Returns
    -------
    DiscreteRealisation
        :math:`\Phi, \Gamma_a, \Gamma_b, C, D`, the step and the delay split
        :math:`\tau = d h + \theta`.

    Raises
    ------
    DataError
        On an unsupported model, a missing or non-positive step, or a step that
        differs from a discrete model's sampling period.
    """
    A, B, C, D, dt, delay = _continuous(model)
    if dt > 0:
        if step is not None and not math.isclose(float(step), dt, rel_tol=1e-12):
            raise DataError(
                f"step {step:g} s differs from the discrete model's sampling period {dt:g} s; "
                "a discrete model is stepped at its own period (leave out the step)"
            )
        return DiscreteRealisation(A, np.zeros_like(B), B.copy(), C, D, dt, 0, False)
    if step is None:
        raise DataError(
            "a continuous-time model needs the FMU's step in seconds (step=..., or --step)"
        )
    h = float(step)
    if not (math.isfinite(h) and h > 0):
        raise DataError(f"step must be a positive number of seconds; got {step!r}")
    d = int(math.floor(delay / h + _DELAY_RTOL))
    theta = delay - d * h
    if theta <= _DELAY_RTOL * h:
        theta = 0.0
    Phi = scipy.linalg.expm(A * h)
    if theta == 0.0:
        return DiscreteRealisation(Phi, np.zeros_like(B), _gamma(A, B, h), C, D, h, d, False)
    Gamma_a = scipy.linalg.expm(A * (h - theta)) @ _gamma(A, B, theta)
    return DiscreteRealisation(Phi, Gamma_a, _gamma(A, B, h - theta), C, D, h, d, True)


# --------------------------------------------------------------------------- building
def find_compiler(compiler: str | None = None) -> str:
    """The C compiler to build with: ``compiler``, else ``$CC``, else ``cc``/``gcc``/``clang``.

    Parameters
    ----------
    compiler : str, optional
        A program name or path.

    Returns
    -------
    str
        The compiler's full path.

    Raises
    ------
    ExportError
        If no compiler is found.
    """
    wanted = [compiler] if compiler else ([os.environ["CC"]] if os.environ.get("CC") else [])
    candidates = wanted or ["cc", "gcc", "clang"]
    for name in candidates:
        found = shutil.which(name)
        if found:
            return found
    if wanted:
        raise ExportError(f"C compiler {wanted[0]!r} not found; install one or pass another")
    raise ExportError(
        "no C compiler found (tried cc, gcc, clang and $CC); install one, e.g. "
        "'apt-get install gcc', or name it with --cc"
    )


def _platform() -> tuple[str, str]:
    """FMI platform folder and shared-library suffix of this machine."""
    bits = "64" if sys.maxsize > 2**32 else "32"
    if sys.platform.startswith("linux"):
        return f"linux{bits}", ".so"
    if sys.platform == "darwin":
        return f"darwin{bits}", ".dylib"
    raise ExportError(
        f"building FMUs is supported on Linux and macOS, not on {platform.system()}"
    )


def _identifier(name: str) -> str:
    ident = re.sub(r"\W", "_", name, flags=re.ASCII) or "model"
    return ident if not ident[0].isdigit() else f"m_{ident}"


def _stop_time(r: DiscreteRealisation) -> float:
    """A default experiment long enough to settle: ten of the slowest time constants."""
    rho = np.max(np.abs(np.linalg.eigvals(r.Phi))) if r.n_states else 0.0
    n = 100 if rho <= 0 or rho >= 1 else int(np.ceil(-10.0 / math.log(rho)))
    return float(max(n, 10) * r.h)


def _compile(source: str, ident: str, compiler: str, folder: Path, suffix: str) -> Path:
    c_file = folder / f"{ident}.c"
    c_file.write_text(source, encoding="utf-8")
    lib = folder / f"{ident}{suffix}"
    cmd = [compiler, "-shared", "-fPIC", "-O2", "-std=c99", "-fvisibility=hidden",
           "-o", str(lib), str(c_file), "-lm"]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    except OSError as exc:
        raise ExportError(f"cannot run the C compiler {compiler!r}: {exc}") from None
    if done.returncode != 0 or not lib.is_file():
        first = next((ln for ln in done.stderr.splitlines() if "error" in ln), "")
        first = first or (done.stderr.strip().splitlines() or ["no message"])[0]
        raise ExportError(f"the C compiler {compiler!r} failed: {first.strip()}")
    return lib


def export_fmu(
    model: Any,
    path: str | Path,
    *,
    step: float | None = None,
    model_identifier: str | None = None,
    compiler: str | None = None,
    description: str | None = None,
) -> Path:
    """Write a model as an FMI 2.0 co-simulation FMU built from generated C source.

    The FMU has the input ``u`` (held over each step), the output ``y`` and the
    parameters ``u_offset`` and ``y_offset`` (default 0:
    ``y = y_offset + G(u - u_offset)``).  It steps the exact zero-order-hold
    recursion of :func:`discretize` at the step ``h`` (``DefaultExperiment
    stepSize``); ``fmi2DoStep`` accepts any whole multiple of ``h`` and rejects
    other step sizes.  The model starts at rest, with the input at ``u_offset``
    before the start (what the delay line holds first).

    Parameters
    ----------
    model : TransferFunctionModel or KautzModel
        The model; see :func:`read_model_file` for the files of the CLI.
    path : str or path-like
        The ``.fmu`` file to write (its folder must exist).
    step : float, optional
        The step in seconds: required for continuous models; discrete models use
        their sampling period.
    model_identifier : str, optional
        Name of the library and the C file; default the file name's stem, made a C
        identifier.
    compiler : str, optional
        The C compiler (:func:`find_compiler`).
    description : str, optional
        The FMU's description; default a summary of the model.

    Returns
    -------
    pathlib.Path
        The FMU file.

    Raises
    ------
    DataError
        On an unsupported model, a bad step or a missing output folder.
    ExportError
        If no C compiler is found or the compilation fails.

    See Also
    --------
    kautztwin.export.export_onnx : The ONNX export of the trained estimators.

    Examples
    --------
    >>> import numpy as np
    >>> from kautztwin.ident import TransferFunctionModel
    >>> from kautztwin.export import discretize
    >>> r = discretize(TransferFunctionModel(num=[2.0], den=[1.0, 2.0]), step=0.1)
    >>> bool(np.isclose(r.Phi[0, 0], np.exp(-0.2)))
    True
    """
    from .. import __version__

    path = Path(path)
    if not path.parent.is_dir():
        raise DataError(f"folder {str(path.parent)!r} of {str(path)!r} does not exist")
    r = discretize(model, step)
    cc = find_compiler(compiler)
    plat, suffix = _platform()
    ident = _identifier(model_identifier or path.stem)
    if description is None:
        kind = "transfer function" if isinstance(model, TransferFunctionModel) else "Kautz model"
        delay = float(getattr(model, "delay", 0.0))
        description = (f"{kind} with {r.n_states} states, step {r.h:g} s"
                       + (f", input delay {delay:g} s" if delay else ""))
    guid = new_guid()
    source = c_source(r, guid, description=description)
    xml = model_description(
        r, model_identifier=ident, model_name=ident, guid=guid, description=description,
        version=__version__, stop_time=_stop_time(r),
    )
    with tempfile.TemporaryDirectory(prefix="kautztwin-fmu-") as tmp:
        lib = _compile(source, ident, cc, Path(tmp), suffix)
        with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("modelDescription.xml", xml)
            zf.write(lib, f"binaries/{plat}/{ident}{suffix}")
            zf.writestr(f"sources/{ident}.c", source)
    return path
