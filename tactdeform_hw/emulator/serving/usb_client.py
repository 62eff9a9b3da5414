"""A pyusb backend that reaches an emulated board served by another process (``emulate --usb``).

The board of ``tactdeform-hw emulate --usb`` lives in the server's process, as a real board lives on its
bus: it survives the programs that use it, and every program sees the same one.  Each
:class:`EmulatorClientBackend` is one connection to the server's Unix socket, and the server treats a
connection as the kernel treats a process's usbfs file: interfaces it claimed are its own until it
releases them or the connection closes — which the kernel does for a process that dies, however it dies.
So a second program's claim fails as busy (libusb's ``LIBUSB_ERROR_BUSY``), and a killed owner's claim is
released at once, which is what lets its guardian take the board.

Wire format (both ways): a 4-byte big-endian length, then a JSON object.  A request names ``op`` and its
arguments; bytes travel as hex.  The answer is ``{"ok": value}`` or ``{"err": kind}`` (a libusb error
kind, raised as pyusb's ``USBError`` with libusb's code and errno) or ``{"notimpl": text}``.

This file imports only the standard library and pyusb, and nothing of the package, so the USB guardian
can load it by path and start fast.
"""

from __future__ import annotations

import errno
import json
import socket
import struct
import threading
from typing import Any

#: libusb error kinds: (libusb code, errno pyusb's libusb1 backend attaches, libusb's message)
LIBUSB_ERRORS: dict[str, tuple[int, int, str]] = {
    "io": (-1, errno.EIO, "Input/output error"),
    "invalid": (-2, errno.EINVAL, "Invalid parameter"),
    "access": (-3, errno.EACCES, "Access denied (insufficient permissions)"),
    "no_device": (-4, errno.ENODEV, "No such device (it may have been disconnected)"),
    "not_found": (-5, errno.ENOENT, "Entity not found"),
    "busy": (-6, errno.EBUSY, "Resource busy"),
    "timeout": (-7, errno.ETIMEDOUT, "Operation timed out"),
    "overflow": (-8, errno.EOVERFLOW, "Overflow"),
    "pipe": (-9, errno.EPIPE, "Pipe error"),
}
ERROR_KINDS = {code: kind for kind, (code, _, _) in LIBUSB_ERRORS.items()}

#: The device-name prefix of a served board: ``usb-emulator://`` + the socket's absolute path.
SERVED_PREFIX = "usb-emulator://"
_MAX_MESSAGE = 1 << 20


def send_message(sock: socket.socket, obj: Any) -> None:
    data = json.dumps(obj, separators=(",", ":")).encode()
    sock.sendall(struct.pack(">I", len(data)) + data)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("the emulated USB board's server closed the connection")
        buf += chunk
    return bytes(buf)


def recv_message(sock: socket.socket) -> Any:
    (n,) = struct.unpack(">I", _recv_exact(sock, 4))
    if n > _MAX_MESSAGE:
        raise ConnectionError(f"message of {n} bytes from the emulated USB board's peer: too long")
    return json.loads(_recv_exact(sock, n))


class _Descriptor:
    """A descriptor as pyusb reads it: plain attributes (sent by the server as a dict)."""

    def __init__(self, fields: dict[str, Any]) -> None:
        self.__dict__.update(fields)

    def __getattr__(self, name: str) -> Any:  # only called for a field the server did not send
        raise AttributeError(name)


class _RemoteDevice:
    def __init__(self, index: int, device: dict[str, Any], config: dict[str, Any]) -> None:
        self.index = index
        fields = dict(device)
        fields["port_numbers"] = tuple(fields.get("port_numbers", ()))
        self.descriptor = _Descriptor(fields)
        self.interfaces = [
            (
                _Descriptor({k: v for k, v in i.items() if k != "endpoints"}),
                [_Descriptor(e) for e in i["endpoints"]],
            )
            for i in config["interfaces"]
        ]
        self.config = _Descriptor({k: v for k, v in config.items() if k != "interfaces"})


class _RemoteHandle:
    def __init__(self, handle_id: int) -> None:
        self.id = handle_id


class EmulatedBoardBackend:
    """What the two pyusb backends of the emulated board share (the bus in this process,
    :class:`~.usb_backend.EmulatedUsbBackend`, and the connection to a served one,
    :class:`EmulatorClientBackend`): a failure raised as pyusb raises libusb's, with libusb's code and
    errno, so that the transport and the guardian see the same error on both; and the endpoints the
    ESP32-S3 does not have (no isochronous endpoint, no interrupt OUT) answer "not found" on both."""

    _usb_error: type[Exception]
    _usb_timeout: type[Exception]

    def _error(self, kind: str) -> Exception:
        code, err, text = LIBUSB_ERRORS.get(kind, LIBUSB_ERRORS["io"])
        cls = self._usb_timeout if kind == "timeout" else self._usb_error
        return cls(text, code, err)

    def intr_write(self, dev_handle: Any, ep: int, intf: int, data: Any, timeout: int) -> int:
        raise self._error("not_found")

    def iso_write(self, dev_handle: Any, ep: int, intf: int, data: Any, timeout: int) -> int:
        raise self._error("not_found")

    def iso_read(self, dev_handle: Any, ep: int, intf: int, buff: Any, timeout: int) -> int:
        raise self._error("not_found")


class EmulatorClientBackend(EmulatedBoardBackend):
    """A pyusb backend over a connection to ``emulate --usb``'s socket at ``path`` (connected at once:
    an ``OSError`` says nobody serves there)."""

    def __init__(self, path: str, *, connect_timeout_s: float = 5.0) -> None:
        import usb.core

        self._usb_error: type[Exception] = usb.core.USBError
        self._usb_timeout: type[Exception] = usb.core.USBTimeoutError
        self.path = path
        self._lock = threading.Lock()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(connect_timeout_s)
        try:
            sock.connect(path)
        except OSError:
            sock.close()
            raise
        sock.settimeout(None)
        self._sock: socket.socket | None = sock

    @property
    def name(self) -> str:
        return SERVED_PREFIX + self.path

    def guardian_backend(self) -> str:
        """How a guardian process reaches the same bus (see
        :mod:`tactdeform_hw.device.safety.usb_guardian`)."""
        return "emulator:" + self.path

    def close(self) -> None:
        """Close the connection: the server releases every claim it held, as the kernel does for a
        process that exits."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def _call(self, op: str, **args: Any) -> Any:
        with self._lock:
            if self._sock is None:
                raise self._error("no_device")
            try:
                send_message(self._sock, {"op": op, **args})
                reply = recv_message(self._sock)
            except (OSError, ValueError):  # the server is gone: so is the board on its bus
                raise self._error("no_device") from None
        if "ok" in reply:
            return reply["ok"]
        if "notimpl" in reply:
            raise NotImplementedError(reply["notimpl"])
        raise self._error(str(reply.get("err", "io")))

    # --- IBackend: enumeration and descriptors --------------------------------------------------------

    def enumerate_devices(self) -> list[_RemoteDevice]:
        return [_RemoteDevice(d["index"], d["device"], d["config"]) for d in self._call("devices")]

    def get_parent(self, dev: _RemoteDevice) -> None:
        return None

    def get_device_descriptor(self, dev: _RemoteDevice) -> _Descriptor:
        return dev.descriptor

    def get_configuration_descriptor(self, dev: _RemoteDevice, config: int) -> _Descriptor:
        if config != 0:
            raise IndexError(f"Invalid configuration index {config}")
        return dev.config

    def _alternates(self, dev: _RemoteDevice, intf: int) -> list[tuple[_Descriptor, list[_Descriptor]]]:
        numbers = sorted({i.bInterfaceNumber for i, _ in dev.interfaces})
        if not 0 <= intf < len(numbers):
            raise IndexError(f"Invalid interface index {intf}")
        return [(i, eps) for i, eps in dev.interfaces if i.bInterfaceNumber == numbers[intf]]

    def get_interface_descriptor(self, dev: _RemoteDevice, intf: int, alt: int, config: int) -> _Descriptor:
        self.get_configuration_descriptor(dev, config)
        alts = self._alternates(dev, intf)
        if not 0 <= alt < len(alts):
            raise IndexError(f"Invalid alternate setting index {alt}")
        return alts[alt][0]

    def get_endpoint_descriptor(
        self, dev: _RemoteDevice, ep: int, intf: int, alt: int, config: int
    ) -> _Descriptor:
        self.get_interface_descriptor(dev, intf, alt, config)
        eps = self._alternates(dev, intf)[alt][1]
        if not 0 <= ep < len(eps):
            raise IndexError(f"Invalid endpoint index {ep}")
        return eps[ep]

    # --- IBackend: handles, configuration, interfaces ---------------------------------------------------

    def open_device(self, dev: _RemoteDevice) -> _RemoteHandle:
        return _RemoteHandle(int(self._call("open", dev=dev.index)))

    def close_device(self, dev_handle: _RemoteHandle) -> None:
        try:
            self._call("close", h=dev_handle.id)
        except self._usb_error:
            pass  # the server is gone: nothing is held there any more

    def set_configuration(self, dev_handle: _RemoteHandle, config_value: int) -> None:
        self._call("set_configuration", h=dev_handle.id, value=config_value)

    def get_configuration(self, dev_handle: _RemoteHandle) -> int:
        return int(self._call("get_configuration", h=dev_handle.id))

    def set_interface_altsetting(self, dev_handle: _RemoteHandle, intf: int, altsetting: int) -> None:
        self._call("set_interface_altsetting", h=dev_handle.id, intf=intf, alt=altsetting)

    def claim_interface(self, dev_handle: _RemoteHandle, intf: int) -> None:
        self._call("claim_interface", h=dev_handle.id, intf=intf)

    def release_interface(self, dev_handle: _RemoteHandle, intf: int) -> None:
        self._call("release_interface", h=dev_handle.id, intf=intf)

    def is_kernel_driver_active(self, dev_handle: _RemoteHandle, intf: int) -> bool:
        return bool(self._call("is_kernel_driver_active", h=dev_handle.id, intf=intf))

    def detach_kernel_driver(self, dev_handle: _RemoteHandle, intf: int) -> None:
        self._call("detach_kernel_driver", h=dev_handle.id, intf=intf)

    def attach_kernel_driver(self, dev_handle: _RemoteHandle, intf: int) -> None:
        self._call("attach_kernel_driver", h=dev_handle.id, intf=intf)

    def clear_halt(self, dev_handle: _RemoteHandle, ep: int) -> None:
        self._call("clear_halt", h=dev_handle.id, ep=ep)

    def reset_device(self, dev_handle: _RemoteHandle) -> None:
        self._call("reset_device", h=dev_handle.id)

    # --- IBackend: transfers ----------------------------------------------------------------------------

    def bulk_write(self, dev_handle: _RemoteHandle, ep: int, intf: int, data: Any, timeout: int) -> int:
        return int(
            self._call(
                "bulk_write", h=dev_handle.id, ep=ep, intf=intf, data=bytes(data).hex(), timeout=timeout
            )
        )

    def bulk_read(self, dev_handle: _RemoteHandle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        size = len(buff) * buff.itemsize
        data = bytes.fromhex(
            self._call("bulk_read", h=dev_handle.id, ep=ep, intf=intf, size=size, timeout=timeout)
        )
        buff[: len(data)] = type(buff)(buff.typecode, data)
        return len(data)

    def intr_read(self, dev_handle: _RemoteHandle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        self._call("intr_read", h=dev_handle.id, ep=ep, intf=intf, timeout=timeout)
        return 0  # pragma: no cover - the server always answers a timeout

    def ctrl_transfer(
        self,
        dev_handle: _RemoteHandle,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        request = {"h": dev_handle.id, "type": bmRequestType, "request": bRequest, "value": wValue,
                   "index": wIndex, "timeout": timeout}  # fmt: skip
        if bmRequestType & 0x80:
            got = bytes.fromhex(self._call("ctrl_in", size=len(data) * data.itemsize, **request))
            data[: len(got)] = type(data)(data.typecode, got)
            return len(got)
        payload = bytes(data) if data is not None else b""
        return int(self._call("ctrl_out", data=payload.hex(), **request))

    # --- beyond IBackend: the board's delivered-pulse record (tests and tools judge with it) --------------

    def board_status(self, since_us: float = 0.0) -> dict[str, Any]:
        """The served board's clock and record: ``now_us`` (device time), ``t0`` (``time.monotonic`` of
        device time 0), ``last_current_pulse_us`` (the last pulse since ``since_us`` that carried
        current, or None), ``current_pulses`` (how many), ``firmware``."""
        result: dict[str, Any] = self._call("board_status", since_us=since_us)
        return result


__all__ = [
    "EmulatedBoardBackend",
    "EmulatorClientBackend",
    "LIBUSB_ERRORS",
    "SERVED_PREFIX",
    "recv_message",
    "send_message",
]
