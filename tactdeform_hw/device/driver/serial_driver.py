"""The eTactileKit driver over any pyserial-compatible port: a real path, a URL, or an in-process port.

It never knows which of these it holds; it asks the port what it can do.  Opening a real port must not
reset the board: pyserial asserts DTR and RTS on open, which an ESP32 can read as a reset request, so the
port is created unopened, both lines are set low, and only then is it opened.

**One owner per board.**  A port opened by path (:class:`ExclusivePort`) is locked before its first byte:
``flock(LOCK_EX | LOCK_NB)`` (pyserial's ``exclusive=True``), then ``TIOCEXCL``, which makes the kernel
refuse any further open of the terminal to everyone but root.  A second program — another command, or a
script using the library — gets :class:`~tactdeform_hw.errors.DeviceBusyError` naming the device and the
process holding it (from ``/proc/locks`` and ``/proc/*/fd``); nothing is written.  The lock belongs to the
open file description, which the owner's guardian (:mod:`.guardian`) shares, so it outlives an owner
killed with SIGKILL until the guardian has switched the board off.

**A guardian per guardable port.**  A port that declares ``guardable = True`` gets a guardian process
when the device opens (see :mod:`.guardian`): it switches the board off if the owner dies without running
code.  The in-process emulator declares nothing: the board it models dies with the process.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

from tactdeform_hw.device.driver.base import Device, DeviceOptions
from tactdeform_hw.device.driver.firmware_probe import FIRMWARE_CHOICES, check_firmware_choice
from tactdeform_hw.device.driver.holders import find_holders
from tactdeform_hw.device.links.port import BUSY_ERRNOS, Port
from tactdeform_hw.errors import DeviceBusyError
from tactdeform_hw.protocol.constants import BAUD_RATE

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing's own from Python 3.11

DEFAULT_TIMEOUT_S = 0.5


#: What the driver uses of a pyserial ``Serial`` (the name this module gave :class:`Port` first).
SerialLike = Port


_exclusive_port_class: type | None = None


def exclusive_port_class() -> type:
    """:class:`ExclusivePort`: pyserial's ``Serial`` that locks the port before its first byte and declares
    itself guardable (built on first use: pyserial is imported lazily)."""
    global _exclusive_port_class
    if _exclusive_port_class is not None:
        return _exclusive_port_class
    import serial

    if sys.platform == "win32":  # pragma: no cover - Windows opens a COM port for one program only anyway
        _exclusive_port_class = serial.Serial
        return _exclusive_port_class
    import fcntl
    import termios

    class ExclusivePort(serial.Serial):  # type: ignore[misc]  # pyserial ships no type information
        """A serial port opened by path, owned by one program at a time (see the module docstring)."""

        #: A guardian process can share this port (an inheritable file descriptor to a terminal).
        guardable = True

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            kwargs["exclusive"] = True
            super().__init__(*args, **kwargs)

        def open(self) -> None:
            try:
                super().open()
            except serial.SerialException as exc:
                if getattr(exc, "errno", None) in BUSY_ERRNOS:
                    raise DeviceBusyError(str(self.port), find_holders(str(self.port)), str(exc)) from exc
                raise
            try:
                fcntl.ioctl(self.fd, termios.TIOCEXCL)
            except OSError:  # not a terminal: the flock alone guards it
                pass

        def close(self) -> None:
            fd = getattr(self, "fd", None)
            if self.is_open and fd is not None:
                try:
                    fcntl.ioctl(fd, termios.TIOCNXCL)  # the next owner may open it (a pty outlives us)
                except OSError:
                    pass
            super().close()

    _exclusive_port_class = ExclusivePort
    return ExclusivePort


#: The device over any pyserial-compatible port (one class: :class:`~.base.Device`).
EtactileKitDevice = Device


def open_port(name: str, *, timeout: float = DEFAULT_TIMEOUT_S, baudrate: int = BAUD_RATE) -> Any:
    """An unopened pyserial port for a path, a URL, or ``emulator`` (the in-process emulator); or a
    pyserial-compatible USB port for ``usb://VID:PID[:SERIAL]`` (pyusb, no serial driver) and
    ``usb-emulator`` (the emulated board behind an emulated USB bus).  The scheme picks the transport
    from :mod:`tactdeform_hw.transports`, which other packages extend."""
    from tactdeform_hw.transports import port_for_name

    return port_for_name(name, timeout=timeout, baudrate=baudrate)


def open_serial_path(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """A serial port path as an unopened :func:`exclusive_port_class` port (locked on open, guardable)."""
    from tactdeform_hw.transports import unopened_port

    return unopened_port(exclusive_port_class(), name, timeout=timeout, baudrate=baudrate)


def open_kit_url(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """``etactilekit://ID[?discovery=HOST:PORT]``: the ``socket://`` port of the kit discovery finds."""
    from tactdeform_hw.transports import open_pyserial_url

    return open_pyserial_url(_resolve_kit(name), timeout=timeout, baudrate=baudrate)


def _resolve_kit(url: str) -> str:
    """``etactilekit://ID[?discovery=HOST:PORT]`` → the ``socket://IP:PORT`` of the one kit that answers
    UDP discovery with that id (default: the subnet broadcast on 8888)."""
    import urllib.parse as urlparse

    from tactdeform_hw.device.driver.wifi_discovery import DISCOVERY_PORT, discover, resolve
    from tactdeform_hw.errors import ConfigurationError

    parts = urlparse.urlsplit(url)
    kit_id = (parts.netloc + parts.path).strip("/")
    if not kit_id:
        raise ConfigurationError(f"{url!r}: expected etactilekit://ID (the id discovery reports)")
    query = urlparse.parse_qs(parts.query)
    target = ("255.255.255.255", DISCOVERY_PORT)
    if "discovery" in query:
        host, _, port = query["discovery"][-1].rpartition(":")
        try:
            target = (host or "127.0.0.1", int(port))
        except ValueError as exc:
            raise ConfigurationError(
                f"{url!r}: discovery={query['discovery'][-1]!r} is not HOST:PORT"
            ) from exc
    unknown = set(query) - {"discovery"}
    if unknown:
        raise ConfigurationError(
            f"{url!r}: unknown option(s) {', '.join(sorted(unknown))} (known: discovery)"
        )
    return resolve(kit_id, discover([target])).url


def open_device(
    name: str = "emulator", *, timeout: float = DEFAULT_TIMEOUT_S, **options: Unpack[DeviceOptions]
) -> EtactileKitDevice:
    """Open a device by name: a serial port path, a pyserial URL, ``usb:VID:PID[:SERIAL]``,
    ``usb-emulator``, or ``emulator`` (the default), with the :class:`~.base.Device` constructor's keyword
    options (:class:`~.base.DeviceOptions`).  ``pacer`` defaults to what the port needs (see
    :func:`~tactdeform_hw.device.driver.pacing.default_pacer`); ``audit`` enables the session's audit log.  A
    port path is locked for this program alone (:class:`~tactdeform_hw.errors.DeviceBusyError` if another
    holds it) and gets a guardian process (``guardian=False`` to do without).  ``offline_clock``: when the
    port declares itself ``instant`` (it answers every byte at once), pace on this clock instead of the wall
    clock, so an offline run keeps session time.

    ``robust_encoding=True``: the loss-tolerant encoding, for any link that can lose bytes (a USB-to-UART
    bridge, a raw UART): a lost byte can then only lower a value or leave it, where under the plain
    encoding one lost byte can set a full-scale pulse until the fail-safe's recovery (docs/safety.md).
    Native USB CDC (CRC-checked) and Wi-Fi/TCP do not lose bytes silently.  ``False``: the plain
    encoding; None (the default): the port's own (plain on every real port).

    ``firmware``: "auto" (the default) drives the version the board proves; "v1.2" or "v2" drives only
    that version and refuses a board that proves the other.  Either way the board is identified first
    (:mod:`.firmware_probe`: v2's command timeout waited out, every current off, then a reply only one
    version gives); silence, a busy board or an answer neither version gives is a refusal naming the
    device, never a default.  Every refusal is a
    :class:`~tactdeform_hw.device.driver.firmware_probe.FirmwareMismatchError` (or, on a board that serves one
    client at a time, :class:`~tactdeform_hw.errors.BoardBusyError`), raised after only bytes that stop
    current on both versions.

    ``settle_s``: how long nothing is written before the identification (default:
    :data:`~.firmware_probe.SETTLE_S`, v2's command timeout and a margin, or 0 on a port that declares its
    board untouched since power-on).  Shorter is safe only when no other program can have written to the
    board since its power-on or since a session that ended with a proved ``close``: a v2 pattern an
    earlier program left cut would otherwise be completed, its heights with it."""
    unknown = sorted(options.keys() - DeviceOptions.__optional_keys__)
    if unknown:  # refused before any port exists, as a misspelt parameter always was
        raise TypeError(f"open_device() got an unexpected keyword argument {unknown[0]!r}")
    if "firmware" in options:
        check_firmware_choice(options["firmware"])
    guard = options.get("guard")
    if guard is not None:
        # calibrated limits bind hardware channels: a mapping that wires an electrode elsewhere is refused
        # before the port is opened
        guard.check_wiring(options.get("mapping"))
    port = open_port(name, timeout=timeout)
    return EtactileKitDevice(port, **options)


__all__ = [
    "DEFAULT_TIMEOUT_S",
    "FIRMWARE_CHOICES",
    "EtactileKitDevice",
    "SerialLike",
    "check_firmware_choice",
    "exclusive_port_class",
    "find_holders",
    "open_device",
    "open_kit_url",
    "open_port",
    "open_serial_path",
]
