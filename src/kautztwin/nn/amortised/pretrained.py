"""The amortised model shipped inside the package: its files, found with importlib.resources.

The folder ``kautztwin/nn/amortised/shipped_model/`` (``estimator.json``, ``metadata.json``,
``weights.pt``; package data of the wheel) holds the model that
:meth:`AmortisedEstimator.load_default <kautztwin.nn.amortised.AmortisedEstimator.load_default>`
and ``kautztwin estimate`` without ``--model`` use.  It was trained with the estimator's
defaults by ``python examples/amortised_estimator.py --train``.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from importlib import resources
from pathlib import Path

from ...exceptions import DataError

__all__ = ["PRETRAINED_FILES", "pretrained_folder"]

_PACKAGE = "kautztwin.nn.amortised"
_FOLDER = "shipped_model"
PRETRAINED_FILES = ("estimator.json", "metadata.json", "weights.pt")


@contextlib.contextmanager
def pretrained_folder() -> Iterator[Path]:
    """The shipped model's folder as a directory on disk, for the life of the context.

    Installed from a wheel, or editable from a checkout, the package lies on disk and this
    is the package's own folder; a package imported from a zip archive has its three files
    copied to a temporary folder first (removed on exit).

    Yields
    ------
    pathlib.Path
        A folder that :meth:`AmortisedEstimator.load
        <kautztwin.nn.amortised.AmortisedEstimator.load>` reads.

    Raises
    ------
    DataError
        If a file of the shipped model cannot be read from the package.

    Examples
    --------
    >>> from kautztwin.nn.amortised.pretrained import pretrained_folder
    >>> with pretrained_folder() as folder:
    ...     sorted(p.name for p in folder.iterdir() if p.is_file())
    ['estimator.json', 'metadata.json', 'weights.pt']
    """
    root = resources.files(_PACKAGE).joinpath(_FOLDER)
    if isinstance(root, Path):
        yield root
        return
    with tempfile.TemporaryDirectory(prefix="kautztwin-amortised-") as tmp:
        for name in PRETRAINED_FILES:
            try:
                data = root.joinpath(name).read_bytes()
            except OSError as exc:
                raise DataError(f"cannot read the shipped amortised model's {name!r} from "
                                f"the kautztwin package: {exc}") from None
            (Path(tmp) / name).write_bytes(data)
        yield Path(tmp)
