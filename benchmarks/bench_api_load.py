"""The twin's HTTP API under load: requests/s and latency of ``/state``, ``/history``, loop timing.

A :class:`~kautztwin.service.TwinService` runs the hydraulic drive in process, paced in real
time ``speed`` times faster (x1: 50 samples/s, x10: 500 samples/s), with its HTTP API
(:mod:`kautztwin.service.api`, uvicorn in a thread of the service) on a free loopback port,
exactly as ``kautztwin twin serve --http 127.0.0.1:0`` builds it.  Once the twin is in closed
loop, phases of ``seconds`` each:

* ``idle`` (before): nothing but the twin;
* ``state``: ``clients`` concurrent clients (default 50) requesting ``GET /state`` back to back;
* ``history``: ``clients`` concurrent clients requesting ``GET /history`` pages (1000 samples
  of ``k,t,u,y,prediction,setpoint`` after a random committed sample);
* ``mixed``: half of the clients on each;
* ``idle`` (after).

The clients run in a separate process (HTTP/1.1 keep-alive connections written on asyncio
streams, so that the load generator costs little CPU), each one request at a time; a
request's latency is from writing it to reading the last byte of the answer.  Per endpoint:
requests/s, p50/p99/max latency, errors (any status but 200).

The sample loop is timed by a clock that wraps the twin's real-time clock
(:class:`TimedClock`; the loop itself is not changed): per sample, the **step latency** is the
loop's busy time from one wait for the plant's next sample to the next (commit, the API's
view and queued jobs, measurement, MPC, twin update, plant step), and the **lateness** is how
far behind its due time the loop reached the next sample (0 when it waited).  A sample reached
more than one sampling period late counts as **late** (the loop's own ``late_ticks``); the
**rate** is the samples processed per wall second over the nominal rate.  The loop keeps up
when the rate stays at 1 and no sample is late.

Run ``python benchmarks/bench_api_load.py`` (speeds x1 and x10, 50 clients, 10 s phases;
about 2.5 minutes; results/api_load.json) or ``--quick`` (x10, 8 clients, 1.5 s phases).
The figures depend on the machine's load: other processes share its cores.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DT = 0.02  # the hydraulic drive's sampling period, s
PHASES = ("idle", "state", "history", "mixed", "idle-after")
HISTORY_QUERY = "signals=k,t,u,y,prediction,setpoint&limit=1000"


# =========================================================================== the load clients
async def _one_client(host: str, port: int, paths: list[str], deadline: float,
                      out: list[tuple[float, int]]) -> None:
    """One keep-alive connection: request ``paths`` in turn until ``deadline``."""
    reader, writer = await asyncio.open_connection(host, port)
    i = 0
    try:
        while time.monotonic() < deadline:
            path = paths[i % len(paths)]
            i += 1
            t0 = time.perf_counter()
            writer.write(f"GET {path} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
            head = await reader.readuntil(b"\r\n\r\n")
            status = int(head.split(b" ", 2)[1])
            length = 0
            for line in head.split(b"\r\n")[1:]:
                name, _, value = line.partition(b":")
                if name.strip().lower() == b"content-length":
                    length = int(value)
            await reader.readexactly(length)
            out.append((time.perf_counter() - t0, status))
    finally:
        writer.close()


async def _load(url: str, kind: str, clients: int, seconds: float, k_max: int,
                seed: int, query: str) -> dict[str, Any]:
    host, port = url.rsplit("/", 1)[1].rsplit(":", 1)
    rng = random.Random(seed)
    top = max(k_max - 1000, 0)
    history = [f"/history?{query}&after={rng.randint(-1, top)}" for _ in range(500)]
    plan: list[tuple[str, list[str]]] = []
    for i in range(clients):
        endpoint = kind if kind != "mixed" else ("state" if i % 2 == 0 else "history")
        plan.append((endpoint, ["/state"] if endpoint == "state" else history[i:] + history[:i]))
    records: dict[str, list[tuple[float, int]]] = {"state": [], "history": []}
    t_start = time.monotonic()
    deadline = t_start + seconds
    await asyncio.gather(*(_one_client(host, int(port), paths, deadline, records[endpoint])
                           for endpoint, paths in plan))
    t_end = time.monotonic()
    return {"t_start": t_start, "t_end": t_end, "clients": clients,
            "records": {k: v for k, v in records.items() if v}}


def load_main(argv: list[str]) -> int:
    """The load generator's process: ``--load URL KIND CLIENTS SECONDS K_MAX SEED QUERY``.

    Parameters
    ----------
    argv : list of str
        The arguments after ``--load``.

    Returns
    -------
    int
        0; the result is one JSON line on stdout.
    """
    url, kind, clients, seconds, k_max, seed, query = argv
    result = asyncio.run(_load(url, kind, int(clients), float(seconds), int(k_max), int(seed),
                               query))
    sys.stdout.write(json.dumps(result) + "\n")
    return 0


# =========================================================================== the loop's timing
def timed_clock(clock: Any) -> Any:
    """A :class:`~kautztwin.twin.physical.Clock` like ``clock`` that records every wait.

    Parameters
    ----------
    clock : Clock
        The twin's clock (real time, sped up).

    Returns
    -------
    TimedClock
        ``ticks``: ``(time.monotonic() at the wait, busy s since the previous wait, lateness
        in plant s)`` per sample.
    """
    from kautztwin.twin.physical import Clock

    class TimedClock(Clock):
        def __init__(self) -> None:
            super().__init__(clock.realtime, speedup=clock.speedup, tolerance=clock.tolerance)
            self.ticks: list[tuple[float, float, float]] = []
            self._back: float | None = None

        def wait_until(self, t: float) -> float:
            now = time.perf_counter()
            busy = math.nan if self._back is None else now - self._back
            late = super().wait_until(t)
            self.ticks.append((time.monotonic(), busy, late))
            self._back = time.perf_counter()
            return late

    return TimedClock()


def loop_stats(ticks: list[tuple[float, float, float]], t0: float, t1: float,
               speed: float) -> dict[str, Any]:
    """The loop's timing over the wall-clock window ``[t0, t1]``.

    Parameters
    ----------
    ticks : list of (float, float, float)
        From :func:`timed_clock`.
    t0, t1 : float
        The window, ``time.monotonic()`` seconds.
    speed : float
        Plant seconds per wall second.

    Returns
    -------
    dict
        ``samples``, ``rate`` (samples per wall second over the nominal rate), step latency
        ``step_ms_p50`` / ``p99`` / ``max``, ``late`` (more than a period late),
        ``behind_ms_max`` (largest lateness, wall ms).
    """
    import numpy as np

    sel = [(b, lt) for ts, b, lt in ticks if t0 <= ts <= t1 and math.isfinite(b)]
    busy = np.array([b for b, _ in sel]) * 1e3
    late = np.array([lt for _, lt in sel])
    nominal = (t1 - t0) * speed / DT
    if not sel:
        return {"samples": 0, "rate": 0.0}
    return {
        "samples": len(sel), "rate": round(len(sel) / nominal, 4),
        "step_ms_p50": round(float(np.percentile(busy, 50)), 3),
        "step_ms_p99": round(float(np.percentile(busy, 99)), 3),
        "step_ms_max": round(float(busy.max()), 3),
        "late": int(np.sum(late > DT)),
        "behind_ms_max": round(float(late.max()) / speed * 1e3, 3),
    }


def request_stats(records: list[tuple[float, int]], seconds: float) -> dict[str, Any]:
    """Requests/s and latency of one endpoint's requests.

    Parameters
    ----------
    records : list of (float, int)
        ``(latency s, HTTP status)`` per request.
    seconds : float
        The load's wall-clock duration.

    Returns
    -------
    dict
    """
    import numpy as np

    lat = np.array([r[0] for r in records]) * 1e3
    return {"requests": len(records), "rps": round(len(records) / seconds, 1),
            "p50_ms": round(float(np.percentile(lat, 50)), 2),
            "p99_ms": round(float(np.percentile(lat, 99)), 2),
            "max_ms": round(float(lat.max()), 2),
            "errors": sum(1 for r in records if r[1] != 200)}


# =========================================================================== one speed
def _wait(pred: Any, timeout: float, what: str) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise RuntimeError(f"timed out waiting for {what}")


def run_speed(speed: float, clients: int, seconds: float, seed: int,
              query: str = HISTORY_QUERY, gc_freeze: bool = True) -> dict[str, Any]:
    """Serve a twin at ``speed`` and run every phase against it.

    Parameters
    ----------
    speed : float
        Real-time speed-up of the plant.
    clients : int
        Concurrent clients of a load phase.
    seconds : float
        Length of a phase, wall seconds.
    seed : int
        Seed of the plant and of the history pages asked for.
    query : str, default=HISTORY_QUERY
        Query of the ``/history`` requests (an ``after`` is added).
    gc_freeze : bool, default=True
        Leave the objects the server froze at its start frozen (what the service does);
        ``False`` unfreezes them, as before that fix, for a comparison.

    Returns
    -------
    dict
        ``speed``, ``phases`` (one entry per phase: ``loop`` and, under load, ``requests``
        per endpoint), ``summary``.
    """
    from kautztwin.service import TwinService, load_service_config

    with tempfile.TemporaryDirectory(prefix="kt-api-load-") as tmp:
        cfg = load_service_config(None, {
            "plant.kind": "hydraulic", "plant.speed": str(speed), "plant.seed": str(seed),
            "model.duration": str(max(600.0, speed * (len(PHASES) * seconds + 120))),
            "model.quick": "true", "service.out": tmp, "service.report": "false",
            "logging.level": "error", "http.bind": "127.0.0.1:0", "http.rate_limit": "0"})
        svc = TwinService(cfg)
        svc.build()
        clock = svc.twin.clock = timed_clock(svc.twin.clock)
        thread = threading.Thread(target=svc.run, name="twin", daemon=True)
        thread.start()
        phases: list[dict[str, Any]] = []
        try:
            _wait(lambda: svc.api is not None and svc.api.ready.is_set(), 60, "the HTTP server")
            if not gc_freeze:
                import gc

                gc.unfreeze()
            view = svc.api.view
            _wait(lambda: view.latest().get("phase") == "closed-loop", 120, "closed loop")
            time.sleep(min(2.0, seconds))  # the controller settles on its first set-point
            for i, name in enumerate(PHASES):
                if name.startswith("idle"):
                    t0 = time.monotonic()
                    time.sleep(seconds)
                    phases.append({"phase": name, "loop": loop_stats(
                        clock.ticks, t0, time.monotonic(), speed)})
                    continue
                k_max = int(view.latest().get("committed", 0))
                proc = subprocess.run(
                    [sys.executable, str(Path(__file__).resolve()), "--load", svc.api.url, name,
                     str(clients), str(seconds), str(k_max), str(seed + i), query],
                    capture_output=True, text=True, timeout=seconds + 60, check=False)
                if proc.returncode != 0:
                    raise RuntimeError(f"the load clients failed: {proc.stderr[-2000:]}")
                res = json.loads(proc.stdout)
                span = res["t_end"] - res["t_start"]
                phases.append({
                    "phase": name, "clients": clients,
                    "loop": loop_stats(clock.ticks, res["t_start"], res["t_end"], speed),
                    "requests": {ep: request_stats(r, span) for ep, r in res["records"].items()},
                })
        finally:
            svc.request_stop()
            thread.join(60)
    idle = phases[0]["loop"]
    loaded = [p["loop"] for p in phases if "requests" in p]
    summary = {
        "step_ms_p99_idle": idle.get("step_ms_p99"),
        "step_ms_p99_load_max": max((p.get("step_ms_p99", math.nan) for p in loaded),
                                    default=None),
        "late_under_load": sum(p.get("late", 0) for p in loaded),
        "rate_under_load_min": min((p.get("rate", 0.0) for p in loaded), default=None),
    }
    summary["keeps_up"] = bool(summary["late_under_load"] == 0
                               and (summary["rate_under_load_min"] or 0) >= 0.98)
    return {"speed": speed, "samples_per_s": speed / DT, "period_ms": DT / speed * 1e3,
            "gc_freeze": gc_freeze, "phases": phases, "summary": summary}


# =========================================================================== report
def print_table(runs: list[dict[str, Any]]) -> None:
    """Print the phases of every speed.

    Parameters
    ----------
    runs : list of dict
        From :func:`run_speed`.
    """
    head = (f"{'speed':>5} {'phase':<10} {'endpoint':<8} {'req/s':>7} {'p50 ms':>7} "
            f"{'p99 ms':>7} {'err':>4} | {'loop p50':>8} {'p99':>7} {'max':>7} "
            f"{'late':>4} {'rate':>6}")
    print(head)
    print("-" * len(head))
    for run in runs:
        for p in run["phases"]:
            lp = p["loop"]
            loop = (f"{lp.get('step_ms_p50', math.nan):8.2f} {lp.get('step_ms_p99', math.nan):7.2f}"
                    f" {lp.get('step_ms_max', math.nan):7.2f} {lp.get('late', 0):4d}"
                    f" {lp.get('rate', 0.0):6.3f}")
            reqs = p.get("requests") or {"-": None}
            for ep, r in reqs.items():
                if r is None:
                    left = f"{'-':<8} {'':>7} {'':>7} {'':>7} {'':>4}"
                else:
                    left = (f"{ep:<8} {r['rps']:7.1f} {r['p50_ms']:7.2f} {r['p99_ms']:7.2f} "
                            f"{r['errors']:4d}")
                tag = "" if run["gc_freeze"] else "*"
                print(f"x{run['speed']:<4g}{tag:1} {p['phase']:<10} {left} | {loop}")
    print("loop: step latency (busy ms per sample), samples more than a period late, "
          "samples/s over nominal; * without the server's gc.freeze()")


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
    args_in = sys.argv[1:] if argv is None else argv
    if args_in[:1] == ["--load"]:
        return load_main(args_in[1:])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="x10, 8 clients, 1.5 s phases (a smoke test)")
    parser.add_argument("--speeds", default=None, help="comma-separated, default 1,10")
    parser.add_argument("--clients", type=int, default=None, help="default 50")
    parser.add_argument("--seconds", type=float, default=None, help="per phase, default 10")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-gc-freeze", action="store_true",
                        help="unfreeze the objects the server froze (the loop's behaviour "
                             "before that fix), for a comparison")
    parser.add_argument("--compare-gc", action="store_true",
                        help="run every speed twice: with the freeze, then without")
    parser.add_argument("--history-query", default=HISTORY_QUERY,
                        help=f"query of the /history requests, default {HISTORY_QUERY!r}")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "api_load.json")
    args = parser.parse_args(args_in)
    speeds = [float(s) for s in (args.speeds or ("10" if args.quick else "1,10")).split(",")]
    clients = args.clients or (8 if args.quick else 50)
    seconds = args.seconds or (1.5 if args.quick else 10.0)
    if clients < 2 or seconds <= 0 or any(s <= 0 for s in speeds):
        parser.error("--clients must be >= 2, --seconds and --speeds positive")
    import logging

    import _common

    for name in ("kautztwin", "uvicorn"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    machine = _common.machine_info()
    modes = [True, False] if args.compare_gc else [not args.no_gc_freeze]
    runs = [run_speed(s, clients, seconds, args.seed, args.history_query, freeze)
            for s in speeds for freeze in modes]
    print_table(runs)
    result = _common.benchmark_result(
        "api_load", argv, quick=args.quick,
        settings={"speeds": speeds, "clients": clients, "seconds_per_phase": seconds,
                  "seed": args.seed, "phases": list(PHASES), "history_query": args.history_query,
                  "gc_freeze": modes,
                  "plant": "hydraulic (quick profile), in process, dt = 0.02 s"},
        machine=machine, runs=runs)
    _common.write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
