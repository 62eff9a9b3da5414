"""The eTactileKit driver over any pyserial-compatible port: a real path, a URL, or an in-process port.

It never knows which of these it holds.  Opening a real port must not reset the board: pyserial asserts
DTR and RTS on open, which an ESP32 can read as a reset request, so the port is created unopened, both
lines are set low, and only then is it opened.
"""

from __future__ import annotations

from typing import Any, Protocol

from ..errors import DeviceGoneError, DeviceTimeoutError, TactDeformError, TransportError
from ..protocol.constants import BAUD_RATE
from ..protocol.units import DEFAULT_TRANSFER, CurrentTransfer
from .audit import AuditLog
from .base import Device
from .mapping import ChannelMapping
from .pacing import Pacer, default_pacer
from .safety import SafetyGuard

DEFAULT_TIMEOUT_S = 0.5


class SerialLike(Protocol):
    """What the driver uses of a pyserial ``Serial``."""

    is_open: bool
    timeout: float | None

    def open(self) -> None: ...
    def close(self) -> None: ...
    def write(self, data: bytes) -> int | None: ...
    def read(self, size: int = 1) -> bytes: ...
    def reset_input_buffer(self) -> None: ...


def _serial_error_types() -> tuple[type[BaseException], ...]:
    import serial

    return (serial.SerialException, OSError)


def _lower_lines(port: SerialLike) -> None:
    """Set DTR and RTS low on an unopened port, so that opening it does not reset the board."""
    for line in ("dtr", "rts"):
        if hasattr(port, line):
            setattr(port, line, False)


class EtactileKitDevice(Device):
    """``port`` may be opened or not; an unopened one gets DTR/RTS low before it is opened."""

    def __init__(
        self,
        port: SerialLike,
        *,
        mapping: ChannelMapping | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        guard: SafetyGuard | None = None,
        pacer: Pacer | None = None,
        audit: AuditLog | None = None,
    ) -> None:
        super().__init__(mapping=mapping, transfer=transfer, guard=guard, pacer=pacer, audit=audit)
        self.port = port
        self._errors = _serial_error_types()
        if not port.is_open:
            _lower_lines(port)
            try:
                port.open()
            except self._errors as exc:
                self._closed = True
                raise TransportError(f"cannot open {getattr(port, 'port', port)!s}: {exc}") from exc
            except TactDeformError:
                self._closed = True
                raise
        if pacer is None:  # what a port needs is known only once it is open (a URL builds its device then)
            self.pacer = default_pacer(port)
        self._open_proof()  # a board in an unknown state: nothing is sent before it proves its parser

    def _write(self, data: bytes) -> None:
        try:
            written = self.port.write(data)
        except self._errors as exc:
            if type(exc).__name__ == "SerialTimeoutException":
                raise DeviceTimeoutError(f"write of {len(data)} byte(s) timed out") from exc
            raise DeviceGoneError(f"write failed: {exc}") from exc
        if written is not None and written != len(data):
            raise DeviceTimeoutError(f"wrote {written} of {len(data)} byte(s)")

    def _read(self, size: int) -> bytes:
        try:
            return bytes(self.port.read(size))
        except self._errors as exc:
            raise DeviceGoneError(f"read failed: {exc}") from exc

    def _waiting(self) -> int | None:
        try:
            waiting = getattr(self.port, "in_waiting", None)
        except self._errors as exc:
            raise DeviceGoneError(f"cannot poll input: {exc}") from exc
        return waiting if isinstance(waiting, int) else None

    def _discard_input(self) -> None:
        try:
            self.port.reset_input_buffer()
        except self._errors as exc:
            raise DeviceGoneError(f"cannot flush input: {exc}") from exc

    def _reopen_transport(self) -> None:
        try:
            self.port.close()
        except self._errors:
            pass
        _lower_lines(self.port)
        try:
            self.port.open()
        except self._errors as exc:
            raise DeviceGoneError(f"cannot reopen {getattr(self.port, 'port', self.port)!s}: {exc}") from exc

    def _can_reset(self) -> bool:
        if callable(getattr(self.port, "pulse_reset", None)):
            return True
        emulator = getattr(self.port, "emulator", None)
        if emulator is not None and callable(getattr(emulator, "reset", None)):
            return True
        return hasattr(self.port, "rts") and hasattr(self.port, "dtr")

    def _reset_transport(self) -> bool:
        """A port that models the reset line offers ``pulse_reset``; the in-process emulator is reset
        directly; a real ESP32-S3 on its USB Serial/JTAG port is held in reset while RTS is asserted with
        DTR released (the sequence esptool uses), so the pulse is RTS high for 100 ms."""
        pulse = getattr(self.port, "pulse_reset", None)
        if callable(pulse):
            try:
                pulse()
            except self._errors as exc:
                raise DeviceGoneError(f"cannot pulse the reset line: {exc}") from exc
            return True
        emulator = getattr(self.port, "emulator", None)
        if emulator is not None and callable(getattr(emulator, "reset", None)):
            emulator.reset()
            return True
        if not (hasattr(self.port, "rts") and hasattr(self.port, "dtr")):
            return False
        try:
            self.port.dtr = False
            self.port.rts = True
            self.pacer.clock.sleep(0.1)
            self.port.rts = False
        except self._errors as exc:
            raise DeviceGoneError(f"cannot pulse the reset line: {exc}") from exc
        return True

    def _close_transport(self) -> None:
        try:
            self.port.close()
        except self._errors:
            pass

    def __repr__(self) -> str:
        name = getattr(self.port, "port", None) or getattr(self.port, "name", None) or type(self.port).__name__
        return f"EtactileKitDevice({name!s}, closed={self._closed})"


def open_port(name: str, *, timeout: float = DEFAULT_TIMEOUT_S, baudrate: int = BAUD_RATE) -> Any:
    """An unopened pyserial port for a path, a URL, or ``emulator`` (the in-process emulator); or a
    pyserial-compatible USB port for ``usb:VID:PID[:SERIAL]`` (pyusb, no serial driver) and
    ``usb-emulator`` (the emulated board behind an emulated USB bus)."""
    import serial

    from .. import register_url_handlers
    from .usb_transport import is_usb_name, usb_port_for_name

    if is_usb_name(name):
        return usb_port_for_name(name, timeout=timeout, baudrate=baudrate)
    register_url_handlers()
    if name in ("emulator", "emu", ""):
        name = "etactile://"
    try:
        if "://" in name:
            port = serial.serial_for_url(name, do_not_open=True, baudrate=baudrate, timeout=timeout)
        else:
            port = serial.Serial(port=None, baudrate=baudrate, timeout=timeout, write_timeout=timeout)
            port.port = name
    except (serial.SerialException, ValueError) as exc:
        raise TransportError(f"cannot create port {name!r}: {exc}") from exc
    return port


def open_device(
    name: str = "emulator",
    *,
    timeout: float = DEFAULT_TIMEOUT_S,
    mapping: ChannelMapping | None = None,
    transfer: CurrentTransfer = DEFAULT_TRANSFER,
    guard: SafetyGuard | None = None,
    pacer: Pacer | None = None,
    audit: AuditLog | None = None,
) -> EtactileKitDevice:
    """Open a device by name: a serial port path, a pyserial URL, ``usb:VID:PID[:SERIAL]``,
    ``usb-emulator``, or ``emulator`` (the default).  ``pacer`` defaults to what the port needs (see
    :func:`~tactdeform_hw.device.pacing.default_pacer`); ``audit`` enables the session's audit log."""
    return EtactileKitDevice(
        open_port(name, timeout=timeout), mapping=mapping, transfer=transfer, guard=guard, pacer=pacer, audit=audit
    )
