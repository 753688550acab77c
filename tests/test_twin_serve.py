"""``kautztwin twin serve``: the twin as a long-lived service (loopback only, bounded in time)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from _service_helpers import (
    ROOT,
    committed,
    free_port,
    log_events,
    samples_digest,
    serve,
    store_state,
    wait_committed,
)
from kautztwin.cli.main import main
from kautztwin.service import load_service_config
from kautztwin.service.process import freeze_garbage, thaw_garbage
from kautztwin.twin.history import SQLiteHistory


def _assert_resumed_without_loss(again: subprocess.Popen, err: str, store: Path, n0: int,
                                 sum0: str, version0: int) -> None:
    """The restarted service resumed at sample n0 and model version0, losing nothing."""
    assert again.returncode == 0, err[-2000:]
    start = next(e for e in log_events(err) if e["event"] == "start")
    assert start["resumed"] is True and start["k"] == n0 and start["committed"] == n0
    assert start["version"] == version0
    n1, _, _ = store_state(store)
    assert n1 > n0
    with SQLiteHistory(store) as h:  # the committed prefix is unchanged, stored once
        m = h.measurements(h.runs()[-1].run_id)
        assert samples_digest(m, n0) == sum0
        assert np.array_equal(m.k, np.arange(n1))


def test_kill_9_mid_run_resumes_same_version_no_sample_lost(tmp_path):
    out = tmp_path / "svc"
    store = out / "history.sqlite"
    argv = ("--plant", "hydraulic", "--speed", "25", "--model-duration", "50", "--model-quick",
            "true", "--model-background", "false", "--out", str(out))
    proc = serve(*argv)
    try:
        wait_committed(proc, store, 1200, 60)  # past the identification phase (400 samples)
    finally:
        proc.kill()  # kill -9: no clean shutdown
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    n0, sum0, version0 = store_state(store)
    assert n0 >= 1200 and version0 >= 1
    again = serve(*argv, "--duration", "1")
    _, err = again.communicate(timeout=60)
    _assert_resumed_without_loss(again, err, store, n0, sum0, version0)


def test_offline_run_and_served_run_give_the_same_metrics(tmp_path):
    common = ["--plant", "hydraulic", "--quick", "--duration", "24"]
    assert main(["twin", "run", *common, "--seed", "3", "--no-static", "--no-plots",
                 "--no-progress", "--out", str(tmp_path / "off")]) == 0
    assert main(["twin", "serve", "--plant", "hydraulic", "--speed", "200", "--model-duration",
                 "24", "--model-quick", "true", "--seed", "3", "--model-background", "false",
                 "--out", str(tmp_path / "srv")]) == 0
    off = json.loads((tmp_path / "off" / "metrics.json").read_text())
    srv = json.loads((tmp_path / "srv" / "metrics.json").read_text())
    assert off["n_samples"] == srv["n_samples"] == 1200
    for key in ("sync_fit_mean", "sync_fit_min", "tracking_iae"):
        assert abs(off[key] - srv[key]) <= 1.0, (key, off[key], srv[key])
    assert off["reidentifications"] == srv["reidentifications"]
    assert srv["constraint_violations"] == 0


def test_example_config_loads_and_serves(tmp_path):
    cfg = load_service_config(ROOT / "examples" / "twin.toml", {"service.out": str(tmp_path)})
    assert cfg.plant["kind"] == "hydraulic" and cfg.plant["drift_events"] == (30.0, 50.0)
    assert cfg.mpc["u_max"] == 0.7 and cfg.history_path == tmp_path / "history.sqlite"
    assert main(["twin", "serve", "--config", str(ROOT / "examples" / "twin.toml"),
                 "--duration", "1", "--out", str(tmp_path)]) == 0
    assert committed(tmp_path / "history.sqlite") > 0


@pytest.mark.parametrize("toml, extra, message", [
    ("[plant\nkind = 1", (), "malformed TOML"),
    ("[plant]\nkindd = 'hydraulic'", (), "unknown key 'kindd' in [plant]"),
    ("[mpc]\nu_max = 'high'", (), "mpc.u_max must be a number"),
    ("[plant]\nspeed = true", (), "plant.speed must be a number"),
    ("[telemetry]\nx = 1", (), "unknown section [telemetry]"),
    ("[estimator]\npath = 'no/such/model'", (), "no such estimator folder"),
    ("", ("--model-n-poles", "three"), "model.n_poles must be an integer"),
    ("[plant]\non_outage = 'stop'", (), "plant.on_outage must be hold or safe"),
    ("[plant]\non_outage = 'safe'", (), "plant.on_outage = safe needs plant.safe_input"),
    ("", ("--plant", "opc.tcp://127.0.0.1:PORT", "--plant-connect-timeout", "1"),
     "cannot connect to opc.tcp://127.0.0.1:"),
    ("", ("--plant", "hydraulic", "--model-duration", "1e7"), "service.max_memory_mb"),
    ("[history]\nsynchronous = 'off'", (), "history.synchronous must be normal or full"),
    ("[model]\nworker = 'gpu'", (), "model.worker must be auto, thread or process"),
])
def test_bad_config_is_one_line_and_exit_2(capsys, tmp_path, toml, extra, message):
    path = tmp_path / "twin.toml"
    path.write_text(toml)
    extra = tuple(a.replace("PORT", str(free_port())) for a in extra)
    t0 = time.monotonic()
    assert main(["twin", "serve", "--config", str(path), *extra,
                 "--out", str(tmp_path / "o")]) == 2
    assert time.monotonic() - t0 < 15
    err = capsys.readouterr().err.strip().splitlines()
    err = [line for line in err if not line.startswith("{") and "level=" not in line]
    assert len(err) == 1 and err[0].startswith("kautztwin: error: ") and message in err[0], err


@pytest.mark.parametrize("table", ["service]\nout = 'a/b/c'", "history]\npath = 'x/y/h.sqlite'"])
def test_store_in_a_missing_nested_folder_is_created(tmp_path, table):
    """A TOML ``service.out`` or ``history.path`` in a folder that does not exist yet."""
    cfg = tmp_path / "cfg"
    cfg.mkdir()
    path = cfg / "twin.toml"
    path.write_text("[plant]\nkind = 'hydraulic'\nspeed = 100.0\n[model]\nduration = 20.0\n"
                    f"quick = true\nbackground = false\n[{table}\n")
    extra = () if table.startswith("service") else ("--out", str(tmp_path / "out"))
    assert main(["twin", "serve", "--config", str(path), "--duration", "1", *extra]) == 0
    store = cfg / ("a/b/c/history.sqlite" if table.startswith("service") else "x/y/h.sqlite")
    assert committed(store) > 0
    # the library (no command line) makes the folders too
    from kautztwin.service import TwinService

    out = tmp_path / "lib" / "deeper" / "run"
    svc = TwinService(load_service_config(None, {
        "plant.kind": "hydraulic", "plant.speed": "200", "model.duration": "4",
        "model.quick": "true", "model.background": "false", "service.out": str(out)}))
    svc.run()
    assert committed(out / "history.sqlite") > 0 and svc.history is None  # closed


def test_the_service_keeps_what_it_built_out_of_full_collections(tmp_path):
    # a full cyclic collection walks every object holding the GIL (90 to 330 ms measured with
    # the twin's libraries loaded): the service freezes what exists before the plant's clock
    # runs (build) and again once the twin is built (run)
    import gc

    from kautztwin.service import TwinService

    gc.unfreeze()
    svc = TwinService(load_service_config(None, {
        "plant.kind": "hydraulic", "plant.speed": "200", "model.duration": "4",
        "model.quick": "true", "model.background": "false", "service.out": str(tmp_path)}))
    try:
        svc.build()
        after_build = gc.get_freeze_count()
        assert after_build > 0
        svc.run()
        assert gc.get_freeze_count() > after_build  # the twin, link and store too
    finally:
        gc.unfreeze()  # the test process's objects back to the collector


@pytest.mark.parametrize("value, pragma", [(None, 1), ("full", 2)])  # NORMAL = 1, FULL = 2
def test_history_synchronous_sets_the_store(tmp_path, value, pragma):
    from kautztwin.service import TwinService

    over = {"plant.kind": "hydraulic", "plant.speed": "200", "model.duration": "4",
            "model.quick": "true", "service.out": str(tmp_path)}
    if value is not None:
        over["history.synchronous"] = value
    svc = TwinService(load_service_config(None, over))
    svc.build()
    try:
        conn = svc.history._conn  # the store's own connection
        assert conn.execute("PRAGMA synchronous").fetchone()[0] == pragma
    finally:
        svc.twin.close()
        svc.history.close()


@pytest.mark.parametrize("kind, worker, expected", [
    ("opcua", "auto", "process"), ("hydraulic", "auto", None), ("opcua", "thread", None),
    ("hydraulic", "process", "process")])
def test_model_worker_picks_the_reidentification_worker(kind, worker, expected):
    from kautztwin.service import TwinService

    over = {"plant.kind": kind, "model.worker": worker, "service.out": "/tmp/unused"}
    if kind == "opcua":
        over["plant.endpoint"] = "opc.tcp://127.0.0.1:4840"
    svc = TwinService(load_service_config(None, over))
    cfg = svc._twin_config("hydraulic", 0.02, ())
    assert cfg.updater.get("worker") == expected


def test_missing_config_file_is_exit_2(capsys, tmp_path):
    assert main(["twin", "serve", "--config", str(tmp_path / "nope.toml"),
                 "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err


#: drift events of the e2e plant, plant seconds: late enough that the twin (started within
#: E2E_START_BY s of plant time, ~3 s wall at x10) has identified its model before the first
E2E_EVENTS = (60.0, 90.0)
E2E_START_BY = 35.0
E2E_RECOVERY = 15.0  # the hydraulic profile's recovery window, s


class _StderrLines:
    """Read a subprocess's stderr in a thread (no full pipe); wait for a JSON log event."""

    def __init__(self, proc: subprocess.Popen) -> None:
        import threading

        self._lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._proc = proc
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stderr:
            self._lines.append(line)

    def text(self) -> str:
        self._thread.join(0 if self._proc.poll() is None else 10)
        return "".join(self._lines)

    def wait_for(self, event: str, timeout: float) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if any(f'"event": "{event}"' in line for line in list(self._lines)):
                return
            assert self._proc.poll() is None, self.text()[-3000:]
            time.sleep(0.05)
        raise AssertionError(f"no {event!r} log event in {timeout} s")


def _pole_retune_figures(store: Path) -> str:
    """One line on the resync pole re-optimisations of the last run: the loop's stall each.

    ``elapsed`` of a ``'pole re-optimisation'`` event is the time the sample loop spent on
    it (the judgement alone when the candidate came from the worker, whose compute time is
    ``worker_s``); at x10 the plant publishes 500 samples per wall-clock second meanwhile.
    """
    with SQLiteHistory(store) as h:
        run = h.runs()[-1].run_id
        evs = [e for e in h.events(run) if e.kind in ("model-update", "model-rejected")
               and "pole re-optimisation" in e.message]
    loop = [float(e.payload.get("elapsed") or 0.0) for e in evs]
    work = [float(e.payload["worker_s"]) for e in evs if "worker_s" in e.payload]
    return (f"pole re-optimisations: {len(evs)} ({sum(e.kind == 'model-update' for e in evs)} "
            f"accepted); loop stall per attempt max {max(loop, default=0.0):.3f} s, total "
            f"{sum(loop):.3f} s (about {500 * max(loop, default=0.0):.0f} samples queued at "
            f"x10); worker compute max {max(work, default=0.0):.3f} s")


def _windows_after_recovery(
    store: Path, offset: float, k0: int
) -> tuple[list[list[float]], list[list[float]]]:
    """Rolling sync fits (the report's windows) after each drift event's recovery window.

    The windows start at the closed-loop start ``k0``, as the report's do (a live twin
    starts it once it has caught up with the samples queued while it identified).
    Segment ``i``: windows ending after event ``i`` + the recovery window and before
    event ``i + 1``; segment 0 is the closed loop before the first event.  Returns the
    fits per segment and the plant times at which their windows end.
    """
    from kautztwin.twin.report import rolling_fit

    with SQLiteHistory(store) as h:
        run = h.runs()[-1]
        m = h.measurements(run.run_id)
        preds = {p.k + 1: float(p.y_pred[0]) for p in h.predictions(run.run_id)}  # one ahead
    cfg = run.config["twin"]
    y_pred = np.array([preds.get(int(k), np.nan) for k in m.k])
    ends, fits = rolling_fit(m.y, y_pred, cfg["monitor_window"], cfg["monitor_stride"], k0)
    t_end = m.t[ends - 1] + offset  # on the plant's clock
    bounds = [-np.inf, *[e + E2E_RECOVERY for e in E2E_EVENTS]]
    limits = [*E2E_EVENTS, np.inf]
    masks = [(t_end > lo) & (t_end <= hi) for lo, hi in zip(bounds, limits, strict=True)]
    return [fits[s].tolist() for s in masks], [t_end[s].tolist() for s in masks]


def _end_to_end_run(tmp_path: Path) -> tuple[dict, list[list[float]], str]:
    """OPC UA plant server (hydraulic, 40 % pole drift, x10) and twin serve against it.

    Returns the run's metrics, the rolling sync fits per segment
    (:func:`_windows_after_recovery`) and a line of figures; asserts the run itself
    (clean stop, every sample stored, >= 60 s of plant time, re-identifications recorded).
    """
    import asyncua  # noqa: F401  (a test extra: missing means a broken install)

    from kautztwin.service import PlantServer
    from kautztwin.twin import make_plant

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    speed = float(os.environ.get("KAUTZTWIN_E2E_SPEED", "10"))  # the acceptance asks >= 10
    plant = make_plant("hydraulic", drift=0.4, drift_events=E2E_EVENTS, seed=0)
    out = tmp_path / "e2e"
    store = out / "history.sqlite"
    end_t = E2E_EVENTS[-1] + E2E_RECOVERY + 12.0  # windows after the last recovery window
    server = PlantServer(plant, endpoint=f"opc.tcp://127.0.0.1:{free_port()}", speed=speed)
    # the twin first: the plant's clock starts when the twin is ready to connect (a loaded
    # host takes seconds to start a Python process: tens of plant seconds at x10)
    proc = serve("--plant", server.endpoint, "--plant-input-limits", "0.3,0.7",
                 "--model-duration", "300", "--plant-drift-events",
                 ",".join(f"{e:g}" for e in E2E_EVENTS), "--plant-connect-timeout", "30",
                 "--out", str(out))
    lines = _StderrLines(proc)
    # the plant server runs in this process: keep the test session's objects out of its
    # full collections (they stalled its ticks, then it caught up in bursts of one input)
    freeze_garbage()
    try:
        lines.wait_for("connecting", 90)
        with server:
            served_from = time.monotonic()
            deadline = time.monotonic() + 60 + end_t / speed
            while server.k * server.dt < end_t:  # cheap polling: the server's plant time
                assert time.monotonic() < deadline, f"plant time {server.k * server.dt:.1f} s"
                assert proc.poll() is None, lines.text()[-3000:]
                time.sleep(0.2)
            served_speed = server.k * server.dt / (time.monotonic() - served_from)
            proc.send_signal(signal.SIGTERM)
            # wait, not communicate: communicate would read stderr too, racing the reader
            # thread for the last lines (the 'stop' event); stdout is a few lines
            proc.wait(timeout=60)
            stdout = proc.stdout.read()
    finally:
        thaw_garbage()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    stderr = lines.text()
    assert proc.returncode == 0, stderr[-3000:]
    assert "twin serve opcua" in stdout
    log = log_events(stderr)
    stop = next(e for e in log if e["event"] == "stop")
    clock = next((e for e in log if e["event"] == "plant-clock"), {})
    assert stop["reason"] == "stop requested"
    assert "offset_s" in clock, f"the twin did not map the plant's clock: {clock}"
    offset = float(clock["offset_s"])  # plant time of the twin's sample 0
    assert offset <= E2E_START_BY, (
        f"the twin started at plant time {offset:.1f} s: too late for the drift events")
    n, _, _ = store_state(store)
    assert n == stop["n_samples"] and n * 0.02 >= 60.0  # >= 60 s of plant time
    metrics = json.loads((out / "metrics.json").read_text())
    k0 = int(round(metrics["closed_loop_start_s"] / metrics["dt"]))
    segments, ends = _windows_after_recovery(store, offset, k0)
    lowest_at = [round(e[int(np.argmin(f))], 1) if f else None
                 for f, e in zip(segments, ends, strict=True)]
    ident = metrics["identification"]
    figures = (f"speed x{speed:g} (the server ran at x{served_speed:.1f}): {n} samples in "
               f"{stop['wall_s']:.1f} s wall "
               f"({stop['samples_per_s']:.0f}/s for {50 * speed:.0f}/s published), twin from "
               f"plant time {offset:.1f} s, identified in {ident['elapsed']:.2f} s wall, "
               f"closed loop from sample {k0} (identification to {ident['n_samples']}), "
               f"drift at {E2E_EVENTS}; re-identifications "
               f"{metrics['reidentifications']}; rolling sync fit min before the first drift "
               f"{min(segments[0], default=float('nan')):.2f} %, after each recovery window "
               f"{[round(min(f), 2) if f else None for f in segments[1:]]} % (each segment's "
               f"lowest window ends at {lowest_at} s of plant time), mean "
               f"{metrics['sync_fit_mean']:.2f} %; constraint violations "
               f"{metrics['constraint_violations']} (max {metrics['max_violation']:.3g}); "
               f"samples {metrics['samples']}")
    print(figures)
    print(_pole_retune_figures(store))
    assert metrics["n_samples"] == n, figures
    # re-identifications recorded (in the store: model versions after the initial one)
    assert metrics["reidentifications"] >= 1, figures
    with SQLiteHistory(store) as h:
        assert len(h.model_versions(h.runs()[-1].run_id)) == metrics["reidentifications"] + 1
    return metrics, segments, figures


def test_end_to_end_against_the_opcua_plant_server(tmp_path):
    """Acceptance of #11 (part): >= 60 s at x10 against the OPC UA plant server with drift.

    Re-identifications recorded (checked in the run) and 0 constraint violations: the applied
    input (its level and rate) and the measured output inside the configured limits over the
    closed loop.  The sync-fit line of the acceptance is the slow test below.
    """
    metrics, segments, figures = _end_to_end_run(tmp_path)
    assert metrics["constraint_violations"] == 0, figures
    assert all(segments), figures  # the run covers every segment the sync check reads


@pytest.mark.slow
def test_end_to_end_sync_fit_after_each_recovery_window(tmp_path):
    """Acceptance of #11: rolling sync fit >= 95 % after each recovery window (and before the
    first drift), 0 constraint violations.

    In the slow set: the windows start at the closed-loop start, once the twin has caught
    up with the samples queued while it identified (as the report's do).  On the quiet
    2-core machine it passed 58 of 68 runs with the re-identification's initial state
    estimated and the controller's states built in blocks (16 of 24 interleaved runs
    without the former): the misses are marginal windows (94.16 to 94.92 %, one 92.35 %),
    8 after a recovery window and 2 in the closed loop's first seconds; with the
    re-identification fits about 1.5x faster, 54 of 64 (34 of 40; then 20 of 24 interleaved
    with a variant not adopted); with a live plant's twin built without stalling the loop
    (``runtime/birth.py``), 35 of 40 (21 of 24 interleaved against 21 of 24 without, its
    lowest window before the first drift 0.4 points higher; then 14 of 16); with the
    resync's hysteresis (``monitor_resync_margin``), 61 of 69 against 56 of 65 for the tree
    without it, run in the same sessions (20 of 24 against 19 of 24 interleaved); with the
    fast path's covariance restarted at a live closed loop's start, 23 of 24 against 18 of
    24 interleaved, 57 of 60 in all (the tree without it: 51 of 62 in the same session);
    with the output-error fits' variable-projection Jacobian (fits 1.8x faster), 46 of 48
    against 42 of 48 interleaved with the tree before it, then 24 of 24 (70 of 72); 36 of
    40 more in a later session (106 of 112); with the hydraulic fast path's quadratic input
    channel and directional forgetting, 23 of 24 against 23 of 24 interleaved (the lowest
    window after the first recovery window a median 0.5 points higher); with the closed
    loop's start as a new regime (``Updater.enter_new_regime``), 21 of 24 against 23 of 24
    interleaved, the arms' data differing: replayed through both trees, the same 48 runs
    had their lowest window before the first drift raised in 42 and lowered in 6; then 28
    of 30 (both misses after the first recovery window), 49 of 54 in all, 78 of 84 with
    a later session's 30; with the output-error fit's starts searched together (fits 1.9x
    faster, the judgement's lag a median 21 samples instead of 37), 20 of 20 against 20
    of 20 interleaved, then 92 of 92 (112 of 112).
    docs/service.md has the figures.  ``-s`` prints them.
    """
    metrics, segments, figures = _end_to_end_run(tmp_path)
    assert all(segments) and all(min(f) >= 95.0 for f in segments), figures
    assert metrics["sync_fit_min_after_recovery"] >= 95.0, figures
    assert metrics["constraint_violations"] == 0, figures


def _wait_until(proc: subprocess.Popen, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()[1][-3000:]  # the twin never exits
        time.sleep(0.05)


def test_link_faults_server_stopped_then_frozen(tmp_path):
    """Acceptance of #11, link faults: the server stopped for 5 s, later frozen for 5 s."""
    import asyncua  # noqa: F401  (a test extra: missing means a broken install)

    from kautztwin.service import PlantServer
    from kautztwin.twin import make_plant

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    speed = float(os.environ.get("KAUTZTWIN_FAULT_SPEED", "2"))
    plant = make_plant("hydraulic", seed=0)
    out = tmp_path / "faults"
    store = out / "history.sqlite"
    server = PlantServer(plant, endpoint="opc.tcp://127.0.0.1:0", speed=speed).start()
    try:
        proc = serve("--plant", server.endpoint, "--plant-input-limits", "0.3,0.7",
                      "--model-duration", "600", "--model-quick", "true",
                      "--plant-on-outage", "safe", "--plant-safe-input", "0.45",
                      "--plant-connect-timeout", "20", "--out", str(out))
        try:
            wait_committed(proc, store, 700, 90)  # past the identification phase
            _wait_until(proc, 2.0)
            stopped_at = time.time()
            server.stop()  # (a) the server goes away for 5 s
            _wait_until(proc, 5.0)
            server.start()
            back_a = time.time()
            _wait_until(proc, 6.0)
            server.freeze()  # (b) connected, but no updates for 5 s
            frozen_at = time.time()
            _wait_until(proc, 5.0)
            server.unfreeze()
            back_b = time.time()
            _wait_until(proc, 6.0)
            proc.send_signal(signal.SIGTERM)
            _, stderr = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    finally:
        server.close()
    assert proc.returncode == 0, stderr[-3000:]
    stop = next(e for e in log_events(stderr) if e["event"] == "stop")
    assert stop["reason"] == "stop requested"
    with SQLiteHistory(store) as h:
        run = h.runs()[-1].run_id
        m = h.measurements(run)
        outages = [e.payload for e in h.events(run, "outage")]
    # both outages are events in the store, each closed
    kinds = [o["kind"] for o in outages]
    assert "link" in kinds and "stale" in kinds, outages
    link = next(o for o in outages if o["kind"] == "link")
    stale = max((o for o in outages if o["kind"] == "stale" and frozen_at < o["start"] < back_b),
                key=lambda o: o["end"] - o["start"])
    reconnect_a = link["end"] - back_a  # the link is up again (session, subscription)
    resume_b = stale["end"] - back_b  # fresh data again after the freeze
    print(f"speed x{speed:g}: link outage {link['end'] - link['start']:.2f} s, reconnected "
          f"{reconnect_a:.2f} s after the server's return; stale outage "
          f"{stale['end'] - stale['start']:.2f} s, data again {resume_b:.2f} s after unfreeze; "
          f"{stop['n_samples']} samples at {stop['samples_per_s']:.0f}/s, sync fit at the end "
          f"{stop['sync_fit']} %")
    assert 0 <= reconnect_a < 2.0 and 0 <= resume_b < 2.0
    assert stopped_at <= link["start"] < back_a - 4.0 and stale["start"] < frozen_at + 1.0
    # the sync fit recovers: the 3 s windows after the faults score >= 95 % again
    from kautztwin.metrics import fit_percent_or_nan

    with SQLiteHistory(store) as h:
        preds = {p.k + 1: float(p.y_pred[0]) for p in h.predictions(run)}  # made one ahead
    y_pred = np.array([preds.get(int(k), np.nan) for k in m.k])
    after = int(np.flatnonzero(np.isnan(m.y))[-1]) + 1  # the end of the freeze
    win = int(round(3.0 / 0.02))
    fits = [fit_percent_or_nan(m.y[i:i + win], y_pred[i:i + win])
            for i in range(after, len(m.y) - win + 1, win // 3)]
    print(f"rolling sync fit after the faults: {np.round(fits, 1).tolist()}")
    # ... and stays: most windows and the last one at 95 % or more (measured: the first
    # window 92.9 to 97.6 %, every later one 95.3 to 98.2 %, in four runs)
    assert fits and np.nanmedian(fits) >= 95.0 and fits[-1] >= 95.0, fits
    # while the link was down or the data stale the twin ran on its model (NaN samples, flagged)
    # and the safe input policy reached the frozen (still writable) server
    history = list(server.history)
    during = [s for s in history if not s.published
              and frozen_at + 1.0 < server.origin_time + s.t / speed < back_b]
    assert during and all(s.u == 0.45 for s in during)
    # every sample published while connected is in the store exactly once (count, checksum)
    stored = m.y[np.isfinite(m.y)]
    assert len(set(stored.tolist())) == len(stored)  # nothing stored twice
    first = np.min(np.flatnonzero(np.isfinite(m.y)))
    t_first = next(s.t for s in history if s.y == m.y[first])
    t_last = next(s.t for s in history if s.y == stored[-1])
    wall = lambda s: server.origin_time + s.t / speed  # noqa: E731
    published = [s.y for s in history if s.published and t_first <= s.t <= t_last
                 and not (link["start"] - 0.1 <= wall(s) <= link["end"] + 0.1)]
    missing = set(published) - set(stored.tolist())
    where = [(s.k, round(wall(s) - stopped_at, 3)) for s in history if s.y in missing]
    assert not missing, (f"{len(missing)} of {len(published)} published samples not stored: "
                         f"(k, s after the stop) {where}; back {back_a - stopped_at:.3f}, "
                         f"frozen {frozen_at - stopped_at:.3f}, unfrozen {back_b - stopped_at:.3f}")
    digest = lambda v: hashlib.sha256(np.sort(np.asarray(v, float)).tobytes()).hexdigest()  # noqa: E731
    in_store = [y for y in stored.tolist() if y in set(published)]
    assert len(in_store) == len(published) and digest(in_store) == digest(published)


def test_kill_9_against_the_opcua_plant_resumes_same_version(tmp_path):
    """Acceptance of #11: kill -9 of ``twin serve`` on an OPC UA plant, restart, resume."""
    import asyncua  # noqa: F401  (a test extra: missing means a broken install)

    from kautztwin.service import PlantServer
    from kautztwin.twin import make_plant

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    out = tmp_path / "k9"
    store = out / "history.sqlite"
    with PlantServer(make_plant("hydraulic", seed=0), endpoint="opc.tcp://127.0.0.1:0",
                     speed=4.0) as server:
        argv = ("--plant", server.endpoint, "--plant-input-limits", "0.3,0.7",
                "--model-duration", "600", "--model-quick", "true", "--model-background", "false",
                "--plant-connect-timeout", "20", "--out", str(out))
        proc = serve(*argv)
        try:
            wait_committed(proc, store, 900, 90)  # past the identification phase
        finally:
            proc.kill()  # kill -9: no clean shutdown
            proc.communicate()
        assert proc.returncode == -signal.SIGKILL
        n0, sum0, version0 = store_state(store)
        assert n0 >= 900 and version0 >= 1
        again = serve(*argv, "--duration", "3")
        _, err = again.communicate(timeout=90)
    _assert_resumed_without_loss(again, err, store, n0, sum0, version0)
