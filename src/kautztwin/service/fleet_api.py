"""The fleet's HTTP API (FastAPI): every asset of a served fleet under ``/assets/{id}/...``.

:func:`create_fleet_app` builds the application around the
:class:`~kautztwin.service.fleet_view.FleetView` of a running
:class:`~kautztwin.service.fleet_service.FleetService`; :class:`FleetApiServer`
serves it with uvicorn in a thread (``kautztwin fleet serve --http
127.0.0.1:8000``).  The endpoints (reference and curl examples in
``docs/api-http.md``, *Fleet*; OpenAPI at ``/docs``):

* ``GET /health``: whether the loop runs, where it is, its pace;
* ``GET /assets``: the asset ids with a status summary (paged);
* ``GET /assets/{id}/state``: the asset's latest sample, fit, version, counts;
* ``GET /assets/{id}/history``: its stored samples, JSON or CSV, paged - the
  shape of the single twin's ``/history`` (``prediction`` is the twin's
  monitored prediction of the sample, ``setpoint`` the set-point in force);
* ``POST /assets/{id}/setpoint``: a set-point for that asset from the next sample;
* ``GET /fleet/metrics``: the per-asset sync-fit distribution,
  re-identifications, desynchronisations, MPC failures, limit violations.

The rules are the single twin's API's and come from the same code
(:mod:`.http_common`): a bind off the loopback interface needs a token, with a token
the writes need ``Authorization: Bearer TOKEN`` (401), writes are
rate-limited per client (429), bad input is a 422 and an unknown asset a 404,
each with a one-line JSON ``message``.  Reads of the history use read-only
connections of their own on the store's file (SQLite in WAL mode: they never
block the loop's commits).
"""


import logging
import math
import os
import sqlite3
import time
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import Depends, FastAPI, Query
from fastapi.responses import JSONResponse, Response

from .fleet_view import FleetView
from .history_reader import HISTORY_SIGNALS, ReadOnlyPages, page_columns, window_query
from .http_common import (
    MAX_PAGE,
    HttpThread,
    ReaderSlot,
    SetpointRequest,
    add_error_handlers,
    field_error,
    history_query,
    history_response,
    json_answer,
    json_numbers,
    server_address,
    write_guard,
)
from .process import freeze_garbage, thaw_garbage
from .twin_view import ApiError, RateLimiter, _num

__all__ = ["FleetApiServer", "FleetHistoryReader", "create_fleet_app"]

_logger = logging.getLogger("kautztwin.service")


class FleetHistoryReader(ReadOnlyPages):
    """Pages of one asset's stored samples, on read-only connections of its own (one a thread).

    Parameters
    ----------
    path : str
        The fleet's SQLite store.
    """

    def __init__(self, path: str) -> None:
        super().__init__(os.path.abspath(path))

    def page(self, run_id: int, asset: int, signals: list[str], *, after: int = -1,
             start: float | None = None, end: float | None = None,
             limit: int = 1000) -> tuple[dict[str, Any], int | None]:
        """One page of asset ``asset``'s samples ``k > after`` within ``[start, end]``.

        Parameters
        ----------
        run_id, asset : int
        signals : list of str
            Among ``k, t, u, y, flags, prediction, setpoint``.
        after : int, default=-1
        start, end : float, optional
        limit : int, default=1000

        Returns
        -------
        dict of str to ndarray
            One column per signal; ``prediction`` is the twin's monitored
            prediction of the sample, ``setpoint`` the set-point in force (NaN in
            the identification phase).
        int or None
            The cursor of the next page (``None``: this was the last).
        """
        if self._closed:
            raise ApiError(503, "the history store is closed")
        query, args = window_query(
            "SELECT k, t, u, y, flags, y_pred FROM fleet_samples WHERE run_id = ? AND asset = ?",
            [run_id, asset], after, start, end, limit)

        def read(conn: sqlite3.Connection) -> tuple[list[Any], Any, list[Any]]:
            rows = conn.execute(query, args).fetchall()
            config = self._run_config(conn, "fleet_runs", run_id)
            sps = conn.execute(
                "SELECT k_from, t, value FROM fleet_setpoints WHERE run_id = ? AND asset = ? "
                "ORDER BY k_from, rowid", (run_id, asset)).fetchall()
            return rows, config, sps

        rows, config, sps = self._snapshot(read)
        events = [("api-setpoint", k, t, {"value": v, "k_from": k}) for k, t, v in sps]
        return page_columns(rows, signals, limit, config, events)


def _asset_metrics(fleet: Any) -> dict[str, Any]:
    """The fleet's metrics now (``/fleet/metrics``), read in the loop's thread."""
    from ..twin.fleet.simulate import distribution

    n = fleet.n_assets
    st = fleet.fit_stats
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(st["n"] > 0, st["sum"] / np.maximum(st["n"], 1), math.nan)
        low = np.where(st["n"] > 0, st["min"], math.nan)
    upd = fleet.updater
    zeros = np.zeros(n, dtype=np.int64)
    attempts = zeros if upd is None else upd.counts["attempts"]
    accepted = zeros if upd is None else upd.counts["accepted"]
    in_sync = np.ones(n, dtype=bool) if upd is None else upd.monitor.in_sync
    desync = np.zeros(n, dtype=np.int64)
    for a, k, kind, _ in fleet.events:
        if kind == "desync" and k >= fleet.k_closed_loop:
            desync[a] += 1
    c = fleet.counts
    viol = c["output_violations"] + c["input_violations"] + c["rate_violations"]
    return {
        "n_assets": n, "k": fleet.k, "t": fleet.k * fleet.config.dt,
        "phase": "closed-loop" if fleet.k > fleet.k_closed_loop else "identification",
        "sync_fit_last": distribution(st["last"]), "sync_fit_mean": distribution(mean),
        "sync_fit_min": distribution(low),
        "in_sync": int(in_sync.sum()), "out_of_sync": int((~in_sync).sum()),
        "desync_events": {"total": int(desync.sum()), "assets": int((desync > 0).sum())},
        "reidentification": {"attempts": int(attempts.sum()), "accepted": int(accepted.sum()),
                             "assets_with_new_model": int((accepted > 0).sum())},
        "mpc": {"failures": int(c["mpc_failures"].sum()),
                "fallbacks_to_daqp": int(c["mpc_fallbacks"].sum())},
        "violations": {"output_samples": int(c["output_violations"].sum()),
                       "input_samples": int(c["input_violations"].sum()),
                       "rate_samples": int(c["rate_violations"].sum()),
                       "assets_with_any": int((viol > 0).sum())},
        "flagged_samples": int(c["flagged"].sum()),
    }


def _asset_counts(fleet: Any, i: int) -> dict[str, Any]:
    """One asset's counts (read in the loop's thread)."""
    upd = fleet.updater
    c = fleet.counts
    st = fleet.fit_stats
    n_fit = int(st["n"][i])
    return {
        "reidentification_attempts": 0 if upd is None else int(upd.counts["attempts"][i]),
        "reidentifications_accepted": 0 if upd is None else int(upd.counts["accepted"][i]),
        "mpc_failures": int(c["mpc_failures"][i]), "mpc_fallbacks": int(c["mpc_fallbacks"][i]),
        "flagged": int(c["flagged"][i]),
        "violations": {"output": int(c["output_violations"][i]),
                       "input": int(c["input_violations"][i]),
                       "rate": int(c["rate_violations"][i])},
        "sync_fit_mean": _num(st["sum"][i] / n_fit) if n_fit else None,
        "sync_fit_min": _num(st["min"][i]) if n_fit else None,
    }


def create_fleet_app(view: FleetView, *, token: str | None = None,
                     limiter: RateLimiter | None = None) -> FastAPI:
    """The FastAPI application of a served fleet.

    Parameters
    ----------
    view : FleetView
        The running service's view.
    token : str, optional
        The API token the writes need (bearer).
    limiter : RateLimiter, optional
        Limits writes per client (none when omitted).

    Returns
    -------
    fastapi.FastAPI
    """
    app = FastAPI(title="kautztwin fleet", version="1",
                  description="The fleet's HTTP API (docs/api-http.md, Fleet).")
    app.state.view = view
    service = view.service
    add_error_handlers(app)

    def _fleet() -> Any:
        fleet = service.fleet
        if fleet is None or not fleet.started:
            raise ApiError(503, "the fleet has not started yet")
        return fleet

    def _asset(asset_id: int) -> int:
        n = service.n_assets
        if not 0 <= asset_id < n:
            raise ApiError(404, f"asset: no asset {asset_id} (the fleet has assets 0 to {n - 1})")
        return asset_id

    # dependency of writes: the token, then the rate limit
    writer = write_guard(token, limiter)
    # the reader of the fleet's store (closed with the server: then 503)
    reads = ReaderSlot(lambda _key: FleetHistoryReader(str(service.history_path)))
    _reader = reads.get
    app.state.close_reads = reads.close

    @app.get("/health", tags=["read"], response_model=None)
    async def health() -> Response:
        """Liveness: whether the loop runs, where it is, and whether it keeps its pace."""
        st = view.step()
        fleet = service.fleet
        return json_answer({"status": "ok", "running": view.running, "k": st.get("k"),
                            "n_assets": service.n_assets, "uptime_s": time.time() - view.started,
                            "run_id": None if fleet is None else fleet.run_id,
                            "loop": view.loop_timing()})

    @app.get("/assets", tags=["read"], response_model=None)
    async def assets(after: int = Query(-1, ge=-1, description="page cursor: ids > after"),
                     limit: int = Query(1000, ge=1, le=MAX_PAGE)) -> Response:
        """Asset ids with their status (in sync, fit, version), a summary, paged by id."""
        st = view.step()
        n = service.n_assets
        ids = np.arange(after + 1, min(n, after + 1 + limit))
        nxt = int(ids[-1]) if ids.size and ids[-1] < n - 1 else None
        out: dict[str, Any] = {"n_assets": n, "k": st.get("k"), "next": nxt}
        if st:
            in_sync, fit, ver = st["in_sync"], st["fit"], st["version"]
            out["summary"] = {"in_sync": int(in_sync.sum()), "out_of_sync": int((~in_sync).sum()),
                              "phase": st["phase"],
                              "median_fit": _num(np.nanmedian(fit)) if np.isfinite(fit).any()
                              else None}
            out["assets"] = [{"id": int(i), "in_sync": bool(in_sync[i]), "fit": f,
                              "version": int(ver[i])}
                             for i, f in zip(ids.tolist(), json_numbers(fit[ids]), strict=True)]
        else:
            out["summary"] = {"in_sync": None, "out_of_sync": None, "phase": "starting",
                              "median_fit": None}
            out["assets"] = [{"id": int(i), "in_sync": None, "fit": None, "version": None}
                             for i in ids.tolist()]
        return json_answer(out)

    @app.get("/assets/{asset_id}/state", tags=["read"], response_model=None)
    def state(asset_id: int) -> Response:
        """One asset's latest sample: y, u, set-point, reference, prediction, fit, version."""
        i = _asset(asset_id)
        out: dict[str, Any] = {"id": i, "running": view.running, **view.asset(i)}
        fleet = service.fleet
        if fleet is not None and fleet.started:
            cfg = fleet.config
            mpc = cfg.mpc
            out.update(run_id=fleet.run_id, dt=cfg.dt, n_samples=cfg.n_samples,
                       setpoint_limits=[_num(mpc.y_min), _num(mpc.y_max)],
                       counts=view.call(lambda svc: _asset_counts(svc.fleet, i))
                       if view.running else _asset_counts(fleet, i),
                       drawn=service.assets[i] if i < len(service.assets) else None)
        return json_answer(out)

    @app.get("/assets/{asset_id}/history", tags=["read"], response_model=None)
    async def history_(
        asset_id: int,
        signals: str = Query("k,t,u,y,flags", description="comma-separated: "
                             + ",".join(HISTORY_SIGNALS)),
        start: float | None = Query(None, description="first time, plant s"),
        end: float | None = Query(None, description="last time, plant s"),
        limit: int = Query(1000, ge=1, le=MAX_PAGE),
        after: int = Query(-1, ge=-1, description="page cursor: samples with k > after"),
        format: Literal["json", "csv"] = "json",
    ) -> Response:
        """One asset's stored samples, predictions and set-points, paged by ``after``."""
        i = _asset(asset_id)
        names = history_query(signals, start, end)
        if isinstance(names, JSONResponse):
            return names
        fleet = service.fleet
        run_id = None if fleet is None else fleet.run_id
        if run_id is None:
            cols: dict[str, Any] = {s: np.empty(0) for s in names}
            nxt = None
        else:
            cols, nxt = _reader().page(int(run_id), i, names, after=after, start=start, end=end,
                                       limit=limit)
        return history_response(run_id, names, cols, nxt, format)

    @app.post("/assets/{asset_id}/setpoint", tags=["write"], response_model=None)
    def setpoint(asset_id: int, req: SetpointRequest,
                 who: Annotated[dict[str, Any], Depends(writer)]) -> Response:
        """Hold a new set-point for one asset from its next sample (within the output limits)."""
        i = _asset(asset_id)
        fleet = _fleet()
        mpc = fleet.config.mpc
        lo, hi = float(mpc.y_min), float(mpc.y_max)
        if not lo <= req.value <= hi:
            return field_error("value", f"set-point {req.value:g} is outside the limits "
                                        f"[{lo:g}, {hi:g}]")

        def job(svc: Any) -> dict[str, Any]:
            k = svc.fleet.set_setpoint([i], req.value)
            return {"k_from": k, "t_from": k * svc.fleet.config.dt}

        out = view.call(job)
        _logger.info("api-setpoint", extra={"event": "api-setpoint", "fields": {
            "who": who["who"], "asset": i, "value": req.value, "k_from": out["k_from"]}})
        view.add_event("api-setpoint", f"asset {i}: set-point {req.value:g} by {who['who']}",
                       asset=i, k=out["k_from"])
        return json_answer({"id": i, "setpoint": req.value, **out, "who": who["who"],
                            "when": who["when"]})

    @app.get("/fleet/metrics", tags=["read"], response_model=None)
    def metrics() -> Response:
        """Per-asset sync-fit distribution, re-identifications, desyncs, MPC, violations."""
        fleet = _fleet()
        if view.running:
            return json_answer(view.call(lambda svc: _asset_metrics(svc.fleet)))
        return json_answer(_asset_metrics(fleet))

    return app


class FleetApiServer:
    """The HTTP API of a :class:`~kautztwin.service.fleet_service.FleetService` (uvicorn thread).

    Parameters
    ----------
    service : FleetService
    bind : str, optional
        ``HOST:PORT`` or ``PORT`` (port 0: a free one); ``None`` builds the app only.
    token : str, optional
        API token (bearer) of the writes.
    rate_limit : float, default=60
        Writes a minute per client (0: no limit).

    Attributes
    ----------
    view : FleetView
    app : fastapi.FastAPI
    url : str or None
        ``http://HOST:PORT`` once started.

    Raises
    ------
    DataError
        A bind off the loopback interface without a token.
    """

    def __init__(self, service: Any, *, bind: str | None = None, token: str | None = None,
                 rate_limit: float = 60.0) -> None:
        self.host, self.port = server_address(bind, token)
        self.bind = bind
        self._token = token
        self.view = FleetView(service)
        self.limiter = RateLimiter(rate_limit)
        self.app = create_fleet_app(self.view, token=token, limiter=self.limiter)
        self.url: str | None = None
        self._http: HttpThread | None = None

    def start(self, timeout: float = 10.0) -> None:
        """Listen and serve in a daemon thread (nothing without a bind).

        Parameters
        ----------
        timeout : float, default=10

        Raises
        ------
        DataError
            The address cannot be bound or the server did not start in time.
        """
        if self.bind is None or self._http is not None:
            return
        http = HttpThread(self.app, self.host, self.port)
        http.start(timeout)
        self._http, self.url = http, http.url
        freeze_garbage()  # as ApiServer: full collections then walk only newer objects
        _logger.info("http", extra={"event": "http", "fields": {
            "url": self.url, "docs": f"{self.url}/docs", "token": self._token is not None}})

    def stop(self, timeout: float = 5.0) -> None:
        """Refuse the queued jobs, stop serving and close the history reads (idempotent).

        Parameters
        ----------
        timeout : float, default=5
        """
        self.view.stopped()
        if self._http is not None:
            self._http.stop(timeout)
        self._http = None
        self.app.state.close_reads()
        thaw_garbage()

