"""What the twin's HTTP API and the fleet's share: answers, guards, ``/history`` pages, the server.

The single twin's API (:mod:`.api`) and the fleet's (:mod:`.fleet_api`) follow
one set of rules, and this module is the one place they are written:

* answers: JSON serialised at once (:func:`json_answer`, NaN and infinities
  as ``null``), one-line errors (:func:`add_error_handlers`: 422 for bad
  input, an :class:`~.twin_view.ApiError`'s own status otherwise;
  :func:`field_error` for a body field checked by hand);
* guards: the bearer token of writes and streams (:func:`bearer_guard`), and
  the dependency of writes, token then per-client rate limit
  (:func:`write_guard`, who wrote from :func:`who_wrote`);
* ``/history``: the query check (:func:`history_query`), the page as JSON or
  CSV (:func:`history_response`), at most :data:`MAX_PAGE` samples, read
  through a store reader opened lazily and closed once with the server
  (:class:`ReaderSlot`);
* ``POST .../setpoint``'s body (:class:`SetpointRequest`);
* serving: the address and its token rule (:func:`server_address`: off the
  loopback interface only with a token) and uvicorn in a daemon thread
  (:class:`HttpThread`).

:mod:`.api` re-exports the public names that used to live there.
"""

import csv
import hmac
import io
import json
import logging
import math
import socket
import threading
import time
from datetime import UTC, datetime
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field
from starlette.requests import HTTPConnection

from ..exceptions import DataError
from .config import _is_loopback, parse_bind
from .history_reader import HISTORY_SIGNALS
from .twin_view import ApiError, RateLimiter

__all__ = ["MAX_PAGE", "HttpThread", "ReaderSlot", "SetpointRequest", "add_error_handlers",
           "bearer_guard", "field_error", "history_query", "history_response", "json_answer",
           "json_numbers", "server_address", "who_wrote", "write_guard"]

_logger = logging.getLogger("kautztwin.service")

#: most samples (or assets) of one ``/history`` (``/assets``) page
MAX_PAGE = 10_000


class SetpointRequest(BaseModel):
    """Body of ``POST /setpoint``.

    Parameters
    ----------
    value : float
        The new set-point (output units), finite, within the output limits.
    """

    model_config = ConfigDict(extra="forbid")
    value: float = Field(allow_inf_nan=False, description="new set-point, output units")


# ---------------------------------------------------------------------- answers
def json_answer(obj: Any) -> Response:
    """A JSON answer serialised at once (no per-element encoding: pages are large).

    Parameters
    ----------
    obj : object
        JSON-ready data; NaN and infinities become ``null``, as everywhere in the API.

    Returns
    -------
    starlette.responses.Response
    """
    try:
        text = json.dumps(obj, allow_nan=False, separators=(",", ":"))
    except ValueError:  # a NaN somewhere: null, as everywhere in the API
        text = json.dumps(_finite(obj), allow_nan=False, separators=(",", ":"))
    return Response(text, media_type="application/json")


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def json_numbers(a: Any) -> list[float | None]:
    """A float array as a JSON-ready list (``None`` for NaN and infinities).

    Parameters
    ----------
    a : array-like

    Returns
    -------
    list of float or None
    """
    return [v if math.isfinite(v) else None for v in np.asarray(a, dtype=float).tolist()]


def field_error(field: str, message: str, status: int = 422) -> JSONResponse:
    """The one-line answer to a body field that fails a check made by hand.

    Parameters
    ----------
    field : str
        The body field.
    message : str
        What is wrong with it.
    status : int, default=422

    Returns
    -------
    fastapi.responses.JSONResponse
        ``{"detail": [{"loc": ["body", field], "msg": message}], "message": "field: message"}``.
    """
    return JSONResponse({"detail": [{"loc": ["body", field], "msg": message}],
                         "message": f"{field}: {message}"}, status_code=status)


def _query_error(field: str, message: str) -> JSONResponse:
    return JSONResponse({"detail": [{"loc": ["query", field], "msg": message}],
                         "message": f"{field}: {message}"}, status_code=422)


# ---------------------------------------------------------------------- errors and guards
def add_error_handlers(app: FastAPI) -> None:
    """Answer bad input with 422 and :class:`ApiError` with its status, one-line JSON each.

    Every error body is ``{"detail": ..., "message": "one line"}``.

    Parameters
    ----------
    app : fastapi.FastAPI
    """

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""),
                   "type": e.get("type", "")} for e in exc.errors()]
        first = errors[0] if errors else {"loc": [], "msg": "invalid request"}
        where = ".".join(str(p) for p in first["loc"][1:]) or ".".join(map(str, first["loc"]))
        return JSONResponse({"detail": errors, "message": f"{where}: {first['msg']}"},
                            status_code=422)

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse({"detail": exc.message, "message": exc.message},
                            status_code=exc.status)


def bearer_guard(token: str | None) -> Any:
    """The token check of writes and streams: ``guard(request)`` raises 401 without it.

    Parameters
    ----------
    token : str or None
        The API token; ``None``: every request passes.

    Returns
    -------
    callable
        ``guard(connection) -> None`` (an HTTP request or a WebSocket); raises
        :class:`ApiError` 401 (logged as ``api-unauthorised``) when the
        ``Authorization: Bearer TOKEN`` header is missing or wrong.
    """

    def guard(request: HTTPConnection) -> None:
        if token is None:
            return
        header = request.headers.get("authorization", "")
        scheme, _, given = header.partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(),
                                                                 token.encode()):
            _logger.warning("api-unauthorised", extra={"event": "api-unauthorised", "fields": {
                "path": request.url.path,
                "client": request.client.host if request.client else "unknown"}})
            raise ApiError(401, "missing or wrong API token (Authorization: Bearer TOKEN)")

    return guard


def who_wrote(request: Request, token: str | None) -> dict[str, Any]:
    """Who sent a write and when (for the event log).

    Parameters
    ----------
    request : starlette.requests.Request
    token : str or None
        The API's token (``auth`` is ``'token'`` when one is set).

    Returns
    -------
    dict
        ``who``, ``client``, ``auth``, ``when`` (ISO time, UTC).
    """
    host = request.client.host if request.client else "unknown"
    auth = "token" if token is not None else "loopback"
    return {"who": f"{host} ({auth})", "client": host, "auth": auth,
            "when": datetime.now(UTC).isoformat(timespec="milliseconds")}


def write_guard(token: str | None, limiter: RateLimiter | None) -> Any:
    """The dependency of writes: the token check, then the per-client rate limit.

    Parameters
    ----------
    token : str or None
        The API token (bearer); ``None``: loopback without a token.
    limiter : RateLimiter or None
        Limits writes per client (none when ``None``).

    Returns
    -------
    callable
        ``writer(request) -> dict``: who wrote (:func:`who_wrote`); raises
        :class:`ApiError` 401 without the token and 429 over the limit.
    """
    guard = bearer_guard(token)

    def writer(request: Request) -> dict[str, Any]:
        guard(request)
        who = who_wrote(request, token)
        if limiter is not None and not limiter.allow(who["client"]):
            raise ApiError(429, f"too many requests: at most {limiter.per_minute:g} writes a "
                                "minute per client")
        return who

    return writer


# ---------------------------------------------------------------------- /history
class ReaderSlot:
    """One lazily opened store reader per server, closed with it (then reads answer 503).

    Parameters
    ----------
    opener : callable
        ``opener(key)`` opens a reader (an object with ``close()``) for ``key``.
    """

    def __init__(self, opener: Any) -> None:
        self._opener = opener
        self._reader: Any = None
        self._key: Any = None
        self._closed = False
        self._lock = threading.Lock()

    def get(self, key: Any = None) -> Any:
        """The reader for ``key`` (reopened when the key changes).

        Parameters
        ----------
        key : object, optional
            What the reader reads (compared by identity).

        Returns
        -------
        object
            The reader.

        Raises
        ------
        ApiError
            503 once the server is stopping.
        """
        with self._lock:
            if self._closed:
                raise ApiError(503, "the service is stopping")
            if self._reader is None or self._key is not key:
                self._reader, self._key = self._opener(key), key
            return self._reader

    def close(self) -> None:
        """Close the reader; later reads answer 503."""
        with self._lock:
            self._closed = True
            reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()


def history_query(signals: str, start: float | None, end: float | None,
                  allowed: tuple[str, ...] = HISTORY_SIGNALS) -> list[str] | JSONResponse:
    """The checked signal names of a ``/history`` query, or its 422 answer.

    Parameters
    ----------
    signals : str
        Comma-separated names.
    start, end : float or None
        Time window, plant s.
    allowed : tuple of str, default=HISTORY_SIGNALS

    Returns
    -------
    list of str or JSONResponse
    """
    names = [s.strip() for s in signals.split(",") if s.strip()]
    bad = [s for s in names if s not in allowed]
    if bad or not names:
        return _query_error("signals", f"unknown signal {bad[0] if bad else '(none)'!r}; "
                                       f"use {', '.join(allowed)}")
    for field, value in (("start", start), ("end", end)):
        if value is not None and not math.isfinite(value):
            return _query_error(field, f"{field} must be a finite time, got {value}")
    if start is not None and end is not None and end < start:
        return _query_error("end", f"end ({end:g}) is before start ({start:g})")
    return names


def history_response(run_id: int | None, names: list[str], cols: dict[str, Any],
                     nxt: int | None, format: str) -> Response:
    """A ``/history`` page as JSON (``run_id, n, next, signals``) or CSV (``X-Next`` header).

    Parameters
    ----------
    run_id : int or None
    names : list of str
        The signals, in order.
    cols : dict of str to ndarray
        One column per signal.
    nxt : int or None
        The page cursor of the next page (``None``: the last page).
    format : {'json', 'csv'}

    Returns
    -------
    starlette.responses.Response
    """
    n = int(next(iter(cols.values())).size)
    if format == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(names)
        for row in zip(*(cols[s].tolist() for s in names), strict=True):
            w.writerow(["" if isinstance(v, float) and not math.isfinite(v) else v
                        for v in row])
        headers = {"X-Next": str(nxt)} if nxt is not None else {}
        return Response(buf.getvalue(), media_type="text/csv", headers=headers)
    data = {s: (cols[s].tolist() if s in ("k", "flags") else json_numbers(cols[s]))
            for s in names}
    return json_answer({"run_id": run_id, "n": n, "next": nxt, "signals": data})


# ---------------------------------------------------------------------- serving
def server_address(bind: str | None, token: str | None) -> tuple[str, int]:
    """The ``(host, port)`` to serve on, refusing a bind off the loopback interface without a token.

    Parameters
    ----------
    bind : str or None
        ``HOST:PORT`` or ``PORT``; ``None``: ``('127.0.0.1', 0)`` (the app is
        only built, not served).
    token : str or None
        The API token.

    Returns
    -------
    tuple of (str, int)

    Raises
    ------
    DataError
        A bind off the loopback interface without a token, or a malformed bind.
    """
    host, port = parse_bind(bind) if bind is not None else ("127.0.0.1", 0)
    if bind is not None and not _is_loopback(host) and token is None:
        raise DataError(f"http.bind {bind!r} is not a loopback address: set an API token")
    return host, port


class HttpThread:
    """An ASGI app served by uvicorn in a daemon thread on ``host:port`` (port 0: a free one).

    The socket is bound here (a busy port is a one-line :class:`DataError`),
    with ``TCP_NODELAY`` on the accepted connections.  Used by
    :class:`~.api.ApiServer` and :class:`~.fleet_api.FleetApiServer`.

    Parameters
    ----------
    app : ASGI application
    host : str
    port : int

    Attributes
    ----------
    url : str or None
        ``http://HOST:PORT`` once started.
    """

    def __init__(self, app: Any, host: str, port: int) -> None:
        self.app, self.host, self.port = app, host, int(port)
        self.url: str | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def started(self) -> bool:
        """Whether the thread runs."""
        return self._thread is not None

    def start(self, timeout: float = 10.0) -> None:
        """Listen and serve in a daemon thread; return once the server answers.

        Parameters
        ----------
        timeout : float, default=10
            Most seconds to wait for the server to come up.

        Raises
        ------
        DataError
            The address cannot be bound or the server did not start in time.
        """
        import uvicorn

        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        # IPPROTO_TCP named: asyncio sets TCP_NODELAY on the accepted connections only then
        # (with proto 0 Nagle's algorithm and the client's delayed ACK add ~40 ms per answer)
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise DataError(f"http.bind: cannot listen on {self.host}:{self.port}: "
                            f"{exc.strerror or exc}") from None
        sock.listen(128)
        port = sock.getsockname()[1]
        host = f"[{self.host}]" if family == socket.AF_INET6 else self.host
        self.url = f"http://{host}:{port}"
        config = uvicorn.Config(self.app, log_level="warning", access_log=False,
                                lifespan="off", timeout_graceful_shutdown=1)
        self._server = server = uvicorn.Server(config)

        def serve() -> None:
            try:
                server.run(sockets=[sock])
            except BaseException as exc:  # reported by start()
                self._error = exc
            finally:
                sock.close()

        self._thread = threading.Thread(target=serve, name="kautztwin-http", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise DataError(f"http.bind: the HTTP server did not start on {self.url}"
                                + (f": {self._error}" if self._error else ""))
            time.sleep(0.02)

    def stop(self, timeout: float = 5.0) -> None:
        """Stop serving and wait for the thread (idempotent).

        Parameters
        ----------
        timeout : float, default=5
        """
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout)
        self._thread = None
        self._server = None
