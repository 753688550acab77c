"""Helpers shared by the plant-link and ``twin serve`` tests (not a test module).

An in-process amqtt broker on a free loopback port, a cheap plant whose output can be
poisoned, and the pieces that launch ``kautztwin twin serve`` as a subprocess and read
the SQLite store it writes.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from kautztwin.twin import Reading
from kautztwin.twin.history import SQLiteHistory

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", MPLBACKEND="Agg", PYTHONUNBUFFERED="1")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (at the time of asking)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker:
    """An amqtt broker on a free loopback port, in a thread of its own.

    ``stop()`` and ``start()`` keep the port.
    """

    def __init__(self) -> None:
        self.port = free_port()
        self.url = f"mqtt://127.0.0.1:{self.port}"
        self._thread: threading.Thread | None = None

    def start(self) -> Broker:
        ready = threading.Event()
        self._thread = threading.Thread(target=asyncio.run, args=(self._main(ready),),
                                        daemon=True)
        self._thread.start()
        assert ready.wait(10), "broker did not start"
        return self

    async def _main(self, ready: threading.Event) -> None:
        from amqtt.broker import Broker as AmqttBroker

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        broker = AmqttBroker({
            "listeners": {"default": {"type": "tcp", "bind": f"127.0.0.1:{self.port}"}},
            "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin":
                        {"allow_anonymous": True}},
        })
        await broker.start()
        ready.set()
        await self._stop.wait()
        await broker.shutdown()

    def stop(self) -> None:
        self._loop.call_soon_threadsafe(self._stop.set)
        assert self._thread is not None
        self._thread.join(10)


class FirstOrderPlant:
    """A cheap noise-free plant ``y+ = 0.8 y + 0.2 u`` whose output can be poisoned."""

    input_limits = (0.0, 10.0)

    def __init__(self, dt: float = 0.05, poison: dict[int, float] | None = None) -> None:
        self.dt = dt
        self.name = "first"
        self.poison = poison or {}

    def reset(self) -> Reading:
        self.k, self.y = 0, 0.0
        return Reading(0.0, 0.0, {"u": math.nan, "k": 0})

    def step(self, u: float | None) -> Reading:
        self.k += 1
        self.y = 0.8 * self.y + 0.2 * float(u)
        y = self.poison.get(self.k % 10, self.y)
        return Reading(self.k * self.dt, y, {"u": u, "k": self.k})

    def close(self) -> None:
        pass


def serve(*argv: str) -> subprocess.Popen:
    """``kautztwin twin serve`` with JSON logs, as a subprocess with piped output."""
    return subprocess.Popen(
        [sys.executable, "-m", "kautztwin", "twin", "serve", "--logging-format", "json", *argv],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)


def committed(store: Path) -> int:
    """How many samples the latest run in ``store`` holds (0 while it is being created)."""
    if not store.exists():
        return 0
    try:
        with SQLiteHistory(store) as h:
            runs = h.runs()
            return len(h.measurements(runs[-1].run_id).k) if runs else 0
    except Exception:  # the service is creating it
        return 0


def wait_committed(proc: subprocess.Popen, store: Path, n: int, timeout: float) -> int:
    """Wait until ``store`` holds ``n`` samples; fail if ``proc`` dies or time runs out."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        c = committed(store)
        if c >= n:
            return c
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        time.sleep(0.1)
    raise AssertionError(f"only {committed(store)} samples committed after {timeout} s")


def log_events(stderr: str) -> list[dict]:
    """The JSON log events in a service's stderr."""
    return [json.loads(line) for line in stderr.splitlines() if line.startswith("{")]


def samples_digest(m, n: int | None = None) -> str:
    """SHA-256 of the first ``n`` (all if None) samples (k, t, u, y) of measurements ``m``."""
    digest = hashlib.sha256()
    for col in (m.k[:n], m.t[:n], m.u[:n], m.y[:n]):
        digest.update(np.ascontiguousarray(col, dtype=float).tobytes())
    return digest.hexdigest()


def store_state(store: Path) -> tuple[int, str, int]:
    """(committed samples, checksum of them, latest model version at or before them)."""
    with SQLiteHistory(store) as h:
        run = h.runs()[-1].run_id
        m = h.measurements(run)
        n = len(m.k)
        versions = [v.version for v in h.model_versions(run)]
    return n, samples_digest(m), max(versions, default=0)


def drive_through_restart(link: Any, stop: Callable[[], Any], start: Callable[[], Any]
                          ) -> tuple[list[Reading], float, list[Reading]]:
    """Step ``link`` while its far end is stopped for 2 s and started again.

    Returns the readings up to the first good one after the restart, the seconds the
    link took to come back, and five readings after that.
    """
    link.reset()
    readings = [link.step(2.0) for _ in range(5)]
    stop()
    down_until = time.monotonic() + 2.0
    while time.monotonic() < down_until:
        readings.append(link.step(3.0))  # never raises while the far end is away
    start()  # same port
    back = time.monotonic()
    while time.monotonic() - back < 5.0:
        r = link.step(3.0)
        readings.append(r)
        if not r.meta["dropout"]:
            break
    reconnected_after = time.monotonic() - back
    tail = [link.step(3.0) for _ in range(5)]
    return readings, reconnected_after, tail
