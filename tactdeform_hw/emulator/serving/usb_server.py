"""The emulated board's USB device served to other processes, as a real board sits on a real bus.

``tactdeform-hw emulate --usb`` runs one :class:`UsbServer`: the real-time board
(:class:`~.realtime.RealtimeEmulator`, the chosen firmware's timed model on the wall clock) behind the
ESP32-S3's USB Serial/JTAG descriptors (:class:`~.usb_backend.EmulatedUsbDevice`), reached through a Unix
socket by the client backend of :mod:`.usb_client` (device name ``usb-emulator://PATH``).  The board lives
in the server's process, not in its users': it outlives an owner killed with SIGKILL, as a board on a
bench does, and every program sees the same one.

The server plays the kernel's part of USB on Linux:

* **one claim of an interface at a time**: each connection is one process's usbfs file; a claim of an
  interface another connection holds fails as busy (libusb's ``LIBUSB_ERROR_BUSY``), so a second
  program is refused before it writes a byte;
* **the claim goes with the process**: when a connection closes — a clean close, or the kernel closing a
  dead process's socket — every handle it opened is closed and every claim released at once, even while
  it waits in a bulk IN transfer (the kernel cancels a dead process's transfers); that is what lets a
  guardian take the board after its owner died;
* **the kernel driver**: ``cdc_acm`` is bound to the CDC interfaces until a client detaches it, and
  stays detached until a client gives it back;
* **bulk OUT packets go into the firmware model's receive queue** with its real tail loss (a full queue
  discards the rest of a packet), **bulk IN** carries the replies the model delivered.

One request outside USB, ``board_status``, gives the board's delivered-pulse record (the last pulse
that carried current), which the stop tests and ``tools/stop_latency.py`` judge with.
"""

from __future__ import annotations

import array
import dataclasses
import math
import os
import select
import socket
import struct
import tempfile
import threading
import time
from typing import Any

from tactdeform_hw.emulator.serving.realtime import BoardServer, RealtimeEmulator, check_served_firmware
from tactdeform_hw.emulator.serving.usb_backend import CLASS_CDC_DATA, EmulatedUsbBackend, EmulatedUsbDevice
from tactdeform_hw.emulator.serving.usb_client import ERROR_KINDS, SERVED_PREFIX, recv_message, send_message
from tactdeform_hw.emulator.timed.base import TimedModel
from tactdeform_hw.errors import ConfigurationError, TransportError

_WATCH_MS = 2  # a waiting transfer looks at its client's socket this often (a dead client's is closed)


class _ClientGone(Exception):
    """The client's socket closed while a transfer of its waited: the kernel cancels it."""


def last_current_pulse_us(timed: TimedModel, since_us: float = 0.0) -> tuple[float | None, int]:
    """The start of the last pulse since ``since_us`` that carried current, and how many did, from the
    firmware model's delivered-pulse record (v1.2 scan runs or v2 scans)."""
    now_us = timed.now_us  # the record also holds the scans the model has already planned: not yet run
    if since_us >= now_us:
        return None, 0
    times = timed.current_pulse_starts_us(since_us, now_us)
    return (max(times) if times else None), len(times)


def _client_gone(conn: socket.socket) -> bool:
    try:
        readable, _, _ = select.select([conn], [], [], 0)
        if not readable:
            return False
        return conn.recv(1, socket.MSG_PEEK) == b""
    except OSError:
        return True


def _peer_pid(conn: socket.socket) -> int | None:
    """The connecting process's pid (Linux ``SO_PEERCRED``), or None where the system does not say."""
    option = getattr(socket, "SO_PEERCRED", None)
    if option is None:
        return None
    try:
        pid, _, _ = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, option, struct.calcsize("3i")))
    except OSError:
        return None
    return int(pid)


class UsbServer(BoardServer):
    """Serve ``board`` (default: a :class:`~.realtime.RealtimeEmulator` running ``firmware``) as a USB
    device on a Unix socket at ``path`` (default: a new private directory); :attr:`name` is the device
    name a program opens.  See :class:`~.realtime.BoardServer` for ``hook``, ``reset_on_open`` and
    ``on_reset`` (a reset on open happens when a client claims the CDC data interface)."""

    thread_name = "etactile-usb"

    def __init__(
        self,
        board: Any = None,
        *,
        firmware: str | None = None,
        path: str | None = None,
        serial_number: str = "F4:12:FA:C0:FF:EE",
        **kwargs: Any,
    ) -> None:
        super().__init__(
            board if board is not None else RealtimeEmulator(firmware=firmware or "v1.2"), **kwargs
        )
        check_served_firmware(self.board, firmware)
        if not isinstance(self.board, RealtimeEmulator):
            raise ConfigurationError("the USB device serves the timed firmware model: drop --untimed")
        if self.board.firmware is None:
            raise ConfigurationError(
                "the USB device enumerates as an eTactileKit; this host build's map declares no firmware"
            )
        self.device = EmulatedUsbDevice(firmware=self.board.firmware, serial_number=serial_number)
        self.backend = EmulatedUsbBackend([self.device], lock=self.board.lock)
        self._usb_error = self.backend.usb_error
        self._usb_timeout = self.backend.usb_timeout
        self._tmpdir: str | None = None
        if path is None:
            self._tmpdir = tempfile.mkdtemp(prefix="etactile-usb-")
            path = os.path.join(self._tmpdir, "board.sock")
        self.path = os.path.abspath(path)
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._listener.bind(self.path)
            os.chmod(self.path, 0o600)  # the bus is this user's, as a udev rule would make it
            self._listener.listen(16)
        except OSError as exc:
            self._listener.close()
            raise TransportError(f"cannot serve the emulated USB board on {self.path}: {exc}") from exc
        self._conns: set[socket.socket] = set()
        self._conns_lock = threading.Lock()
        #: every connection so far: its client number, the peer's pid (Linux), the bytes it wrote to the
        #: board and whether it ever claimed the data interface (what a test proves "refused" with)
        self.client_log: list[dict[str, Any]] = []

    @property
    def name(self) -> str:
        """The device name a program opens (``usb-emulator://PATH``)."""
        return SERVED_PREFIX + self.path

    # --- the loop: accept clients, keep the model on the wall clock ---------------------------------------

    def serve_forever(self) -> None:
        cpu0 = time.thread_time()
        self._begin()
        self.device.run_firmware(self.board.timed, self.board.t0)
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._listener, self._wake_r], [], [], self.poll_s)
            except (OSError, ValueError):  # closed under us by stop()
                break
            if self._wake_r in ready:
                self._drain_wake()
            if self._listener in ready:
                try:
                    conn, _ = self._listener.accept()
                except OSError:
                    continue
                self.clients += 1
                with self._conns_lock:
                    self._conns.add(conn)
                    self.client_log.append(
                        {"client": self.clients, "pid": _peer_pid(conn), "bytes_in": 0, "claimed": False}
                    )
                    del self.client_log[:-1000]
                threading.Thread(
                    target=self._serve_client, args=(conn, self.clients), name=f"{self.thread_name}-client",
                    daemon=True,
                ).start()  # fmt: skip
            self.board.state()  # the model keeps time (and trims its history) between transfers
            self.cpu_s = time.thread_time() - cpu0

    def _close_fds(self) -> None:
        self._listener.close()
        with self._conns_lock:
            for conn in self._conns:
                try:
                    conn.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        try:
            os.unlink(self.path)
        except OSError:
            pass
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass

    # --- one client: one process's usbfs file ---------------------------------------------------------

    def _serve_client(self, conn: socket.socket, number: int) -> None:
        handles: dict[int, Any] = {}
        try:
            while not self._stop.is_set():
                try:
                    request = recv_message(conn)
                except (OSError, ValueError):
                    break  # closed: the process closed the device, or died
                try:
                    reply: dict[str, Any] = {"ok": self._do(conn, number, handles, request)}
                except _ClientGone:
                    break
                except NotImplementedError as exc:
                    reply = {"notimpl": str(exc)}
                except (KeyError, TypeError, ValueError, IndexError):
                    reply = {"err": "invalid"}
                except Exception as exc:  # pyusb's USBError, as the emulated bus raises it
                    if not isinstance(exc, self._usb_error):
                        raise
                    reply = {"err": ERROR_KINDS.get(getattr(exc, "backend_error_code", -1), "io")}
                try:
                    send_message(conn, reply)
                except OSError:
                    break
        finally:
            for handle in handles.values():  # the kernel releases what a closed file held
                self.backend.close_device(handle)
            with self._conns_lock:
                self._conns.discard(conn)
            conn.close()

    def _do(self, conn: socket.socket, number: int, handles: dict[int, Any], req: dict[str, Any]) -> Any:
        op = req["op"]
        b = self.backend
        if op == "devices":
            return [
                {"index": i, "device": self._device_fields(d), "config": dataclasses.asdict(self._config(d))}
                for i, d in enumerate(b.devices)
                if d.plugged
            ]
        if op == "open":
            handle = b.open_device(b.devices[int(req["dev"])])
            handles[id(handle)] = handle
            return id(handle)
        if op == "board_status":
            return self.board_status(float(req.get("since_us", 0.0)))
        h = handles[int(req["h"])]
        if op == "close":
            b.close_device(handles.pop(int(req["h"])))
            return None
        if op == "set_configuration":
            return b.set_configuration(h, int(req["value"]))
        if op == "get_configuration":
            return b.get_configuration(h)
        if op == "set_interface_altsetting":
            return b.set_interface_altsetting(h, int(req["intf"]), int(req["alt"]))
        if op == "claim_interface":
            intf = int(req["intf"])
            held = h.device.claims.get(intf) is h
            b.claim_interface(h, intf)
            if not held and self._is_data_interface(intf):
                self._log(number)["claimed"] = True
                self._claimed_by(number)
            return None
        if op == "release_interface":
            return b.release_interface(h, int(req["intf"]))
        if op == "is_kernel_driver_active":
            return b.is_kernel_driver_active(h, int(req["intf"]))
        if op == "detach_kernel_driver":
            return b.detach_kernel_driver(h, int(req["intf"]))
        if op == "attach_kernel_driver":
            return b.attach_kernel_driver(h, int(req["intf"]))
        if op == "clear_halt":
            return b.clear_halt(h, int(req["ep"]))
        if op == "reset_device":
            return b.reset_device(h)
        if op == "bulk_write":
            data = bytes.fromhex(req["data"])
            n = b.bulk_write(h, int(req["ep"]), int(req["intf"]), data, int(req["timeout"]))
            self._log(number)["bytes_in"] += n
            self._seen("host->dev", data)
            return n
        if op == "bulk_read":
            got = self._bulk_read(
                conn, h, int(req["ep"]), int(req["intf"]), int(req["size"]), int(req["timeout"])
            )
            self._seen("dev->host", got)
            return got.hex()
        if op == "intr_read":
            self._wait_out(conn, int(req["timeout"]))
            raise self._usb_timeout(*self._timeout_args())
        if op in ("ctrl_in", "ctrl_out"):
            buf: Any = array.array(
                "B", bytes(int(req["size"])) if op == "ctrl_in" else bytes.fromhex(req["data"])
            )
            setup = (int(req["type"]), int(req["request"]), int(req["value"]), int(req["index"]))
            n = b.ctrl_transfer(h, *setup, buf, int(req["timeout"]))
            return bytes(buf[:n]).hex() if op == "ctrl_in" else n
        raise ValueError(op)

    def _bulk_read(
        self, conn: socket.socket, h: Any, ep: int, intf: int, size: int, timeout_ms: int
    ) -> bytes:
        """A bulk IN transfer that ends when its client dies, as the kernel cancels a dead process's."""
        deadline = None if not timeout_ms else time.monotonic() + timeout_ms / 1000
        buf = array.array("B", bytes(size))
        while True:
            step_ms = _WATCH_MS
            if deadline is not None:
                step_ms = max(1, min(_WATCH_MS, math.ceil((deadline - time.monotonic()) * 1000)))
            try:
                n = self.backend.bulk_read(h, ep, intf, buf, step_ms)
                return bytes(buf[:n])
            except self._usb_timeout:
                if deadline is not None and time.monotonic() >= deadline:
                    raise
            if _client_gone(conn):
                raise _ClientGone

    def _wait_out(self, conn: socket.socket, timeout_ms: int) -> None:
        end = time.monotonic() + max(1, timeout_ms) / 1000
        while time.monotonic() < end:
            if _client_gone(conn):
                raise _ClientGone
            time.sleep(_WATCH_MS / 1000)

    @staticmethod
    def _timeout_args() -> tuple[str, int, int]:
        from tactdeform_hw.emulator.serving.usb_client import LIBUSB_ERRORS

        code, err, text = LIBUSB_ERRORS["timeout"]
        return text, code, err

    def _log(self, number: int) -> dict[str, Any]:
        with self._conns_lock:
            for entry in reversed(self.client_log):
                if entry["client"] == number:
                    found: dict[str, Any] = entry
                    return found
        return {"client": number, "pid": None, "bytes_in": 0, "claimed": False}  # aged out of the log

    def _is_data_interface(self, intf: int) -> bool:
        return any(
            i.bInterfaceNumber == intf and i.bInterfaceClass == CLASS_CDC_DATA for i in self.device.interfaces
        )

    def _claimed_by(self, number: int) -> None:
        """A new program took the serial function: replies written before are not its own (and on v2 a
        command the previous owner cut may take its first bytes, which the model records)."""
        self.bytes_dropped += len(self.board.client_opened(f"client {number}"))
        self.connected = True
        if self.reset_on_open:
            self.reset("a client claimed the USB interface (--reset-on-open)")

    def _seen(self, direction: str, data: bytes) -> None:
        if not data:
            return
        if direction == "host->dev":
            self.bytes_in += len(data)
        else:
            self.bytes_out += len(data)
        if self.hook is not None:
            self.hook(direction, data, time.monotonic())

    @staticmethod
    def _device_fields(d: EmulatedUsbDevice) -> dict[str, Any]:
        desc = d.descriptor()
        fields = dataclasses.asdict(desc)
        fields["port_numbers"] = list(desc.port_numbers)
        return fields

    @staticmethod
    def _config(d: EmulatedUsbDevice) -> Any:
        return _ConfigFields.of(d)

    # --- the board's record ---------------------------------------------------------------------------

    def board_status(self, since_us: float = 0.0) -> dict[str, Any]:
        """See :meth:`.usb_client.EmulatorClientBackend.board_status`."""
        with self._conns_lock:
            clients = [dict(entry) for entry in self.client_log]
        with self.board.lock:
            self.board.state()
            timed = self.board.timed
            last, count = last_current_pulse_us(timed, since_us)
            return {
                "now_us": timed.now_us,
                "t0": self.board.t0,
                "last_current_pulse_us": last,
                "current_pulses": count,
                "firmware": self.board.firmware.name,
                "clients": clients,
            }


@dataclasses.dataclass
class _ConfigFields:
    """A configuration descriptor with the counts pyusb reads (computed properties on the emulated
    bus's descriptors), as plain fields for the wire."""

    bLength: int
    bDescriptorType: int
    wTotalLength: int
    bNumInterfaces: int
    bConfigurationValue: int
    iConfiguration: int
    bmAttributes: int
    bMaxPower: int
    extra_descriptors: list[int]
    interfaces: list[dict[str, Any]]

    @classmethod
    def of(cls, d: EmulatedUsbDevice) -> _ConfigFields:
        c = d.configuration_descriptor()
        interfaces = []
        for i in c.interfaces:
            fields = dataclasses.asdict(i)
            fields["bNumEndpoints"] = i.bNumEndpoints
            interfaces.append(fields)
        return cls(c.bLength, c.bDescriptorType, c.wTotalLength, c.bNumInterfaces, c.bConfigurationValue,
                   c.iConfiguration, c.bmAttributes, c.bMaxPower, list(c.extra_descriptors),
                   interfaces)  # fmt: skip


__all__ = ["UsbServer", "last_current_pulse_us"]
