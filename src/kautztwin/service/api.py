"""The twin's HTTP API and live dashboard (FastAPI): watch it, query it, steer it.

:func:`create_app` builds the FastAPI application around a
:class:`~kautztwin.service.twin_view.TwinView` of a running
:class:`~kautztwin.service.TwinService`; :class:`ApiServer` serves it with
uvicorn in a thread, started and stopped with the service
(``kautztwin twin serve --http 127.0.0.1:8000``).  The endpoints (reference and
curl examples in ``docs/api-http.md``; OpenAPI at ``/docs``):

* reads: ``GET /health`` (with the loop's pace), ``/state``, ``/models``,
  ``/models/{version}`` (``?format=file``: the model file), ``/history`` (JSON
  or CSV, paged: samples, the twin's predictions, set-points), ``/events``,
  ``/recent``, and ``/`` the dashboard;
* ``POST /whatif``: the current model's response to a planned input (or a
  set-point step) from the current state, with a band from its uncertainty;
* writes: ``POST /setpoint`` (within the output limits; from the next sample),
  ``POST /reidentify``;
* ``GET /stream``: server-sent events of samples and events; ``WS /stream/ws``
  the same as WebSocket messages.

Security: the server binds 127.0.0.1 unless told otherwise, and a bind off
the loopback interface needs a token (checked by the configuration).  With a
token, the writes, ``/whatif`` and both streams need ``Authorization: Bearer
TOKEN`` (401 otherwise, and nothing changes; the WebSocket closes with 1008
before sending anything); writes and what-ifs are rate-limited per client
(429), and every write is logged in the store as an ``api-*`` event with who
and when.

The sample loop shares the process (and its interpreter lock) with the
server: the cheap reads are coroutines (no hand-over to worker threads),
``/history`` pages come from read-only connections of their own
(:class:`~.history_reader.HistoryReader`, never the store's lock), answers are
serialised at once, and :meth:`ApiServer.start` freezes the objects that exist
before the loop starts, so that the full garbage collections the handlers'
garbage triggers stay short (they walked ~10^5 objects, 0.1-0.2 s holding the
lock, and made the loop late).  ``benchmarks/bench_api_load.py`` measures it.

The pieces both this API and the fleet's (:mod:`.fleet_api`) use live in
:mod:`.http_common`: the JSON and one-line error answers, the token and
write guards, the ``/history`` query check and page, the store reader slot,
the address rule and the uvicorn thread.  The public ones are re-exported
here (:class:`SetpointRequest`, :class:`HttpThread`, :class:`ReaderSlot`,
:func:`add_error_handlers`, :func:`bearer_guard`, :func:`who_wrote`,
:func:`write_guard`, :func:`history_query`, :func:`history_response`), so
that ``from kautztwin.service.api import ...`` keeps working; new code
imports them from :mod:`.http_common`.

Size: over 600 lines because every endpoint's request and response shape lives
here with its docstring (the OpenAPI page is generated from them), with the
jobs that the writes and what-ifs hand to the sample loop
(:func:`_apply_setpoint`, :func:`_request_reidentification`, :func:`_what_if`);
the state the endpoints read and the job queue are in :mod:`.twin_view`.
"""

import asyncio
import contextlib
import json
import logging
import math
import threading
import time
from datetime import UTC, datetime
from importlib import resources
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import Depends, FastAPI, Query, Request, WebSocket
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator
from starlette.websockets import WebSocketDisconnect

from .history_reader import HISTORY_SIGNALS, HistoryReader
from .http_common import (
    MAX_PAGE,
    HttpThread,
    ReaderSlot,
    SetpointRequest,
    add_error_handlers,
    bearer_guard,
    field_error,
    history_query,
    history_response,
    json_answer,
    server_address,
    who_wrote,
    write_guard,
)
from .process import freeze_garbage, thaw_garbage
from .twin_view import ApiError, RateLimiter, TwinView, _num

__all__ = ["ApiServer", "HttpThread", "ReidentifyRequest", "SetpointRequest", "WhatIfRequest",
           "ReaderSlot", "add_error_handlers", "bearer_guard", "create_app", "history_query",
           "history_response", "who_wrote", "write_guard"]

_logger = logging.getLogger("kautztwin.service")

#: most samples of one what-if
MAX_WHATIF = 5_000


# ---------------------------------------------------------------------- request bodies
class ReidentifyRequest(BaseModel):
    """Body of ``POST /reidentify`` (optional; no fields yet but a note for the event log).

    Parameters
    ----------
    reason : str, optional
        Why, for the event log (at most 200 characters).
    """

    model_config = ConfigDict(extra="forbid")
    reason: str = Field("", max_length=200)


class WhatIfRequest(BaseModel):
    """Body of ``POST /whatif``: exactly one of ``u`` and ``setpoint``.

    Parameters
    ----------
    u : list of float, optional
        Planned inputs of the next samples (1 to 5000, finite).
    setpoint : float, optional
        A set-point step: the input that brings the model's steady state to
        it (within the input limits), held for ``steps`` samples.
    steps : int, default=200
        Samples of a set-point step's prediction (1 to 5000).
    """

    model_config = ConfigDict(extra="forbid")
    u: list[float] | None = Field(None, min_length=1, max_length=MAX_WHATIF)
    setpoint: float | None = Field(None, allow_inf_nan=False)
    steps: int = Field(200, ge=1, le=MAX_WHATIF)

    @model_validator(mode="after")
    def _one_of(self) -> "WhatIfRequest":
        if (self.u is None) == (self.setpoint is None):
            raise ValueError("give exactly one of u (an input sequence) and setpoint")
        if self.u is not None and not all(math.isfinite(v) for v in self.u):
            raise ValueError("u must hold finite numbers")
        return self


# ---------------------------------------------------------------------- the loop's jobs
def _next_time(service: Any) -> tuple[int, float]:
    twin = service.twin
    dt = twin.config.dt
    t = twin.state.t
    return int(twin.k), (float(t) + dt if math.isfinite(t) else twin.k * dt)


def _apply_setpoint(value: float, who: dict[str, Any]) -> Any:
    """A job: hold ``value`` from the next sample on (replaces the rest of the schedule)."""

    def job(service: Any) -> dict[str, Any]:
        from dataclasses import replace

        twin = service.twin
        cfg = twin.config
        if not cfg.controlled:
            raise ApiError(409, "the twin does not control this plant (no set-point)")
        k, t_next = _next_time(service)
        t_from = t_next - 0.5 * cfg.dt
        schedule = tuple(p for p in cfg.setpoints if p[0] < t_from) + ((t_from, value),)
        twin.config = replace(cfg, setpoints=schedule)
        payload = {"value": value, **who, "k_from": k}
        twin.history.log_event(twin.run_id, "api-setpoint",
                               f"set-point {value:g} from sample {k} by {who['who']}",
                               k=k, t=t_next, payload=payload)
        return {"setpoint": value, "k_from": k, "t_from": t_next}

    return job


def _request_reidentification(who: dict[str, Any], reason: str) -> Any:
    def job(service: Any) -> dict[str, Any]:
        twin = service.twin
        upd = twin.updater
        if upd is None:
            raise ApiError(409, "the twin has no model yet (identification phase)")
        scheduled = upd.request_reidentification()
        k, t_next = _next_time(service)
        if not scheduled:
            raise ApiError(409, "a re-identification is already scheduled or running "
                                "(or re-identification is disabled)")
        twin.history.log_event(twin.run_id, "api-reidentify",
                               f"re-identification requested by {who['who']}"
                               + (f": {reason}" if reason else ""),
                               k=k, t=t_next, payload={**who, "reason": reason})
        return {"scheduled": True, "k": k, "version": int(twin.state.version)}

    return job


def _what_if(req: WhatIfRequest, sigma: float) -> Any:
    def job(service: Any) -> dict[str, Any]:
        twin = service.twin
        upd = twin.updater
        if upd is None:
            raise ApiError(409, "the twin has no model yet (identification phase)")
        est = upd.estimator_
        mode = "input"
        u_ss = None
        if req.setpoint is not None:
            u_ss = est.steady_input(req.setpoint)
            if not math.isfinite(u_ss):
                raise ApiError(409, "the current model has no static gain")
            lo, hi = twin.plant.input_limits if twin.config.mpc is None else (
                twin.config.mpc.u_min, twin.config.mpc.u_max)
            u_ss = float(np.clip(u_ss, lo, hi))
            u = np.full(req.steps, u_ss)
            mode = "setpoint"
        else:
            u = np.asarray(req.u, dtype=float)
        x0 = est.state_
        y = est.simulate(u, x0=x0)
        X = est.regressors(u, x0)
        P = est.covariance_
        lower = upper = None
        if math.isfinite(sigma) and P.shape[0] == X.shape[1]:
            spread = np.einsum("ij,jk,ik->i", X, P, X)
            half = 2.0 * sigma * np.sqrt(1.0 + np.maximum(spread, 0.0))
            lower, upper = (y - half).tolist(), (y + half).tolist()
        k, t_next = _next_time(service)
        dt = twin.config.dt
        return {"mode": mode, "k": k, "version": int(twin.state.version), "dt": dt,
                "t": (t_next + dt * np.arange(u.size)).tolist(), "u": u.tolist(),
                "y": [_num(v) for v in y], "lower": lower, "upper": upper,
                "sigma": _num(sigma), "u_steady": u_ss,
                "band": "y ± 2σ·sqrt(1 + xᵀPx): σ the RMS one-step error of the recent "
                        "samples, P the recursive estimator's covariance"}

    return job


# ---------------------------------------------------------------------- the application
def create_app(view: TwinView, *, token: str | None = None,
               limiter: RateLimiter | None = None) -> FastAPI:
    """The FastAPI application of a twin's view.

    Parameters
    ----------
    view : TwinView
        The running service's view.
    token : str, optional
        The API token the writes, ``/whatif`` and ``/stream`` need (bearer).
    limiter : RateLimiter, optional
        Limits writes and what-ifs per client (none when omitted).

    Returns
    -------
    fastapi.FastAPI
    """
    app = FastAPI(title="kautztwin twin", version="1",
                  description="The digital twin's HTTP API (docs/api-http.md).")
    app.state.view = view
    service = view.service

    add_error_handlers(app)
    _authorised = bearer_guard(token)

    def reader(request: Request) -> None:
        """Dependency of the stream: the token when one is set."""
        _authorised(request)

    # dependency of writes and what-ifs: the token, then the rate limit
    writer = write_guard(token, limiter)
    # the reader of the twin's store (closed with the server: then 503)
    reads = ReaderSlot(HistoryReader)
    _reader = reads.get
    app.state.close_reads = reads.close

    def _store() -> tuple[Any, int | None]:
        """The store and the run (``None`` before the run is opened: empty answers)."""
        twin = service.twin
        if twin is None or twin.run_id is None:
            return None, None
        return twin.history, int(twin.run_id)

    def _log_write(kind: str, who: dict[str, Any], **fields: Any) -> None:
        _logger.info(kind, extra={"event": kind, "fields": {"who": who["who"], **fields}})

    # ------------------------------------------------------------------ reads
    # cheap reads are coroutines: served on the event loop, no hand-over to a worker thread
    @app.get("/health", tags=["read"], response_model=None)
    async def health() -> Response:
        """Liveness: whether the sample loop runs, where it is, and whether it keeps its pace."""
        latest = view.latest()
        return json_answer({"status": "ok", "running": view.running, "k": latest.get("k"),
                            "uptime_s": time.time() - view.started,
                            "run_id": None if service.twin is None else service.twin.run_id,
                            "loop": view.loop_timing()})

    @app.get("/state", tags=["read"], response_model=None)
    async def state() -> Response:
        """The latest sample: measured y, input u, set-point, twin prediction, fit, version."""
        latest = view.latest()
        twin = service.twin
        kind = service.config.plant["kind"]
        link = "in-process"
        if kind not in ("hydraulic", "tclab", "replay"):
            down = any(getattr(o, "kind", "") == "link"
                       for o in getattr(service, "_open_outages", ()))
            link = "down" if down else "up"
        out: dict[str, Any] = {**latest, "running": view.running, "link": link,
                               "plant": kind}
        if twin is not None:
            cfg = twin.config
            lo, hi = _setpoint_limits(service)
            out.update(run_id=twin.run_id, dt=cfg.dt, n_samples=cfg.n_samples,
                       controlled=cfg.controlled,
                       setpoint_limits=[_num(lo), _num(hi)])
        return json_answer(out)

    @app.get("/models", tags=["read"])
    def models() -> list[dict[str, Any]]:
        """Every model version of the run with its provenance and validation fit."""
        history, run_id = _store()
        if history is None:
            return []
        active = history.active_model(run_id)
        info = _version_events(history, run_id)
        return [_model_summary(dm, info.get(dm.version), active) for dm in
                history.model_versions(run_id)]

    @app.get("/models/{version}", tags=["read"], response_model=None)
    def model(version: int,
              format: Literal["json", "file"] = "json") -> dict[str, Any] | Response:
        """One version: provenance, poles, coefficients, transfer function (or its file)."""
        history, run_id = _store()
        found = [] if history is None else [
            dm for dm in history.model_versions(run_id) if dm.version == version]
        if not found:
            raise ApiError(404, f"version: no model version {version}"
                                + (f" in run {run_id}" if run_id is not None else " yet"))
        dm = found[0]
        if format == "file":
            body = json.dumps(dm.to_dict(), indent=2) + "\n"
            return Response(body, media_type="application/json", headers={
                "Content-Disposition": f'attachment; filename="model-v{version}.json"'})
        out = _model_summary(dm, _version_events(history, run_id).get(version),
                             history.active_model(run_id))
        m = dm.model
        num, den = m.transfer_function()
        out.update(coefficients=m.coefficients.tolist(), dt=m.dt,
                   transfer_function={"num": num.tolist(), "den": den.tolist(),
                                      "variable": "z" if m.dt > 0 else "s"},
                   dc_gain=_num(m.dc_gain), file=f"/models/{version}?format=file")
        return out

    @app.get("/history", tags=["read"], response_model=None)
    async def history_(
        signals: str = Query("k,t,u,y,flags", description="comma-separated: "
                             + ",".join(HISTORY_SIGNALS)),
        start: float | None = Query(None, description="first time, plant s"),
        end: float | None = Query(None, description="last time, plant s"),
        limit: int = Query(1000, ge=1, le=MAX_PAGE),
        after: int = Query(-1, ge=-1, description="page cursor: samples with k > after"),
        format: Literal["json", "csv"] = "json",
    ) -> Response:
        """Stored samples, the twin's predictions and set-points, paged by ``after``."""
        names = history_query(signals, start, end)
        if isinstance(names, JSONResponse):
            return names
        history, run_id = _store()
        if history is None:
            cols: dict[str, Any] = {s: np.empty(0) for s in names}
            nxt = None
        else:
            cols, nxt = _reader(history).page(run_id, names, after=after, start=start,
                                              end=end, limit=limit)
        return history_response(run_id, names, cols, nxt, format)

    @app.get("/events", tags=["read"])
    def events(kind: str | None = None, after: int = Query(0, ge=0),
               limit: int = Query(500, ge=1, le=MAX_PAGE)) -> dict[str, Any]:
        """Logged events (model versions, re-identifications, outages, API writes)."""
        history, run_id = _store()
        evs = [] if history is None else [
            e for e in history.events(run_id, kind) if e.event_id > after]
        more = len(evs) > limit
        evs = evs[:limit]
        return {"run_id": run_id, "next": evs[-1].event_id if more else None,
                "events": [{"id": e.event_id, "k": e.k, "t": _num(e.t), "kind": e.kind,
                            "message": e.message, "payload": e.payload} for e in evs]}

    # ------------------------------------------------------------------ what-if and writes
    @app.post("/whatif", tags=["predict"])
    def whatif(req: WhatIfRequest,
               who: Annotated[dict[str, Any], Depends(writer)]) -> dict[str, Any]:
        """The current model's response to planned inputs (or a set-point step), from now."""
        return view.call(_what_if(req, view.residual_sigma()))

    @app.post("/setpoint", tags=["write"], response_model=None)
    def setpoint(req: SetpointRequest,
                 who: Annotated[dict[str, Any], Depends(writer)]) -> dict[str, Any] | JSONResponse:
        """Hold a new set-point from the next sample on (within the output limits)."""
        lo, hi = _setpoint_limits(service)
        if not lo <= req.value <= hi:
            return field_error("value", f"set-point {req.value:g} is outside the limits "
                                        f"[{lo:g}, {hi:g}]")
        out = view.call(_apply_setpoint(req.value, who))
        _log_write("api-setpoint", who, value=req.value, k_from=out["k_from"])
        view.add_event("api-setpoint", f"set-point {req.value:g} by {who['who']}",
                       k=out["k_from"], t=out["t_from"])
        return {**out, "who": who["who"], "when": who["when"]}

    @app.post("/reidentify", tags=["write"])
    def reidentify(who: Annotated[dict[str, Any], Depends(writer)],
                   req: ReidentifyRequest | None = None) -> dict[str, Any]:
        """Schedule a re-identification on the recent window (judged like a drift-triggered one)."""
        reason = "" if req is None else req.reason
        out = view.call(_request_reidentification(who, reason))
        _log_write("api-reidentify", who, k=out["k"])
        view.add_event("api-reidentify", f"re-identification requested by {who['who']}",
                       k=out["k"])
        return {**out, "who": who["who"], "when": who["when"]}

    # ------------------------------------------------------------------ live
    @app.get("/stream", tags=["live"])
    async def stream(request: Request, _: Annotated[None, Depends(reader)],
                     since: int = Query(0, ge=0),
                     max_messages: int | None = Query(None, ge=1),
                     period: float = Query(0.2, ge=0.02, le=5.0)) -> StreamingResponse:
        """Server-sent events: ``samples`` (batches) and ``event`` messages, every ``period`` s."""

        async def gen() -> Any:
            last = since
            last_ev = max((e["seq"] for e in view.events()), default=0)
            sent = 0
            yield ": kautztwin stream\n\n"
            while max_messages is None or sent < max_messages:
                if await request.is_disconnected():
                    return
                batch = view.samples(since=last, limit=2000)
                if batch:
                    last = batch[-1]["seq"]
                    yield f"event: samples\ndata: {json.dumps(batch)}\n\n"
                    sent += 1
                for ev in view.events(since=last_ev):
                    last_ev = ev["seq"]
                    yield f"event: event\ndata: {json.dumps(ev, default=str)}\n\n"
                    sent += 1
                await asyncio.sleep(period)

        return StreamingResponse(gen(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache"})

    @app.websocket("/stream/ws")
    async def stream_ws(websocket: WebSocket) -> None:
        """WebSocket twin of ``/stream``: JSON messages of samples and events.

        Query: ``since``, ``max_messages``, ``period`` as for ``/stream``.  Each text
        message is ``{"type": "samples", "samples": [...]}`` or ``{"type": "event",
        "event": {...}}``.  A missing or wrong token closes the connection with code 1008
        (policy violation) before anything is sent; a bad query parameter with code 4422
        and the field in the reason; the end of ``max_messages`` with 1000.
        """
        await websocket.accept()
        try:
            _authorised(websocket)
        except ApiError as exc:
            await websocket.close(code=1008, reason=exc.message)
            return
        try:
            since, max_messages, period = _stream_params(websocket.query_params)
        except ApiError as exc:
            await websocket.close(code=4422, reason=exc.message)
            return
        gone = asyncio.Event()

        async def watch() -> None:  # the client's messages are ignored; its close ends us
            try:
                while (await websocket.receive())["type"] != "websocket.disconnect":
                    pass
            finally:
                gone.set()

        watcher = asyncio.create_task(watch())
        last, sent = since, 0
        last_ev = max((e["seq"] for e in view.events()), default=0)
        try:
            while (max_messages is None or sent < max_messages) and not gone.is_set():
                batch = view.samples(since=last, limit=2000)
                messages = []
                if batch:
                    last = batch[-1]["seq"]
                    messages.append({"type": "samples", "samples": batch})
                for ev in view.events(since=last_ev):
                    last_ev = ev["seq"]
                    messages.append({"type": "event", "event": ev})
                for msg in messages[:None if max_messages is None else max_messages - sent]:
                    await websocket.send_text(json.dumps(msg, default=str))
                    sent += 1
                if max_messages is not None and sent >= max_messages:
                    break
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(gone.wait(), period)
            if not gone.is_set():
                watcher.cancel()
                await websocket.close(code=1000)
        except (WebSocketDisconnect, OSError, RuntimeError):
            pass  # the client went away mid-send
        finally:
            watcher.cancel()

    @app.get("/recent", tags=["live"], response_model=None)
    async def recent(since: int = Query(0, ge=0),
                     limit: int = Query(2000, ge=1, le=MAX_PAGE)) -> Response:
        """Samples of the live ring buffer after ``since`` (what the dashboard starts from)."""
        batch = view.samples(since=since, limit=limit)
        return json_answer({"samples": batch, "seq": view.seq, "capacity": view.capacity})

    # ------------------------------------------------------------------ dashboard
    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def dashboard() -> HTMLResponse:
        return HTMLResponse(_static("dashboard.html"))

    @app.get("/static/{name}", include_in_schema=False)
    def static(name: str) -> Response:
        if name not in ("dashboard.js", "dashboard.css", "LICENSE.txt"):
            raise ApiError(404, f"no static file {name!r}")
        media = {"js": "text/javascript", "css": "text/css", "txt": "text/plain"}
        return Response(_static(name), media_type=media[name.rsplit(".", 1)[1]])

    return app


def _stream_params(query: Any) -> tuple[int, int | None, float]:
    """``since``, ``max_messages``, ``period`` of a stream's query (as ``/stream`` checks them)."""
    out: list[Any] = []
    for name, kind, lo, hi, default in (("since", int, 0, None, 0),
                                        ("max_messages", int, 1, None, None),
                                        ("period", float, 0.02, 5.0, 0.2)):
        raw = query.get(name)
        if raw is None:
            out.append(default)
            continue
        try:
            value = kind(raw)
        except ValueError:
            raise ApiError(422, f"{name}: not a valid {kind.__name__}: {raw!r}") from None
        if not math.isfinite(value) or value < lo or (hi is not None and value > hi):
            bound = f">= {lo:g}" + (f" and <= {hi:g}" if hi is not None else "")
            raise ApiError(422, f"{name}: must be {bound}, got {raw}")
        out.append(value)
    return out[0], out[1], out[2]


def _static(name: str) -> str:
    return resources.files("kautztwin.service").joinpath("static", name).read_text("utf-8")


def _setpoint_limits(service: Any) -> tuple[float, float]:
    """The output limits of the MPC (``-inf, inf`` when unbounded or uncontrolled)."""
    twin = service.twin
    mpc = None if twin is None else twin.config.mpc
    if mpc is None:
        return -math.inf, math.inf
    return float(mpc.y_min), float(mpc.y_max)


def _version_events(history: Any, run_id: int) -> dict[int, dict[str, Any]]:
    """``{version: payload}`` of the run's ``model-version`` events (k, t, offset...)."""
    out: dict[int, dict[str, Any]] = {}
    for e in history.events(run_id, "model-version"):
        p = e.payload if isinstance(e.payload, dict) else {}
        if "version" in p:
            out[int(p["version"])] = p
    return out


def _method(provenance: str) -> str:
    """The identification method behind a provenance: OE, DNN, RLS or the provenance."""
    p = provenance.lower()
    if "dnn" in p or "estimator" in p or "step" in p:
        return "DNN"
    if "identification" in p:
        return "OE"  # Kautz output error (ident.identify_output_error)
    if "rls" in p:
        return "RLS"
    return provenance


def _model_summary(dm: Any, info: dict[str, Any] | None, active: Any) -> dict[str, Any]:
    info = info or {}
    poles = [[float(p.real), float(p.imag)] for p in dm.model.poles]
    method = _method(dm.provenance)
    return {"version": dm.version, "provenance": dm.provenance, "method": method,
            "created": dm.created,
            "created_iso": datetime.fromtimestamp(dm.created, UTC).isoformat(timespec="seconds"),
            "fit_percent": _num(dm.fit_percent), "k": info.get("k"), "t": _num(info.get("t")),
            "offset": _num(info.get("offset")), "n_functions": dm.model.n_functions,
            "poles": poles, "active": active is not None and active.version == dm.version}


class ApiServer:
    """The HTTP API of a :class:`~kautztwin.service.TwinService`, served by uvicorn in a thread.

    Parameters
    ----------
    service : TwinService
        The service (its loop feeds :attr:`view`).
    bind : str, optional
        ``HOST:PORT`` or ``PORT`` to serve on (port 0: a free one); ``None``
        builds the app only (tests drive it with ``fastapi.testclient``).
    token : str, optional
        API token (bearer) of the writes, ``/whatif`` and ``/stream``.
    rate_limit : float, default=60
        Writes and what-ifs a minute per client (0: no limit).
    capacity : int, default=3000
        Samples of the live ring buffer.

    Attributes
    ----------
    view : TwinView
    app : fastapi.FastAPI
    limiter : RateLimiter
    url : str or None
        ``http://HOST:PORT`` once started.
    ready : threading.Event
        Set once the server answers (:meth:`start` returned).

    Raises
    ------
    DataError
        A bind off the loopback interface without a token.
    """

    def __init__(self, service: Any, *, bind: str | None = None, token: str | None = None,
                 rate_limit: float = 60.0, capacity: int = 3000) -> None:
        self.host, self.port = server_address(bind, token)
        self.bind = bind
        self._token = token
        self.view = TwinView(service, capacity=capacity)
        self.limiter = RateLimiter(rate_limit)
        self.app = create_app(self.view, token=token, limiter=self.limiter)
        self.url: str | None = None
        self._http: HttpThread | None = None
        self.ready = threading.Event()

    @classmethod
    def from_service(cls, service: Any) -> "ApiServer":
        """The server of the service's ``[http]`` section.

        Parameters
        ----------
        service : TwinService

        Returns
        -------
        ApiServer
        """
        h = service.config.values["http"]
        return cls(service, bind=h["bind"], token=h["token"], rate_limit=h["rate_limit"])

    def start(self, timeout: float = 10.0) -> None:
        """Listen and serve in a daemon thread (nothing without a bind).

        Parameters
        ----------
        timeout : float, default=10
            Most seconds to wait for the server to come up.

        Raises
        ------
        DataError
            The address cannot be bound (busy, not on this machine) or the
            server did not start in time.
        """
        if self.bind is None or self._http is not None:
            return
        http = HttpThread(self.app, self.host, self.port)
        http.start(timeout)
        self._http = http
        self.url = http.url
        # the handlers' garbage triggers full collections: see kautztwin.service.process
        freeze_garbage()
        self.ready.set()
        _logger.info("http", extra={"event": "http", "fields": {
            "url": self.url, "docs": f"{self.url}/docs", "token": self.token_set}})

    @property
    def _server(self) -> Any:
        """The running ``uvicorn.Server`` (``None`` when not serving)."""
        return None if self._http is None else self._http._server

    @property
    def token_set(self) -> bool:
        """Whether the writes, ``/whatif`` and ``/stream`` need a token."""
        return self._token is not None

    def stop(self, timeout: float = 5.0) -> None:
        """Refuse the queued jobs, stop serving and close the history reads (idempotent).

        Parameters
        ----------
        timeout : float, default=5
            Most seconds to wait for the server thread.
        """
        self.view.stopped()
        self.ready.clear()
        if self._http is not None:
            self._http.stop(timeout)
        self._http = None
        self.app.state.close_reads()
        thaw_garbage()  # the frozen objects may be collected again once they are garbage
