"""Long-running services around the twin: a simulated plant behind an OPC UA server.

:class:`PlantServer` runs any :class:`~kautztwin.twin.Plant` (the hydraulic
drive, the TCLab emulator...) in real or scaled time behind an OPC UA server
(``asyncua``, install ``kautztwin[service]``), with the address space
documented in ``docs/service.md``.  It is the stand-in for a PLC in tests,
demos and docs; the twin's OPC UA link talks to it and to a real PLC with the
same node ids alike.
"""

from __future__ import annotations

from .plant_server import (
    DEFAULT_ENDPOINT,
    Channel,
    PlantServer,
    default_channels,
)

__all__ = [
    "DEFAULT_ENDPOINT",
    "Channel",
    "PlantServer",
    "default_channels",
]
