"""A fleet of twins: N assets of one type stepped together as array operations.

:class:`Fleet` (:mod:`.step`) runs the :class:`~kautztwin.twin.runtime.DigitalTwin`
of many plants at once: the state of every module is an ``(n_assets, ...)``
array (:mod:`.update`, :mod:`.sync`, :mod:`.mpc_batch`), the rare per-asset
work (identification, re-identification, controller builds) runs in a worker
pool (:mod:`.assets`), the plants are simulated as one array (:mod:`.plants`)
and one SQLite store holds every asset's history (:mod:`.store`).
:func:`~.simulate.hydraulic_fleet` builds a simulated fleet of hydraulic
drives with parameter spread and drift, :func:`~.simulate.summarize` its
metrics; :mod:`.shards` runs a fleet sharded over Ray actors (optional).
:mod:`kautztwin.service.fleet_service` serves a fleet on the wall clock with
one HTTP API for all its assets.  See docs/fleet.md.
"""

from __future__ import annotations

from .mpc_batch import BatchedController, solve_qp_batch
from .plants import FleetPlant, HydraulicFleetPlant, LoopedFleetPlant
from .step import Fleet, FleetRun
from .store import FleetStore

__all__ = [
    "BatchedController",
    "Fleet",
    "FleetPlant",
    "FleetRun",
    "FleetStore",
    "HydraulicFleetPlant",
    "LoopedFleetPlant",
    "solve_qp_batch",
]
