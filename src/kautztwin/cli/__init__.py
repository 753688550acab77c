"""Command-line interface ``kautztwin`` (also ``python -m kautztwin``).

The commands are thin wrappers over the library: they parse flags, call one
library function and print or write its result.  The entry point is
:func:`kautztwin.cli.main.main`.
"""

from __future__ import annotations

__all__: list[str] = []
