"""Clocks with the ``now``/``sleep`` interface the driver's pacer, the fail-safe watchdog and the
timed emulator's ports share: wall time, wall time that never waits, and simulated time.

They live at the package root because both the device layer and the emulator use them, and neither may
import the other.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class MonotonicClock:
    """Wall time (``time.monotonic``) and real sleeps."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class InstantClock:
    """Wall time that never waits: for a device that consumes every byte the moment it is written (the
    untimed in-process emulator).  The pacer still keeps its books; ``skipped_s`` is what it would have
    waited on a real link."""

    def __init__(self) -> None:
        self.skipped_s = 0.0

    def now(self) -> float:
        # the waits that were skipped count as having passed, so the pacer's books stay consistent
        return time.monotonic() + self.skipped_s

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.skipped_s += seconds


class SimulatedClock:
    """Time that passes only when someone sleeps (or calls :meth:`advance`); ``on_advance`` lets a
    simulation run up to the new time."""

    def __init__(self, start: float = 0.0, on_advance: Callable[[float], None] | None = None) -> None:
        self._t = float(start)
        self.on_advance = on_advance

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.advance(seconds)

    def advance(self, seconds: float) -> None:
        self._t += seconds
        if self.on_advance is not None:
            self.on_advance(self._t)
