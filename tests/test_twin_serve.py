"""``kautztwin twin serve``: the twin as a long-lived service (loopback only, bounded in time)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from kautztwin.cli.main import main
from kautztwin.service import load_service_config
from kautztwin.twin.history import SQLiteHistory

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", MPLBACKEND="Agg", PYTHONUNBUFFERED="1")


def _serve(*argv: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "kautztwin", "twin", "serve", "--logging-format", "json", *argv],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)


def _committed(store: Path) -> int:
    if not store.exists():
        return 0
    try:
        with SQLiteHistory(store) as h:
            runs = h.runs()
            return len(h.measurements(runs[-1].run_id).k) if runs else 0
    except Exception:  # the service is creating it
        return 0


def _wait_committed(proc: subprocess.Popen, store: Path, n: int, timeout: float) -> int:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        c = _committed(store)
        if c >= n:
            return c
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        time.sleep(0.1)
    raise AssertionError(f"only {_committed(store)} samples committed after {timeout} s")


def _events(stderr: str) -> list[dict]:
    return [json.loads(line) for line in stderr.splitlines() if line.startswith("{")]


def _store_state(store: Path) -> tuple[int, str, int]:
    """(committed samples, checksum of them, latest model version at or before them)."""
    with SQLiteHistory(store) as h:
        run = h.runs()[-1].run_id
        m = h.measurements(run)
        digest = hashlib.sha256()
        for col in (m.k, m.t, m.u, m.y):
            digest.update(np.ascontiguousarray(col, dtype=float).tobytes())
        n = len(m.k)
        versions = [v.version for v in h.model_versions(run)]
    return n, digest.hexdigest(), max(versions, default=0)


def test_kill_9_mid_run_resumes_same_version_no_sample_lost(tmp_path):
    out = tmp_path / "svc"
    store = out / "history.sqlite"
    argv = ("--plant", "hydraulic", "--speed", "25", "--model-duration", "50", "--model-quick",
            "true", "--model-background", "false", "--out", str(out))
    proc = _serve(*argv)
    try:
        _wait_committed(proc, store, 1200, 60)  # past the identification phase (400 samples)
    finally:
        proc.kill()  # kill -9: no clean shutdown
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    n0, sum0, version0 = _store_state(store)
    assert n0 >= 1200 and version0 >= 1
    again = _serve(*argv, "--duration", "1")
    _, err = again.communicate(timeout=60)
    assert again.returncode == 0, err[-2000:]
    start = next(e for e in _events(err) if e["event"] == "start")
    assert start["resumed"] is True and start["k"] == n0 and start["committed"] == n0
    assert start["version"] == version0
    n1, _, _ = _store_state(store)
    assert n1 > n0
    with SQLiteHistory(store) as h:  # the committed prefix is unchanged, stored once
        m = h.measurements(h.runs()[-1].run_id)
        digest = hashlib.sha256()
        for col in (m.k[:n0], m.t[:n0], m.u[:n0], m.y[:n0]):
            digest.update(np.ascontiguousarray(col, dtype=float).tobytes())
        assert digest.hexdigest() == sum0
        assert np.array_equal(m.k, np.arange(n1))


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
    assert _committed(tmp_path / "history.sqlite") > 0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("toml, extra, message", [
    ("[plant\nkind = 1", (), "malformed TOML"),
    ("[plant]\nkindd = 'hydraulic'", (), "unknown key 'kindd' in [plant]"),
    ("[mpc]\nu_max = 'high'", (), "mpc.u_max must be a number"),
    ("[plant]\nspeed = true", (), "plant.speed must be a number"),
    ("[telemetry]\nx = 1", (), "unknown section [telemetry]"),
    ("[estimator]\npath = 'no/such/model'", (), "no such estimator folder"),
    ("", ("--model-n-poles", "three"), "model.n_poles must be an integer"),
    ("", ("--plant", "opc.tcp://127.0.0.1:PORT", "--plant-connect-timeout", "1"),
     "cannot connect to opc.tcp://127.0.0.1:"),
    ("", ("--plant", "hydraulic", "--model-duration", "1e7"), "service.max_memory_mb"),
])
def test_bad_config_is_one_line_and_exit_2(capsys, tmp_path, toml, extra, message):
    path = tmp_path / "twin.toml"
    path.write_text(toml)
    extra = tuple(a.replace("PORT", str(_free_port())) for a in extra)
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
    pytest.importorskip("asyncua")
    from kautztwin.service import PlantServer
    from kautztwin.twin import make_plant

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    speed = float(os.environ.get("KAUTZTWIN_E2E_SPEED", "10"))  # the acceptance asks >= 10
    events = (30.0, 50.0)
    plant = make_plant("hydraulic", drift=0.4, drift_events=events, seed=0)
    out = tmp_path / "e2e"
    store = out / "history.sqlite"
    with PlantServer(plant, endpoint="opc.tcp://127.0.0.1:0", speed=speed) as server:
        proc = _serve("--plant", server.endpoint, "--plant-input-limits", "0.3,0.7",
                      "--model-duration", "120", "--plant-drift-events", "30,50",
                      "--plant-connect-timeout", "20", "--out", str(out))
        try:
            _wait_committed(proc, store, 3100, 75)  # > 60 s of plant time on the twin's clock
            proc.send_signal(signal.SIGTERM)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        served_s = server.k * server.dt
    assert proc.returncode == 0, stderr[-3000:]
    assert "twin serve opcua" in stdout
    log = _events(stderr)
    stop = next(e for e in log if e["event"] == "stop")
    assert stop["reason"] == "stop requested" and served_s >= 60
    n, _, _ = _store_state(store)
    assert n == stop["n_samples"] >= 3100
    metrics = json.loads((out / "metrics.json").read_text())
    figures = (f"speed x{speed:g}: {n} samples in {stop['wall_s']:.1f} s wall "
               f"({stop['samples_per_s']:.0f}/s for {50 * speed:.0f}/s published), "
               f"re-identifications {metrics['reidentifications']}, sync fit min after recovery "
               f"{metrics['sync_fit_min_after_recovery']}, mean {metrics['sync_fit_mean']}, "
               f"constraint violations {metrics['constraint_violations']}")
    print(figures)
    # What this run establishes: the service attaches to an OPC UA plant, runs for over 60 s of
    # plant time, stores every sample it took, shuts down cleanly on SIGTERM and reports.
    # Not asserted, because it is not met yet (issue #11, measured in docs/service.md): a sync
    # fit >= 95 % after recovery and 0 violations at x10. Each step waits for a synchronous
    # write (about 5 ms), the twin falls behind the server and its (u, y) pairs are misaligned.
    assert metrics["n_samples"] == n, figures
    assert all(k in metrics for k in ("sync_fit_mean", "constraint_violations")), figures
