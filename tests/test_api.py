"""The HTTP API of ``twin serve`` (issue #12): every endpoint against a real in-process twin.

A hydraulic twin runs in a thread on a sped-up clock (the service's own loop);
the FastAPI app is driven with ``fastapi.testclient`` and, in the last tests,
served by a real uvicorn on a free loopback port.
"""

import json
import math
import socket
import threading
import time
import warnings

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from kautztwin.cli.main import main
from kautztwin.exceptions import DataError
from kautztwin.service import TwinService, load_service_config
from kautztwin.service.api import ApiServer
from kautztwin.service.client import ApiClientError, TwinClient
from kautztwin.service.config import parse_bind
from kautztwin.service.twin_view import RateLimiter
from kautztwin.twin import DigitalModel

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

TOKEN = "s3cret-token-for-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _config(out, **extra):
    values = {"plant.kind": "hydraulic", "plant.speed": "10", "model.duration": "3000",
              "model.quick": "true", "service.out": str(out), "service.report": "false",
              "logging.level": "error"}
    values.update(extra)
    return load_service_config(None, values)


def _wait(pred, timeout=30.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A running twin with the API attached (token set, no rate limit), and a client.

    The API is also served by uvicorn on a free loopback port (``svc.api.url``: the
    WebSocket tests); the ``TestClient`` drives the same app in process.
    """
    svc = TwinService(_config(tmp_path_factory.mktemp("api")))
    svc.build()
    svc.api = ApiServer(svc, bind="127.0.0.1:0", token=TOKEN, rate_limit=0)
    th = threading.Thread(target=svc.run, daemon=True)
    th.start()
    client = TestClient(svc.api.app)
    _wait(lambda: client.get("/state").json().get("phase") == "closed-loop", 60, "closed loop")
    yield svc, client
    svc.request_stop()
    th.join(30)
    assert not th.is_alive()
    assert svc.summary["reason"] == "stop requested"


def _api_events(client):
    return [e for e in client.get("/events").json()["events"] if e["kind"].startswith("api-")]


# ---------------------------------------------------------------------- reads
def test_health_and_state(live):
    _, c = live
    h = c.get("/health").json()
    assert h["status"] == "ok" and h["running"] and h["run_id"] == 1
    s1 = c.get("/state").json()
    for key in ("k", "t", "y", "u", "setpoint", "y_pred", "fit", "version", "link", "mpc_ms"):
        assert key in s1
    assert s1["link"] == "in-process" and s1["controlled"] and s1["version"] >= 1
    assert s1["setpoint_limits"][0] < s1["setpoint_limits"][1]
    _wait(lambda: c.get("/state").json()["k"] > s1["k"], 10, "new samples")


def test_models_and_one_model(live):
    _, c = live
    models = c.get("/models").json()
    assert models and models[0]["version"] == 1 and models[0]["method"] == "OE"
    assert sum(m["active"] for m in models) == 1
    m = c.get("/models/1").json()
    assert len(m["poles"]) == m["n_functions"] == len(m["coefficients"])
    assert m["transfer_function"]["variable"] == "z" and m["transfer_function"]["den"][0] == 1
    assert m["fit_percent"] > 50 and m["k"] > 0 and math.isfinite(m["dc_gain"])
    r = c.get("/models/1?format=file")
    assert r.status_code == 200 and "attachment" in r.headers["content-disposition"]
    dm = DigitalModel.from_dict(r.json())
    assert dm.version == 1 and dm.model.n_functions == m["n_functions"]


@pytest.mark.parametrize("path, status, field", [
    ("/models/999", 404, "version"),
    ("/models/abc", 422, "version"),
    ("/models/1?format=xml", 422, "format"),
    ("/history?start=5&end=1", 422, "end"),
    ("/history?signals=y,bogus", 422, "signals"),
    ("/history?signals=y,predictions", 422, "signals"),
    ("/history?signals=,", 422, "signals"),
    ("/history?start=nan", 422, "start"),
    ("/history?end=inf", 422, "end"),
    ("/history?start=abc", 422, "start"),
    ("/history?after=-2", 422, "after"),
    ("/history?limit=0", 422, "limit"),
    ("/history?limit=x", 422, "limit"),
    ("/history?format=xml", 422, "format"),
    ("/events?after=-3", 422, "after"),
    ("/events?limit=0", 422, "limit"),
    ("/recent?since=-1", 422, "since"),
    ("/recent?limit=abc", 422, "limit"),
    ("/stream?period=0", 422, "period"),
    ("/stream?max_messages=0", 422, "max_messages"),
])
def test_bad_queries_are_4xx_naming_the_field(live, path, status, field):
    _, c = live
    r = c.get(path, headers=AUTH)
    assert r.status_code == status, r.text
    assert field in r.json()["message"]
    assert c.get("/health").json()["running"]


def test_history_json_csv_and_paging(live):
    _, c = live
    first = c.get("/history?limit=100").json()
    assert first["n"] == 100 and first["next"] == 99
    assert first["signals"]["k"] == list(range(100))
    second = c.get(f"/history?limit=100&after={first['next']}&signals=k,y").json()
    assert second["signals"]["k"][0] == 100 and set(second["signals"]) == {"k", "y"}
    window = c.get("/history?start=1&end=2&signals=t").json()["signals"]["t"]
    assert window and min(window) >= 1 and max(window) <= 2
    r = c.get("/history?limit=5&format=csv&signals=k,t,u,y")
    lines = r.text.strip().splitlines()
    assert r.headers["content-type"].startswith("text/csv") and r.headers["x-next"] == "4"
    assert lines[0] == "k,t,u,y" and len(lines) == 6 and lines[1].startswith("0,0.0,")


def _floats(values):
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def test_history_serves_the_twins_predictions_and_setpoints(live):
    """#12: ``prediction`` and ``setpoint`` of /history are what the loop used at each sample.

    The oracle is the loop's own per-sample arrays (its ``y_pred`` and ``setpoint``), not the
    store the API reads: the stored prediction of sample k (made at k - 1) and the set-point
    rebuilt from the run's configuration and its ``api-setpoint`` events must equal them.
    """
    svc, c = live
    arrays = svc.twin._record.arrays
    n_ident = svc.twin.config.n_ident  # the closed loop's first sample
    _wait(lambda: c.get("/state").json()["k"] > n_ident + 150, 30, "closed-loop samples")
    r = c.post("/setpoint", json={"value": 98.5}, headers=AUTH)
    assert r.status_code == 200, r.text
    k_from = r.json()["k_from"]
    try:
        _wait(lambda: c.get("/state").json()["committed"] > k_from + 300, 30, "commits")
        after = k_from - 101
        page = c.get(f"/history?signals=k,y,prediction,setpoint&after={after}&limit=200").json()
        cols = page["signals"]
        k = np.array(cols["k"])
        assert page["n"] == 200 and k[0] == k_from - 100 and page["next"] == k[-1]
        pred, sp = _floats(cols["prediction"]), _floats(cols["setpoint"])
        np.testing.assert_array_equal(pred, arrays["y_pred"][k])  # exact: the stored floats
        np.testing.assert_array_equal(sp, arrays["setpoint"][k])
        assert np.all(sp[k >= k_from] == 98.5) and not np.any(sp[k < k_from] == 98.5)
        assert np.isfinite(pred).all()
        # the identification phase: no set-point in force, no prediction made (the twin's
        # first model comes at its end; the loop's arrays hold values filled in afterwards)
        first = c.get(f"/history?signals=k,prediction,setpoint&limit={n_ident}").json()
        assert first["signals"]["setpoint"] == [None] * n_ident
        assert first["signals"]["prediction"] == [None] * n_ident
        # CSV: the same numbers
        text = c.get(f"/history?signals=k,prediction,setpoint&after={after}&limit=200"
                     "&format=csv").text.strip().splitlines()
        assert text[0] == "k,prediction,setpoint" and len(text) == 201
        rows = np.array([[float(v) if v else np.nan for v in line.split(",")]
                         for line in text[1:]])
        np.testing.assert_array_equal(rows[:, 0], k)
        np.testing.assert_array_equal(rows[:, 1], pred)
        np.testing.assert_array_equal(rows[:, 2], sp)
        # the Python client: float arrays, NaN where missing
        with TwinClient(svc.api.url) as tc:
            h = tc.history(signals="k,prediction,setpoint", end=float(arrays["t"][k[-1]]),
                           page=4000)
        assert h["prediction"].dtype == float and h["k"].dtype == np.int64
        np.testing.assert_array_equal(h["k"], np.arange(k[-1] + 1))
        closed = slice(n_ident, k[-1] + 1)
        np.testing.assert_array_equal(h["prediction"][closed], arrays["y_pred"][closed])
        np.testing.assert_array_equal(h["setpoint"], arrays["setpoint"][: k[-1] + 1])
        assert np.isnan(h["prediction"][:n_ident]).all()
    finally:
        c.post("/setpoint", json={"value": 100.0}, headers=AUTH)


def test_health_reports_the_loops_pace(live):
    _, c = live
    loop = c.get("/health").json()["loop"]
    assert loop["samples"] > 10 and loop["period_ms"] == pytest.approx(2.0)  # dt 0.02 s, x10
    assert 0 < loop["interval_ms_p50"] <= loop["interval_ms_p99"] <= loop["interval_ms_max"]
    assert loop["late"] >= 0 and loop["behind_ms_max"] >= 0


def test_events(live):
    _, c = live
    evs = c.get("/events").json()["events"]
    kinds = {e["kind"] for e in evs}
    assert {"phase", "model-version"} <= kinds
    only = c.get("/events?kind=model-version").json()["events"]
    assert only and all(e["kind"] == "model-version" for e in only)
    page = c.get("/events?limit=1").json()
    assert len(page["events"]) == 1 and page["next"] == page["events"][0]["id"]


# ---------------------------------------------------------------------- what-if
def test_whatif_input_sequence_and_setpoint_step(live):
    _, c = live
    r = c.post("/whatif", json={"u": [0.5] * 40}, headers=AUTH)
    assert r.status_code == 200, r.text
    w = r.json()
    assert w["mode"] == "input" and len(w["y"]) == len(w["t"]) == 40
    assert all(lo <= y <= hi for lo, y, hi in zip(w["lower"], w["y"], w["upper"], strict=True))
    assert w["t"][1] - w["t"][0] == pytest.approx(0.02)
    lo, hi = c.get("/state").json()["setpoint_limits"]
    target = 100.0
    w = c.post("/whatif", json={"setpoint": target, "steps": 1500}, headers=AUTH).json()
    assert w["mode"] == "setpoint" and len(w["y"]) == 1500 and w["u_steady"] is not None
    assert abs(w["y"][-1] - target) < 1.0  # the model settles on the set-point


@pytest.mark.parametrize("body, field", [
    ({}, "u"),
    ({"u": [0.5], "setpoint": 100}, "u"),
    ({"u": []}, "u"),
    ({"u": "abc"}, "u"),
    ({"u": [0.5, "x"]}, "u"),
    ({"setpoint": "high"}, "setpoint"),
    ({"setpoint": 100, "steps": 0}, "steps"),
    ({"setpoint": 100, "steps": 10**6}, "steps"),
    ({"setpoint": 100, "colour": 1}, "colour"),
])
def test_whatif_bad_bodies(live, body, field):
    _, c = live
    r = c.post("/whatif", json=body, headers=AUTH)
    assert r.status_code == 422 and field in r.json()["message"], r.text


def test_whatif_rejects_non_finite_inputs(live):
    _, c = live
    for text in ('{"u": [NaN]}', '{"u": [Infinity]}', '{"u": -Infinity}',
                 '{"value": Infinity}'):
        path = "/setpoint" if "value" in text else "/whatif"
        r = c.post(path, content=text, headers={**AUTH, "Content-Type": "application/json"})
        assert r.status_code == 422, (text, r.text)


# ---------------------------------------------------------------------- writes
def test_setpoint_reaches_the_loop_and_is_logged(live):
    svc, c = live
    lo, hi = c.get("/state").json()["setpoint_limits"]
    value = 101.5
    r = c.post("/setpoint", json={"value": value}, headers=AUTH)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["setpoint"] == value and "token" in out["who"] and out["when"]
    _wait(lambda: c.get("/state").json()["setpoint"] == value, 10, "the new set-point")
    ev = [e for e in _api_events(c) if e["kind"] == "api-setpoint"][-1]
    assert ev["payload"]["value"] == value and ev["payload"]["who"] == out["who"]
    assert ev["k"] == out["k_from"]
    # the MPC tracks it
    _wait(lambda: abs(c.get("/state").json()["y"] - value) < 1.0, 30, "tracking")


@pytest.mark.parametrize("body, field", [
    ({}, "value"),
    ({"value": "high"}, "value"),
    ({"value": None}, "value"),
    ({"value": 1e9}, "value"),
    ({"value": -1e9}, "value"),
    ({"value": 100, "extra": 1}, "extra"),
])
def test_bad_setpoints_change_nothing(live, body, field):
    _, c = live
    before = c.get("/state").json()["setpoint"]
    n_events = len(_api_events(c))
    r = c.post("/setpoint", json=body, headers=AUTH)
    assert r.status_code == 422 and field in r.json()["message"], r.text
    time.sleep(0.1)
    assert c.get("/state").json()["setpoint"] == before
    assert len(_api_events(c)) == n_events


def test_reidentify_schedules_an_attempt(live):
    svc, c = live
    attempts = svc.twin.updater.counts["attempts"]
    r = c.post("/reidentify", json={"reason": "test"}, headers=AUTH)
    if r.status_code == 409:  # a drift-triggered attempt runs: wait and ask again
        _wait(lambda: not svc.twin.updater.pending, 30, "the attempt in flight")
        r = c.post("/reidentify", json={"reason": "test"}, headers=AUTH)
    assert r.status_code == 200, r.text
    assert r.json()["scheduled"]
    _wait(lambda: svc.twin.updater.counts["attempts"] > attempts, 30, "the attempt")
    ev = [e for e in _api_events(c) if e["kind"] == "api-reidentify"][-1]
    assert ev["payload"]["reason"] == "test"
    assert c.post("/reidentify", json={"reason": 3}, headers=AUTH).status_code == 422


# ---------------------------------------------------------------------- security
WRITES = [("post", "/setpoint", {"value": 99.0}), ("post", "/reidentify", {}),
          ("post", "/whatif", {"u": [0.5]}), ("get", "/stream?max_messages=1", None)]


@pytest.mark.parametrize("method, path, body", WRITES)
@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong-token"},
                                     {"Authorization": TOKEN}, {"Authorization": "Basic x"}])
def test_writes_need_the_token(live, method, path, body, headers):
    svc, c = live
    before = c.get("/state").json()["setpoint"]
    n_events = len(_api_events(c))
    attempts = svc.twin.updater.counts["attempts"]
    kwargs = {"headers": headers} if body is None else {"headers": headers, "json": body}
    r = getattr(c, method)(path, **kwargs)
    assert r.status_code == 401 and "token" in r.json()["message"]
    time.sleep(0.05)
    assert c.get("/state").json()["setpoint"] == before
    assert len(_api_events(c)) == n_events
    if path == "/reidentify":
        assert not svc.twin.updater.pending or svc.twin.updater.counts["attempts"] == attempts


def test_every_endpoint_over_the_loopback_port(live):
    """The happy path of every endpoint through the real server (uvicorn on 127.0.0.1:0)."""
    svc, _ = live
    with httpx.Client(base_url=svc.api.url, timeout=20) as h:
        for path in ("/health", "/state", "/models", "/models/1", "/events", "/recent?limit=5",
                     "/history?signals=k,t,u,y,flags,prediction,setpoint&limit=5",
                     "/openapi.json"):
            r = h.get(path)
            assert r.status_code == 200 and r.headers["content-type"].startswith(
                "application/json"), (path, r.text)
        assert h.get("/history?format=csv&limit=3").text.startswith("k,t,u,y,flags\n")
        assert h.get("/models/1?format=file").json()["version"] == 1
        for path in ("/", "/docs", "/static/dashboard.js", "/static/dashboard.css",
                     "/static/LICENSE.txt"):
            assert h.get(path).status_code == 200, path
        with h.stream("GET", "/stream?max_messages=1&period=0.05", headers=AUTH) as r:
            assert r.status_code == 200
            assert any(line.startswith("data: ") for line in r.iter_lines())
        r = h.post("/whatif", json={"setpoint": 100.0, "steps": 50}, headers=AUTH)
        assert r.status_code == 200 and len(r.json()["y"]) == 50
        r = h.post("/setpoint", json={"value": 100.0}, headers=AUTH)
        assert r.status_code == 200 and r.json()["setpoint"] == 100.0
        r = h.post("/reidentify", json={"reason": "over the port"}, headers=AUTH)
        if r.status_code == 409:  # one is running already: wait for it, then ask again
            _wait(lambda: not svc.twin.updater.pending, 30, "the attempt in flight")
            r = h.post("/reidentify", json={"reason": "over the port"}, headers=AUTH)
        assert r.status_code == 200 and r.json()["scheduled"], r.text


def test_reads_need_no_token(live):
    _, c = live
    for path in ("/health", "/state", "/models", "/history?limit=1", "/events", "/", "/recent"):
        assert c.get(path).status_code == 200, path


def test_rate_limit(live):
    svc, c = live
    lim = svc.api.limiter
    lim.per_minute = 2
    lim.reset()
    try:
        codes = [c.post("/whatif", json={"u": [0.5]}, headers=AUTH).status_code
                 for _ in range(3)]
        assert codes == [200, 200, 429]
        assert "2 writes a minute" in c.post("/setpoint", json={"value": 100.0},
                                             headers=AUTH).json()["message"]
    finally:
        lim.per_minute = 0
        lim.reset()


def test_rate_limiter_window():
    lim = RateLimiter(3)
    assert [lim.allow("a", now=t) for t in (0, 1, 2, 3)] == [True, True, True, False]
    assert lim.allow("a", now=60.5) and lim.allow("b", now=3)
    assert RateLimiter(0).allow("x")


# ---------------------------------------------------------------------- live stream
def test_stream_sends_samples(live):
    _, c = live
    with c.stream("GET", "/stream?max_messages=3&period=0.05", headers=AUTH) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        lines = list(r.iter_lines())
    data = [json.loads(line[6:]) for line in lines if line.startswith("data: ")]
    batches = [d for d in data if isinstance(d, list)]
    assert batches and {"k", "y", "y_pred", "u", "setpoint", "seq"} <= set(batches[0][0])


# ---------------------------------------------------------------------- WebSocket stream
def _ws(svc, query="", headers=None):
    from websockets.sync.client import connect

    url = svc.api.url.replace("http://", "ws://") + "/stream/ws" + query
    return connect(url, additional_headers=headers or {}, open_timeout=10, close_timeout=5)


def _ws_messages(ws, n_max=200, timeout=10.0):
    """Messages until the server closes (at most ``n_max``); and the close frame."""
    from websockets.exceptions import ConnectionClosed

    out = []
    try:
        while len(out) < n_max:
            out.append(json.loads(ws.recv(timeout=timeout)))
    except ConnectionClosed as exc:
        return out, exc.rcvd
    raise AssertionError(f"the server did not close after {n_max} messages")


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong-token"},
                                     {"Authorization": TOKEN}, {"Authorization": "Basic x"}],
                         ids=["missing", "wrong", "no-scheme", "basic"])
def test_ws_stream_needs_the_token(live, headers):
    """Without the token the WebSocket closes with 1008 (policy violation), nothing sent."""
    svc, _ = live
    with _ws(svc, "?period=0.02", headers) as ws:
        messages, close = _ws_messages(ws)
    assert messages == []
    assert close.code == 1008 and "token" in close.reason


def test_ws_stream_sends_samples_then_closes(live):
    svc, _ = live
    with _ws(svc, "?max_messages=3&period=0.05", AUTH) as ws:
        messages, close = _ws_messages(ws)
    assert close.code == 1000 and len(messages) == 3
    batches = [m["samples"] for m in messages if m["type"] == "samples"]
    assert batches and {"k", "y", "y_pred", "u", "setpoint", "version", "seq"} <= set(batches[0][0])
    ks = [s["k"] for b in batches for s in b]
    assert ks == list(range(ks[0], ks[0] + len(ks)))  # consecutive samples, none twice
    with _ws(svc, f"?since={batches[-1][-1]['seq']}&max_messages=1", AUTH) as ws:
        (later,), _ = _ws_messages(ws)
    assert later["samples"][0]["k"] == ks[-1] + 1  # resumes after the last seq seen


def test_ws_stream_carries_api_events(live):
    svc, c = live
    with _ws(svc, "?period=0.05", AUTH) as ws:
        assert c.post("/setpoint", json={"value": 100.0}, headers=AUTH).status_code == 200
        end = time.monotonic() + 10
        seen = None
        while seen is None and time.monotonic() < end:
            m = json.loads(ws.recv(timeout=10))
            if m["type"] == "event" and m["event"]["kind"] == "api-setpoint":
                seen = m["event"]
    assert seen is not None and seen["source"] == "api" and "100" in seen["message"]


@pytest.mark.parametrize("query, field", [("?period=0", "period"), ("?period=x", "period"),
                                          ("?since=-1", "since"), ("?max_messages=0",
                                                                   "max_messages")])
def test_ws_stream_bad_query_closes_naming_the_field(live, query, field):
    svc, _ = live
    with _ws(svc, query, AUTH) as ws:
        messages, close = _ws_messages(ws)
    assert messages == [] and close.code == 4422 and field in close.reason


def test_dashboard_is_served(live):
    _, c = live
    page = c.get("/").text
    assert "<canvas" in page and "/static/dashboard.js" in page and "://" not in page
    js = c.get("/static/dashboard.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"]
    assert "fetch(" in js.text and "https://" not in js.text
    assert c.get("/static/LICENSE.txt").status_code == 200
    assert c.get("/static/secrets.txt").status_code == 404
    recent = c.get("/recent?since=0&limit=10").json()
    assert len(recent["samples"]) == 10 and recent["seq"] >= recent["samples"][-1]["seq"]


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=st.dictionaries(st.sampled_from(["u", "setpoint", "steps", "value", "reason", "x"]),
                            st.one_of(st.none(), st.booleans(), st.integers(-10**9, 10**9),
                                      # JSON has no inf (httpx refuses to send it): the
                                      # non-finite tokens are posted raw in the test above
                                      st.floats(allow_nan=False, allow_infinity=False),
                                      st.text(max_size=5),
                                      st.lists(st.floats(-2, 2), max_size=5)),
                            max_size=3),
       path=st.sampled_from(["/whatif", "/setpoint", "/reidentify"]))
def test_fuzz_post_bodies(live, body, path):
    svc, c = live
    r = c.post(path, json=body, headers=AUTH)
    assert r.status_code in (200, 409, 422), (path, body, r.text)
    if r.status_code == 422:
        assert r.json()["message"]
    if path == "/setpoint" and r.status_code == 200:  # keep the plant where the tests expect
        c.post("/setpoint", json={"value": 100.0}, headers=AUTH)


# ---------------------------------------------------------------------- configuration
def test_parse_bind():
    assert parse_bind("8000") == ("127.0.0.1", 8000)
    assert parse_bind("0.0.0.0:80") == ("0.0.0.0", 80)
    for bad in ("host:port", "1.2.3.4:70000", ":", "a b:1"):
        with pytest.raises(DataError, match="http.bind"):
            parse_bind(bad)


def test_non_loopback_bind_needs_a_token(tmp_path, monkeypatch):
    monkeypatch.delenv("KAUTZTWIN_HTTP_TOKEN", raising=False)
    with pytest.raises(DataError, match="not a loopback address"):
        _config(tmp_path, **{"http.bind": "0.0.0.0:8000"})
    assert _config(tmp_path, **{"http.bind": "0.0.0.0:8000", "http.token": TOKEN})
    assert _config(tmp_path, **{"http.bind": "localhost:8000"})
    monkeypatch.setenv("KAUTZTWIN_HTTP_TOKEN", TOKEN)
    cfg = _config(tmp_path, **{"http.bind": "0.0.0.0:8000"})
    assert cfg.values["http"]["token"] == TOKEN and cfg.to_dict()["http"]["token"] == "***"
    with pytest.raises(DataError, match="at least 8"):
        _config(tmp_path, **{"http.token": "short"})


def test_cli_refuses_a_public_bind_without_token(capsys, tmp_path, monkeypatch):
    monkeypatch.delenv("KAUTZTWIN_HTTP_TOKEN", raising=False)
    assert main(["twin", "serve", "--plant", "hydraulic", "--http", "0.0.0.0:8000",
                 "--out", str(tmp_path)]) == 2
    assert not list(tmp_path.iterdir())  # refused before anything ran: no store, no report
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if "level=" not in line]
    assert len(err) == 1 and err[0].startswith("kautztwin: error: http.bind"), err


# ---------------------------------------------------------------------- a real server
def test_real_uvicorn_on_a_free_loopback_port(tmp_path):
    cfg = _config(tmp_path, **{"http.bind": "127.0.0.1:0", "http.token": TOKEN,
                               "http.rate_limit": "100"})
    svc = TwinService(cfg)
    th = threading.Thread(target=svc.run, daemon=True)
    th.start()
    try:
        _wait(lambda: svc.api is not None and svc.api.url, 30, "the server")
        url = svc.api.url
        assert url.startswith("http://127.0.0.1:")
        with httpx.Client(base_url=url, timeout=10) as c:
            assert c.get("/health").json()["status"] == "ok"
            # the listening socket names TCP, so that asyncio turns Nagle off on each
            # connection (#12 load benchmark: without it every answer waited ~40 ms for the
            # client's delayed ACK)
            (listening,) = svc.api._server.servers[0].sockets
            assert listening.proto == socket.IPPROTO_TCP
            _wait(lambda: c.get("/state").json().get("phase") == "closed-loop", 60, "closed loop")
            assert c.post("/setpoint", json={"value": 99.0}).status_code == 401
            r = c.post("/setpoint", json={"value": 99.0}, headers=AUTH)
            assert r.status_code == 200, r.text
            _wait(lambda: c.get("/state").json()["setpoint"] == 99.0, 10, "set-point")
            assert "openapi" in c.get("/openapi.json").json()
            assert c.get("/docs").status_code == 200
            # the Python client
            with TwinClient(url, token=TOKEN) as tc:
                assert tc.health()["status"] == "ok" and tc.state()["version"] >= 1
                h = tc.history(signals="k,t,y", end=2.0, page=30)
                assert h["k"].dtype == np.int64 and list(h["k"]) == list(range(h["k"].size))
                assert h["k"].size in (100, 101) and np.isfinite(h["y"]).all()  # 4 pages
                assert tc.model(1).version == 1 and tc.models()[0]["version"] == 1
                w = tc.what_if([0.5] * 20)
                assert w["y"].shape == (20,) and isinstance(w["y"], np.ndarray)
                assert tc.set_setpoint(100.0)["setpoint"] == 100.0
                assert any(e["kind"] == "api-setpoint" for e in tc.events("api-setpoint"))
                with pytest.raises(ApiClientError, match="422.*value"):
                    tc.set_setpoint(1e9)
            with TwinClient(url) as anonymous, pytest.raises(ApiClientError, match="401"):
                anonymous.set_setpoint(100.0)
            # a second server on the same port is refused with a one-line error
            busy = ApiServer(svc, bind=url.rsplit("/", 1)[1])
            with pytest.raises(DataError, match="cannot listen"):
                busy.start()
    finally:
        svc.request_stop()
        th.join(30)
    assert not th.is_alive()
    with pytest.raises(httpx.TransportError):
        httpx.get(f"{url}/health", timeout=2)


def test_before_the_run_opens_reads_are_empty_and_writes_503(tmp_path):
    svc = TwinService(_config(tmp_path))
    svc.build()
    try:
        c = TestClient(ApiServer(svc).app)
        assert c.get("/health").json()["running"] is False
        assert c.get("/models").json() == [] and c.get("/events").json()["events"] == []
        assert c.get("/history").json()["n"] == 0
        assert c.get("/models/1").status_code == 404
        r = c.post("/setpoint", json={"value": 100.0})
        assert r.status_code == 503 and "not running" in r.json()["message"]
    finally:
        svc.twin.close()
