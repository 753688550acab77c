"""The input sent to a live plant and not yet seen applied; the link's latency, as the loop sees it.

A live link (OPC UA, MQTT) reports with each sample the input the plant applied
over its period (``meta['u_applied']``) and how many newer samples it already
holds (``meta['queued']``).  :class:`InputsInFlight` keeps the one input the
loop sent and has not seen applied, and learns from the sample stream alone
(no clock) how many samples an input takes to reach the plant:

* an input sent after reading sample ``k`` with ``q`` newer samples queued
  leaves when the plant has published at least sample ``k + q`` (the newest the
  link holds); it is seen applied over period ``p`` (the reading of sample
  ``p + 1`` reports it); ``p - (k + q)`` is one measurement of the **wire
  latency** in samples;
* the **input delay** of a decision at sample ``k`` (samples from the reading to
  the period the plant applies the input over) is then ``queued + median``
  latency (:meth:`InputsInFlight.delay`): the queue is seen at once, the wire
  is learnt;
* an input counts as applied once the loop sees it applied (on a sample at or
  after ``k + q``), or after ``max_wait`` samples (:meth:`InputsInFlight.awaiting`).
  Confirming it earlier, once the plant had published more samples past
  ``k + q`` than the largest recent latency plus 2, was tried and dropped: in one
  run against the OPC UA plant at x10 on a loaded host the plant's input then
  jumped by 0.053 with ``du_max = 0.05``: a command change of 0.013 where one
  decision may make 0.01, so a decided input had been jumped over (the
  client's own backlog of notifications not yet handled is not in ``queued``,
  and it can grow faster than the latencies learnt).

The estimate needs no clock shared with the plant: a plant server that runs
slower than its nominal speed (a loaded host) leaves it right, where an index
from the wall clock drifts.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass

__all__ = ["InputsInFlight"]

@dataclass
class _Sent:
    value: float
    k: int  # the reading after which it was sent
    newest: int  # the newest sample the link held then (k + queued)
    armed: bool  # the plant applied another value since it was sent (a change to see)


class InputsInFlight:
    """The input sent to a live plant and not yet confirmed, and the wire latency learnt.

    Parameters
    ----------
    max_wait : int
        Samples (read by the loop) after which an input never seen applied is
        given up on (refused, lost) and the loop decides again.
    window : int, default=32
        Latency measurements kept.

    Attributes
    ----------
    latencies : deque of int
        The recent wire latencies, samples.

    Examples
    --------
    >>> f = InputsInFlight(max_wait=50)
    >>> f.send(0.6, k=10, queued=3, applied=0.5)
    >>> f.awaiting(11, applied=0.5, queued=3)
    True
    >>> f.awaiting(16, applied=0.6, queued=0)  # applied over period 15 (16's reading says)
    False
    >>> list(f.latencies), f.delay(queued=4)  # 15 - (10 + 3) samples on the wire
    ([2], 6)
    """

    def __init__(self, max_wait: int, window: int = 32) -> None:
        self.max_wait = int(max_wait)
        self.latencies: deque[int] = deque(maxlen=int(window))
        self._sent: _Sent | None = None

    @property
    def pending(self) -> bool:
        """Whether an input is in flight (sent, not yet confirmed)."""
        return self._sent is not None

    def send(self, value: float, k: int, queued: int, applied: float) -> None:
        """A new input ``value`` went out after reading sample ``k`` (``queued`` newer ones held).

        Parameters
        ----------
        value : float
            The input sent.
        k : int
            The sample just read.
        queued : int
            Newer samples the link already held (``meta['queued']``).
        applied : float
            The input the plant applied over sample ``k``'s period.
        """
        armed = not _same(applied, value)
        self._sent = _Sent(float(value), int(k), int(k) + max(0, int(queued)), armed)

    def awaiting(self, k: int, applied: float, queued: int) -> bool:
        """Whether the input in flight is still unconfirmed at sample ``k``.

        It is confirmed when sample ``k`` shows it applied (a latency is
        learnt when the applied input changed to it); only a sample at or after
        the newest one the link held at sending counts (an older sample that
        shows the same value shows an earlier input: a loop that is behind reads
        the inputs of the past, and a dither takes the same values again); or
        after ``max_wait`` samples.

        Parameters
        ----------
        k : int
            The sample just read.
        applied : float
            The input the plant applied over its period (NaN: not reported).
        queued : int
            Newer samples the link already holds (not used: kept so that the
            caller passes what the reading says).

        Returns
        -------
        bool
        """
        s = self._sent
        if s is None:
            return False
        period = int(k) - 1  # the reading of sample k reports the input of period k - 1
        if period >= s.newest and _same(applied, s.value):
            if s.armed:
                self.latencies.append(period - s.newest)
            self._sent = None
            return False
        if math.isfinite(applied) and not _same(applied, s.value):
            s.armed = True
        if k - s.k > self.max_wait:
            self._sent = None
            return False
        return True

    def delay(self, queued: int) -> int | None:
        """Input delay of a decision now: ``queued`` plus the median latency (``None``: unknown).

        Parameters
        ----------
        queued : int
            Newer samples the link already holds.

        Returns
        -------
        int or None
        """
        if not self.latencies:
            return None
        return max(0, int(queued)) + int(round(statistics.median(self.latencies)))


def _same(a: float, b: float) -> bool:
    return math.isfinite(a) and abs(a - b) <= 1e-9 * max(1.0, abs(b))
