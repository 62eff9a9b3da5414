"""Which port a device name opens: one table from URL scheme to the callable that makes the port.

=====================================  ===============================================================
name                                   port
=====================================  ===============================================================
``/dev/ttyACM0``, ``COM3`` (a path)    pyserial's ``Serial``, locked for this program and guardable
``emulator`` (or ``emu``, empty)       the in-process emulator, answering at once (``etactile://?timed=0``)
``etactile://[NAME][?options]``        the emulator's pyserial URL handler
``socket://HOST:PORT``                 pyserial's TCP port, guardable (a kit over Wi-Fi, ``emulate --tcp``)
``etactilekit://ID``                   the kit that answers UDP discovery with that id, over ``socket://``
``usb://303a:1001``, ``usb:303a:1001``  the pyusb CDC-ACM transport (extra ``[usb]``)
``usb-emulator[?options]``             that transport over an emulated bus in this process
``usb-emulator://PATH``                 that transport to the board ``emulate --usb`` serves on socket PATH
other ``SCHEME://…``                    pyserial's own URL handlers (``loop://``, ``rfc2217://``, …)
=====================================  ===============================================================

Each entry is ``"module:callable"``, imported only when a name with that scheme is opened, so an optional
dependency is needed only by the transport that uses it.  The callable takes ``(name, *, timeout,
baudrate)`` and returns an unopened pyserial-compatible port.  Other packages add schemes through the
``tactdeform_hw.transports`` entry-point group (python-can style)::

    [project.entry-points."tactdeform_hw.transports"]
    ble = "mypackage.ble:open_ble_port"

or at run time with :func:`register_transport`.  The table names the emulator's entries by string, which
is how the emulated USB device is reached without the device layer importing the emulator.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from .errors import MissingDependencyError, TransportError, TransportUnavailableError

ENTRY_POINT_GROUP = "tactdeform_hw.transports"

PortFactory = Callable[..., Any]

#: The schemes the package provides.
BUILTIN_TRANSPORTS: dict[str, str] = {
    "path": "tactdeform_hw.device.driver.serial_driver:open_serial_path",
    "etactile": "tactdeform_hw.transports:open_pyserial_url",
    "socket": "tactdeform_hw.transports:open_socket_port",
    "etactilekit": "tactdeform_hw.device.driver.serial_driver:open_kit_url",
    "usb": "tactdeform_hw.device.driver.usb_transport:usb_port_for_name",
    "usb-emulator": "tactdeform_hw.transports:open_usb_emulator",
}

#: The in-process emulator's short names.
EMULATOR_NAMES = ("emulator", "emu", "")
EMULATOR_URL = "etactile://?timed=0"

_registered: dict[str, str | PortFactory] = {}
_entry_points: dict[str, str] | None = None


def register_transport(scheme: str, target: str | PortFactory) -> None:
    """Make names with ``scheme`` open through ``target`` (a callable, or ``"module:callable"``
    imported when first used); a registration here takes precedence over the table and entry points."""
    _registered[scheme] = target


def _plugin_transports() -> dict[str, str]:
    global _entry_points
    if _entry_points is None:
        from importlib.metadata import entry_points

        _entry_points = {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)}
    return _entry_points


def scheme_of(name: str) -> str:
    """The transport scheme a device name selects (``"path"`` for a serial port path)."""
    if name == "usb-emulator" or name.startswith("usb-emulator?"):
        return "usb-emulator"
    if name.startswith("usb:"):
        return "usb"
    if "://" in name:
        return name.split("://", 1)[0]
    return "path"


def available_transports() -> dict[str, str]:
    """Every scheme that can be opened, with where its factory lives."""
    out = dict(BUILTIN_TRANSPORTS)
    for scheme, target in _plugin_transports().items():
        out.setdefault(scheme, target)
    for scheme, given in _registered.items():
        out[scheme] = given if isinstance(given, str) else f"{given.__module__}:{given.__qualname__}"
    return out


def _load(scheme: str, target: str) -> PortFactory:
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        if isinstance(exc, MissingDependencyError):
            raise
        raise TransportUnavailableError(scheme, target, exc) from exc
    try:
        factory: PortFactory = getattr(module, attr)
    except AttributeError as exc:
        raise TransportUnavailableError(scheme, target, exc) from exc
    return factory


def factory_for(scheme: str) -> PortFactory | None:
    """The callable that opens ``scheme``, or None when nothing provides it."""
    target: str | PortFactory | None = _registered.get(scheme)
    if target is None:
        target = BUILTIN_TRANSPORTS.get(scheme)
    if target is None:
        target = _plugin_transports().get(scheme)
    if target is None:
        return None
    return _load(scheme, target) if isinstance(target, str) else target


def port_for_name(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """An unopened port for a device name (see the module documentation)."""
    if name in EMULATOR_NAMES:
        name = EMULATOR_URL  # the in-process emulator answers at once
    scheme = scheme_of(name)
    factory = factory_for(scheme)
    if factory is None:
        factory = open_pyserial_url  # pyserial's own handlers, or its error naming the scheme
    return factory(name, timeout=timeout, baudrate=baudrate)


def open_pyserial_url(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """A pyserial URL (``etactile://``, ``socket://``, ``loop://``, …) as an unopened port; a
    ``socket://`` URL (also the one a kit's discovery resolves to) gets :func:`open_socket_port`'s port."""
    import serial

    from . import register_url_handlers

    if scheme_of(name) == "socket":
        return open_socket_port(name, timeout=timeout, baudrate=baudrate)

    register_url_handlers()
    try:
        return serial.serial_for_url(name, do_not_open=True, baudrate=baudrate, timeout=timeout)
    except (serial.SerialException, ValueError) as exc:
        raise TransportError(f"cannot create port {name!r}: {exc}") from exc


_socket_port_class: type | None = None


def socket_port_class() -> type:
    """:class:`SocketPort`: pyserial's ``socket://`` port declaring itself guardable (built on first use:
    pyserial is imported lazily)."""
    global _socket_port_class
    if _socket_port_class is not None:
        return _socket_port_class
    from serial.urlhandler import protocol_socket

    class SocketPort(protocol_socket.Serial):  # type: ignore[misc]  # pyserial ships no type information
        """A board's TCP connection (its Wi-Fi build).  A guardian process can share it: it inherits the
        socket's file descriptor, so the connection stays open until both the owner and the guardian have
        closed it — the board, which serves one client at a time, is nobody else's meanwhile.  It has no
        reset line: RTS and DTR do not travel over TCP."""

        guardable = True
        reset_line = False
        #: the board serves one connection at a time; a later one waits in its backlog unanswered
        serves_one_client = True

        def fileno(self) -> int:
            """The socket's file descriptor (what a guardian inherits)."""
            if not self.is_open or self._socket is None:
                raise protocol_socket.PortNotOpenError()
            return int(self._socket.fileno())

    _socket_port_class = SocketPort
    return SocketPort


def open_socket_port(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """``socket://HOST:PORT`` as an unopened :func:`socket_port_class` port (guardable)."""
    return unopened_port(socket_port_class(), name, timeout=timeout, baudrate=baudrate)


def unopened_port(port_class: Callable[..., Any], name: str, *, timeout: float | None, baudrate: int) -> Any:
    """A pyserial port of ``port_class`` named ``name`` but not yet opened (the device opens it); a name or
    setting pyserial refuses is a :class:`~tactdeform_hw.errors.TransportError` naming the port."""
    import serial

    try:
        port = port_class(port=None, baudrate=baudrate, timeout=timeout, write_timeout=timeout)
        port.port = name
    except (serial.SerialException, ValueError) as exc:
        raise TransportError(f"cannot create port {name!r}: {exc}") from exc
    return port


def open_usb_emulator(name: str, *, timeout: float | None, baudrate: int) -> Any:
    """``usb-emulator[?options]``: the pyusb transport (device layer) over an emulated bus in this process
    (the board dies with it); ``usb-emulator://PATH``: over a connection to the board that ``emulate --usb``
    serves on the Unix socket PATH (a board with a life of its own, shared as a real one is).  It sits here
    because neither layer may import the other."""
    from tactdeform_hw.device.driver.usb_transport import UsbCdcPort

    from .protocol.constants import ESP32S3_USB_JTAG_PID, ESPRESSIF_VID

    backend: Any
    if name.startswith("usb-emulator://"):
        from tactdeform_hw.emulator.serving.usb_client import EmulatorClientBackend

        path = name[len("usb-emulator://") :]
        try:
            backend = EmulatorClientBackend(path)
        except OSError as exc:
            raise TransportError(
                f"device={name!r}: no emulated USB board answers on {path} ({exc}); start one with "
                "`tactdeform-hw emulate --usb` and use the name it prints"
            ) from exc
    else:
        from tactdeform_hw.emulator.serving.usb_backend import backend_from_name

        backend = backend_from_name(name)
    return UsbCdcPort(
        ESPRESSIF_VID, ESP32S3_USB_JTAG_PID, backend=backend, timeout=timeout, write_timeout=timeout,
        baudrate=baudrate, name=name,
    )  # fmt: skip


__all__ = [
    "BUILTIN_TRANSPORTS",
    "ENTRY_POINT_GROUP",
    "available_transports",
    "factory_for",
    "open_socket_port",
    "port_for_name",
    "register_transport",
    "scheme_of",
    "unopened_port",
]
