"""The port a device drives: a pyserial-compatible object, and the link operations the driver needs of it.

The driver never knows whether it holds a real path, a URL or an in-process port; it asks the port what
it can do (:mod:`tactdeform_hw.ports`).  :class:`PortLink` turns the port's own errors into the package's
(:class:`~tactdeform_hw.errors.DeviceGoneError`, :class:`~tactdeform_hw.errors.DeviceTimeoutError`) and
knows how to open, reopen and reset it without resetting the board by accident: pyserial asserts DTR and
RTS on open, which an ESP32 can read as a reset request, so an unopened port gets both lines low first.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from typing import Any, Protocol

from tactdeform_hw.device.driver.holders import find_holders
from tactdeform_hw.errors import (
    DeviceBusyError,
    DeviceGoneError,
    DeviceTimeoutError,
    TactDeformError,
    TransportError,
)


class Port(Protocol):
    """What the driver uses of a pyserial ``Serial`` (optional capabilities: :mod:`tactdeform_hw.ports`)."""

    is_open: bool
    timeout: float | None

    def open(self) -> None: ...
    def close(self) -> None: ...
    def write(self, data: bytes) -> int | None: ...
    def read(self, size: int = 1) -> bytes: ...
    def reset_input_buffer(self) -> None: ...


def serial_error_types() -> tuple[type[BaseException], ...]:
    """The errors a pyserial port raises (pyserial is imported here, on first use)."""
    import serial

    return (serial.SerialException, OSError)


def lower_lines(port: Port) -> None:
    """Set DTR and RTS low on an unopened port, so that opening it does not reset the board."""
    for line in ("dtr", "rts"):
        if hasattr(port, line):
            setattr(port, line, False)


#: An ``open`` that fails with one of these found the port held by another program.
BUSY_ERRNOS = frozenset({errno.EWOULDBLOCK, errno.EAGAIN, errno.EBUSY, errno.EACCES})


def port_name(port: Any) -> str:
    """What to call ``port`` in a message: its path or URL, its name, or its type."""
    return str(getattr(port, "port", None) or getattr(port, "name", None) or type(port).__name__)


def no_delay(port: Any) -> None:
    """pyserial's ``socket://`` leaves Nagle's algorithm on: a one-byte request written after a small
    command then waits for the board's delayed acknowledgement (about 40 ms), longer than any reply's
    deadline.  The board's TCP server sets no delay too; so does the kit's own host library."""
    sock = getattr(port, "_socket", None)
    if sock is None:
        return
    import socket

    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except OSError:  # not a TCP socket
        pass


class PortLink:
    """A port and the operations the driver needs of it, each failure typed (see the module docstring).

    ``sleep`` times the reset line's pulse (the device's pacing clock)."""

    def __init__(self, port: Port, sleep: Callable[[float], None]) -> None:
        self.port = port
        self.sleep = sleep
        self.errors = serial_error_types()

    @property
    def name(self) -> str:
        return port_name(self.port)

    def open(self) -> None:
        """Open an unopened port with both lines low and, for a pyserial port left at its default, locked
        for this program; a port another program holds raises :class:`DeviceBusyError` naming it."""
        port = self.port
        lower_lines(port)
        if getattr(port, "exclusive", False) is None:  # a pyserial port left at its default: lock it too
            port.exclusive = True  # type: ignore[attr-defined]
        try:
            port.open()
        except self.errors as exc:
            name = str(getattr(port, "port", port))
            if getattr(exc, "errno", None) in BUSY_ERRNOS:
                raise DeviceBusyError(name, find_holders(name), str(exc)) from exc
            raise TransportError(f"cannot open {name}: {exc}") from exc
        except TactDeformError:
            raise

    def write(self, data: bytes) -> None:
        """Write one whole command (a partial or timed-out write raises)."""
        try:
            written = self.port.write(data)
        except self.errors as exc:
            if type(exc).__name__ == "SerialTimeoutException":
                raise DeviceTimeoutError(f"write of {len(data)} byte(s) timed out") from exc
            raise DeviceGoneError(f"write failed: {exc}") from exc
        if written is not None and written != len(data):
            raise DeviceTimeoutError(f"wrote {written} of {len(data)} byte(s)")

    def read(self, size: int) -> bytes:
        """Up to ``size`` bytes, honouring the port's timeout."""
        try:
            return bytes(self.port.read(size))
        except self.errors as exc:
            raise DeviceGoneError(f"read failed: {exc}") from exc

    def waiting(self) -> int | None:
        """Bytes from the board waiting to be read, if the port can tell (then replies are polled to
        their deadline instead of read with the port's own timeout)."""
        try:
            waiting = getattr(self.port, "in_waiting", None)
        except self.errors as exc:
            raise DeviceGoneError(f"cannot poll input: {exc}") from exc
        return waiting if isinstance(waiting, int) else None

    def discard_input(self) -> None:
        """Drop stale bytes waiting from the board."""
        try:
            self.port.reset_input_buffer()
        except self.errors as exc:
            raise DeviceGoneError(f"cannot flush input: {exc}") from exc

    def reopen(self) -> None:
        """Close and reopen the port (after the board vanished), both lines low before the open."""
        try:
            self.port.close()
        except self.errors:
            pass
        lower_lines(self.port)
        try:
            self.port.open()
        except self.errors as exc:
            raise DeviceGoneError(f"cannot reopen {getattr(self.port, 'port', self.port)!s}: {exc}") from exc

    def can_reset(self) -> bool:
        """Whether the port has a reset line (asked before draining for a reset)."""
        if not getattr(self.port, "reset_line", True):  # the port says it has none (TCP)
            return False
        if callable(getattr(self.port, "pulse_reset", None)):
            return True
        return hasattr(self.port, "rts") and hasattr(self.port, "dtr")

    def reset(self) -> bool:
        """Pulse the board's reset line; False when the port has none.  A port that models the line
        declares ``pulse_reset`` (every emulated board does); a real ESP32-S3 on its USB Serial/JTAG port
        is held in reset while RTS is asserted with DTR released (the sequence esptool uses), so the pulse
        is RTS high for 100 ms."""
        if not self.can_reset():
            return False
        pulse = getattr(self.port, "pulse_reset", None)
        if callable(pulse):
            try:
                pulse()
            except self.errors as exc:
                raise DeviceGoneError(f"cannot pulse the reset line: {exc}") from exc
            return True
        if not (hasattr(self.port, "rts") and hasattr(self.port, "dtr")):
            return False
        try:
            self.port.dtr = False
            self.port.rts = True
            self.sleep(0.1)
            self.port.rts = False
        except self.errors as exc:
            raise DeviceGoneError(f"cannot pulse the reset line: {exc}") from exc
        return True

    def close(self) -> None:
        """Release the port (its own errors on close are of no use to anyone)."""
        try:
            self.port.close()
        except self.errors:
            pass


__all__ = ["BUSY_ERRNOS", "Port", "PortLink", "lower_lines", "no_delay", "port_name", "serial_error_types"]
