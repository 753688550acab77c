"""The physical module of the twin: links to plants behind one :class:`Plant` protocol.

The twin talks to the physical system through the small :class:`Plant`
protocol (:mod:`.base`): it reads the output, applies an input for one
sampling period and reads again.  The links:

* :class:`HydraulicPlant` (:mod:`.simulated`): the electro-hydraulic servo-drive
  simulator of :mod:`kautztwin.simulators.hydraulic`, with an oil-temperature
  schedule that moves its poles during the run (:class:`TemperatureSchedule`,
  :meth:`HydraulicPlant.with_pole_drift`), sensor noise, and the ODE state
  carried from one sample (chunk) to the next;
* :class:`TCLabPlant` (:mod:`.tclab`): the Temperature Control Lab through the
  third-party ``tclab`` package, its emulator ``tclab.TCLabModel`` on a
  simulated clock, or a real board (``connected=True``) on the same code path;
* :class:`ReplayPlant` (:mod:`.replay`): a recorded CSV file of ``t, u, y``
  played back;
* :class:`OPCUAPlant` (:mod:`.opcua`): a plant behind an OPC UA server (a PLC, or
  :class:`kautztwin.service.PlantServer`), with reconnection and stale-data flags;
* :class:`MQTTPlant` (:mod:`.mqtt`): JSON samples and inputs over an MQTT broker
  (``paho-mqtt``, imported only when the link connects), with the same fault behaviour.

:func:`make_plant` (:mod:`.factory`) builds a link from a twin configuration.

A :class:`Clock` (:mod:`.clock`) paces the plants: in real time (optionally sped
up) with ``time.monotonic``/``time.sleep``, or as fast as possible (simulated
time).  :class:`SampleSanitizer` (:mod:`.sanitize`) cleans the measured signal
(dropouts, outliers, late samples) before the twin uses it.
"""

from __future__ import annotations

from .base import Plant, PlantRun, Reading, run_open_loop
from .clock import Clock
from .factory import make_plant
from .mqtt import DEFAULT_BROKER, MQTTPlant, default_topics, parse_broker
from .opcua import NAMESPACE_URI, LinkError, OPCUAPlant, Outage, parse_endpoint
from .replay import ReplayExhaustedError, ReplayInputWarning, ReplayPlant
from .sanitize import SampleFlag, SampleSanitizer, SanitizedSample
from .simulated import HydraulicPlant, TemperatureSchedule, temperature_for_pole_ratio
from .tclab import TCLabPlant

__all__ = [
    "DEFAULT_BROKER",
    "NAMESPACE_URI",
    "Clock",
    "HydraulicPlant",
    "LinkError",
    "MQTTPlant",
    "OPCUAPlant",
    "Outage",
    "Plant",
    "PlantRun",
    "Reading",
    "ReplayExhaustedError",
    "ReplayInputWarning",
    "ReplayPlant",
    "SampleFlag",
    "SampleSanitizer",
    "SanitizedSample",
    "TCLabPlant",
    "TemperatureSchedule",
    "default_topics",
    "make_plant",
    "parse_broker",
    "parse_endpoint",
    "run_open_loop",
    "temperature_for_pole_ratio",
]
