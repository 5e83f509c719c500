"""Time for the tether code: the system clock, or a virtual one shared with the emulator.

Every wait in the drivers and flows goes through a clock (``now()``, ``sleep()``),
so that an emulated camera and the host can share a :class:`VirtualClock`: the
host's waits advance the emulator's time, and a camera that is busy for
seconds costs no real time in the tests.
"""

from __future__ import annotations

import time


class SystemClock:
    """``time.monotonic`` and ``time.sleep``."""

    def now(self) -> float:
        """Seconds on a monotonic clock."""
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (nothing for <= 0)."""
        if seconds > 0:
            time.sleep(seconds)


class VirtualClock:
    """A clock that only moves when someone sleeps or calls :meth:`advance`.

    Parameters
    ----------
    start : float
        Initial time, s.
    """

    def __init__(self, start: float = 0.0) -> None:
        self.t = float(start)

    def now(self) -> float:
        """The virtual time, s."""
        return self.t

    def sleep(self, seconds: float) -> None:
        """Advance the virtual time by ``seconds`` (at once)."""
        self.advance(seconds)

    def advance(self, seconds: float) -> None:
        """Move time forward (negative values are ignored)."""
        if seconds > 0:
            self.t += seconds


SYSTEM_CLOCK = SystemClock()
