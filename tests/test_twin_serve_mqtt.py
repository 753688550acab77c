"""``kautztwin twin serve`` on the MQTT plant and the replay plant (loopback only, bounded time)."""

from __future__ import annotations

import gc
import json
import logging
import signal
import time

import numpy as np
import pytest

from _service_helpers import ROOT, committed, free_port, log_events, serve
from kautztwin.cli.main import main
from kautztwin.exceptions import DataError
from kautztwin.service import load_service_config
from kautztwin.twin.history import SQLiteHistory

TCLAB_CSV = ROOT / "data" / "tclab_step_tests" / "tclab-data.csv"

for _name in ("amqtt", "transitions", "kautztwin.service.mqtt_plant", "kautztwin.twin.physical"):
    logging.getLogger(_name).setLevel(logging.CRITICAL)


def _main_alone(capsys, argv: list[str]) -> int:
    """``main(argv)`` with the garbage of earlier tests collected first.

    The broker of an earlier test leaves asyncio streams behind; collected during
    ``main``, their ``ResourceWarning`` would be printed by the CLI's warning handler
    among this test's output (seen once in a full run).
    """
    gc.collect()
    capsys.readouterr()  # what the collection printed is not this command's
    return main(argv)


def _one_error_line(err: str) -> list[str]:
    lines = [ln for ln in err.strip().splitlines()
             if not ln.startswith("{") and "level=" not in ln]
    assert len(lines) == 1 and lines[0].startswith("kautztwin: error: "), lines
    return lines


# --------------------------------------------------------------------------- configuration
def test_config_reads_mqtt_and_replay_kinds(tmp_path):
    cfg = load_service_config(None, {"plant.kind": "mqtt://127.0.0.1:1884",
                                     "service.out": str(tmp_path)})
    assert cfg.plant["kind"] == "mqtt" and cfg.plant["broker"] == "mqtt://127.0.0.1:1884"
    toml = tmp_path / "twin.toml"
    toml.write_text('[plant]\nkind = "mqtt"\ntopic = "line1/drive"\ndt = 0.02\n'
                    'topics = {u = "line1/cmd"}\n')
    cfg = load_service_config(toml, {"service.out": str(tmp_path)})
    assert cfg.plant["broker"] == "mqtt://127.0.0.1:1883"  # the default broker
    assert (cfg.plant["topic"], cfg.plant["topics"], cfg.plant["dt"]) == (
        "line1/drive", {"u": "line1/cmd"}, 0.02)
    csv = tmp_path / "rec.csv"
    csv.write_text("Time,Q1,T1\n0,1,2\n1,1,3\n")
    toml.write_text('[plant]\nkind = "replay"\nfile = "rec.csv"\n'
                    'columns = {t = "Time", u = "Q1", y = "T1"}\n')
    cfg = load_service_config(toml, {"service.out": str(tmp_path)})  # relative to the file
    assert cfg.plant["file"] == str(csv) and cfg.plant["columns"]["y"] == "T1"
    cfg = load_service_config(None, {"plant.kind": f"replay:{csv}", "service.out": "o"})
    assert cfg.plant["kind"] == "replay" and cfg.plant["columns"] == {"t": "t", "u": "u", "y": "y"}


@pytest.mark.parametrize("overrides, message", [
    ({"plant.kind": "mqtt", "plant.broker": "tcp://127.0.0.1:1883"}, "plant.broker"),
    ({"plant.kind": "mqtt://127.0.0.1:99999"}, "invalid port"),
    ({"plant.kind": "mqtt", "plant.topic": "a/#"}, "plant.topic"),
    ({"plant.kind": "mqtt", "plant.topics": "x=a/b"}, "unknown role 'x'"),
    ({"plant.kind": "hydraulic", "plant.topic": "a/b"}, "applies to an MQTT plant"),
    ({"plant.kind": "replay"}, "plant.file is needed"),
    ({"plant.kind": "replay:/no/such.csv"}, "no such file"),
    ({"plant.kind": "modbus"}, "plant.kind must be one of"),
])
def test_bad_mqtt_and_replay_entries_are_one_line(overrides, message):
    with pytest.raises(DataError) as info:
        load_service_config(None, {**overrides, "service.out": "o"})
    text = str(info.value)
    assert message in text and "\n" not in text, text


# --------------------------------------------------------------------------- MQTT, end to end
def test_twin_serve_against_the_mqtt_plant_server(broker, tmp_path):
    from kautztwin.service import MQTTPlantServer
    from kautztwin.twin import make_plant

    out = tmp_path / "mqtt"
    store = out / "history.sqlite"
    plant = make_plant("hydraulic", seed=0)
    with MQTTPlantServer(plant, broker=broker.url, speed=5.0) as server:
        # stale after 50 periods (0.2 s at x5): the in-process Python broker's delivery
        # jitter is over the default 3 periods (12 ms) now and then (see docs/service.md)
        proc = serve("--plant", broker.url, "--plant-connect-timeout", "20",
                      "--plant-stale-periods", "50",
                      "--model-duration", "120", "--model-quick", "true", "--out", str(out))
        try:
            end = time.monotonic() + 60
            while committed(store) < 300:
                assert time.monotonic() < end, "fewer than 300 samples committed in 60 s"
                assert proc.poll() is None, proc.communicate()[1][-3000:]
                time.sleep(0.1)
            proc.send_signal(signal.SIGTERM)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        published = [s for s in server.history if s.published]
    assert proc.returncode == 0, stderr[-3000:]
    assert "twin serve mqtt" in stdout
    log = log_events(stderr)
    start = next(e for e in log if e["event"] == "start")
    stop = next(e for e in log if e["event"] == "stop")
    assert start["link"] == "mqtt" and start["endpoint"] == broker.url
    assert stop["reason"] == "stop requested"
    with SQLiteHistory(store) as h:
        m = h.measurements(h.runs()[-1].run_id)
    n = len(m.k)
    assert n == stop["n_samples"] >= 300
    assert np.array_equal(m.k, np.arange(n))  # every sample stored once, in order
    assert np.allclose(np.diff(m.t), 0.02)  # consecutive samples of the plant
    ys = {round(s.y, 9) for s in published}  # the stored outputs are the published ones
    finite = m.y[np.isfinite(m.y)]
    assert finite.size >= 0.95 * n
    assert np.mean([round(float(y), 9) in ys for y in finite]) >= 0.99
    # each stored input is the one the plant applied over the sample's period (the sample's
    # "u" on the wire), not the one the twin asked for: sample k's input shaped y(k + 1)
    applied = {s.y: s.u for s in published}
    pairs = [(m.u[i], applied[m.y[i + 1]]) for i in range(n - 1) if m.y[i + 1] in applied]
    assert len(pairs) >= 0.9 * n and all(u == a for u, a in pairs)
    assert (out / "metrics.json").exists()


def test_bad_broker_url_is_one_line_exit_2(capsys, tmp_path):
    assert _main_alone(capsys, ["twin", "serve", "--plant", "mqtt", "--plant-broker",
                                "mqtt://127.0.0.1:0", "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys.readouterr().err)[0]
    assert "plant.broker" in line and "mqtt://HOST:PORT" in line


def test_unreachable_broker_is_one_line_exit_2(capsys, tmp_path):
    import paho.mqtt  # noqa: F401  (a test extra: missing means a broken install)
    url = f"mqtt://127.0.0.1:{free_port()}"  # nothing listens there
    t0 = time.monotonic()
    assert _main_alone(capsys, ["twin", "serve", "--plant", url, "--plant-connect-timeout",
                                "1", "--out", str(tmp_path / "o")]) == 2
    assert time.monotonic() - t0 < 15
    line = _one_error_line(capsys.readouterr().err)[0]
    assert f"cannot connect to {url} within 1 s" in line


# --------------------------------------------------------------------------- replay
def test_replay_of_a_shipped_record_runs_to_its_end(tmp_path):
    out = tmp_path / "replay"
    proc = serve("--plant", f"replay:{TCLAB_CSV.relative_to(ROOT)}",
                  "--plant-columns", "t=Time,u=Q1,y=T1", "--speed", "400", "--out", str(out))
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr[-3000:]
    stop = next(e for e in log_events(stderr) if e["event"] == "stop")
    assert stop["reason"] == "horizon reached" and stop["status"] == "finished"
    rows = TCLAB_CSV.read_text().strip().splitlines()[1:]
    recorded = np.array([[float(c) for c in r.split(",")] for r in rows])
    with SQLiteHistory(out / "history.sqlite") as h:
        m = h.measurements(h.runs()[-1].run_id)
    n = len(m.k)
    assert n == stop["n_samples"] == len(rows) - 1  # the record, to its last period
    assert np.allclose(m.y, recorded[:n, 1]) and np.allclose(m.t, recorded[:n, 0])
    assert stop["wall_s"] < 30  # paced at 400x the recorded pace: about 2 s


def test_replay_sped_up_is_paced_by_the_wall_clock(tmp_path):
    t = np.arange(0.0, 40.0, 0.1)  # a small first-order record: 400 samples of 0.1 s
    u = np.where((t // 5) % 2 == 0, 1.0, 0.0)
    y = np.zeros_like(t)
    for k in range(1, t.size):
        y[k] = 0.9 * y[k - 1] + 0.1 * u[k - 1]
    csv = tmp_path / "rec.csv"
    csv.write_text("t,u,y\n" + "\n".join(f"{a:.1f},{b:g},{c:.9f}" for a, b, c in zip(t, u, y,
                                                                                     strict=True)))
    t0 = time.monotonic()
    assert main(["twin", "serve", "--plant", f"replay:{csv}", "--speed", "20",
                 "--out", str(tmp_path / "o")]) == 0
    wall = time.monotonic() - t0
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["n_samples"] == t.size - 1
    assert wall >= 39.9 / 20 * 0.9  # not faster than 20x the recorded pace
