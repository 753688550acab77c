"""``kautztwin fleet serve`` (issue #15): one HTTP service for all assets of a fleet.

A real uvicorn server on a free loopback port, driven with httpx; every wait is
bounded.  Oracles: the fleet's own store (read directly) for ``/history``, the
single twin's ``/history`` shape, the configured set-point schedule, and a
resumed run that recomputes the stored samples (set-points written through the
API included) without a mismatch.
"""

from __future__ import annotations

import math
import threading
import time

import httpx
import numpy as np
import pytest

from _service_helpers import free_port
from kautztwin.exceptions import DataError
from kautztwin.service.fleet_api import FleetApiServer
from kautztwin.service.fleet_service import FleetService
from kautztwin.twin.fleet import FleetStore

TOKEN = "fleet-token-123"


def _wait(pred, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        out = pred()
        if out:
            return out
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet")
    svc = FleetService(3, out, speed=10.0, duration=60.0, http=f"127.0.0.1:{free_port()}",
                       seed=4, drift_spread=0.0)
    svc.build()
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(svc.run()), daemon=True)
    thread.start()
    _wait(lambda: svc.api.url is not None and svc.api.view.running, 60, "the loop")
    client = httpx.Client(base_url=svc.api.url, timeout=10.0)
    k_cl = svc.fleet.k_closed_loop
    # the identification ends (3 initial identifications, then the closed loop)
    _wait(lambda: (client.get("/health").json()["k"] or 0) > k_cl + 30, 120, "the closed loop")
    yield svc, client, result, thread
    client.close()
    svc.request_stop()
    thread.join(60)


def test_assets_lists_every_id_with_a_summary(served) -> None:
    svc, client, _, _ = served
    body = client.get("/assets").json()
    assert body["n_assets"] == 3 and body["next"] is None
    assert [a["id"] for a in body["assets"]] == [0, 1, 2]
    assert body["summary"]["phase"] == "closed-loop"
    assert body["summary"]["in_sync"] + body["summary"]["out_of_sync"] == 3
    page = client.get("/assets", params={"limit": 2}).json()
    assert [a["id"] for a in page["assets"]] == [0, 1] and page["next"] == 1
    rest = client.get("/assets", params={"after": 1}).json()
    assert [a["id"] for a in rest["assets"]] == [2]


def test_unknown_asset_is_a_one_line_404_and_bad_input_a_422(served) -> None:
    _, client, _, _ = served
    for path in ("/assets/3/state", "/assets/-1/history", "/assets/99/setpoint"):
        r = (client.post(path, json={"value": 100.0}) if path.endswith("setpoint")
             else client.get(path))
        assert r.status_code == 404, (path, r.text)
        assert "no asset" in r.json()["message"] and "\n" not in r.json()["message"]
    for r in (client.get("/assets/x/state"),
              client.get("/assets/0/history", params={"signals": "y,bogus"}),
              client.get("/assets/0/history", params={"start": 5, "end": 1}),
              client.get("/assets", params={"limit": 0}),
              client.post("/assets/0/setpoint", json={"value": "high"}),
              client.post("/assets/0/setpoint", json={"value": 1.0, "extra": 1})):
        assert r.status_code == 422, r.text
        assert isinstance(r.json()["message"], str) and "\n" not in r.json()["message"]


def test_state_of_one_asset(served) -> None:
    svc, client, _, _ = served
    s = client.get("/assets/2/state").json()
    assert s["id"] == 2 and s["running"] and s["phase"] == "closed-loop"
    assert s["dt"] == svc.fleet.config.dt and s["version"] >= 1
    assert math.isfinite(s["y"]) and math.isfinite(s["u"]) and math.isfinite(s["setpoint"])
    assert s["setpoint"] == svc.fleet.config.setpoint(s["t"])  # no override: the schedule
    assert set(s["counts"]) >= {"reidentification_attempts", "mpc_failures", "violations"}


def test_history_is_the_stored_samples_in_the_single_twin_shape(served) -> None:
    svc, client, _, _ = served
    body = client.get("/assets/1/history", params={"signals": "k,t,u,y,flags,prediction",
                                                    "limit": 100}).json()
    assert set(body) == {"run_id", "n", "next", "signals"}  # as the twin's GET /history
    assert body["n"] == 100 and body["next"] == 99
    with _Store(svc) as store:
        rows = store.samples(body["run_id"], asset=1)
    sig = body["signals"]
    np.testing.assert_array_equal(sig["k"], np.arange(100))
    np.testing.assert_array_equal(sig["u"], rows["u"][:100])
    np.testing.assert_array_equal(sig["y"], rows["y"][:100])
    np.testing.assert_array_equal(sig["flags"], rows["flags"][:100])
    pred = np.array([np.nan if v is None else v for v in sig["prediction"]])
    np.testing.assert_array_equal(pred, rows["y_pred"][:100])
    nxt = client.get("/assets/1/history", params={"after": 99, "limit": 5}).json()
    assert nxt["signals"]["k"] == [100, 101, 102, 103, 104]
    csv = client.get("/assets/1/history", params={"format": "csv", "limit": 3,
                                                  "signals": "k,y"})
    lines = csv.text.strip().splitlines()
    assert lines[0] == "k,y" and len(lines) == 4 and csv.headers["X-Next"] == "2"
    assert float(lines[1].split(",")[1]) == rows["y"][0]


class _Store:
    def __init__(self, svc) -> None:
        self.store = FleetStore(str(svc.history_path))

    def __enter__(self):
        return self.store

    def __exit__(self, *exc) -> None:
        self.store._con.close()


def test_setpoint_of_one_asset_and_its_history(served) -> None:
    svc, client, _, _ = served
    mpc = svc.fleet.config.mpc
    value = 0.5 * (mpc.y_min + mpc.y_max) + 7.0
    r = client.post("/assets/1/setpoint", json={"value": value})
    assert r.status_code == 200, r.text
    k_from = r.json()["k_from"]
    _wait(lambda: client.get("/assets/1/state").json()["k"] >= k_from + 60, 60, "samples")
    assert client.get("/assets/1/state").json()["setpoint"] == value
    assert client.get("/assets/0/state").json()["setpoint"] != value
    # the history: the schedule before, the value from k_from on (this asset only)
    _wait(lambda: client.get("/assets/1/history", params={"after": k_from + 40}).json()["n"],
          60, "the commit")
    for asset, expect in ((1, value), (0, None)):
        h = client.get("/assets/1/history" if asset else "/assets/0/history",
                       params={"signals": "k,t,setpoint", "after": k_from - 3,
                               "limit": 40}).json()["signals"]
        sched = [svc.fleet.config.setpoint(t) for t in h["t"]]
        got = h["setpoint"]
        if expect is None:
            assert got == sched
        else:
            assert got[:2] == sched[:2] and all(v == value for v in got[2:])
    bad = client.post("/assets/1/setpoint", json={"value": mpc.y_max + 1.0})
    assert bad.status_code == 422 and "outside the limits" in bad.json()["message"]


def test_fleet_metrics(served) -> None:
    svc, client, _, _ = served
    m = client.get("/fleet/metrics").json()
    assert m["n_assets"] == 3 and m["phase"] == "closed-loop"
    for key in ("sync_fit_last", "sync_fit_mean", "sync_fit_min"):
        assert m[key]["n"] == 3 and m[key]["min"] <= m[key]["median"] <= m[key]["max"]
    assert set(m["reidentification"]) == {"attempts", "accepted", "assets_with_new_model"}
    assert set(m["violations"]) == {"output_samples", "input_samples", "rate_samples",
                                    "assets_with_any"}
    assert m["in_sync"] + m["out_of_sync"] == 3


def test_token_rule_is_the_single_services(served, tmp_path) -> None:
    svc, _, _, _ = served
    with pytest.raises(DataError, match="not a loopback address"):
        FleetApiServer(svc, bind="0.0.0.0:8123")
    with pytest.raises(DataError, match="at least 8 characters"):
        FleetService(2, tmp_path, token="short")
    api = FleetApiServer(svc, bind=f"127.0.0.1:{free_port()}", token=TOKEN)
    api.start()
    try:
        with httpx.Client(base_url=api.url, timeout=10.0) as c:
            assert c.get("/assets").status_code == 200  # reads need no token
            assert c.post("/assets/0/setpoint", json={"value": 100.0}).status_code == 401
            wrong = c.post("/assets/0/setpoint", json={"value": 100.0},
                           headers={"Authorization": "Bearer nope-nope-nope"})
            assert wrong.status_code == 401 and "token" in wrong.json()["message"]
            ok = c.post("/assets/0/setpoint", json={"value": 100.0},
                        headers={"Authorization": f"Bearer {TOKEN}"})
            assert ok.status_code == 503  # authorised; this second server's view has no loop
    finally:
        api.stop()


def test_stop_then_resume_replays_the_setpoints_without_a_mismatch(served) -> None:
    svc, client, result, thread = served
    svc.request_stop()
    thread.join(60)
    assert not thread.is_alive() and result["reason"] == "stop requested"
    with _Store(svc) as store:
        n_before = store.committed_steps(result["run_id"])
        assert store.setpoints(result["run_id"])  # the set-point written above
    again = FleetService(3, svc.out, speed=50.0, duration=60.0, seed=4, drift_spread=0.0)
    again.build()
    s = again.run()
    assert s["run_id"] == result["run_id"] and s["resumed_at"] == n_before > 0
    assert s["reason"] == "horizon reached" and s["n_samples"] == again.fleet.config.n_samples
    assert again.fleet.replay_mismatches == 0


def test_cli_fleet_serve_runs_to_the_horizon(tmp_path, capsys) -> None:
    import json

    from kautztwin.cli.main import main

    out = tmp_path / "svc"
    assert main(["fleet", "serve", "--assets", "2", "--duration", "5", "--speed", "100",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reason"] == "horizon reached" and summary["n_assets"] == 2
    assert summary["n_samples"] == 250 and "violations" in summary
    assert "fleet serve of 2: 250 samples, horizon reached" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "message"), [
    (["--assets", "0"], "--assets must be a positive"),
    (["--assets", "2", "--http", "0.0.0.0:8000"], "not a loopback address"),
    (["--assets", "2", "--speed", "-1"], "speed must be positive"),
    (["--assets", "2", "--duration", "0"], "duration must be a positive"),
], ids=["assets", "bind", "speed", "duration"])
def test_cli_fleet_serve_bad_input_is_one_line(tmp_path, capsys, argv, message) -> None:
    from kautztwin.cli.main import main

    assert main(["fleet", "serve", *argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_setpoint_during_a_resumed_runs_replay_waits_for_its_end(tmp_path) -> None:
    from dataclasses import replace

    from kautztwin.twin.fleet import Fleet
    from kautztwin.twin.fleet.simulate import hydraulic_fleet
    from kautztwin.twin.runtime import TwinConfig

    cfg = replace(TwinConfig.for_plant("hydraulic", duration=6.0, quick=True, static_twin=False,
                                       retune=False), commit_every=10)
    path = str(tmp_path / "fleet.sqlite")
    plant, _ = hydraulic_fleet(2, cfg, seed=3, drift_spread=0.0)
    with Fleet(plant, cfg, store=path, record=False) as first:
        first.run(until=cfg.n_ident + 40, progress=False)
    plant, _ = hydraulic_fleet(2, cfg, seed=3, drift_spread=0.0)
    with Fleet(plant, cfg, store=path) as again:
        again.start()
        assert again.resumed_at == cfg.n_ident + 40 and again.k == 0
        k_from = again.set_setpoint([1], 101.0)  # asked while the stored samples are recomputed
        assert k_from == again.resumed_at
        run = again.run(progress=False)
        assert again.replay_mismatches == 0
        assert again.store.setpoints(again.run_id) == [(k_from, 1, 101.0)]
    # the reference filter (first order, tau = reference_tau) moves asset 1 towards 101 from
    # k_from on and asset 0 along the configured schedule
    ref = run.arrays["reference"]
    alpha = 1.0 - math.exp(-cfg.dt / cfg.reference_tau)
    ks = np.arange(k_from, cfg.n_samples)
    sched = np.array([cfg.setpoint(k * cfg.dt) for k in ks])
    np.testing.assert_allclose(ref[1, ks], ref[1, ks - 1] + alpha * (101.0 - ref[1, ks - 1]),
                               rtol=1e-13)
    np.testing.assert_allclose(ref[0, ks], ref[0, ks - 1] + alpha * (sched - ref[0, ks - 1]),
                               rtol=1e-13)
    assert not np.all(sched == 101.0)
