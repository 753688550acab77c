"""The MQTT plant server and the twin's MQTT link, on a real broker on loopback (amqtt)."""

from __future__ import annotations

import json
import logging
import math
import time

import amqtt  # noqa: F401  (a test extra: missing means a broken install)
import numpy as np
import paho.mqtt  # noqa: F401  (a test extra: missing means a broken install)
import paho.mqtt.client as mqtt  # noqa: E402
import pytest

from _service_helpers import Broker, FirstOrderPlant, drive_through_restart, free_port
from kautztwin.exceptions import DataError  # noqa: E402
from kautztwin.service import MQTTPlantServer  # noqa: E402
from kautztwin.twin import HydraulicPlant  # noqa: E402
from kautztwin.twin.physical import LinkError, MQTTPlant, parse_broker  # noqa: E402

for _name in ("amqtt", "transitions", "kautztwin.service.mqtt_plant", "kautztwin.twin.physical"):
    logging.getLogger(_name).setLevel(logging.CRITICAL)


def _publisher(broker: Broker) -> mqtt.Client:
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    client.connect("127.0.0.1", broker.port)
    client.loop_start()
    return client


# --------------------------------------------------------------------------- closed loop
def test_closed_loop_matches_in_process_run(broker):
    plant = HydraulicPlant(temperature=20.0, noise=0.0)
    with MQTTPlantServer(plant, broker=broker.url, speed=1.0) as server, \
            MQTTPlant(broker.url, plant="hydraulic", connect_timeout=10) as link:
        r = link.reset()
        assert (link.dt, link.speed, link.input_limits) == (0.02, 1.0, (-1.0, 1.0))
        readings = []
        for i in range(50):  # a proportional speed controller around two set-points
            ref = 98.0 if i < 25 else 102.0
            u = float(np.clip(0.5 + 0.02 * (ref - r.y), -1.0, 1.0))
            r = link.step(u)
            readings.append(r)
        history = {s.k: s for s in server.history}
    assert all(not rd.meta["dropout"] and rd.meta["link"] == "up" for rd in readings)
    t = np.array([rd.t for rd in readings])
    assert np.allclose(np.diff(t), 0.02)
    ks = [round((rd.meta["source_time"] - server.origin_time) / server.dt) for rd in readings]
    assert ks == list(range(ks[0], ks[0] + 50))
    assert all(rd.y == history[k].y for rd, k in zip(readings, ks, strict=True))
    ref_plant = HydraulicPlant(temperature=20.0, noise=0.0)
    ref_plant.reset()
    y_ref = {k: ref_plant.step(history[k].u).y for k in range(1, ks[-1] + 1)}
    assert max(abs(rd.y - y_ref[k]) for rd, k in zip(readings, ks, strict=True)) < 1e-9
    # every sample is paired with the input the plant applied over its period (the sample's
    # "u"), whether the input published for that period arrived in time or not
    assert all(rd.meta["u_applied"] == rd.meta["u"] == history[k].u
               for rd, k in zip(readings, ks, strict=True))
    assert all(isinstance(rd.meta["input_delay"], int) and rd.meta["input_delay"] >= 0
               for rd in readings)


# --------------------------------------------------------------------------- bad input
def test_out_of_range_input_refused(broker):
    with MQTTPlantServer(FirstOrderPlant(), broker=broker.url) as server:
        with MQTTPlant(broker.url, plant="first") as link:
            link.reset()
            assert link.input_limits == (0.0, 10.0)
            with pytest.raises(DataError, match="outside the input limits") as info:
                link.step(12.0)
            assert "\n" not in str(info.value)
            with pytest.raises(DataError, match="outside the input limits"):
                link.step(math.nan)
        # the plant rejects what a link with wider limits (or anyone) sends
        with MQTTPlant(broker.url, plant="first", input_limits=(-5.0, 50.0)) as link:
            link.reset()
            r = link.step(20.0)
            for _ in range(3):
                if r.meta["write"].startswith("rejected"):
                    break
                r = link.step(4.0)
            assert link.counters["rejected_writes"] >= 1
        pub = _publisher(broker)
        try:
            for payload in ('{"u": 99}', '{"u": NaN}', '"x"', "not json"):
                pub.publish(server.topics["u"], payload, qos=1).wait_for_publish(2)
            time.sleep(0.3)
        finally:
            pub.loop_stop()
            pub.disconnect()
        assert len(server.rejected) >= 5
    assert all(0.0 <= s.u <= 10.0 for s in server.history if math.isfinite(s.u))


def test_config_errors():
    with pytest.raises(DataError, match="mqtt://HOST:PORT"):
        MQTTPlant("tcp://127.0.0.1:1883")
    with pytest.raises(DataError, match="unknown role"):
        MQTTPlant(topics={"out": "a/b"})
    with pytest.raises(DataError, match="wildcards"):
        MQTTPlant(topic="plants/#")
    assert parse_broker("mqtt://localhost") == ("localhost", 1883)
    with pytest.raises(LinkError, match="cannot connect") as info:
        MQTTPlant(f"mqtt://127.0.0.1:{free_port()}", connect_timeout=1.0).reset()
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------- link faults
def test_nan_inf_and_garbage_are_flagged_dropouts(broker):
    server = MQTTPlantServer(FirstOrderPlant(poison={3: math.nan, 7: math.inf}),
                             broker=broker.url, topic="test/poison").start()
    try:
        with MQTTPlant(broker.url, topic="test/poison", stale_periods=10) as link:
            link.reset()
            readings = [link.step(5.0) for _ in range(25)]
            # garbage straight onto the output topic, newest timestamps
            pub = _publisher(broker)
            try:
                now = time.time()
                for i, payload in enumerate([b"not json", b'{"y": NaN, "ts": %f}' % (now + 0.001),
                                             b'{"y": Infinity, "ts": %f}' % (now + 0.002),
                                             b'{"y": "12", "ts": %f}' % (now + 0.003), b"[1, 2]"]):
                    del i
                    pub.publish(server.topics["y"], payload, qos=1).wait_for_publish(2)
            finally:
                pub.loop_stop()
                pub.disconnect()
            extra = [link.step(5.0) for _ in range(12)]
    finally:
        server.close()
    poisoned = [r for r in readings if r.meta["status"] == "BadValue"]
    assert len(poisoned) >= 4
    assert all(math.isnan(r.y) and r.meta["dropout"] and not r.meta["stale"] for r in poisoned)
    good = [r for r in readings if r.meta["status"] == "Good"]
    assert len(good) >= 15 and all(math.isfinite(r.y) and not r.meta["dropout"] for r in good)
    statuses = [r.meta["status"] for r in extra]
    assert statuses.count("BadDecoding") >= 2 and statuses.count("BadValue") >= 3
    assert all(math.isnan(r.y) for r in extra if r.meta["status"] != "Good")


def test_frozen_publisher_gives_stale_flagged_readings(broker):
    server = MQTTPlantServer(FirstOrderPlant(), broker=broker.url, topic="test/frozen").start()
    try:
        with MQTTPlant(broker.url, topic="test/frozen", stale_periods=3) as link:
            link.reset()
            for _ in range(3):
                assert not link.step(1.0).meta["stale"]
            server.freeze()
            try:
                start = time.monotonic()
                frozen = [link.step(1.0) for _ in range(20)]
                elapsed = time.monotonic() - start
            finally:
                server.unfreeze()
            after = [link.step(1.0) for _ in range(5)]
    finally:
        server.close()
    stale = [r for r in frozen if r.meta["stale"]]
    assert len(stale) >= 12
    assert all(math.isnan(r.y) and r.meta["dropout"] and r.meta["link"] == "up" for r in stale)
    assert elapsed < 20 * 0.05 * 2
    assert np.all(np.diff([r.t for r in frozen + after]) > 0)
    assert not after[-1].meta["stale"] and any(math.isfinite(r.y) for r in after)
    outage = [o for o in link.outages if o.kind == "stale"]
    assert len(outage) == 1 and outage[0].end is not None and link.counters["stale"] >= 12


def test_safe_input_policy_while_frozen_then_resync(broker):
    """Outage policy as the OPC UA link: the safe input while the data are stale, then back."""
    server = MQTTPlantServer(FirstOrderPlant(), broker=broker.url, topic="test/safe").start()
    try:
        with MQTTPlant(broker.url, topic="test/safe", stale_periods=3, on_outage="safe",
                       safe_input=1.5) as link:
            link.reset()
            before = [link.step(4.0) for _ in range(5)]
            server.freeze()
            try:
                frozen = [link.step(4.0) for _ in range(20)]
            finally:
                server.unfreeze()
            after = [link.step(4.0) for _ in range(10)]
    finally:
        server.close()
    assert all(r.meta["write"] == "ok" for r in before)
    stale = [r for r in frozen if r.meta["stale"]]
    assert len(stale) >= 10
    # the first stale reading's step began with fresh data; from then on the safe input goes out
    assert all(r.meta["write"] == "sent: safe input 1.5" for r in stale[1:])
    silent = [s for s in server.history if not s.published]
    assert silent and silent[-1].u == 1.5  # it reached the frozen (still listening) plant
    outage = [o for o in link.outages if o.kind == "stale"]
    assert len(outage) == 1 and outage[0].end is not None  # resynchronised: fresh data again
    assert after[-1].meta["write"] == "ok" and after[-1].meta["u"] == 4.0
    assert not after[-1].meta["stale"] and math.isfinite(after[-1].y)


def test_outage_policy_config_errors():
    with pytest.raises(DataError, match="on_outage must be 'hold' or 'safe'"):
        MQTTPlant(on_outage="stop")
    with pytest.raises(DataError, match="needs a safe_input"):
        MQTTPlant(on_outage="safe")


def test_broker_restart_reconnects_and_records_outage():
    broker = Broker().start()
    plant = FirstOrderPlant()
    server = MQTTPlantServer(plant, broker=broker.url).start()
    try:
        with MQTTPlant(broker.url, plant="first", stale_periods=3) as link:
            readings, reconnected_after, tail = drive_through_restart(link, broker.stop,
                                                                      broker.start)
    finally:
        server.close()
        broker.stop()
    assert reconnected_after < 2.0
    down = [r for r in readings if r.meta["link"] == "down"]
    assert len(down) >= 10 and all(math.isnan(r.y) and r.meta["dropout"] for r in down)
    # (the first may have been written while the link was still up: its step began then)
    assert all(r.meta["write"] == "not sent: holding (link down)" for r in down[1:])
    assert all(not r.meta["dropout"] and r.meta["write"] == "ok" for r in tail)
    link_outages = [o for o in link.outages if o.kind == "link"]
    assert len(link_outages) == 1 and link_outages[0].end is not None
    assert 1.5 < link_outages[0].duration < 6.0
    assert link.counters["reconnects"] == 1
    # the plant ran on while the broker was away; those samples were not published
    silent = [s for s in server.history if not s.published]
    assert len(silent) >= 20
    assert tail[-1].meta["u"] == 3.0


def test_meta_and_status_topics(broker):
    got: dict[str, object] = {}
    with MQTTPlantServer(FirstOrderPlant(), broker=broker.url, topic="test/meta", speed=2.0):
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        client.on_message = lambda c, u, m: got.__setitem__(m.topic, json.loads(m.payload))
        client.connect("127.0.0.1", broker.port)
        client.subscribe("test/meta/#", qos=1)
        client.loop_start()
        try:
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline and len(got) < 3:
                time.sleep(0.05)
        finally:
            client.loop_stop()
            client.disconnect()
    meta = got["test/meta/meta"]
    assert meta["dt"] == 0.05 and meta["speed"] == 2.0 and meta["u"]["high"] == 10.0
    assert got["test/meta/status"] in ("running", "catching-up")
    sample = got["test/meta/y"]
    assert set(sample) >= {"k", "t", "y", "u", "ts"}
