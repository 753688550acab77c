"""Helpers shared by the benchmark scripts: machine description, timing, JSON results.

Every benchmark records where its numbers come from (CPU, library versions, BLAS, thread
environment variables, load average, git commit and whether the tree was dirty) and writes
one JSON file.  The scripts import this module as ``_common``: run as
``python benchmarks/<script>.py``, the ``benchmarks`` folder is on ``sys.path``.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import scipy

import kautztwin as kt

__all__ = [
    "benchmark_result",
    "blas_info",
    "command_line",
    "cpu_model",
    "git",
    "load_average",
    "machine_info",
    "run_conditions",
    "thread_env",
    "timed",
    "utc_now",
    "write_json",
]

HERE = Path(__file__).resolve().parent
#: environment variables that set the size of the BLAS / OpenMP thread pools
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

T = TypeVar("T")


# =========================================================================== machine
def git(*args: str) -> str | None:
    """Output of a git command run in the benchmarks folder.

    Parameters
    ----------
    *args : str
        Arguments of ``git``, e.g. ``"rev-parse", "HEAD"``.

    Returns
    -------
    str or None
        The stripped standard output, or None when git is missing or fails.
    """
    try:
        out = subprocess.run(
            ["git", *args], cwd=HERE, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def cpu_model() -> str:
    """The CPU's model name.

    Returns
    -------
    str
        From ``/proc/cpuinfo`` where there is one, else what :mod:`platform` says.
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def blas_info() -> str | None:
    """Name and version of the BLAS numpy was built with.

    Returns
    -------
    str or None
        For instance ``'scipy-openblas 0.3.31'``; None when numpy does not say.
    """
    try:
        config = np.show_config(mode="dicts")
        blas = config["Build Dependencies"]["blas"]
        return f"{blas.get('name')} {blas.get('version', '')}".strip()
    except Exception:  # purely informative: any failure just leaves it out
        return None


def load_average() -> list[float] | None:
    """The 1-, 5- and 15-minute load averages.

    Returns
    -------
    list of float or None
        None where the platform has no load average.
    """
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def thread_env() -> dict[str, str]:
    """The thread-pool environment variables that are set.

    Returns
    -------
    dict
        ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` and ``MKL_NUM_THREADS``, where set.
    """
    return {k: os.environ[k] for k in THREAD_VARS if k in os.environ}


def run_conditions() -> dict[str, Any]:
    """The state of the machine and the source tree at the start of a run.

    Returns
    -------
    dict
        ``load_average_at_start``, ``thread_env``, ``git_commit`` (None outside a git
        checkout) and ``git_dirty`` (whether ``git status`` lists changes; None when
        unknown), in this order.
    """
    status = git("status", "--porcelain")
    return {
        "load_average_at_start": load_average(),
        "thread_env": thread_env(),
        "git_commit": git("rev-parse", "HEAD") or None,
        "git_dirty": None if status is None else bool(status),
    }


def machine_info(software: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Where the numbers come from: CPU, library versions, BLAS, thread settings, load.

    Parameters
    ----------
    software : mapping, optional
        The library entries, in order (name to version or setting).  By default
        ``numpy``, ``scipy``, ``kautztwin`` and ``blas`` (:func:`blas_info`).

    Returns
    -------
    dict
        ``platform``, ``cpu_model``, ``cpu_count``, ``cpus_available``, ``python``, the
        ``software`` entries, then the entries of :func:`run_conditions`.
    """
    if software is None:
        software = {
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "kautztwin": kt.__version__,
            "blas": blas_info(),
        }
    affinity = getattr(os, "sched_getaffinity", None)
    return {
        "platform": platform.platform(),
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_available": len(affinity(0)) if affinity else os.cpu_count(),
        "python": platform.python_version(),
        **software,
        **run_conditions(),
    }


# =========================================================================== timing
def timed(fn: Callable[[], T]) -> tuple[T, float]:
    """Call ``fn`` once and measure its wall-clock time.

    Parameters
    ----------
    fn : callable
        Called without arguments.

    Returns
    -------
    value
        What ``fn`` returned.
    float
        Seconds it took (``time.perf_counter``).
    """
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


# =========================================================================== results
def utc_now() -> str:
    """The current UTC time, ISO 8601 to the second.

    Returns
    -------
    str
        For instance ``'2026-11-22T05:46:09+00:00'``.
    """
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def command_line(argv: list[str] | None) -> str:
    """The command that ran the benchmark: the script's name and its arguments.

    Parameters
    ----------
    argv : list of str or None
        The arguments given to the script's ``main``; None for ``sys.argv[1:]``.

    Returns
    -------
    str
    """
    return " ".join([Path(sys.argv[0]).name, *(sys.argv[1:] if argv is None else argv)])


def benchmark_result(
    name: str,
    argv: list[str] | None,
    *,
    quick: bool,
    settings: dict[str, Any],
    machine: dict[str, Any],
    **sections: Any,
) -> dict[str, Any]:
    """The JSON-ready result of a run, with its header; records the load at the end.

    Parameters
    ----------
    name : str
        The benchmark's name (``'core'``, ``'adaptive'``, ...).
    argv : list of str or None
        The arguments given to the script's ``main`` (see :func:`command_line`).
    quick : bool
        Whether it was the quick (smoke-test) run.
    settings : dict
        The run's settings.
    machine : dict
        From :func:`machine_info`, taken at the start of the run; ``load_average_at_end``
        is added to it here.
    **sections
        The results, in the order they go in the file.

    Returns
    -------
    dict
        ``benchmark``, ``created_utc``, ``command``, ``quick``, ``settings``, ``machine``,
        then ``sections``.
    """
    result = {
        "benchmark": name,
        "created_utc": utc_now(),
        "command": command_line(argv),
        "quick": quick,
        "settings": settings,
        "machine": machine,
        **sections,
    }
    machine["load_average_at_end"] = load_average()
    return result


def write_json(path: Path, result: Any, *, indent: int = 2) -> None:
    """Write a result as JSON (one trailing newline), creating the folder if needed.

    Parameters
    ----------
    path : Path
        The file to write.
    result : object
        Anything :func:`json.dumps` takes.
    indent : int, default=2
        Indentation of the JSON text.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=indent) + "\n", encoding="utf-8")
