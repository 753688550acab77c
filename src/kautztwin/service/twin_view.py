"""What the HTTP API sees of a running twin: :class:`TwinView`, fed by the sample loop.

The service's sample loop calls :meth:`TwinView.after_sample` once per sample:
the view keeps the latest state and bounded ring buffers of recent samples and
events (so a dashboard open for hours costs constant memory), and runs the
jobs that request handlers queued (:meth:`TwinView.call`): a set-point
override, a re-identification request, a what-if prediction.  Those jobs run
in the loop's thread between two samples, so nothing of the twin is touched
by two threads at once; a handler waits for its job's result.

Reads of models and events go straight to the store, which serialises its
connection with a lock; pages of ``/history`` come from
:class:`~kautztwin.service.history_reader.HistoryReader` instead.
:class:`RateLimiter` bounds the writes per client.  The loop's pace is watched
by :meth:`TwinView.loop_timing` (served by ``/health``).
"""

from __future__ import annotations

import collections
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..exceptions import KautzTwinError

__all__ = ["ApiError", "RateLimiter", "TwinView"]

#: fields of a sample kept in the ring buffer (and streamed)
SAMPLE_FIELDS = ("k", "t", "phase", "y", "u", "setpoint", "reference", "y_pred", "fit",
                 "version", "mpc_ms", "update_ms", "flags")
#: intervals between samples kept for :meth:`TwinView.loop_timing`
TIMING_WINDOW = 5000


class ApiError(KautzTwinError):
    """A request the twin cannot serve now, with the HTTP status to answer.

    Parameters
    ----------
    status : int
        The HTTP status code (409: not in this phase, 503: the loop is not running).
    message : str
        One line for the client.
    """

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = int(status)
        self.message = message


def _num(x: Any) -> float | None:
    """A JSON-ready number: ``None`` for NaN or infinity."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


@dataclass
class _Job:
    fn: Callable[[Any], Any]
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None


class TwinView:
    """Thread-safe window on a running :class:`~kautztwin.service.TwinService`.

    Parameters
    ----------
    service : TwinService
        The service whose loop feeds the view.
    capacity : int, default=3000
        Samples kept in the ring buffer (older ones are dropped).
    event_capacity : int, default=500
        Events kept for the live stream.

    Attributes
    ----------
    seq : int
        Number of samples seen so far (the ring buffer holds the last ``capacity``).
    running : bool
        Whether the service's loop is stepping the twin.
    """

    def __init__(self, service: Any, *, capacity: int = 3000, event_capacity: int = 500) -> None:
        self.service = service
        self.capacity = int(capacity)
        self._lock = threading.Lock()
        self._samples: collections.deque[dict[str, Any]] = collections.deque(maxlen=capacity)
        self._events: collections.deque[dict[str, Any]] = collections.deque(
            maxlen=event_capacity)
        self._jobs: queue.Queue[_Job] = queue.Queue()
        self._latest: dict[str, Any] = {}
        self._n_events = 0
        self._intervals: collections.deque[float] = collections.deque(maxlen=TIMING_WINDOW)
        self._last_sample: float | None = None
        self.seq = 0
        self.running = False
        self.started = time.time()

    # ------------------------------------------------------------------ the loop's side
    def after_sample(self, state: Any) -> None:
        """Record one sample and run the queued jobs (called by the loop's thread).

        Parameters
        ----------
        state : TwinState
            What :meth:`DigitalTwin.step` returned.
        """
        now = time.perf_counter()
        sample = {f: getattr(state, f) for f in SAMPLE_FIELDS}
        for key in ("k", "version", "flags"):
            sample[key] = int(sample[key])
        for key, value in sample.items():
            if isinstance(value, float):
                sample[key] = _num(value)
        twin = self.service.twin
        new_events: list[dict[str, Any]] = []
        if state.events and twin is not None:
            for ev in twin._record.events[-len(state.events):]:
                new_events.append({"kind": ev.kind, "k": ev.k, "t": _num(ev.t),
                                   "message": ev.message, "source": "twin"})
        with self._lock:
            if self._last_sample is not None:
                self._intervals.append(now - self._last_sample)
            self._last_sample = now
            self.seq += 1
            sample["seq"] = self.seq
            self._samples.append(sample)
            self._latest = dict(sample, committed=int(state.committed), events=list(state.events))
            for ev in new_events:
                self._push_event(ev)
        self.running = True
        self.run_jobs()

    def run_jobs(self) -> None:
        """Run every queued job now (the loop's thread; also when the loop ends)."""
        while True:
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                return
            try:
                job.result = job.fn(self.service)
            except BaseException as exc:  # handed to the waiting request
                job.error = exc
            job.done.set()

    def stopped(self) -> None:
        """The loop has ended: refuse queued and later jobs (called by the loop's thread)."""
        self.running = False
        while True:
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                return
            job.error = ApiError(503, "the twin has stopped")
            job.done.set()

    def _push_event(self, ev: dict[str, Any]) -> None:
        self._n_events += 1
        ev["seq"] = self._n_events
        ev.setdefault("time", time.time())
        self._events.append(ev)

    def add_event(self, kind: str, message: str, **payload: Any) -> None:
        """Put an event of the service (an API write) on the live stream.

        Parameters
        ----------
        kind : str
            The event's kind.
        message : str
            One line.
        **payload
            Extra JSON-ready fields.
        """
        with self._lock:
            self._push_event({"kind": kind, "message": message, "source": "api", **payload})

    # ------------------------------------------------------------------ the handlers' side
    def call(self, fn: Callable[[Any], Any], timeout: float = 10.0) -> Any:
        """Run ``fn(service)`` in the loop's thread before the next sample and return its result.

        Parameters
        ----------
        fn : callable
            Takes the service.
        timeout : float, default=10
            Most seconds to wait.

        Returns
        -------
        object
            What ``fn`` returned.

        Raises
        ------
        ApiError
            503 when the loop is not running or did not take the job in time.
        Exception
            Whatever ``fn`` raised.
        """
        if not self.running:
            raise ApiError(503, "the twin's sample loop is not running")
        job = _Job(fn)
        self._jobs.put(job)
        if not job.done.wait(timeout):
            raise ApiError(503, f"the twin's sample loop did not answer within {timeout:g} s")
        if job.error is not None:
            raise job.error
        return job.result

    def latest(self) -> dict[str, Any]:
        """The latest sample (empty before the first).

        Returns
        -------
        dict
        """
        with self._lock:
            return dict(self._latest)

    def samples(self, since: int = 0, limit: int | None = None) -> list[dict[str, Any]]:
        """Samples of the ring buffer with ``seq > since``, oldest first.

        Parameters
        ----------
        since : int, default=0
            The last ``seq`` the caller has.
        limit : int, optional
            At most this many, the newest.

        Returns
        -------
        list of dict
        """
        with self._lock:
            out = [s for s in self._samples if s["seq"] > since]
        return out if limit is None else out[-limit:]

    def events(self, since: int = 0) -> list[dict[str, Any]]:
        """Events of the live buffer with ``seq > since``, oldest first.

        Parameters
        ----------
        since : int, default=0

        Returns
        -------
        list of dict
        """
        with self._lock:
            return [e for e in self._events if e["seq"] > since]

    def loop_timing(self) -> dict[str, Any]:
        """How regularly the sample loop hands over samples (``/health``'s ``loop``).

        Returns
        -------
        dict
            ``samples`` (intervals in the window, the last 5000), ``interval_ms_p50``,
            ``interval_ms_p99``, ``interval_ms_max`` (wall time between two samples
            reaching the view), and for a real-time clock ``period_ms`` (the nominal
            interval), ``late`` (samples the loop reached more than its clock's
            tolerance, one period, after their time, since the run started) and
            ``behind_ms_max`` (the largest lateness, wall ms).
        """
        with self._lock:
            iv = np.array(self._intervals) * 1e3
        out: dict[str, Any] = {"samples": int(iv.size)}
        if iv.size:
            p50, p99 = np.percentile(iv, [50, 99])
            out.update(interval_ms_p50=round(float(p50), 3), interval_ms_p99=round(float(p99), 3),
                       interval_ms_max=round(float(iv.max()), 3))
        twin = self.service.twin
        clock = getattr(twin, "clock", None)
        if clock is not None and getattr(clock, "realtime", False):
            out.update(period_ms=round(twin.config.dt / clock.speedup * 1e3, 3),
                       late=int(clock.n_late),
                       behind_ms_max=round(clock.max_lateness / clock.speedup * 1e3, 3))
        return out

    def residual_sigma(self) -> float:
        """Standard deviation of ``y - y_pred`` over the ring buffer (NaN when unknown).

        Returns
        -------
        float
        """
        with self._lock:
            pairs = [(s["y"], s["y_pred"]) for s in self._samples
                     if s["y"] is not None and s["y_pred"] is not None]
        if len(pairs) < 5:
            return math.nan
        r = np.array([a - b for a, b in pairs[-1000:]])
        return float(np.sqrt(np.mean(r * r)))


class RateLimiter:
    """At most ``per_minute`` writes per client over any sliding minute.

    Parameters
    ----------
    per_minute : float
        Allowed writes a minute per client (0: no limit).

    Examples
    --------
    >>> lim = RateLimiter(2)
    >>> [lim.allow("a", now=0.0), lim.allow("a", now=1.0), lim.allow("a", now=2.0)]
    [True, True, False]
    >>> lim.allow("a", now=61.0), lim.allow("b", now=2.0)
    (True, True)
    """

    def __init__(self, per_minute: float) -> None:
        self.per_minute = float(per_minute)
        self._lock = threading.Lock()
        self._hits: dict[str, collections.deque[float]] = {}

    def allow(self, client: str, now: float | None = None) -> bool:
        """Count one write of ``client``; whether it is within the limit.

        Parameters
        ----------
        client : str
            Who writes.
        now : float, optional
            The time (``time.monotonic()`` when omitted).

        Returns
        -------
        bool
        """
        if self.per_minute <= 0:
            return True
        now = time.monotonic() if now is None else now
        with self._lock:
            hits = self._hits.setdefault(client, collections.deque())
            while hits and hits[0] <= now - 60.0:
                hits.popleft()
            if len(hits) >= self.per_minute:
                return False
            hits.append(now)
            if len(self._hits) > 10_000:  # bounded: forget idle clients
                for key in [k for k, v in self._hits.items() if not v][:5000]:
                    del self._hits[key]
            return True

    def reset(self) -> None:
        """Forget every client's writes."""
        with self._lock:
            self._hits.clear()
