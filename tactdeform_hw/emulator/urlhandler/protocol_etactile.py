"""``etactile://[NAME][?board=compact|large&switching_boards=N&stack_reading=R&firmware=v1.2|v2&spy=1]``

The emulated eTactileKit as a pyserial port, so ``serial.serial_for_url("etactile://")`` gives the same
object type, exceptions and calls as a real board on ``/dev/ttyACM0``.  With a ``NAME``, every port opened
with that name in this process talks to one shared emulator (like a named virtual bus), so a test can
open a second handle to inspect or disturb the same device.  ``spy=1`` hex-dumps every byte both ways
with timestamps to stderr.  Unknown options are rejected.
"""

from __future__ import annotations

import sys
import threading
import time
import urllib.parse as urlparse
from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from ...errors import ConfigurationError
from ..core import Emulator

_shared: dict[str, Emulator] = {}
_shared_lock = threading.Lock()


def shared_emulator(name: str) -> Emulator | None:
    """The emulator behind ``etactile://NAME`` if one was opened in this process."""
    return _shared.get(name)


def forget_shared(name: str | None = None) -> None:
    """Drop one (or every) named emulator, e.g. between tests."""
    with _shared_lock:
        if name is None:
            _shared.clear()
        else:
            _shared.pop(name, None)


class Serial(SerialBase):  # type: ignore[misc]  # pyserial ships no type information: SerialBase is Any
    """pyserial port backed by an in-process :class:`Emulator`."""

    is_open: bool  # set by SerialBase.__init__; declared so the checker knows its type

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.emulator: Emulator | None = None
        self._rx = bytearray()
        self._lock = threading.Lock()
        self._spy = False
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        self.emulator = self.from_url(self.port)
        self._rx.clear()
        self.is_open = True

    def close(self) -> None:
        self.is_open = False
        super().close()

    def from_url(self, url: str) -> Emulator:
        parts = urlparse.urlsplit(url)
        if parts.scheme != "etactile":
            raise SerialException(f"expected etactile://[NAME][?options], not {url!r}")
        opts: dict[str, str] = {}
        for option, values in urlparse.parse_qs(parts.query, keep_blank_values=True).items():
            if option not in ("board", "switching_boards", "stack_reading", "firmware", "spy"):
                raise SerialException(
                    f"unknown option {option!r} in {url!r} (known: board, switching_boards, stack_reading, firmware, spy)"
                )
            opts[option] = values[-1]
        try:
            board = opts.get("board", "compact")
            switching = int(opts.get("switching_boards", "1"))
            reading = float(opts["stack_reading"]) if "stack_reading" in opts else None
            firmware = opts.get("firmware", "v1.2")
        except ValueError as exc:
            raise SerialException(f"bad option value in {url!r}: {exc}") from exc
        self._spy = opts.get("spy", "0") not in ("0", "", "false", "no")
        name = (parts.netloc + parts.path).strip("/")
        try:
            if not name:
                return Emulator(board, switching, stack_reading=reading, firmware=firmware)
            with _shared_lock:
                emu = _shared.get(name)
                if emu is None:
                    emu = _shared[name] = Emulator(board, switching, stack_reading=reading, firmware=firmware)
                return emu
        except (ValueError, ConfigurationError) as exc:
            raise SerialException(str(exc)) from exc

    def _reconfigure_port(self) -> None:
        """Line settings mean nothing to an in-process device (on native USB the baud rate is nominal)."""

    def _dump(self, direction: str, data: bytes) -> None:
        if self._spy and data:
            sys.stderr.write(f"{time.monotonic():.6f} {direction} {data.hex(' ')}\n")

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        return len(self._rx)

    @property
    def out_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        return 0

    def read(self, size: int = 1) -> bytes:
        """Replies exist as soon as the write that caused them returned; nothing else can arrive, so a
        short read returns at once instead of sleeping out the timeout."""
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            out = bytes(self._rx[:size])
            del self._rx[:size]
        return out

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        assert self.emulator is not None
        data = bytes(data)
        with self._lock:
            self._dump("host->dev", data)
            reply = self.emulator.feed(data)
            self._dump("dev->host", reply)
            self._rx += reply
        return len(data)

    def reset_input_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            self._rx.clear()

    def reset_output_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()

    def _update_break_state(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
