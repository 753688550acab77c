"""Model folders on disk: ``weights.pt`` and ``metadata.json`` with checksums, for both estimators.

:func:`save_verified` writes the common header (format, versions, time grid and its hash,
weights checksum) beside the fields an estimator adds; :func:`load_verified` checks it all
before the estimator rebuilds itself from the files (with :func:`stored_grid`,
:func:`check_network` and :func:`load_weights`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from ..exceptions import DataError, KautzTwinError

__all__ = ["check_network", "load_verified", "load_weights", "save_verified", "stored_grid"]

_WEIGHTS = "weights.pt"
_METADATA = "metadata.json"


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _grid_hash(t: NDArray[np.float64]) -> str:
    return hashlib.sha256(np.ascontiguousarray(t, dtype="<f8").tobytes()).hexdigest()


def _canonical(meta: Mapping[str, Any]) -> bytes:
    body = {k: v for k, v in meta.items() if k != "metadata_sha256"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def save_verified(
    directory: str | Path,
    fmt: str,
    version: int,
    state: dict[str, torch.Tensor],
    t: NDArray[np.float64],
    fields: dict[str, Any],
) -> Path:
    """Write ``weights.pt`` and ``metadata.json`` with checksums (read by :func:`load_verified`).

    The common header (format, versions, time grid and its hash, weights checksum)
    is written here; ``fields`` adds what the estimator needs to rebuild itself.

    Parameters
    ----------
    directory : str or path-like
        Folder to write (created if needed).
    fmt : str
        Format name, e.g. ``'kautztwin.CoefficientEstimator'``.
    version : int
        Format version.
    state : dict of str to torch.Tensor
        The tensors, written with ``torch.save``.
    t : ndarray of shape (n_samples,)
        The estimator's time grid.
    fields : dict
        JSON-ready fields of the estimator.

    Returns
    -------
    pathlib.Path
        The directory.
    """
    from .. import __version__

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    weights = directory / _WEIGHTS
    torch.save(state, weights)
    meta: dict[str, Any] = {
        "format": fmt,
        "format_version": version,
        "kautztwin_version": __version__,
        "torch_version": torch.__version__,
        "time_grid": {
            "t0": float(t[0]),
            "t_end": float(t[-1]),
            "n_samples": int(t.size),
            "sha256": _grid_hash(t),
            "t": t.tolist(),
        },
        **fields,
        "weights": {"file": _WEIGHTS, "sha256": _sha256_file(weights)},
    }
    meta["metadata_sha256"] = hashlib.sha256(_canonical(meta)).hexdigest()
    (directory / _METADATA).write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return directory


def load_verified(
    directory: str | Path,
    fmt: str,
    version: int,
    label: str,
    from_files: Callable[[dict[str, Any], Path], Any],
) -> Any:
    """Read a model folder, verify format, version and both checksums, then build the model.

    Shared by every estimator that saves ``metadata.json`` + ``weights.pt``; any
    problem is a one-line :class:`DataError`.

    Parameters
    ----------
    directory : str or path-like
        Folder written by :func:`save_verified`.
    fmt : str
        Expected format name.
    version : int
        The format version this kautztwin reads.
    label : str
        Name of the estimator in messages.
    from_files : callable
        ``from_files(meta, weights_path)`` builds the model from the verified files.

    Returns
    -------
    object
        What ``from_files`` returns.

    Raises
    ------
    DataError
        If a file is missing or unreadable, of another format or version, malformed,
        or modified after saving (checksum mismatch).
    """
    directory = Path(directory)
    meta_path = directory / _METADATA
    weights_path = directory / _WEIGHTS
    for path in (meta_path, weights_path):
        if not path.is_file():
            raise DataError(f"model file {str(path)!r} does not exist")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise DataError(f"cannot read model file {str(meta_path)!r}: {msg}") from None
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        raise DataError(f"{str(meta_path)!r} is not a kautztwin {label} file")
    if meta.get("format_version") != version:
        raise DataError(
            f"model file {str(meta_path)!r} has format version "
            f"{meta.get('format_version')!r}; this kautztwin reads version {version}"
        )
    try:
        expected = hashlib.sha256(_canonical(meta)).hexdigest()
    except ValueError:
        expected = ""
    if meta.get("metadata_sha256") != expected:
        raise DataError(f"model file {str(meta_path)!r} was modified (checksum mismatch)")
    try:
        weights_sha = meta["weights"]["sha256"]
    except (KeyError, TypeError):
        raise DataError(
            f"model file {str(meta_path)!r} is malformed: no weights checksum"
        ) from None
    if _sha256_file(weights_path) != weights_sha:
        raise DataError(f"model file {str(weights_path)!r} was modified (checksum mismatch)")
    try:
        return from_files(meta, weights_path)
    except KautzTwinError as exc:
        raise DataError(f"model {str(directory)!r} is malformed: {exc}") from None
    except (KeyError, TypeError, ValueError, RuntimeError, OSError) as exc:
        msg = " ".join(str(exc).split())[:300]
        raise DataError(
            f"model {str(directory)!r} is malformed: {type(exc).__name__}: {msg}"
        ) from None



def stored_grid(meta: Mapping[str, Any]) -> NDArray[np.float64]:
    """The time grid stored in ``metadata.json``, checked against its stored length and hash.

    Parameters
    ----------
    meta : mapping
        The metadata read by :func:`load_verified`.

    Returns
    -------
    ndarray of shape (n_samples,)

    Raises
    ------
    DataError
        If the grid does not match its length or hash.
    """
    grid = meta["time_grid"]
    t = np.asarray(grid["t"], dtype=float)
    if t.shape != (int(grid["n_samples"]),) or _grid_hash(t) != grid["sha256"]:
        raise DataError("the stored time grid does not match its length or hash")
    return t


def check_network(arch: Mapping[str, Any], network: type) -> None:
    """Raise :class:`DataError` unless the stored architecture names ``network``."""
    if arch["network"] != network.__name__:
        raise DataError(f"unknown network {arch['network']!r}")


def load_weights(weights_path: Path) -> dict[str, torch.Tensor]:
    """Read ``weights.pt`` as tensors only (``weights_only=True``, nothing unpickled).

    Raises
    ------
    DataError
        If the file does not hold a dictionary.
    """
    state = torch.load(weights_path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise DataError("the weights file does not hold a dictionary of tensors")
    return state
