"""The OPC UA plant server and the twin's OPC UA link, on loopback (real server and client)."""

from __future__ import annotations

import asyncio
import logging
import math
import time

import asyncua  # noqa: F401  (a test extra: missing means a broken install)
import numpy as np
import pytest
from asyncua import Client, ua  # noqa: E402

from _service_helpers import FirstOrderPlant, drive_through_restart
from kautztwin.exceptions import DataError  # noqa: E402
from kautztwin.service import Channel, PlantServer  # noqa: E402
from kautztwin.twin import HydraulicPlant, Reading  # noqa: E402
from kautztwin.twin.physical import NAMESPACE_URI, LinkError, OPCUAPlant  # noqa: E402

LOOPBACK = "opc.tcp://127.0.0.1:0"  # port 0: the server picks a free port

logging.getLogger("asyncua").setLevel(logging.CRITICAL)


@pytest.fixture(scope="module")
def hydraulic_server():
    plant = HydraulicPlant(temperature=20.0, noise=0.0)
    with PlantServer(plant, endpoint=LOOPBACK, speed=1.0) as server:
        yield server


@pytest.fixture(scope="module")
def first_server():
    with PlantServer(FirstOrderPlant(poison={3: math.nan, 7: math.inf}), endpoint=LOOPBACK,
                     speed=1.0) as server:
        yield server


def _source_k(server: PlantServer, reading: Reading) -> int:
    return round((reading.meta["source_time"] - server.origin_time) * server.speed / server.dt)


# --------------------------------------------------------------------------- address space
def test_address_space_browse(hydraulic_server):
    server = hydraulic_server
    deadline = time.monotonic() + 5.0
    while server.k < 1 and time.monotonic() < deadline:  # a loaded host: the first tick
        time.sleep(0.01)

    async def browse():
        async with Client(server.endpoint, timeout=5) as client:
            idx = await client.get_namespace_index(NAMESPACE_URI)
            objects = await client.nodes.objects.get_children()
            names = [(await n.read_browse_name()).Name for n in objects]
            obj = client.get_node(ua.NodeId("hydraulic", idx))
            children = {(await n.read_browse_name()).Name: n for n in await obj.get_children()}
            props = {}
            for var in ("u", "y"):
                props[var] = {(await p.read_browse_name()).Name: await p.read_value()
                              for p in await children[var].get_properties()}
            access = {v: await children[v].read_attribute(ua.AttributeIds.UserAccessLevel)
                      for v in ("u", "y")}
            values = {k: await children[k].read_value() for k in ("status", "dt", "speed", "k")}
            y_dv = await children["y"].read_data_value()
            return names, sorted(children), props, access, values, y_dv

    names, children, props, access, values, y_dv = asyncio.run(browse())
    assert "hydraulic" in names
    assert children == ["dt", "k", "speed", "status", "t", "u", "u_applied", "y"]
    u_range, y_eu = props["u"]["EURange"], props["y"]["EngineeringUnits"]
    assert (u_range.Low, u_range.High) == (-1.0, 1.0)
    assert y_eu.DisplayName.Text == "rad/s" and y_eu.UnitId == 12865  # UNECE '2A'
    assert props["y"]["EURange"].High > 100.0
    write_bit = 1 << ua.AccessLevel.CurrentWrite
    assert access["u"].Value.Value & write_bit and not access["y"].Value.Value & write_bit
    assert values["status"] == "running" and values["dt"] == 0.02 and values["speed"] == 1.0
    assert values["k"] > 0 and y_dv.SourceTimestamp is not None


# --------------------------------------------------------------------------- closed loop
def test_closed_loop_matches_in_process_run(hydraulic_server):
    server = hydraulic_server
    with OPCUAPlant(server.endpoint, plant="hydraulic", connect_timeout=10) as link:
        r = link.reset()
        assert (link.dt, link.speed, link.input_limits) == (0.02, 1.0, (-1.0, 1.0))
        readings = []
        for i in range(50):  # a proportional speed controller around two set-points
            ref = 98.0 if i < 25 else 102.0
            u = float(np.clip(0.5 + 0.02 * (ref - r.y), -1.0, 1.0))
            r = link.step(u)
            readings.append(r)
        # a node read over the link's own session (the twin service maps the plant's clock)
        assert link.read("hydraulic.dt")[0] == 0.02
        t_node, stamp = link.read(f"nsu={NAMESPACE_URI};s=hydraulic.t")
        assert abs((stamp - server.origin_time) * server.speed - t_node) < 1e-3
        with pytest.raises(DataError, match="cannot read 'hydraulic.nope'"):
            link.read("hydraulic.nope")
    assert all(not rd.meta["dropout"] and rd.meta["link"] == "up" for rd in readings)
    t = np.array([rd.t for rd in readings])
    assert np.allclose(np.diff(t), 0.02)
    history = {s.k: s for s in server.history}
    ks = [_source_k(server, rd) for rd in readings]
    assert ks == list(range(ks[0], ks[0] + 50))
    # the client sees exactly what the server published
    assert all(rd.y == history[k].y for rd, k in zip(readings, ks, strict=True))
    # an in-process run of the same plant with the inputs the server applied gives the same y
    ref_plant = HydraulicPlant(temperature=20.0, noise=0.0)
    ref_plant.reset()
    y_ref = {k: ref_plant.step(history[k].u).y for k in range(1, ks[-1] + 1)}
    assert max(abs(rd.y - y_ref[k]) for rd, k in zip(readings, ks, strict=True)) < 1e-9
    # and the server applied the inputs the client wrote (when the write made it in time)
    on_time = [history[k].u == rd.meta["u"] for rd, k in zip(readings, ks, strict=True)
               if not rd.meta["late"]]
    assert len(on_time) >= 25 and np.mean(on_time) >= 0.8
    # every sample is paired with the input the plant applied over its period (u_applied)
    assert all(rd.meta["u_applied"] == rd.meta["u"] == history[k].u
               for rd, k in zip(readings, ks, strict=True))


def test_input_delay_estimate_matches_the_server(hydraulic_server):
    """meta['input_delay']: the period an input sent now is applied over, from the link's view."""
    server = hydraulic_server
    with OPCUAPlant(server.endpoint, plant="hydraulic", connect_timeout=10) as link:
        first = link.reset()
        sent = []
        for i in range(60):
            u = 0.45 + 0.001 * i  # a new value every step: each one identifies its period
            before = link.input_delay
            r = link.step(u)
            sent.append((u, before, r))
    readings = [first] + [r for _, _, r in sent]
    history = {s.k: s for s in server.history}
    k0 = _source_k(server, first)
    errors = []
    for i, (u, estimate, _) in enumerate(sent):
        applied = [k for k in range(k0 + i + 1, k0 + i + 40) if k in history
                   and history[k].u == u]
        if applied and i >= 10:  # after a few changes the wire's latency is learnt
            actual = applied[0] - 1 - (k0 + i)  # period index minus the reading index
            errors.append(estimate - actual)
    assert len(errors) >= 25 and all(r.meta["k"] == j for j, r in enumerate(readings))
    # speed 1 (50 periods a second): most inputs are applied over the next period or the one
    # after; the estimate is right to the sample for most and never off by more than 2
    assert np.mean(np.abs(errors) <= 1) >= 0.9 and max(np.abs(errors)) <= 2, errors


# --------------------------------------------------------------------------- bad input
def test_out_of_range_write_rejected(hydraulic_server):
    server = hydraulic_server

    async def write(value):
        async with Client(server.endpoint, timeout=5) as client:
            idx = await client.get_namespace_index(NAMESPACE_URI)
            node = client.get_node(ua.NodeId("hydraulic.u", idx))
            await node.write_value(ua.DataValue(ua.Variant(value, ua.VariantType.Double)))

    before = server.last_input
    for bad in (1.5, -3.0, math.nan, math.inf):
        with pytest.raises(ua.uaerrors.BadOutOfRange):
            asyncio.run(write(bad))
    time.sleep(0.05)
    assert server.last_input == before
    assert all(abs(s.u) <= 1.0 for s in server.history if math.isfinite(s.u))

    # the link refuses it before it goes out ...
    with OPCUAPlant(server.endpoint, plant="hydraulic") as link:
        link.reset()
        with pytest.raises(DataError, match="outside the input limits") as info:
            link.step(1.5)
        assert "\n" not in str(info.value)
    # ... and reports a server-side rejection when its own limits are wider
    with OPCUAPlant(server.endpoint, plant="hydraulic", input_limits=(-2.0, 2.0)) as link:
        link.reset()
        r = link.step(1.5)
        assert r.meta["write"] == "rejected: BadOutOfRange" and math.isfinite(r.y)
        assert link.counters["rejected_writes"] == 1
        assert r.meta["u"] != 1.5


def test_bad_node_ids_and_config(hydraulic_server):
    endpoint = hydraulic_server.endpoint
    with pytest.raises(DataError, match="does not exist") as info:
        OPCUAPlant(endpoint, plant="hydraulic", nodes={"y": "hydraulic.nope"}).reset()
    assert "\n" not in str(info.value) and "hydraulic.nope" in str(info.value)
    with pytest.raises(DataError, match="does not exist"):
        OPCUAPlant(endpoint, plant="nosuchplant").reset()
    with pytest.raises(DataError, match="not an OPC UA node id"):
        OPCUAPlant(endpoint, nodes={"u": "ns=x;q=1"})
    with pytest.raises(DataError, match="unknown role"):
        OPCUAPlant(endpoint, nodes={"out": "hydraulic.y"})
    with pytest.raises(DataError, match="opc.tcp"):
        OPCUAPlant("http://127.0.0.1:4840")
    with pytest.raises(LinkError, match="cannot connect") as info:
        OPCUAPlant("opc.tcp://127.0.0.1:9", connect_timeout=1.0).reset()
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------- link faults
def test_write_hung_across_an_outage_is_counted_not_reported_after_it(first_server):
    """A write whose answer never comes (the server went away with it) fails after the
    reconnection; its failure is counted, but readings after the reconnection carry the
    status of their own writes, which go out over the new connection."""
    server = first_server
    with OPCUAPlant(server.endpoint, plant="first", stale_periods=10,
                    request_timeout=5.0) as link:
        link.reset()
        real_write, release = link._write_async, asyncio.Event()
        hung = []

        async def hang_first(node, raw):  # the fault: one write is not answered in time
            if not hung:
                hung.append(raw)
                await release.wait()
            return await real_write(node, raw)

        link._write_async = hang_first
        assert link.step(1.0).meta["write"] in ("ok", "pending")  # the hung write goes out
        server.stop()
        down = [link.step(2.0) for _ in range(10)]
        assert all(r.meta["write"].startswith("not sent") for r in down), down
        server.start()
        deadline = time.monotonic() + 10.0
        while not link.link_up and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.link_up
        queued = [link.step(3.0) for _ in range(3)]  # coalesced behind the hung write
        link._loop.call_soon_threadsafe(release.set)  # it fails now, on the old connection
        while link.counters["failed_writes"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        after = queued + [link.step(3.0) for _ in range(10)]
        assert hung == [1.0] and link.counters["failed_writes"] == 1
    statuses = [r.meta["write"] for r in after]
    assert not any(s.startswith("failed") for s in statuses), statuses
    assert set(statuses[-5:]) <= {"ok", "pending"} and "ok" in statuses[-5:], statuses


def test_nan_and_inf_from_the_plant_are_flagged_dropouts(first_server):
    with OPCUAPlant(first_server.endpoint, plant="first", stale_periods=10) as link:
        link.reset()
        assert link.input_limits == (0.0, 10.0)
        readings = [link.step(5.0) for _ in range(25)]
    readings = [r for r in readings if not r.meta["stale"]]  # (none unless the host stalls)
    ks = [_source_k(first_server, r) for r in readings]
    bad = [r for r, k in zip(readings, ks, strict=True) if k % 10 in (3, 7)]
    good = [r for r, k in zip(readings, ks, strict=True) if k % 10 not in (3, 7)]
    assert len(bad) >= 4
    assert all(math.isnan(r.y) and r.meta["dropout"] and not r.meta["stale"] for r in bad)
    assert all(math.isfinite(r.y) and not r.meta["dropout"] for r in good)


def test_frozen_server_gives_stale_flagged_readings(first_server):
    server = first_server
    with OPCUAPlant(server.endpoint, plant="first", stale_periods=3) as link:
        link.reset()
        for _ in range(3):
            assert not link.step(1.0).meta["stale"]  # (some samples are poisoned: NaN, inf)
        server.freeze()
        try:
            start = time.monotonic()
            frozen = [link.step(1.0) for _ in range(20)]
            elapsed = time.monotonic() - start
        finally:
            server.unfreeze()
        after = [link.step(1.0) for _ in range(5)]
    stale = [r for r in frozen if r.meta["stale"]]
    assert len(stale) >= 12  # the first few are samples already on their way
    assert all(math.isnan(r.y) and r.meta["dropout"] and r.meta["link"] == "up" for r in stale)
    assert elapsed < 20 * 0.05 * 2  # paced: one NaN per period, not stale_periods each
    assert np.all(np.diff([r.t for r in frozen + after]) > 0)
    assert not after[-1].meta["stale"] and any(math.isfinite(r.y) for r in after)
    outage = [o for o in link.outages if o.kind == "stale"]
    assert len(outage) == 1 and outage[0].end is not None and link.counters["stale"] >= 12


def test_server_restart_reconnects_and_records_outage():
    plant = FirstOrderPlant()
    server = PlantServer(plant, endpoint=LOOPBACK, speed=1.0).start()
    try:
        with OPCUAPlant(server.endpoint, plant="first", stale_periods=3) as link:
            readings, reconnected_after, tail = drive_through_restart(link, server.stop,
                                                                      server.start)
    finally:
        server.close()
    assert reconnected_after < 2.0
    down = [r for r in readings if r.meta["link"] == "down"]
    assert len(down) >= 10 and all(math.isnan(r.y) and r.meta["dropout"] for r in down)
    assert all(not r.meta["dropout"] for r in tail)
    # writes do not block: a status is 'pending' until the server's answer has arrived
    statuses = [r.meta["write"] for r in tail]
    assert "ok" in statuses and set(statuses) <= {"ok", "pending"}, statuses
    link_outages = [o for o in link.outages if o.kind == "link"]
    assert len(link_outages) == 1 and link_outages[0].end is not None
    assert 1.5 < link_outages[0].duration < 6.0
    assert link.counters["reconnects"] == 1
    assert server.restarts == 1 and server.port == int(server.endpoint.rsplit(":", 1)[1])
    # the plant ran on while the server was down (caught up with the wall clock, silently)
    silent = [s for s in server.history if not s.published]
    assert len(silent) >= 30 and tail[-1].t > len(silent) * plant.dt
    assert all(s.u == 2.0 for s in silent)  # holding the last input it had


def test_channels_and_endpoint_validation():
    with pytest.raises(DataError, match="low < high"):
        Channel("m", 1.0, 1.0)
    with pytest.raises(DataError, match="inside the plant's input limits"):
        PlantServer(FirstOrderPlant(), input_channel=Channel("", -1.0, 20.0))
    with pytest.raises(DataError, match="opc.tcp://HOST:PORT"):
        PlantServer(FirstOrderPlant(), endpoint="tcp://127.0.0.1:4840")
    with pytest.raises(DataError, match="speed"):
        PlantServer(FirstOrderPlant(), speed=0)


def test_username_password_passthrough():
    with PlantServer(FirstOrderPlant(), endpoint=LOOPBACK, users={"twin": "s3cret"}) as server:
        with OPCUAPlant(server.endpoint, plant="first", username="twin",
                        password="s3cret") as link:
            link.reset()
            # writes do not block the loop: a write's status comes with the first reading
            # after the server answered ('pending' until then)
            writes = [link.step(4.0).meta["write"] for _ in range(5)]
            assert "ok" in writes and set(writes) <= {"ok", "pending"}, writes
        for user, password in (("twin", "wrong"), (None, None)):
            with pytest.raises(LinkError, match="refused the session"):
                OPCUAPlant(server.endpoint, plant="first", username=user, password=password,
                           connect_timeout=5).reset()


def _self_signed(tmp_path, name: str, uri: str, server: bool) -> tuple[str, str]:
    """A self-signed application certificate and its key, PEM files in ``tmp_path``."""
    from asyncua.crypto.cert_gen import (
        dump_private_key_as_pem,
        generate_private_key,
        generate_self_signed_app_certificate,
    )
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = generate_private_key()
    use = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    cert = generate_self_signed_app_certificate(
        key, name, {}, [x509.UniformResourceIdentifier(uri), x509.DNSName("localhost")], [use])
    cert_path, key_path = tmp_path / f"{name}.pem", tmp_path / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(dump_private_key_as_pem(key))
    return str(cert_path), str(key_path)


def test_sign_and_encrypt_with_username_password_and_one_line_errors(tmp_path, capsys):
    """#11 item 2: username/password and the server's security policy (Basic256Sha256)."""
    from kautztwin.cli.main import main

    server_cert, server_key = _self_signed(tmp_path, "server", "urn:kautztwin:server", True)
    client_cert, client_key = _self_signed(tmp_path, "client", "urn:freeopcua:client", False)
    security = f"Basic256Sha256,SignAndEncrypt,{client_cert},{client_key}"
    with PlantServer(FirstOrderPlant(), endpoint=LOOPBACK, users={"twin": "s3cret"},
                     certificate=server_cert, private_key=server_key) as server:
        with OPCUAPlant(server.endpoint, plant="first", username="twin", password="s3cret",
                        security=security, connect_timeout=10) as link:
            link.reset()
            readings = [link.step(4.0) for _ in range(5)]
        assert all(not r.meta["dropout"] for r in readings)
        assert "ok" in [r.meta["write"] for r in readings]
        # the server offers no unencrypted endpoint: refused at once, not after the timeout
        t0 = time.monotonic()
        with pytest.raises(LinkError, match="offers no endpoint with security None"):
            OPCUAPlant(server.endpoint, plant="first", username="twin", password="s3cret",
                       connect_timeout=8).reset()
        assert time.monotonic() - t0 < 6
        # a wrong password through `twin serve`: one line, exit 2
        argv = ["twin", "serve", "--plant", server.endpoint, "--plant-username", "twin",
                "--plant-security", security, "--plant-connect-timeout", "8",
                "--out", str(tmp_path / "o")]
        capsys.readouterr()
        assert main([*argv, "--plant-password", "wrong"]) == 2
        err = [line for line in capsys.readouterr().err.strip().splitlines()
               if not line.startswith("{") and "level=" not in line]
        assert len(err) == 1 and err[0].startswith("kautztwin: error: ") and (
            "refused the session" in err[0] and "BadUserAccessDenied" in err[0]), err
    with pytest.raises(DataError, match="both certificate and private_key"):
        PlantServer(FirstOrderPlant(), certificate=server_cert)
    with pytest.raises(DataError, match="unknown policy 'Basic128'"):
        PlantServer(FirstOrderPlant(), certificate=server_cert, private_key=server_key,
                    security=("Basic128",))
    with pytest.raises(DataError, match="no such certificate"):
        PlantServer(FirstOrderPlant(), certificate=tmp_path / "nope.pem", private_key=server_key)


def test_plant_serve_cli_serves_for_its_duration_with_the_collector_frozen(capsys):
    import gc

    from _service_helpers import free_port
    from kautztwin.cli.main import main

    gc.unfreeze()
    try:
        endpoint = f"opc.tcp://127.0.0.1:{free_port()}"
        assert main(["plant", "serve", "--plant", "hydraulic", "--endpoint", endpoint,
                     "--speed", "5", "--duration", "1"]) == 0
        # what the server built stays out of full collections (they stalled its ticks)
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
    out = capsys.readouterr().out
    assert f"serving hydraulic on {endpoint}" in out and "stopped after" in out
