"""JSON-ready values: numpy scalars and arrays, tuples, complex and non-finite numbers.

One conversion for every JSON the package writes (run configurations, metrics, history
payloads, ``--json`` output): numpy values become Python ones, arrays and tuples lists,
complex numbers ``[re, im]``, and NaN or inf ``null`` (strict JSON has no NaN).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from .exceptions import DataError

__all__ = ["to_jsonable"]


def to_jsonable(obj: Any, name: str | None = None) -> Any:
    """Return ``obj`` with every value made representable in strict JSON.

    Parameters
    ----------
    obj : object
        Nested mappings, sequences, arrays and scalars.
    name : str, optional
        What ``obj`` is, for the message. When given, a value JSON cannot represent (an
        arbitrary object) raises :class:`DataError`; without it such a value is returned
        unchanged (and ``json.dumps`` decides).

    Returns
    -------
    object

    Examples
    --------
    >>> import numpy as np
    >>> to_jsonable({"a": np.float64(1.5), "b": (1, float("nan")), "c": 1 + 2j})
    {'a': 1.5, 'b': [1, None], 'c': [1.0, 2.0]}
    """
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, complex | np.complexfloating):
        return [to_jsonable(obj.real, name), to_jsonable(obj.imag, name)]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist(), name)
    if isinstance(obj, Mapping):
        return {str(key): to_jsonable(value, name) for key, value in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(value, name) for value in obj]
    if name is not None:
        raise DataError(
            f"{name} holds a {type(obj).__name__} ({obj!r}), which JSON cannot represent"
        )
    return obj
