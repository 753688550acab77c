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


def test_missing_config_file_is_exit_2(capsys, tmp_path):
    assert main(["twin", "serve", "--config", str(tmp_path / "nope.toml"),
                 "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_end_to_end_against_the_opcua_plant_server(tmp_path):
    import asyncua  # noqa: F401  (a test extra: missing means a broken install)

    from kautztwin.service import PlantServer
    from kautztwin.twin import make_plant

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    speed = float(os.environ.get("KAUTZTWIN_E2E_SPEED", "10"))  # the acceptance asks >= 10
    events = (30.0, 50.0)
    plant = make_plant("hydraulic", drift=0.4, drift_events=events, seed=0)
    out = tmp_path / "e2e"
    store = out / "history.sqlite"
    with PlantServer(plant, endpoint="opc.tcp://127.0.0.1:0", speed=speed) as server:
        proc = serve("--plant", server.endpoint, "--plant-input-limits", "0.3,0.7",
                      "--model-duration", "120", "--plant-drift-events", "30,50",
                      "--plant-connect-timeout", "20", "--out", str(out))
        try:
            wait_committed(proc, store, 3100, 75)  # > 60 s of plant time on the twin's clock
            proc.send_signal(signal.SIGTERM)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        served_s = server.k * server.dt
    assert proc.returncode == 0, stderr[-3000:]
    assert "twin serve opcua" in stdout
    log = log_events(stderr)
    stop = next(e for e in log if e["event"] == "stop")
    assert stop["reason"] == "stop requested" and served_s >= 60
    n, _, _ = store_state(store)
    assert n == stop["n_samples"] >= 3100
    metrics = json.loads((out / "metrics.json").read_text())
    figures = (f"speed x{speed:g}: {n} samples in {stop['wall_s']:.1f} s wall "
               f"({stop['samples_per_s']:.0f}/s for {50 * speed:.0f}/s published), "
               f"re-identifications {metrics['reidentifications']}, sync fit min after recovery "
               f"{metrics['sync_fit_min_after_recovery']}, mean {metrics['sync_fit_mean']}, "
               f"constraint violations {metrics['constraint_violations']}")
    print(figures)
    # What holds: the service attaches to an OPC UA plant, keeps up with it (the twin handles
    # every sample the server publishes), runs for over 60 s of plant time, stores every sample
    # it took, learns from the inputs the plant applied (u_applied), re-identifies after the
    # drift, shuts down cleanly on SIGTERM and reports.
    assert metrics["n_samples"] == n, figures
    assert metrics["reidentifications"] >= 1, figures
    # Not asserted, because it is not met yet (issue #11 stays open; figures in docs/service.md
    # and printed above): rolling sync fit >= 95 % after each recovery window and 0 constraint
    # violations at x10.  The inputs reach the plant 2 to 5 samples late (link latency at 500
    # samples/s) and the MPC does not model that delay, so the loop oscillates.


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
    # the sync fit recovers: a 3 s window after the faults scores >= 95 % again
    from kautztwin.metrics import fit_percent_or_nan

    with SQLiteHistory(store) as h:
        preds = {p.k + 1: float(p.y_pred[0]) for p in h.predictions(run)}  # made one ahead
    y_pred = np.array([preds.get(int(k), np.nan) for k in m.k])
    after = int(np.flatnonzero(np.isnan(m.y))[-1]) + 1  # the end of the freeze
    win = int(round(3.0 / 0.02))
    fits = [fit_percent_or_nan(m.y[i:i + win], y_pred[i:i + win])
            for i in range(after, len(m.y) - win + 1, win // 3)]
    print(f"rolling sync fit after the faults: {np.round(fits, 1).tolist()}")
    assert fits and np.nanmax(fits) >= 95.0
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
