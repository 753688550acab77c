"""The Temperature Control Lab (emulator or real board) as a twin plant."""

from __future__ import annotations

import contextlib
import io
import math
from typing import Any

import numpy as np

from ..._validation import check_nonnegative, check_positive
from ...exceptions import DataError
from .base import Reading, clip_input
from .clock import Clock

__all__ = ["TCLabPlant"]

_TCLAB_NOISE = 0.043  # standard deviation of tclab's emulated thermistor noise, °C


class TCLabPlant:
    """The Temperature Control Lab (heater -> temperature) through the ``tclab`` package.

    With ``connected=False`` (default) the plant is ``tclab.TCLabModel``, the
    package's emulator of the board (two heaters, two thermistors, a
    fourth-order heat-transfer model), driven on a simulated clock: its
    ``update(t)`` integrates to the plant time of each sample, so a run goes as
    fast as the CPU allows (or paced by a real-time ``clock``).  With
    ``connected=True`` the same code path drives a real board through
    ``tclab.TCLab`` (serial port) in real time.

    Parameters
    ----------
    dt : float, default=1.0
        Sampling period, s.
    connected : bool, default=False
        Use a real board (``tclab.TCLab``) instead of the emulator.
    heater : {1, 2}, default=1
        Which heater/thermistor pair is the input/output (``Q1``/``T1`` or ``Q2``/``T2``).
    clock : Clock, optional
        Pacing.  Emulator: as fast as possible when omitted.  Real board: a
        real-time clock (the default); a faster clock is an error.
    noise : float, default=0.043
        Emulator only: standard deviation of the thermistor noise, °C (tclab's
        own value).  It is drawn from ``random_state`` (tclab draws from the
        global ``random`` module, which would make runs irreproducible); the
        reading is then quantised as tclab does.
    port : str, default=''
        Real board only: serial port ('' searches for the board).
    random_state : int, numpy.random.Generator or None, default=None
        Seed of the emulator's noise.
    name : str, default='tclab'
        Name of the plant.

    Raises
    ------
    ImportError
        If the ``tclab`` package is missing (``pip install 'kautztwin[tclab]'``).
    DataError
        If ``heater`` or ``dt`` is invalid, or a real board is asked to run
        faster than real time.

    Attributes
    ----------
    input_limits : tuple of float
        ``(0.0, 100.0)``: heater power in percent.

    See Also
    --------
    HydraulicPlant, ReplayPlant : The other plants.

    Notes
    -----
    The emulator is driven through its documented attributes of tclab 1.0:
    ``TCLabModel(synced=False)``, ``Q1``/``Q2``, ``update(t)``, ``quantize``
    and the noise-free thermistor temperatures ``_T1``/``_T2``.  tclab prints
    a banner on connection; it is suppressed.  ``meta`` holds ``u``, ``k``,
    ``y_true`` (emulator only) and ``lateness`` (s behind the real-time clock).

    Examples
    --------
    >>> from kautztwin.twin.physical import TCLabPlant
    >>> lab = TCLabPlant(dt=1.0, random_state=0)
    >>> r0 = lab.reset()
    >>> readings = [lab.step(100.0) for _ in range(120)]
    >>> readings[-1].t, bool(readings[-1].y > r0.y + 2.0)
    (120.0, True)
    >>> lab.close()
    """

    input_limits: tuple[float, float] = (0.0, 100.0)

    def __init__(
        self,
        *,
        dt: float = 1.0,
        connected: bool = False,
        heater: int = 1,
        clock: Clock | None = None,
        noise: float = _TCLAB_NOISE,
        port: str = "",
        random_state: int | np.random.Generator | None = None,
        name: str = "tclab",
    ) -> None:
        try:
            import tclab
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "TCLabPlant needs the tclab package: pip install 'kautztwin[tclab]'"
            ) from exc
        self._tclab = tclab
        self.dt = check_positive(dt, "dt")
        if heater not in (1, 2):
            raise DataError(f"heater must be 1 or 2, got {heater!r}")
        self.heater = int(heater)
        self.connected = bool(connected)
        if clock is None:
            clock = Clock.real_time() if self.connected else Clock()
        if self.connected and not (clock.realtime and clock.speedup == 1.0):
            raise DataError(
                "a real TCLab board runs in real time: pass clock=Clock.real_time() (speedup 1)"
            )
        self.clock = clock
        self.noise = check_nonnegative(noise, "noise")
        self.port = str(port)
        self.random_state = random_state
        self.name = str(name)
        self._lab: Any = None
        self.reset()

    def _quiet(self) -> contextlib.AbstractContextManager[Any]:
        return contextlib.redirect_stdout(io.StringIO())

    def _set_heater(self, value: float) -> None:
        (self._lab.Q1 if self.heater == 1 else self._lab.Q2)(value)

    def reset(self) -> Reading:
        """Start a new run and return the reading at ``t = 0``.

        The emulator restarts from ambient temperature (a fresh
        ``TCLabModel``).  A real board cannot be reset: its heaters are
        switched off and the clock restarts; wait for it to cool first when a
        run needs to start from ambient.

        Returns
        -------
        Reading
        """
        self._k = 0
        self._rng = np.random.default_rng(self.random_state)
        with self._quiet():
            if self.connected:
                if self._lab is None:
                    self._lab = self._tclab.TCLab(port=self.port)
                self._set_heater(0.0)
            else:
                if self._lab is not None:
                    self._lab.close()
                self._lab = self._tclab.TCLabModel(synced=False)
                self._origin = float(self._lab.tlast)  # the emulator's own time origin
        self.clock.start()
        return self._read(math.nan, 0.0)

    def step(self, u: float | None) -> Reading:
        """Set the heater to ``u`` percent for one period and return the next reading.

        Parameters
        ----------
        u : float
            Heater power, %, clipped to ``[0, 100]``.

        Returns
        -------
        Reading

        Raises
        ------
        DataError
            If ``u`` is not a finite number.
        """
        v = clip_input(u, self.input_limits, self.name)
        self._set_heater(v)
        self._k += 1
        t1 = self._k * self.dt
        late = self.clock.wait_until(t1)
        if not self.connected:
            self._lab.update(self._origin + t1)
        return self._read(v, late)

    def _read(self, u: float, late: float) -> Reading:
        meta: dict[str, Any] = {"u": u, "k": self._k, "lateness": late}
        if self.connected:
            y = float(self._lab.T1 if self.heater == 1 else self._lab.T2)
        else:
            y_true = float(self._lab._T1 if self.heater == 1 else self._lab._T2)
            y = float(self._lab.quantize(y_true + self.noise * self._rng.standard_normal()))
            meta["y_true"] = y_true
        return Reading(self._k * self.dt, y, meta)

    def close(self) -> None:
        """Switch the heaters off and release the board (or the emulator)."""
        if self._lab is not None:
            with self._quiet():
                self._lab.close()
            self._lab = None

    def __repr__(self) -> str:
        kind = "board" if self.connected else "emulator"
        return f"TCLabPlant({kind}, dt={self.dt:g}, heater={self.heater}, clock={self.clock!r})"
