"""The board's native USB CDC-ACM interface driven directly with pyusb: no serial driver involved.

pyusb has no CDC-ACM helper, so this module does what a serial driver would: find the board (Espressif's
vendor id 0x303A by default, or a given VID, PID and serial number), find its CDC communication
(class 0x02) and data (class 0x0A) interfaces, detach the kernel's ``cdc_acm`` driver where it holds
them (and give them back on close), claim both, send SET_LINE_CODING (921600 8N1 — nominal on native
USB, but some stacks want it) and SET_CONTROL_LINE_STATE, and pick the data interface's OUT and IN
endpoints by direction, checking that both are bulk.

:class:`UsbCdcPort` looks like a pyserial ``Serial`` (``open``/``close``/``read``/``write``/
``in_waiting``/``out_waiting``/``reset_input_buffer``/``timeout``/``is_open``/``dtr``/``rts``), so
:class:`~tactdeform_hw.device.driver.serial_driver.EtactileKitDevice` drives it unchanged.

Things that differ from a serial port, and why:

* DTR and RTS default to *low*.  The ESP32-S3's USB Serial/JTAG controller resets the chip when RTS is
  asserted without DTR; pyserial asserts both on open.  Setting them before ``open`` is honoured.
* Writes go out one packet (``wMaxPacketSize`` bytes) per bulk transfer.  When an endpoint stalls, the
  host then knows exactly which packet the device refused, so it can clear the halt and send that packet
  again without duplicating or losing protocol bytes (the protocol has no framing to recover from
  either).  A second stall on the same packet is reported, not retried.
* Reads also go one packet at a time, so a transfer always ends at the device's packet boundary and a
  reply of exactly 64 bytes does not wait for a zero-length packet.
* ``in_waiting`` has to ask the device: it polls the IN endpoint once (1 ms) before answering.
* A write timeout raises pyserial's ``SerialTimeoutException`` (what a pyserial caller expects); a
  vanished device raises :class:`~tactdeform_hw.errors.DeviceGoneError`; everything else that goes
  wrong with the link is a :class:`~tactdeform_hw.errors.TransportError` whose message says what to do.

pyusb is imported lazily; without it, creating a port raises
:class:`~tactdeform_hw.errors.MissingDependencyError` naming the ``usb`` extra.
"""

from __future__ import annotations

import errno
import math
import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

from tactdeform_hw.device.driver.holders import find_holders
from tactdeform_hw.errors import (
    ConfigurationError,
    DeviceBusyError,
    DeviceGoneError,
    MissingDependencyError,
    PortNotOpenError,
    TransportError,
)
from tactdeform_hw.ports import PortBase
from tactdeform_hw.protocol.constants import BAUD_RATE, ESPRESSIF_VID

if TYPE_CHECKING:
    from tactdeform_hw.device.safety.guardian import Guardian

#: Who holds a path open: ``(pid, command line)`` each (:func:`~.holders.find_holders`).
HolderFinder = Callable[[str], list[tuple[int, str]]]

CLASS_CDC_COMM = 0x02
CLASS_CDC_DATA = 0x0A
_REQ_OUT_CLASS_INTERFACE = 0x21
_SET_LINE_CODING = 0x20
_SET_CONTROL_LINE_STATE = 0x22
_POLL_MS = 1

USB_PREFIX = "usb:"

NO_BACKEND_HELP = (
    "pyusb found no USB backend: the libusb-1.0 library is not installed (or not on the library path). "
    "Install it — Debian/Ubuntu: sudo apt install libusb-1.0-0; Fedora: sudo dnf install libusb1; "
    "macOS: brew install libusb; Windows: pip install libusb-package (or put libusb-1.0.dll on PATH). "
    "Or use the board's serial port instead (e.g. --device /dev/ttyACM0 or COM3)."
)

ACCESS_HELP = (
    "your user may not open this USB device. On Linux add a udev rule, e.g. "
    "/etc/udev/rules.d/99-etactilekit.rules containing "
    'SUBSYSTEM=="usb", ATTR{idVendor}=="303a", MODE="0660", GROUP="plugdev" '
    "then run: sudo udevadm control --reload-rules && sudo udevadm trigger, "
    "add yourself to the group (sudo usermod -aG plugdev $USER) and log in again. "
    "On Windows the interface needs the WinUSB driver (install it with Zadig) — or use the COM port."
)

BUSY_HELP = (
    "another program holds it: close serial terminals or tools that have the board's serial port open "
    "(/dev/ttyACM*, COM*), stop ModemManager if it probes the port, or close the other tactdeform-hw "
    "session. On macOS and Windows the system's serial driver owns the interface: use the serial port "
    "(or, on Windows, bind WinUSB with Zadig)."
)


def import_usb() -> tuple[ModuleType, ModuleType]:
    try:
        import usb.core
        import usb.util
    except ImportError as exc:
        raise MissingDependencyError("pyusb", "usb", "the USB transport (usb:VID:PID devices)") from exc
    return usb.core, usb.util


def default_backend() -> Any:
    """The system's libusb backend for pyusb, or None when there is none.

    Tries libusb 1.0, then the DLL shipped by the ``libusb-package`` wheel (pyusb does not look there
    by itself), then OpenUSB and libusb 0.1.
    """
    import_usb()
    from tactdeform_hw.device.safety.usb_guardian import libusb1_backend

    backend = libusb1_backend()
    if backend is None:
        import usb.backend.libusb0 as libusb0
        import usb.backend.openusb as openusb

        backend = openusb.get_backend() or libusb0.get_backend()
    return backend


# --- names -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class UsbDeviceSpec:
    """Which board to open: ``usb:VID[:PID[:SERIAL]]`` with hexadecimal ids (PID may be empty or
    ``*`` for any; the serial number may itself contain colons, as ESP32 MAC-style serials do)."""

    vid: int = ESPRESSIF_VID
    pid: int | None = None
    serial_number: str | None = None

    @classmethod
    def parse(cls, name: str) -> UsbDeviceSpec:
        if not name.startswith(USB_PREFIX):
            raise ConfigurationError(f"device={name!r}: a USB device name starts with {USB_PREFIX!r}")
        parts = name[len(USB_PREFIX) :].split(":", 2)
        vid_s = parts[0] if parts else ""
        pid_s = parts[1] if len(parts) > 1 else ""
        serial = parts[2] if len(parts) > 2 and parts[2] else None
        vid = cls._hex("vid", vid_s, name) if vid_s not in ("", "*") else ESPRESSIF_VID
        pid = cls._hex("pid", pid_s, name) if pid_s not in ("", "*") else None
        return cls(vid, pid, serial)

    @staticmethod
    def _hex(field: str, text: str, name: str) -> int:
        try:
            value = int(text, 16)
        except ValueError:
            value = -1
        if not 0 <= value <= 0xFFFF:
            raise ConfigurationError(
                f"device={name!r}: {field}={text!r} is not a 16-bit hexadecimal id (e.g. usb:303a:1001)"
            )
        return value

    @property
    def name(self) -> str:
        text = (
            f"{USB_PREFIX}{self.vid:04x}:{self.pid:04x}"
            if self.pid is not None
            else f"{USB_PREFIX}{self.vid:04x}"
        )
        if self.serial_number:
            text += f"{'' if self.pid is not None else ':*'}:{self.serial_number}"
        return text

    def describe(self) -> str:
        ids = f"{self.vid:04x}:{self.pid:04x}" if self.pid is not None else f"{self.vid:04x}:*"
        return ids + (f" with serial number {self.serial_number}" if self.serial_number else "")


def usb_port_for_name(name: str, *, timeout: float | None = 0.5, baudrate: int = BAUD_RATE) -> UsbCdcPort:
    """An unopened :class:`UsbCdcPort` for ``usb://VID:PID[:SERIAL]`` (or ``usb:VID:PID[:SERIAL]``).  The
    emulated bus (``usb-emulator``) is another scheme of :func:`tactdeform_hw.transports.port_for_name`."""
    if name.startswith(USB_PREFIX + "//"):
        name = USB_PREFIX + name[len(USB_PREFIX) + 2 :]
    spec = UsbDeviceSpec.parse(name)
    return UsbCdcPort(
        spec.vid, spec.pid, spec.serial_number, timeout=timeout, write_timeout=timeout, baudrate=baudrate,
        name=name,
    )  # fmt: skip


# --- errors ---------------------------------------------------------------------------------------------


def _errno_of(exc: BaseException) -> int | None:
    err = getattr(exc, "errno", None)
    if isinstance(err, int):
        return err
    code = getattr(exc, "backend_error_code", None)
    return (
        {-1: errno.EIO, -3: errno.EACCES, -4: errno.ENODEV, -6: errno.EBUSY, -9: errno.EPIPE}.get(code)
        if isinstance(code, int)
        else None
    )


# --- the port -------------------------------------------------------------------------------------------


class UsbCdcPort(PortBase):
    """A pyserial-compatible port over a board's USB CDC-ACM interface, through pyusb.

    ``backend`` is any pyusb backend (default: the system's libusb); the emulated board in
    :mod:`tactdeform_hw.emulator.serving.usb_backend` is one.  ``timeout`` and ``write_timeout`` are in
    seconds
    as in pyserial (None blocks, 0 polls once).

    ``sysfs_root``, ``dev_root`` and ``holders`` are where the port looks before it detaches the kernel's
    serial driver (``/sys``, ``/dev`` and :func:`~.holders.find_holders`; tests inject a fake
    tree): a board whose ``/dev/ttyACM*`` another program holds open is refused, never cut off.

    A port on the system's libusb, or on a board served by another process (``emulate --usb``), is
    guardable: :meth:`start_guardian` starts the process that switches the board off if the owner dies
    without running code (:mod:`.usb_guardian`).  A board on an emulated bus in this process dies with
    it, so that port is not.
    """

    bytesize = 8
    parity = "N"
    stopbits = 1

    def __init__(
        self,
        vid: int = ESPRESSIF_VID,
        pid: int | None = None,
        serial_number: str | None = None,
        *,
        backend: Any = None,
        timeout: float | None = 0.5,
        write_timeout: float | None = 1.0,
        baudrate: int = BAUD_RATE,
        name: str | None = None,
        sysfs_root: str = "/sys",
        dev_root: str = "/dev",
        holders: HolderFinder | None = None,
    ) -> None:
        self._core, self._util = import_usb()
        self.sysfs_root = sysfs_root
        self.dev_root = dev_root
        self._holders = holders
        self.spec = UsbDeviceSpec(vid, pid, serial_number)
        self.port = name or self.spec.name
        self.timeout = timeout
        self.write_timeout = write_timeout
        self._baudrate = baudrate
        self._dtr = False
        self._rts = False
        self.backend = backend
        self.is_open = False
        self.usb_device: Any = None  # the pyusb Device while open
        self.comm_interface: int | None = None
        self.data_interface: int | None = None
        self.ep_out: int | None = None
        self.ep_in: int | None = None
        self.packet_size = 64
        self.detached: list[int] = []  # interfaces whose kernel driver this port detached
        self.line_coding_accepted: bool | None = None
        self.stalls_cleared = 0
        self._claimed: list[int] = []
        self._rx = bytearray()
        self._gone: str | None = None

    @property
    def name(self) -> str:
        return self.port

    # --- the guardian -------------------------------------------------------------------------------------

    @property
    def guardable(self) -> bool:
        """Whether a guardian process can reach this board once the owner is gone: the system's libusb,
        or a backend that says how (``guardian_backend()``: a board served by another process)."""
        return self.backend is None or callable(getattr(self.backend, "guardian_backend", None))

    def start_guardian(self, name: str, *, stop: bytes | None = None) -> Guardian:
        """The guardian factory the device layer calls: a process that waits for this owner's end, then
        claims the interfaces once the owner's claim is gone and sends the stop bytes it was told (see
        :mod:`.usb_guardian`).  The port must be open."""
        from tactdeform_hw.device.safety.usb_guardian import start_usb_guardian

        dev = self._check_open()
        how = self.backend.guardian_backend() if self.backend is not None else "libusb"
        return start_usb_guardian(
            name,
            backend=how,
            bus=int(dev.bus),
            address=int(dev.address),
            vid=int(dev.idVendor),
            pid=int(dev.idProduct),
            comm_interface=self.comm_interface,
            data_interface=int(self.data_interface if self.data_interface is not None else -1),
            ep_out=int(self.ep_out if self.ep_out is not None else -1),
            ep_in=int(self.ep_in if self.ep_in is not None else -1),
            packet_size=self.packet_size,
            give_back=list(self.detached),
            stop=stop,
            release_owner=self.release_for_guardian,
        )

    def release_for_guardian(self) -> None:
        """Let go of the interfaces without giving them to the kernel driver, so the guardian can claim
        them at once (an owner that abandons the board to its guardian while still alive)."""
        self.is_open = False
        if self.usb_device is not None:
            self._release(reattach=False)

    # --- line settings ------------------------------------------------------------------------------

    @property
    def baudrate(self) -> int:
        return self._baudrate

    @baudrate.setter
    def baudrate(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 < value <= 0xFFFFFFFF:
            raise ConfigurationError(f"baudrate={value!r} is out of range: a positive 32-bit integer")
        self._baudrate = value
        if self.is_open:
            self._set_line_coding()

    @property
    def dtr(self) -> bool:
        return self._dtr

    @dtr.setter
    def dtr(self, value: bool) -> None:
        self._dtr = bool(value)
        if self.is_open:
            self._set_control_lines()

    @property
    def rts(self) -> bool:
        return self._rts

    @rts.setter
    def rts(self, value: bool) -> None:
        self._rts = bool(value)
        if self.is_open:
            self._set_control_lines()

    # --- open / close --------------------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            raise TransportError(f"{self.port} is already open")
        backend = self.backend if self.backend is not None else default_backend()
        if backend is None:
            raise TransportError(NO_BACKEND_HELP)
        self._rx.clear()
        self._gone = None
        dev = self._find(backend)
        self.usb_device = dev
        try:
            self._configure(dev)
        except BaseException:
            self._release(reattach=True)
            raise
        self.is_open = True

    def close(self) -> None:
        """Release the interfaces and give detached interfaces back to the kernel driver.  Idempotent;
        never raises for a device that has gone."""
        self.is_open = False
        if self.usb_device is not None:
            self._release(reattach=self._gone is None)

    def _release(self, *, reattach: bool) -> None:
        dev, usb_error = self.usb_device, self._core.USBError
        if dev is None:
            return
        for n in self._claimed:
            try:
                self._util.release_interface(dev, n)
            except (usb_error, ValueError):
                pass
        self._claimed.clear()
        if reattach:
            for n in self.detached:
                try:
                    dev.attach_kernel_driver(n)
                except (usb_error, NotImplementedError):
                    pass
        self.detached.clear()
        try:
            self._util.dispose_resources(dev)
        except usb_error:
            pass
        self.usb_device = None

    # --- finding and configuring ------------------------------------------------------------------------

    def _find(self, backend: Any) -> Any:
        core, util = self._core, self._util
        what = self.spec.describe()
        match: dict[str, int] = {"idVendor": self.spec.vid}
        if self.spec.pid is not None:
            match["idProduct"] = self.spec.pid
        try:
            devices = list(core.find(find_all=True, backend=backend, **match))
        except core.NoBackendError as exc:
            raise TransportError(NO_BACKEND_HELP) from exc
        except core.USBError as exc:
            raise self._error(exc, "listing USB devices") from exc
        if not devices:
            raise TransportError(
                f"no USB device {what} is attached. Check that the board is plugged in with a data cable "
                "(a charge-only cable shows nothing) and powered; `tactdeform-hw ports` lists what the "
                "host sees.",
                code=errno.ENODEV,
            )
        if self.spec.serial_number is not None:
            found, unreadable, seen = [], [], []
            for d in devices:
                try:
                    sn = util.get_string(d, d.iSerialNumber) if d.iSerialNumber else None
                except (core.USBError, ValueError):
                    unreadable.append(d)
                    continue
                seen.append(sn or "(none)")
                if sn == self.spec.serial_number:
                    found.append(d)
            if not found:
                if unreadable:
                    raise TransportError(
                        f"access denied: cannot read the serial number of {len(unreadable)} USB device(s) "
                        f"{self.spec.vid:04x}:* to look for {self.spec.serial_number!r}: {ACCESS_HELP}",
                        code=errno.EACCES,
                    )
                raise TransportError(
                    f"no USB device {what} is attached (serial numbers present: {', '.join(seen)})",
                    code=errno.ENODEV,
                )
            devices = found
        if len(devices) > 1:
            listing = []
            for d in devices:
                try:
                    sn = util.get_string(d, d.iSerialNumber) if d.iSerialNumber else None
                except (core.USBError, ValueError):
                    sn = None
                listing.append(
                    f"{d.idVendor:04x}:{d.idProduct:04x} bus {d.bus} address {d.address}"
                    + (f" serial {sn}" if sn else "")
                )
            raise ConfigurationError(
                f"{len(devices)} USB devices match {what}: name one by serial number "
                f"(usb:VID:PID:SERIAL). Found: {'; '.join(listing)}"
            )
        return devices[0]

    def _configure(self, dev: Any) -> None:
        core, util = self._core, self._util
        try:
            cfg = dev.get_active_configuration()
        except core.USBError as exc:
            if _errno_of(exc) in (errno.EACCES, errno.ENODEV, errno.EIO):
                raise self._error(exc, "opening the device") from exc
            try:  # not configured yet (no driver has selected a configuration)
                dev.set_configuration()
                cfg = dev.get_active_configuration()
            except core.USBError as exc2:
                raise self._error(exc2, "selecting the USB configuration") from exc2
        comm = util.find_descriptor(cfg, bInterfaceClass=CLASS_CDC_COMM)
        data = util.find_descriptor(cfg, bInterfaceClass=CLASS_CDC_DATA)
        if data is None:
            classes = ", ".join(f"{i.bInterfaceNumber}: class 0x{i.bInterfaceClass:02x}" for i in cfg)
            raise TransportError(
                f"{self.spec.describe()} has no CDC data interface (class 0x0A), so it is not a CDC-ACM "
                f"serial device (interfaces {classes})"
            )
        self.comm_interface = comm.bInterfaceNumber if comm is not None else None
        self.data_interface = data.bInterfaceNumber
        for n in ([self.comm_interface] if self.comm_interface is not None else []) + [self.data_interface]:
            self._detach_kernel_driver(dev, n)
            try:
                util.claim_interface(dev, n)
            except core.USBError as exc:
                if _errno_of(exc) == errno.EBUSY:
                    usbfs = f"{self.dev_root}/bus/usb/{dev.bus:03d}/{dev.address:03d}"
                    busy = DeviceBusyError(
                        self.port, self._find_holders(usbfs), f"interface {n} is claimed: {BUSY_HELP}"
                    )
                    busy.code = errno.EBUSY
                    raise busy from exc
                raise self._error(exc, f"claiming interface {n}") from exc
            self._claimed.append(n)
        self.ep_out, self.ep_in, self.packet_size = self._bulk_endpoints(data)
        self.line_coding_accepted = None
        if self.comm_interface is not None:
            self._set_line_coding()
            self._set_control_lines()

    def _detach_kernel_driver(self, dev: Any, n: int) -> None:
        core = self._core
        try:
            active = bool(dev.is_kernel_driver_active(n))
        except NotImplementedError:
            return  # the platform cannot tell (Windows, macOS): claiming will say if it is held
        except core.USBError as exc:
            raise self._error(exc, f"checking the kernel driver on interface {n}") from exc
        if active:
            self._refuse_if_tty_held(dev, n)
            try:
                dev.detach_kernel_driver(n)
            except core.USBError as exc:
                raise self._error(exc, f"detaching the kernel driver (cdc_acm) from interface {n}") from exc
            self.detached.append(n)

    def _find_holders(self, path: str) -> list[tuple[int, str]]:
        if self._holders is not None:
            return self._holders(path)
        return find_holders(path)

    def interface_ttys(self, dev: Any, n: int) -> list[str]:
        """The serial devices the kernel made of interface ``n`` (``/dev/ttyACM0``, from sysfs:
        ``/sys/bus/usb/devices/BUS-PORTS:CONFIG.N/tty/``); empty where there is no such tree."""
        try:
            ports = ".".join(str(p) for p in dev.port_numbers or ())
            config = int(dev.get_active_configuration().bConfigurationValue)
        except (self._core.USBError, NotImplementedError, AttributeError, TypeError):
            return []
        if not ports:
            return []
        base = os.path.join(
            self.sysfs_root, "bus", "usb", "devices", f"{dev.bus}-{ports}:{config}.{n}", "tty"
        )
        try:
            names = sorted(os.listdir(base))
        except OSError:
            return []
        return [os.path.join(self.dev_root, tty) for tty in names]

    def _refuse_if_tty_held(self, dev: Any, n: int) -> None:
        """Detaching ``cdc_acm`` takes the board from whoever has its tty open — another program, a
        serial owner and its guardian: refuse instead, naming them, before a byte is written."""
        for tty in self.interface_ttys(dev, n):
            holders = self._find_holders(tty)
            if holders:
                busy = DeviceBusyError(
                    self.port,
                    holders,
                    f"its serial device {tty} (interface {n}, kernel driver cdc_acm) is open; detaching "
                    "the driver would cut that program off",
                )
                busy.code = errno.EBUSY
                raise busy

    def _bulk_endpoints(self, data: Any) -> tuple[int, int, int]:
        util = self._util
        outs = [e for e in data if util.endpoint_direction(e.bEndpointAddress) == util.ENDPOINT_OUT]
        ins = [e for e in data if util.endpoint_direction(e.bEndpointAddress) == util.ENDPOINT_IN]
        if not outs or not ins:
            raise TransportError(
                f"the CDC data interface {data.bInterfaceNumber} lacks an "
                f"{'OUT' if not outs else 'IN'} endpoint; this is not a usable CDC-ACM device"
            )
        kinds = {0: "control", 1: "isochronous", 2: "bulk", 3: "interrupt"}
        for e in (outs[0], ins[0]):
            kind = util.endpoint_type(e.bmAttributes)
            if kind != util.ENDPOINT_TYPE_BULK:
                raise TransportError(
                    f"endpoint 0x{e.bEndpointAddress:02x} of the CDC data interface {data.bInterfaceNumber} "
                    f"is {kinds.get(kind, kind)}, not bulk: this is not a CDC-ACM data interface"
                )
        size = min(int(outs[0].wMaxPacketSize), int(ins[0].wMaxPacketSize)) or 64
        return int(outs[0].bEndpointAddress), int(ins[0].bEndpointAddress), size

    def _set_line_coding(self) -> None:
        """921600 8N1 by default.  A device that stalls the request still works (on native USB the rate
        is nominal); ``line_coding_accepted`` records what happened."""
        if self.comm_interface is None or self.usb_device is None:
            return
        coding = struct.pack("<IBBB", self._baudrate, 0, 0, 8)  # rate, 1 stop bit, no parity, 8 data bits
        try:
            self.usb_device.ctrl_transfer(
                _REQ_OUT_CLASS_INTERFACE,
                _SET_LINE_CODING,
                0,
                self.comm_interface,
                coding,
                self._ctrl_timeout_ms(),
            )
            self.line_coding_accepted = True
        except self._core.USBError as exc:
            if _errno_of(exc) != errno.EPIPE:
                raise self._error(exc, "SET_LINE_CODING") from exc
            self.line_coding_accepted = False

    def _set_control_lines(self) -> None:
        if self.comm_interface is None or self.usb_device is None:
            return
        value = (1 if self._dtr else 0) | (2 if self._rts else 0)
        try:
            self.usb_device.ctrl_transfer(
                _REQ_OUT_CLASS_INTERFACE,
                _SET_CONTROL_LINE_STATE,
                value,
                self.comm_interface,
                None,
                self._ctrl_timeout_ms(),
            )
        except self._core.USBError as exc:
            raise self._error(exc, "SET_CONTROL_LINE_STATE") from exc

    def _ctrl_timeout_ms(self) -> int:
        return 1000 if self.write_timeout is None else max(1, math.ceil(self.write_timeout * 1000))

    # --- I/O ------------------------------------------------------------------------------------------

    def _check_open(self) -> Any:
        if self._gone is not None:
            raise DeviceGoneError(self._gone)
        if not self.is_open or self.usb_device is None:
            raise PortNotOpenError(f"{self.port} is not open")
        return self.usb_device

    def write(self, data: bytes | bytearray | memoryview) -> int:
        """Send every byte, one packet per bulk transfer.  Returns the number of bytes written."""
        dev = self._check_open()
        payload = bytes(data)
        deadline = None if not self.write_timeout else time.monotonic() + self.write_timeout
        size = self.packet_size
        for start in range(0, len(payload), size):
            self._write_packet(dev, payload[start : start + size], start, len(payload), deadline)
        return len(payload)

    def _write_packet(self, dev: Any, pkt: bytes, done: int, total: int, deadline: float | None) -> None:
        core = self._core
        for attempt in (1, 2):
            try:
                n = dev.write(self.ep_out, pkt, self._remaining_ms(deadline))
            except core.USBTimeoutError as exc:
                import serial

                raise serial.SerialTimeoutException(
                    f"write timeout on {self.port}: {done} of {total} byte(s) sent before the device stopped "
                    "accepting data"
                ) from exc
            except core.USBError as exc:
                if _errno_of(exc) == errno.EPIPE and attempt == 1:
                    self._clear_halt(dev, self.ep_out)
                    continue
                if _errno_of(exc) == errno.EPIPE:
                    raise TransportError(
                        f"bulk OUT endpoint 0x{self.ep_out:02x} of {self.port} stalled again after its halt "
                        f"was cleared; {done} of {total} byte(s) were delivered, so the device may hold part "
                        "of a command: close and reopen the device, then resync() before sending anything "
                        "else",
                        code=errno.EPIPE,
                    ) from exc
                raise self._error(exc, "bulk OUT") from exc
            if n != len(pkt):
                raise TransportError(f"bulk OUT on {self.port} accepted {n} of {len(pkt)} byte(s)")
            return

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes: waits until they have all arrived or the timeout has passed."""
        dev = self._check_open()
        if size <= 0:
            return b""
        if self.timeout is None:
            deadline: float | None = None
        else:
            deadline = time.monotonic() + self.timeout
        while len(self._rx) < size:
            if deadline is None:
                timeout_ms = 0  # libusb: no time limit
            else:
                remaining = deadline - time.monotonic()
                if remaining <= 0 and self.timeout != 0:
                    break
                timeout_ms = max(_POLL_MS, math.ceil(remaining * 1000))
            chunk = self._read_packet(dev, timeout_ms)
            if chunk:
                self._rx += chunk
            elif self.timeout == 0:
                break
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def _read_packet(self, dev: Any, timeout_ms: int) -> bytes:
        core = self._core
        for attempt in (1, 2):
            try:
                arr = dev.read(self.ep_in, self.packet_size, timeout_ms)
                return bytes(arr.tobytes())
            except core.USBTimeoutError:
                return b""
            except core.USBError as exc:
                if _errno_of(exc) == errno.EPIPE and attempt == 1:
                    self._clear_halt(dev, self.ep_in)
                    continue
                if _errno_of(exc) == errno.EPIPE:
                    raise TransportError(
                        f"bulk IN endpoint 0x{self.ep_in:02x} of {self.port} stalled again after its halt "
                        "was cleared: the device is not sending; reset or replug the board",
                        code=errno.EPIPE,
                    ) from exc
                raise self._error(exc, "bulk IN") from exc
        return b""  # pragma: no cover - the loop always returns or raises

    def _clear_halt(self, dev: Any, ep: int | None) -> None:
        try:
            dev.clear_halt(ep)
        except self._core.USBError as exc:
            raise self._error(exc, f"clearing the halt on endpoint 0x{ep:02x}") from exc
        self.stalls_cleared += 1

    @staticmethod
    def _remaining_ms(deadline: float | None) -> int:
        if deadline is None:
            return 0
        return max(_POLL_MS, math.ceil((deadline - time.monotonic()) * 1000))

    @property
    def in_waiting(self) -> int:
        """Bytes already received.  USB has no such count on the host side, so this polls the IN
        endpoint once (about 1 ms when the device has nothing to send)."""
        dev = self._check_open()
        self._rx += self._read_packet(dev, _POLL_MS)
        return len(self._rx)

    def reset_input_buffer(self) -> None:
        """Drop received bytes, including packets the device had already queued for the host."""
        dev = self._check_open()
        self._rx.clear()
        for _ in range(64):
            if not self._read_packet(dev, _POLL_MS):
                break

    # --- errors ---------------------------------------------------------------------------------------

    def _error(self, exc: BaseException, action: str) -> Exception:
        """A pyusb error as the package's error, with what the user should do about it."""
        err = _errno_of(exc)
        what = f"{self.spec.describe()}"
        if err in (errno.ENODEV, errno.EIO):
            self._gone = (
                f"the USB device {what} is gone ({action} failed: {exc}); it was unplugged, reset or lost "
                "power. Plug it back in and open it again: the board restarts in its power-on state, so "
                "configure it again."
            )
            self.is_open = False
            return DeviceGoneError(self._gone, code=err)
        if err == errno.EACCES:
            return TransportError(f"access denied to USB device {what} ({action}): {ACCESS_HELP}", code=err)
        if err == errno.EBUSY:
            return TransportError(f"USB device {what} is busy ({action}): {BUSY_HELP}", code=err)
        return TransportError(f"USB device {what}: {action} failed: {exc}", code=err)

    # --- context manager and description ----------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        """What was found and set up (for logs and ``--json`` output)."""
        dev = self.usb_device
        return {
            "port": self.port,
            "vid": f"{self.spec.vid:04x}",
            "pid": f"{dev.idProduct:04x}"
            if dev is not None
            else (f"{self.spec.pid:04x}" if self.spec.pid is not None else None),
            "bus": getattr(dev, "bus", None),
            "address": getattr(dev, "address", None),
            "comm_interface": self.comm_interface,
            "data_interface": self.data_interface,
            "ep_out": self.ep_out,
            "ep_in": self.ep_in,
            "packet_size": self.packet_size,
            "kernel_driver_detached": list(self.detached),
            "line_coding_accepted": self.line_coding_accepted,
            "baudrate": self._baudrate,
            "dtr": self._dtr,
            "rts": self._rts,
            "is_open": self.is_open,
        }

    def __repr__(self) -> str:
        return f"UsbCdcPort({self.port!r}, open={self.is_open})"
