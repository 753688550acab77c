"""The live twin's transports: sample-to-prediction latency and the highest sustained sample rate.

For the hydraulic drive (dt = 0.02 s), one twin (:class:`~kautztwin.twin.runtime.DigitalTwin`,
the quick hydraulic profile, background re-identification - in a worker process for the
network links, as ``twin serve`` builds it) is run
in this process against three plant links, side by side:

* ``in-process``: the simulator stepped in this process, paced by a real-time clock sped up
  ``speed`` times (the baseline: no transport at all);
* ``opcua``: ``kautztwin plant serve`` in a process of its own, the twin's
  :class:`~kautztwin.twin.physical.OPCUAPlant` on loopback;
* ``mqtt``: ``kautztwin plant serve --transport mqtt`` in a process of its own, an ``amqtt``
  broker in a third process, the twin's :class:`~kautztwin.twin.physical.MQTTPlant`.

The link is wrapped in a probe that timestamps every step of the loop (``time.time``):

* **source time** of a sample: its timestamp at the server (``origin + t / speed``: the plant
  time mapped to the wall clock); for the in-process plant, the same mapping on the twin's clock;
* **arrival**: when the link hands the sample to the twin (``Plant.step`` returns);
* **prediction available**: when the twin has processed the sample (stored it, its
  prediction and sync fit updated, the MPC's next input computed) and calls
  ``Plant.step`` with that input.

Latency = prediction available - source time (split into transport = arrival - source and
processing = prediction - arrival), over the closed-loop phase, at real time (x1) by default.
The rate sweep runs the server at ``speed`` = 1, 2, 4, ... (50, 100, 200, ... samples/s) until
the twin takes fewer than 95 % of the published samples per wall-clock second (``twin
falls behind``); the highest speed that passes is the sustained rate.

Run ``python benchmarks/bench_service.py`` (results/service.json) or ``--quick``
(a coarser sweep, shorter windows; under a minute).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import _common
import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DT = 0.02  # the hydraulic drive's sampling period, s
TRANSPORTS = ("in-process", "opcua", "mqtt")
#: fraction of the published rate the twin must take to count as keeping up
KEEP_UP = 0.95
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONUNBUFFERED="1")

BROKER_SCRIPT = """
import asyncio, logging, sys
logging.disable(logging.CRITICAL)
from amqtt.broker import Broker
async def main(port):
    broker = Broker({"listeners": {"default": {"type": "tcp", "bind": f"127.0.0.1:{port}"}},
                     "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin":
                                 {"allow_anonymous": True}}})
    await broker.start()
    print("ready", flush=True)
    await asyncio.Event().wait()
asyncio.run(main(int(sys.argv[1])))
"""


# =========================================================================== helpers
def free_port() -> int:
    """A free TCP port on the loopback interface.

    Returns
    -------
    int
    """
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_process(argv: list[str], ready: str, timeout: float = 30.0) -> tuple[Any, str]:
    """Start a helper process and wait for its first stdout line that contains ``ready``.

    Parameters
    ----------
    argv : list of str
        The command.
    ready : str
        Text of the line that says it is up.
    timeout : float, default=30.0
        Seconds to wait for it.

    Returns
    -------
    subprocess.Popen
        The process.
    str
        The line.

    Raises
    ------
    RuntimeError
        If it exits or says nothing in time.
    """
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV, cwd=ROOT)
    end = time.monotonic() + timeout
    assert proc.stdout is not None
    os.set_blocking(proc.stdout.fileno(), False)
    buffer = ""
    while time.monotonic() < end:
        chunk = proc.stdout.readline()
        buffer += chunk or ""
        if ready in buffer:
            return proc, buffer.strip()
        if proc.poll() is not None:
            err = proc.stderr.read()[-500:] if proc.stderr else ""
            raise RuntimeError(f"{argv[:4]} exited: {err}")
        if not chunk:
            time.sleep(0.02)
    stop_process(proc)
    raise RuntimeError(f"{argv[:4]} did not start within {timeout:g} s")


def stop_process(proc: Any) -> None:
    """Stop a helper process started by :func:`start_process` (SIGTERM, then SIGKILL).

    Parameters
    ----------
    proc : subprocess.Popen
    """
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


class Probe:
    """A plant link wrapped to timestamp every step of the twin's loop.

    Parameters
    ----------
    plant : Plant
        The link.
    speed : float
        Plant seconds per wall-clock second (maps an in-process sample's time to the wall).
    remote : bool
        Whether the link carries the server's source timestamps (``meta['source_time']``).

    Attributes
    ----------
    rows : list of tuple
        One ``(source, arrival, prediction, finite)`` per processed sample (wall s, POSIX).
    """

    def __init__(self, plant: Any, speed: float, remote: bool) -> None:
        self._plant = plant
        self.speed = float(speed)
        self.remote = remote
        self.connected = remote  # a remote plant is never re-simulated on resume
        self.rows: list[tuple[float, float, float, bool]] = []
        self._pending: tuple[float, float, bool] | None = None
        self._origin = math.nan

    def __getattr__(self, name: str) -> Any:
        return getattr(self._plant, name)

    def _note(self, reading: Any) -> Any:
        arrival = time.time()
        if self.remote:
            source = float(reading.meta.get("source_time", math.nan))
        else:
            source = self._origin + reading.t / self.speed
        self._pending = (source, arrival, math.isfinite(source) and math.isfinite(reading.y))
        return reading

    def reset(self) -> Any:
        """Reset the link and note the sample it returns.

        Returns
        -------
        Reading
        """
        reading = self._plant.reset()
        self._origin = time.time()  # the twin starts its clock right after reset
        return self._note(reading)

    def step(self, u: float | None) -> Any:
        """Note that the last sample was processed, step the link, note the new sample.

        Parameters
        ----------
        u : float or None
            The twin's input.

        Returns
        -------
        Reading
        """
        now = time.time()
        if self._pending is not None:
            source, arrival, finite = self._pending
            self.rows.append((source, arrival, now, finite))
        if self.remote:
            return self._note(self._plant.step(u))
        reading = self._plant.step(u)  # computed ahead: the loop waits for its time
        source = self._origin + reading.t / self.speed
        self._pending = (source, math.nan, math.isfinite(reading.y))
        return reading

    def close(self) -> None:
        """Close the link."""
        self._plant.close()


def _percentiles(values: np.ndarray) -> dict[str, float | None]:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {"median_ms": None, "p99_ms": None, "max_ms": None}
    return {"median_ms": float(np.median(values) * 1e3),
            "p99_ms": float(np.percentile(values, 99) * 1e3),
            "max_ms": float(values.max() * 1e3)}


# =========================================================================== one case
def run_case(transport: str, speed: float, *, window: float, ident: float,
             broker: str | None) -> dict[str, Any]:
    """Run one twin against one transport at one server speed and measure it.

    Parameters
    ----------
    transport : {'in-process', 'opcua', 'mqtt'}
        The link.
    speed : float
        Server speed: plant seconds per wall-clock second (``50 * speed`` samples/s).
    window : float
        Wall-clock seconds measured, after the identification phase and 100 samples
        (or half a wall-clock second) more.
    ident : float
        Identification phase, plant s.
    broker : str or None
        The MQTT broker's URL (``transport == 'mqtt'``).

    Returns
    -------
    dict
        ``published_per_s``, ``processed_per_s``, ``ratio``, ``keeps_up``, the latency,
        transport and processing percentiles (ms), ``samples``, ``dropouts``.
    """
    from kautztwin.twin import make_plant
    from kautztwin.twin.physical import Clock, MQTTPlant, OPCUAPlant
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig

    server = None
    try:
        if transport == "in-process":
            plant: Any = make_plant("hydraulic", seed=0)
            clock = Clock.real_time(speed, tolerance=DT)
        else:
            argv = [sys.executable, "-m", "kautztwin", "plant", "serve", "--plant", "hydraulic",
                    "--speed", f"{speed:g}", "--seed", "0"]
            if transport == "opcua":
                argv += ["--endpoint", f"opc.tcp://127.0.0.1:{free_port()}"]
            else:
                argv += ["--transport", "mqtt", "--broker", str(broker)]
            server, line = start_process(argv, "serving")
            if transport == "opcua":
                endpoint = re.search(r"opc\.tcp://\S+", line)
                assert endpoint is not None, line
                plant = OPCUAPlant(endpoint.group(0).rstrip(",;"), plant="hydraulic",
                                   connect_timeout=20)
            else:
                plant = MQTTPlant(str(broker), plant="hydraulic", connect_timeout=20)
            clock = Clock()  # the link paces the loop
        probe = Probe(plant, speed, remote=transport != "in-process")
        n_ident = int(round(ident / DT))
        config = TwinConfig.for_plant("hydraulic", quick=True, duration=3600.0,
                                      ident_duration=ident, seed=0)
        if transport != "in-process":  # as twin serve (model.worker = auto): a fit process
            config = replace(config, updater={**config.updater, "worker": "process"})
        twin = DigitalTwin(probe, config, history=None, clock=clock, background=True)
        try:
            twin.start(resume=False)
            w0 = w1 = math.nan
            k0 = n_ident + max(100, int(0.5 * speed / DT))  # past the first model: 0.5 s wall
            deadline = time.monotonic() + 4 * ident / speed + 3 * window + 30
            while time.monotonic() < deadline:
                twin.step()
                if twin.k == k0:
                    w0, i0 = time.time(), len(probe.rows)
                if twin.k > k0 and time.time() - w0 >= window:
                    w1, i1 = time.time(), len(probe.rows)
                    break
        finally:
            twin.close()
        rows = np.array(probe.rows[i0:i1] if math.isfinite(w1) else [], dtype=float)
    finally:
        if server is not None:
            stop_process(server)
    published = speed / DT
    if rows.size == 0:
        return {"transport": transport, "speed": speed, "published_per_s": published,
                "processed_per_s": 0.0, "ratio": 0.0, "keeps_up": False,
                "error": "the twin did not reach the measuring window"}
    source, arrival, prediction, finite = rows.T
    real = finite.astype(bool)
    processed = float(real.sum()) / (w1 - w0)
    ratio = processed / published
    out: dict[str, Any] = {
        "transport": transport, "speed": speed, "published_per_s": published,
        "processed_per_s": processed, "ratio": ratio, "keeps_up": bool(ratio >= KEEP_UP),
        "window_s": w1 - w0, "samples": int(real.size), "dropouts": int((~real).sum()),
        "latency": _percentiles((prediction - source)[real]),
        "processing": _percentiles(
            (prediction - (arrival if transport != "in-process" else source))[real]),
    }
    if transport != "in-process":
        out["transport_delay"] = _percentiles((arrival - source)[real])
    lat = (prediction - source)[real]
    half = lat.size // 2
    if half:  # a twin that falls behind: the latency grows through the window
        out["latency_growth_ms"] = float((np.median(lat[half:]) - np.median(lat[:half])) * 1e3)
    return out


# =========================================================================== main
def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table, write the JSON.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (``sys.argv[1:]`` when omitted).

    Returns
    -------
    int
        0.
    """
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="coarse sweep, short windows")
    parser.add_argument("--transports", default=",".join(TRANSPORTS),
                        help="comma-separated subset of " + ", ".join(TRANSPORTS))
    parser.add_argument("--max-speed", type=float, default=None, help="stop the sweep here")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "service.json")
    args = parser.parse_args(argv)
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    for t in transports:
        if t not in TRANSPORTS:
            parser.error(f"unknown transport {t!r}")
    for name in ("amqtt", "transitions", "asyncua", "kautztwin"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    machine = _common.machine_info()
    if args.quick:
        settings = {"latency_speed": 2.0, "speeds": [2.0, 8.0, 32.0, 128.0], "window_s": 1.5,
                    "ident_s": 2.0}
    else:
        settings = {"latency_speed": 1.0, "speeds": [2.0 ** i for i in range(9)],
                    "window_s": 6.0, "ident_s": 2.0}
    if args.max_speed is not None:
        settings["speeds"] = [s for s in settings["speeds"] if s <= args.max_speed]
    settings.update(plant="hydraulic", dt=DT, keep_up=KEEP_UP,
                    profile="TwinConfig.for_plant('hydraulic', quick=True), background=True; "
                    "re-identification in a worker process for opcua and mqtt (twin serve's "
                    "model.worker = auto)")
    broker_proc = None
    broker = None
    sweeps: dict[str, list[dict[str, Any]]] = {}
    latency: dict[str, dict[str, Any]] = {}
    t_start = time.monotonic()
    try:
        if "mqtt" in transports:
            port = free_port()
            broker_proc, _ = start_process([sys.executable, "-c", BROKER_SCRIPT, str(port)],
                                           "ready")
            broker = f"mqtt://127.0.0.1:{port}"
        for transport in transports:
            sweeps[transport] = cases = []
            speeds = sorted(set(settings["speeds"]) | {settings["latency_speed"]})
            for speed in speeds:
                case = run_case(transport, speed, window=settings["window_s"],
                                ident=settings["ident_s"], broker=broker)
                cases.append(case)
                lat = case.get("latency", {})
                print(f"  {transport:10s} x{speed:<5g} {case['published_per_s']:7.0f}/s "
                      f"published, {case['processed_per_s']:7.0f}/s processed "
                      f"({100 * case['ratio']:5.1f} %), latency median "
                      f"{lat.get('median_ms') or math.nan:7.2f} ms", flush=True)
                if speed == settings["latency_speed"]:
                    latency[transport] = case
                if not case["keeps_up"] and speed >= settings["latency_speed"]:
                    break
    finally:
        if broker_proc is not None:
            stop_process(broker_proc)
    summary = {}
    for transport, cases in sweeps.items():
        ok = [c for c in cases if c["keeps_up"]]
        best = max(ok, key=lambda c: c["speed"]) if ok else None
        first_fail = next((c for c in cases if not c["keeps_up"]), None)
        lat = latency.get(transport, {})
        summary[transport] = {
            "latency_median_ms": lat.get("latency", {}).get("median_ms"),
            "latency_p99_ms": lat.get("latency", {}).get("p99_ms"),
            "processing_median_ms": lat.get("processing", {}).get("median_ms"),
            "transport_median_ms": lat.get("transport_delay", {}).get("median_ms"),
            "max_sustained_speed": best["speed"] if best else None,
            "max_sustained_per_s": best["published_per_s"] if best else None,
            "max_sustained_processed_per_s": best["processed_per_s"] if best else None,
            "first_failing_speed": first_fail["speed"] if first_fail else None,
            "sweep_capped": first_fail is None,
        }
    base = summary.get("in-process", {})
    for s in summary.values():
        for key, ref in (("latency_median_ms", "latency_vs_in_process"),
                         ("max_sustained_per_s", "rate_vs_in_process")):
            a, b = s.get(key), base.get(key)
            s[ref] = (a / b) if a is not None and b else None
    wall = time.monotonic() - t_start
    print(f"\nhydraulic drive, dt = {DT} s; latency at x{settings['latency_speed']:g} "
          f"({settings['latency_speed'] / DT:.0f} samples/s); wall {wall:.0f} s")
    print(f"{'transport':11s} {'latency median':>15s} {'p99':>9s} {'(transport':>11s} "
          f"{'+ twin)':>8s} {'vs base':>8s} {'sustained':>12s} {'vs base':>8s}")
    for t, s in summary.items():
        def f(v: Any, spec: str = ".2f", unit: str = "") -> str:
            return "-" if v is None else f"{v:{spec}}{unit}"
        sustained = ("-" if s["max_sustained_per_s"] is None else
                     f"{s['max_sustained_per_s']:.0f}/s" + ("+" if s["sweep_capped"] else ""))
        print(f"{t:11s} {f(s['latency_median_ms'], '.2f', ' ms'):>15s} "
              f"{f(s['latency_p99_ms'], '.2f', ' ms'):>9s} "
              f"{f(s['transport_median_ms'], '.2f'):>11s} "
              f"{f(s['processing_median_ms'], '.2f'):>8s} "
              f"{f(s['latency_vs_in_process'], '.1f', 'x'):>8s} {sustained:>12s} "
              f"{f(s['rate_vs_in_process'], '.2f', 'x'):>8s}")
    settings["wall_s"] = wall
    result = _common.benchmark_result("service", argv, quick=args.quick, settings=settings,
                                      machine=machine, summary=summary, sweeps=sweeps)
    _common.write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
