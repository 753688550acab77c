"""``kautztwin plant serve``: a simulated plant behind an OPC UA server or on an MQTT broker."""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from typing import Any

from ._common import CLIError, stop_on_signals

__all__ = ["register", "serve"]

DESCRIPTION = """\
Simulated plants you can talk to over OPC UA: the stand-in for a PLC in tests,
demos and docs.  A real PLC with the same node ids works with the twin unchanged.
"""

SERVE_DESCRIPTION = """\
Run a simulated plant in real time (or --speed times faster) behind an OPC UA
server.  Every dt/speed wall-clock seconds the plant is stepped with the last
input written to ns=<urn:kautztwin:plant>;s=PLANT.u and its output is published
on s=PLANT.y with a source timestamp; writes outside the input range are
rejected (BadOutOfRange).  Other variables: PLANT.u_applied, PLANT.k, PLANT.t,
PLANT.dt, PLANT.speed, PLANT.status; units and ranges are the EngineeringUnits
and EURange properties of u and y.  See docs/service.md.

plants:
  hydraulic   electro-hydraulic servo drive: valve command -1..1 -> speed in rad/s,
              dt 0.02 s; --drift slows its dominant pole during the run
  tclab       Temperature Control Lab emulator: heater 0..100 % -> degC, dt 1 s

With --transport mqtt the plant is an MQTT client of --broker instead: it publishes
samples {"k","t","y","u","ts"} on kautztwin/PLANT/y, takes {"u": ..} on kautztwin/PLANT/u
(out-of-range inputs are rejected on kautztwin/PLANT/u/ack), and keeps kautztwin/PLANT/meta
and kautztwin/PLANT/status retained.

Runs until Ctrl-C / SIGTERM, or for --duration wall-clock seconds.
"""

EPILOG = """\
examples:
  kautztwin plant serve --plant hydraulic --speed 10 --drift 0.4
  kautztwin plant serve --plant tclab --endpoint opc.tcp://127.0.0.1:4841 --speed 20
  kautztwin plant serve --plant hydraulic --drift 0.4@30,60 --duration 120
  kautztwin plant serve --plant hydraulic --transport mqtt --broker mqtt://127.0.0.1:1883
"""


def register(subparsers: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
    """Add the ``plant`` command (with its ``serve`` action) to the command-line parser.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``kautztwin`` command's subparsers.
    common : argparse.ArgumentParser
        Parent parser with the flags every command shares (``--debug``).
    """
    p = subparsers.add_parser(
        "plant", parents=[common], allow_abbrev=False,
        help="serve a simulated plant over OPC UA (a stand-in for a PLC)",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = p.add_subparsers(dest="action", title="actions", metavar="ACTION", required=True)
    s = actions.add_parser(
        "serve", parents=[common], allow_abbrev=False,
        help="run a simulated plant behind an OPC UA server until stopped",
        description=SERVE_DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("--plant", required=True, choices=("hydraulic", "tclab"),
                   help="which simulator to serve")
    s.add_argument("--transport", choices=("opcua", "mqtt"), default="opcua",
                   help="serve over OPC UA (a server) or MQTT (a client of --broker) "
                   "(default: %(default)s)")
    s.add_argument("--endpoint", default="opc.tcp://127.0.0.1:4840", metavar="URL",
                   help="OPC UA: where to listen (default: %(default)s; port 0 picks a free "
                   "port)")
    s.add_argument("--broker", default="mqtt://127.0.0.1:1883", metavar="URL",
                   help="MQTT: the broker to publish on (default: %(default)s)")
    s.add_argument("--speed", default="1", metavar="X",
                   help="plant seconds per wall-clock second (default: 1, real time)")
    s.add_argument(
        "--drift", metavar="FRACTION[@T1,T2,...]",
        help="hydraulic only: slow the dominant pole by FRACTION (0.4 = 40 %%) in equal steps "
        "starting at plant times T1, T2, ... s (default: 20,40)",
    )
    s.add_argument("--duration", metavar="S",
                   help="stop after S wall-clock seconds (default: run until stopped)")
    s.add_argument("--noise", metavar="SIGMA",
                   help="sensor noise standard deviation in output units (default: the plant's)")
    s.add_argument("--seed", type=int, default=0, help="seed of the sensor noise (default: 0)")
    s.add_argument("--user", action="append", metavar="NAME:PASSWORD",
                   help="OPC UA: accept this user (repeatable); anonymous sessions are refused")
    s.add_argument("--certificate", metavar="FILE",
                   help="OPC UA: the server's certificate (PEM/DER); with --private-key the server "
                   "offers only Basic256Sha256 Sign&Encrypt")
    s.add_argument("--private-key", metavar="FILE", help="OPC UA: the certificate's private key")
    s.set_defaults(run=serve)


def _number(text: str | None, flag: str, *, positive: bool = False,
            nonnegative: bool = False) -> float | None:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise CLIError(f"{flag} must be a number, got {text!r}") from None
    if not math.isfinite(value) or (positive and value <= 0) or (nonnegative and value < 0):
        kind = "a positive" if positive else "a non-negative" if nonnegative else "a finite"
        raise CLIError(f"{flag} must be {kind} number, got {text!r}")
    return value


def _parse_drift(text: str | None) -> tuple[float, tuple[float, ...]]:
    if text is None:
        return 0.0, ()
    value, _, times = text.partition("@")
    drift = _number(value, "--drift")
    assert drift is not None
    if not -0.9 < drift < 0.9:
        raise CLIError(f"--drift must be a fraction in (-0.9, 0.9), got {drift:g}")
    if not times:
        return drift, (20.0, 40.0)
    try:
        events = tuple(sorted(float(x) for x in times.split(",") if x.strip()))
    except ValueError:
        raise CLIError(f"--drift: cannot read the event times in {text!r}") from None
    if not events or any(not (math.isfinite(e) and e > 0) for e in events):
        raise CLIError(f"--drift: event times must be positive plant seconds, got {times!r}")
    return drift, events


def _users(items: list[str] | None) -> dict[str, str] | None:
    if not items:
        return None
    users = {}
    for item in items:
        name, sep, password = item.partition(":")
        if not sep or not name or not password:
            raise CLIError(f"--user must be NAME:PASSWORD, got {item!r}")
        users[name] = password
    return users


def serve(args: argparse.Namespace) -> int:
    """Run the ``plant serve`` command.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed command line.

    Returns
    -------
    int
        0 after a clean stop (signal or ``--duration``).

    Raises
    ------
    CLIError
        On bad option values.
    KautzTwinError
        If the endpoint is invalid or cannot be listened on.
    """
    speed = _number(args.speed, "--speed", positive=True)
    duration = _number(args.duration, "--duration", positive=True)
    noise = _number(args.noise, "--noise", nonnegative=True)
    if args.plant != "hydraulic" and args.drift is not None:
        raise CLIError("--drift applies to the hydraulic plant only")
    drift, events = _parse_drift(args.drift)
    from ..service import MQTTPlantServer, PlantServer
    from ..service.process import freeze_garbage
    from ..twin import make_plant
    from ..twin.physical import parse_broker, parse_endpoint

    mqtt = getattr(args, "transport", "opcua") == "mqtt"
    if mqtt:  # a one-line error before the plant is built
        parse_broker(args.broker)
    else:
        parse_endpoint(args.endpoint)
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    plant = make_plant(args.plant, drift=drift, drift_events=events, seed=args.seed, noise=noise)
    server: Any
    users = _users(getattr(args, "user", None))
    cert, key = getattr(args, "certificate", None), getattr(args, "private_key", None)
    if mqtt:
        if users or cert or key:
            raise CLIError("--user, --certificate and --private-key apply to --transport opcua")
        server = MQTTPlantServer(plant, broker=args.broker, speed=speed)
    else:
        server = PlantServer(plant, endpoint=args.endpoint, speed=speed, users=users,
                             certificate=cert, private_key=key)
    stop = threading.Event()
    with stop_on_signals(stop.set):
        try:
            server.start()
            freeze_garbage()  # its ticks are not stalled by full collections
            drift_text = f", pole drift {drift:g} at {','.join(f'{e:g}' for e in events)} s" \
                if drift else ""
            if mqtt:
                topics = server.topics
                print(f"serving {args.plant} on {server.broker} ({topics['u']} in, {topics['y']} "
                      f"out; dt {server.dt:g} s, speed x{server.speed:g}{drift_text}); "
                      "Ctrl-C to stop", flush=True)
            else:
                ids = server.node_ids
                print(f"serving {args.plant} on {server.endpoint} (namespace {server.namespace}: "
                      f"{ids['u']} in, {ids['y']} out; dt {server.dt:g} s, speed x{server.speed:g}"
                      f"{drift_text}); Ctrl-C to stop", flush=True)
            end = math.inf if duration is None else time.monotonic() + duration
            while not stop.is_set() and time.monotonic() < end:
                stop.wait(min(0.5, max(0.0, end - time.monotonic())))
                if server.status.startswith("fault"):
                    sys.stderr.write(f"kautztwin: warning: plant {server.status}\n")
                    break
            print(f"stopped after {server.k + 1} samples ({(server.k) * server.dt:g} plant s)",
                  flush=True)
        finally:
            server.close()
    return 0
