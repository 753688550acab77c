"""Long-running services around the twin: an OPC UA plant server, and the twin as a service.

:class:`TwinService` (``kautztwin twin serve``) runs the twin on the wall
clock against a plant link until it is stopped, resumable from its store;
:func:`load_service_config` reads its TOML configuration.

:class:`PlantServer` runs any :class:`~kautztwin.twin.Plant` (the hydraulic
drive, the TCLab emulator...) in real or scaled time behind an OPC UA server
(``asyncua``, install ``kautztwin[service]``), with the address space
documented in ``docs/service.md``.  It is the stand-in for a PLC in tests,
demos and docs; the twin's OPC UA link talks to it and to a real PLC with the
same node ids alike.  :class:`MQTTPlantServer` serves the same plants over MQTT
(``paho-mqtt``, a broker of your own), stepped by the same code
(:mod:`~kautztwin.service.pacing`).

``twin serve --http`` adds the twin's HTTP API and live dashboard
(:mod:`~kautztwin.service.api`, FastAPI, imported only then) and
:mod:`~kautztwin.service.client` is its Python client.

:class:`FleetService` (``kautztwin fleet serve``) steps a batched fleet of twins on the
wall clock and serves every asset over one HTTP API (:mod:`~kautztwin.service.fleet_api`,
``/assets/{id}/...``).
"""

from __future__ import annotations

from .config import ServiceConfig, load_service_config
from .fleet_service import FleetService
from .mqtt_plant import MQTTPlantServer
from .plant_server import (
    DEFAULT_ENDPOINT,
    Channel,
    PlantServer,
    default_channels,
)
from .twin_service import TwinService, configure_logging, load_estimator

__all__ = [
    "DEFAULT_ENDPOINT",
    "Channel",
    "FleetService",
    "MQTTPlantServer",
    "PlantServer",
    "ServiceConfig",
    "TwinService",
    "configure_logging",
    "default_channels",
    "load_estimator",
    "load_service_config",
]
