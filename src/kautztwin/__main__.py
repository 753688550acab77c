"""Run the command-line interface: ``python -m kautztwin --help``."""

from __future__ import annotations

__all__: list[str] = []

if __name__ == "__main__":
    from kautztwin.cli.main import main

    raise SystemExit(main())
