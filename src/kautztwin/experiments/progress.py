"""Signs of life for long commands: a bar on a terminal, a line every few seconds otherwise.

:class:`Pulse` wraps a command's stage log (``say``).  On a terminal it
shows a bar of the elapsed time against the expected time, with the log
lines printed above it; elsewhere (a log file, CI) a background thread
writes a line whenever ``every`` seconds pass without one, naming the stage
in progress, the time spent and the time expected.  :class:`Counter` does
the same for work counted in items (records written, samples simulated).
:func:`about` words a duration for the first line of a command ("about
4 min").
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

__all__ = ["Counter", "Pulse", "about"]


def about(seconds: float) -> str:
    """A rough duration in words: ``'about 40 s'``, ``'about 4 min'``, ``'about 2 h'``.

    Parameters
    ----------
    seconds : float
        The expected duration.

    Returns
    -------
    str

    Examples
    --------
    >>> about(42), about(250), about(9000)
    ('about 40 s', 'about 4 min', 'about 2.5 h')
    """
    if not seconds == seconds or seconds < 0:  # NaN or negative: no estimate
        return "an unknown time"
    if seconds < 60:
        return f"about {max(1, round(seconds, -1 if seconds >= 15 else 0)):.0f} s"
    if seconds < 3600:
        return f"about {round(seconds / 60):.0f} min"
    return f"about {seconds / 3600:.2g} h"


def _is_tty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class Pulse:
    """A stage log that keeps showing progress while a stage is silent.

    Parameters
    ----------
    expected : float
        Expected duration of the whole command, s (drives the bar and the
        "left" figure; a rough figure is fine).
    stream : file, optional
        Where to write (default: ``sys.stderr``).
    every : float, default=15.0
        Seconds of silence after which a line is written (not on a terminal).
    bar : bool or None, default=None
        Show a bar; ``None``: only when ``stream`` is a terminal.
    enabled : bool, default=True
        ``False`` writes nothing at all (``--quiet``).

    Examples
    --------
    >>> import io
    >>> buf = io.StringIO()
    >>> with Pulse(10.0, stream=buf, every=0.05) as pulse:
    ...     pulse.say("stage one")
    ...     time.sleep(0.2)
    >>> lines = buf.getvalue().splitlines()
    >>> lines[0], lines[1].startswith("  ... stage one: ")
    ('stage one', True)
    """

    def __init__(self, expected: float, *, stream: TextIO | None = None, every: float = 15.0,
                 bar: bool | None = None, enabled: bool = True) -> None:
        self.expected = float(expected)
        self.stream = stream if stream is not None else sys.stderr
        self.every = float(every)
        self.enabled = bool(enabled)
        self.stage = "starting"
        self._t0 = self._last = time.monotonic()
        self._stage_t0 = self._t0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bar: Any = None
        use_bar = _is_tty(self.stream) if bar is None else bool(bar)
        if self.enabled and use_bar:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=max(1, round(self.expected)), unit="s", file=self.stream,
                             bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s expected",
                             dynamic_ncols=True, leave=False)

    def say(self, message: str) -> None:
        """Write one log line; a line that does not start with a space names a new stage.

        Parameters
        ----------
        message : str
        """
        if not self.enabled:
            return
        with self._lock:
            now = time.monotonic()
            self._last = now
            if not message.startswith(" "):
                self.stage = message.rstrip(".: ")
                self._stage_t0 = now
            if self._bar is not None:
                self._bar.write(message, file=self.stream)
            else:
                self.stream.write(message + "\n")
                self.stream.flush()

    def _tick(self) -> None:
        while not self._stop.wait(0.5 if self._bar is not None else min(1.0, self.every / 4)):
            with self._lock:
                now = time.monotonic()
                elapsed = now - self._t0
                if self._bar is not None:
                    self._bar.n = min(elapsed, self._bar.total)
                    self._bar.refresh()
                elif now - self._last >= self.every:
                    left = self.expected - elapsed
                    tail = (f", {about(left)} left" if left > 0 else
                            f", taking longer than the {about(self.expected)[6:]} expected")
                    self.stream.write(
                        f"  ... {self.stage}: {now - self._stage_t0:.0f} s in this stage, "
                        f"{elapsed:.0f} s in all{tail}\n")
                    self.stream.flush()
                    self._last = now

    def __enter__(self) -> Pulse:
        if self.enabled:
            self._thread = threading.Thread(target=self._tick, name="kautztwin-pulse",
                                            daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._bar is not None:
            self._bar.close()


class Counter:
    """Progress of work counted in items: a bar on a terminal, a line every ``every`` s otherwise.

    Parameters
    ----------
    total : int
        Items to do.
    what : str
        What an item is, plural (``'records'``).
    stream : file, optional
        Where to write (default: ``sys.stderr``).
    every : float, default=15.0
        Seconds between lines (not on a terminal).
    bar : bool or None, default=None
        Show a bar; ``None``: only when ``stream`` is a terminal.
    clock : callable, default=time.monotonic
        Time source (tests pass a fake one).

    Examples
    --------
    >>> import io
    >>> buf = io.StringIO()
    >>> ticks = iter([0.0, 20.0, 21.0])
    >>> c = Counter(4, "records", stream=buf, clock=lambda: next(ticks))
    >>> c.update(2)
    >>> buf.getvalue()
    '  ... 2/4 records (50 %), 20 s elapsed, about 20 s left\\n'
    """

    def __init__(self, total: int, what: str, *, stream: TextIO | None = None,
                 every: float = 15.0, bar: bool | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total = int(total)
        self.what = what
        self.stream = stream if stream is not None else sys.stderr
        self.every = float(every)
        self.done = 0
        self._clock = clock
        self._t0 = self._last = clock()
        self._bar: Any = None
        if _is_tty(self.stream) if bar is None else bool(bar):
            from tqdm.auto import tqdm

            self._bar = tqdm(total=self.total, unit=" " + what, file=self.stream,
                             dynamic_ncols=True, leave=False)

    def update(self, n: int = 1) -> None:
        """Count ``n`` more items done.

        Parameters
        ----------
        n : int, default=1
        """
        self.done += int(n)
        if self._bar is not None:
            self._bar.update(int(n))
            return
        now = self._clock()
        if now - self._last >= self.every and self.done < self.total:
            elapsed = now - self._t0
            left = elapsed * (self.total - self.done) / max(self.done, 1)
            self.stream.write(
                f"  ... {self.done}/{self.total} {self.what} "
                f"({100 * self.done / max(self.total, 1):.0f} %), {elapsed:.0f} s elapsed, "
                f"{about(left)} left\n")
            self.stream.flush()
            self._last = now

    def close(self) -> None:
        """Remove the bar (if any)."""
        if self._bar is not None:
            self._bar.close()
