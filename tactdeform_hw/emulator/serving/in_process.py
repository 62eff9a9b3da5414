"""A plain in-process port around an :class:`Emulator`: the smallest thing the driver can talk to.

It has the parts of pyserial's ``Serial`` the driver uses (``open``, ``close``, ``write``, ``read``,
``in_waiting``, ``out_waiting``, ``reset_input_buffer``, ``timeout``, ``dtr``, ``rts``), no more, so tests
run without pyserial's machinery.  Replies are available as soon as ``write`` returns; a read asks for
more than the device wrote returns what there is at once (in-process, waiting could not bring more).
The port declares that (``instant``, and ``pacing_clock``: a clock that never waits), so a driver paces
it without sleeping; it also declares ``pulse_reset()``, ``board_state()`` and ``board_hazards`` (see
:mod:`tactdeform_hw.ports`).
An optional ``spy`` callable sees every byte both ways with a timestamp.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from tactdeform_hw.clock import InstantClock
from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.hazards import Hazard
from tactdeform_hw.ports import PortBase
from tactdeform_hw.protocol.state import BoardState

SpyFn = Callable[[str, bytes, float], None]


class EmulatorPort(PortBase):
    instant = True  # every byte is parsed the moment it is written

    def __init__(
        self, emulator: Emulator | None = None, *, timeout: float | None = 0.5, spy: SpyFn | None = None
    ) -> None:
        self.emulator = emulator if emulator is not None else Emulator()
        self.timeout = timeout
        self.write_timeout: float | None = None
        self.is_open = False
        self.dtr = False
        self.rts = False
        self.port = "emulator"
        self.spy = spy
        self.bytes_written = 0
        self._rx = bytearray()  # device → host, not yet read
        self._lock = threading.Lock()
        self.pacing_clock = InstantClock()  # what a driver paces this port in: nothing to wait for

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    # --- what the port declares (tactdeform_hw.ports) -----------------------------------------------------

    def pulse_reset(self) -> None:
        """Power-cycle the board: its registers return to power-on, the parser to between commands."""
        self.emulator.reset()

    def board_state(self) -> BoardState:
        return self.emulator.state()

    @property
    def board_untouched(self) -> bool:
        """No byte has reached the board since its power-on (see :mod:`tactdeform_hw.ports`)."""
        return self.emulator.received_bytes == 0

    @property
    def board_hazards(self) -> list[Hazard]:
        return self.emulator.hazards

    def write(self, data: bytes) -> int:
        self._check_open()
        data = bytes(data)
        with self._lock:
            if self.spy:
                self.spy("tx", data, time.monotonic())
            # the waits the pacer skipped are the board's time: a v2 command cut before a wait times out
            at_us = int(self.pacing_clock.skipped_s * 1e6)
            reply = self.emulator.feed(data, at_us=at_us or None)
            self.bytes_written += len(data)
            if reply:
                if self.spy:
                    self.spy("rx", reply, time.monotonic())
                self._rx += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        self._check_open()
        with self._lock:
            out = bytes(self._rx[:size])
            del self._rx[:size]
        return out

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def reset_input_buffer(self) -> None:
        self._check_open()
        self._rx.clear()
