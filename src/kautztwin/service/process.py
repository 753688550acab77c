"""What the interpreter does behind a long-running service's loop: the cyclic garbage collector.

A full cyclic collection walks every object of the process while it holds the GIL.  With a
twin's libraries loaded (numpy, scipy, torch, asyncua, the store) that took 90 to 330 ms on
the 2-core development machine: 45 to 165 samples of the hydraulic drive at x10, during
which a twin's loop reads nothing (and the plant's input holds), a plant server publishes
nothing and then catches up in a burst, and an HTTP server answers nothing.  The objects
that exist once a service is built (modules, the twin, the link, the store, the server)
live as long as the service: :func:`freeze_garbage` leaves them out of later collections,
which then walk only the newer objects; :func:`thaw_garbage` gives them back when it stops.
"""

from __future__ import annotations

import gc

__all__ = ["freeze_garbage", "thaw_garbage"]


def freeze_garbage() -> None:
    """Collect once, then leave every object that exists now out of later collections.

    Call it when a service has built what lives as long as it does, before its loop runs
    (again after building more: each call freezes what was built since).

    Examples
    --------
    >>> import gc
    >>> from kautztwin.service.process import freeze_garbage, thaw_garbage
    >>> freeze_garbage()
    >>> gc.get_freeze_count() > 0
    True
    >>> thaw_garbage()
    >>> gc.get_freeze_count()
    0
    """
    gc.collect()  # no garbage is frozen
    gc.freeze()


def thaw_garbage() -> None:
    """Give the frozen objects back to the collector (a service that stops: they may be garbage).

    Examples
    --------
    >>> from kautztwin.service.process import thaw_garbage
    >>> thaw_garbage()
    """
    gc.unfreeze()
