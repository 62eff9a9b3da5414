"""An emulated ESP32-S3 USB Serial/JTAG controller behind a pyusb backend, wired to the emulator.

pyusb lets a caller pass any object with the ``IBackend`` methods to ``usb.core.find(backend=...)``;
everything above the backend (``usb.core.Device``, ``usb.util``) is pyusb's own code.  So the USB
transport runs its real code paths — find, configuration, kernel-driver detach, claim, CDC class
requests, bulk transfers, halt recovery, disconnection — in CI with no hardware and no libusb.

What the device presents is what the XIAO ESP32S3 shows on a Linux host (``lsusb -v``): VID 0x303A,
PID 0x1001, three interfaces — CDC-ACM communication (class 0x02, interrupt IN 0x82), CDC data
(class 0x0A, bulk OUT 0x01 / bulk IN 0x81) and the vendor-specific JTAG interface (class 0xFF, bulk
OUT 0x02 / bulk IN 0x83) — with the kernel's ``cdc_acm`` driver bound to the first two.

Behind the CDC data endpoints sits the timed emulator
(:class:`~tactdeform_hw.emulator.timed.model_v1_2.TimedEmulator`): the same parser and registers as everywhere
else, on a clock — OUT packets of at most 64 bytes from the next 1 ms frame
(:class:`~tactdeform_hw.emulator.timed.link.UsbFsLink`), the 256-byte receive queue that discards the rest of
a
packet when full (every loss reported), one command with a payload per RTOS tick, scans that pre-empt
the parser, replies back over the same kind of link, the interrupt watchdog.

The device advances lazily: whenever the host touches it, the firmware is simulated up to the clock's
"now".  With the default clock that is wall time, so a host sees the latencies a board would give;
with :class:`VirtualClock` the same events happen in simulated time, deterministically.

Fault injection for tests: :meth:`EmulatedUsbBackend.unplug` (at once, or after a number of OUT bytes),
:meth:`EmulatedUsbBackend.replug`, :meth:`EmulatedUsbDevice.halt` (a stalled endpoint, transient or
sticky), ``access_denied`` (no permission to open), ``kernel_driver`` (bound, absent or unsupported).
Asserting RTS with DTR low holds the chip in reset, as the real USB Serial/JTAG controller does; the
count is in :attr:`EmulatedUsbDevice.resets`, so a test can prove that opening the port did not reset it.

pyusb is imported only when a backend is created (it supplies the exception types).
"""

from __future__ import annotations

import copy
import struct
import threading
import urllib.parse as urlparse
from dataclasses import dataclass, field
from typing import Any, TypedDict

from tactdeform_hw.clock import Clock, MonotonicClock, SimulatedClock
from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.firmware.skin import SkinModel
from tactdeform_hw.emulator.serving.usb_client import EmulatedBoardBackend
from tactdeform_hw.emulator.timed.base import TimedModel
from tactdeform_hw.emulator.timed.link import LinkModel
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import ConfigurationError, MissingDependencyError
from tactdeform_hw.protocol.constants import (
    ESP32S3_USB_JTAG_PID,
    ESPRESSIF_VID,
    USB_PACKET_SIZE,
)
from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.state import BoardState

# --- USB constants ------------------------------------------------------------------------------------

CLASS_CDC_COMM = 0x02
CLASS_CDC_DATA = 0x0A
CLASS_VENDOR = 0xFF
EP_BULK = 0x02
EP_INTERRUPT = 0x03
DIR_IN = 0x80
_POLL_S = 250e-6  # how often a waiting transfer looks at the firmware's clock (a quarter frame)

REQ_GET_DESCRIPTOR = 0x06
DESC_STRING = 0x03
CDC_SET_LINE_CODING = 0x20
CDC_GET_LINE_CODING = 0x21
CDC_SET_CONTROL_LINE_STATE = 0x22
CDC_SEND_BREAK = 0x23

LANGID_EN_US = 0x0409
SPEED_FULL = 2  # usb.util.SPEED_FULL


# --- clocks ---------------------------------------------------------------------------------------------


#: The bus runs on a clock from :mod:`tactdeform_hw.clock`: wall time by default (the emulated board
#: answers with a real board's latencies), or simulated time (``sleep`` moves it on at once, so timed
#: scenarios run fast and repeat exactly; ``advance`` moves it by hand).
RealClock = MonotonicClock
VirtualClock = SimulatedClock


# --- descriptors ----------------------------------------------------------------------------------------


@dataclass
class EndpointDescriptor:
    bEndpointAddress: int
    bmAttributes: int
    wMaxPacketSize: int = USB_PACKET_SIZE
    bInterval: int = 0
    bLength: int = 7
    bDescriptorType: int = 0x05
    bRefresh: int = 0
    bSynchAddress: int = 0
    extra_descriptors: list[int] = field(default_factory=list)


@dataclass
class InterfaceDescriptor:
    bInterfaceNumber: int
    bInterfaceClass: int
    bInterfaceSubClass: int
    bInterfaceProtocol: int
    endpoints: list[EndpointDescriptor]
    bAlternateSetting: int = 0
    iInterface: int = 0
    bLength: int = 9
    bDescriptorType: int = 0x04
    extra_descriptors: list[int] = field(default_factory=list)

    @property
    def bNumEndpoints(self) -> int:
        return len(self.endpoints)


@dataclass
class ConfigurationDescriptor:
    bConfigurationValue: int
    interfaces: list[InterfaceDescriptor]
    iConfiguration: int = 0
    bmAttributes: int = 0xC0
    bMaxPower: int = 250  # 500 mA in 2 mA units
    bLength: int = 9
    bDescriptorType: int = 0x02
    extra_descriptors: list[int] = field(default_factory=list)

    @property
    def bNumInterfaces(self) -> int:
        return len({i.bInterfaceNumber for i in self.interfaces})

    @property
    def wTotalLength(self) -> int:
        n = self.bLength + len(self.extra_descriptors)
        for i in self.interfaces:
            n += i.bLength + len(i.extra_descriptors)
            n += sum(e.bLength + len(e.extra_descriptors) for e in i.endpoints)
        return n


@dataclass
class DeviceDescriptor:
    idVendor: int
    idProduct: int
    bus: int
    address: int
    port_number: int
    bcdUSB: int = 0x0200
    bDeviceClass: int = 0xEF  # miscellaneous: the function is described by an interface association
    bDeviceSubClass: int = 0x02
    bDeviceProtocol: int = 0x01
    bMaxPacketSize0: int = 64
    bcdDevice: int = 0x0101
    iManufacturer: int = 1
    iProduct: int = 2
    iSerialNumber: int = 3
    bNumConfigurations: int = 1
    bLength: int = 18
    bDescriptorType: int = 0x01
    speed: int = SPEED_FULL

    @property
    def port_numbers(self) -> tuple[int, ...]:
        return (self.port_number,)


def esp32s3_interfaces() -> list[InterfaceDescriptor]:
    """The ESP32-S3 USB Serial/JTAG controller's interfaces, as a host enumerates them."""
    cdc_functional = [
        0x05, 0x24, 0x00, 0x10, 0x01,  # header, CDC 1.10
        0x05, 0x24, 0x01, 0x03, 0x01,  # call management: data interface 1
        0x04, 0x24, 0x02, 0x02,  # ACM: line coding and serial state
        0x05, 0x24, 0x06, 0x00, 0x01,  # union: master 0, slave 1
    ]  # fmt: skip
    return [
        InterfaceDescriptor(
            0, CLASS_CDC_COMM, 0x02, 0x00,
            [EndpointDescriptor(0x82, EP_INTERRUPT, 64, bInterval=1)],
            extra_descriptors=cdc_functional,
        ),
        InterfaceDescriptor(
            1, CLASS_CDC_DATA, 0x00, 0x00,
            [EndpointDescriptor(0x01, EP_BULK), EndpointDescriptor(0x81, EP_BULK)],
        ),
        InterfaceDescriptor(
            2, CLASS_VENDOR, 0xFF, 0x01,
            [EndpointDescriptor(0x02, EP_BULK), EndpointDescriptor(0x83, EP_BULK)],
        ),
    ]  # fmt: skip


# --- the device ---------------------------------------------------------------------------------------


class _TimedOptions(TypedDict):
    """What each power-up builds the firmware's :class:`TimedEmulator` from."""

    board: str
    switching_boards: int
    link: str | LinkModel
    tx_link: str | LinkModel | None
    model: TimingModel | None
    skin: SkinModel | None
    stack_reading: float | None


class EmulatedUsbDevice:
    """One emulated board on the bus: a :class:`~tactdeform_hw.emulator.timed.model_v1_2.TimedEmulator` (the
    firmware in time — link, receive queue, parser rhythm, scans, watchdog) behind USB descriptors,
    interfaces and endpoints.

    ``link`` / ``tx_link`` are the host→device and device→host link models (USB full speed by default;
    a :class:`~tactdeform_hw.emulator.timed.link.LinkFilter` here injects byte-level faults); each power-up
    gets
    fresh copies.  ``firmware``: the version the board runs — ``"v1.2"`` (:class:`TimedEmulator`) or
    ``"v2"`` (:class:`~tactdeform_hw.emulator.timed.model_v2.TimedEmulatorV2`: its 1024-byte queue, whole
    payloads, the 2 s command timeout; its ADC reads the same ``skin`` model, stored unshifted).
    ``kernel_driver``: True — Linux with ``cdc_acm`` bound to the CDC interfaces (the
    transport must detach it and re-attach on close); False — nothing bound; None — the platform cannot
    tell (pyusb raises ``NotImplementedError``, as on Windows and macOS).
    """

    def __init__(
        self,
        board: str = "compact",
        switching_boards: int = 1,
        *,
        vid: int = ESPRESSIF_VID,
        pid: int = ESP32S3_USB_JTAG_PID,
        serial_number: str | None = "F4:12:FA:C0:FF:EE",
        manufacturer: str | None = "Espressif",
        product: str | None = "USB JTAG/serial debug unit",
        interfaces: list[InterfaceDescriptor] | None = None,
        kernel_driver: bool | None = True,
        access_denied: bool = False,
        configured: bool = True,
        timing: TimingModel | None = None,
        link: str | LinkModel = "usb",
        tx_link: str | LinkModel | None = None,
        skin: SkinModel | None = None,
        stack_reading: float | None = None,
        firmware: str | FirmwareSpec = "v1.2",
    ) -> None:
        self._entry = model_entry(firmware)
        self.firmware: FirmwareSpec = self._entry.spec
        self._make = _TimedOptions(board=board, switching_boards=switching_boards, link=link, tx_link=tx_link,
                                   model=timing, skin=skin, stack_reading=stack_reading)  # fmt: skip
        self.timed = self._new_timed()  # raises ConfigurationError for a bad board or model
        self.vid, self.pid = vid, pid
        self.strings: dict[int, str | None] = {1: manufacturer, 2: product, 3: serial_number}
        self.interfaces = interfaces if interfaces is not None else esp32s3_interfaces()
        self.kernel_driver_supported = kernel_driver is not None
        self.access_denied = access_denied
        self._start_configured = configured
        cdc = [
            i.bInterfaceNumber
            for i in self.interfaces
            if i.bInterfaceClass in (CLASS_CDC_COMM, CLASS_CDC_DATA)
        ]
        self._kernel_default = set(cdc) if kernel_driver else set()
        # bus state (set when plugged)
        self.backend: EmulatedUsbBackend | None = None
        self.plugged = False
        self.generation = 0
        self.bus = 1
        self.address = 0
        self.t0 = 0.0
        self.configuration = 0
        self.kernel_bound: set[int] = set()
        self.claims: dict[int, _Handle] = {}
        self.halted: set[int] = set()
        self.sticky_halts: set[int] = set()
        self.line_coding = struct.pack("<IBBB", 115_200, 0, 0, 8)
        self.dtr = False
        self.rts = False
        self.resets = 0
        self.download_mode = False
        self.control_log: list[tuple[int, int, int, int, bytes]] = []
        self.bytes_accepted = 0  # OUT bytes handed to the firmware's link since power-up
        self.unplug_after_out: int | None = None
        self.nak_out = False  # the device NAKs every OUT packet (firmware no longer servicing USB)

    def _new_timed(self) -> TimedModel:
        opts = self._make.copy()
        if isinstance(opts["link"], LinkModel):
            opts["link"] = copy.deepcopy(opts["link"])
        if isinstance(opts["tx_link"], LinkModel):
            opts["tx_link"] = copy.deepcopy(opts["tx_link"])
        return self._entry.timed_class().served(**opts)

    # --- identity --------------------------------------------------------------------------------------

    @property
    def emulator(self) -> Emulator:
        """The firmware's parser and registers (``emulator.hazards`` lists what it ran into)."""
        return self.timed.emulator

    @property
    def serial_number(self) -> str | None:
        return self.strings.get(3)

    @property
    def line_rate(self) -> int:
        return int(struct.unpack_from("<I", self.line_coding)[0])

    def descriptor(self) -> DeviceDescriptor:
        return DeviceDescriptor(
            self.vid,
            self.pid,
            self.bus,
            self.address,
            port_number=self.address,
            iManufacturer=1 if self.strings.get(1) else 0,
            iProduct=2 if self.strings.get(2) else 0,
            iSerialNumber=3 if self.strings.get(3) else 0,
        )

    def configuration_descriptor(self) -> ConfigurationDescriptor:
        return ConfigurationDescriptor(1, self.interfaces)

    def endpoint(self, address: int) -> EndpointDescriptor | None:
        for i in self.interfaces:
            for e in i.endpoints:
                if e.bEndpointAddress == address:
                    return e
        return None

    # --- faults ----------------------------------------------------------------------------------------

    def halt(self, endpoint: int, *, sticky: bool = False) -> None:
        """Stall ``endpoint``: every transfer on it fails with a pipe error until the host clears the
        halt.  ``sticky`` makes the halt come back at once (an endpoint the firmware keeps stalling)."""
        if self.endpoint(endpoint) is None:
            raise ConfigurationError(f"endpoint=0x{endpoint:02x} is not one of this device's endpoints")
        self.halted.add(endpoint)
        if sticky:
            self.sticky_halts.add(endpoint)

    def unplug_after(self, out_bytes: int) -> None:
        """Disconnect once ``out_bytes`` more bytes have been accepted on a bulk OUT endpoint (the cable
        is pulled mid-write; a packet is delivered whole or not at all)."""
        if out_bytes < 0:
            raise ConfigurationError(f"out_bytes={out_bytes!r} must be at least 0")
        self.unplug_after_out = out_bytes

    # --- time ------------------------------------------------------------------------------------------

    def now_us(self) -> float:
        """Device time: µs since the board was powered up (never behind the firmware's own clock)."""
        assert self.backend is not None
        return max((self.backend.clock.now() - self.t0) * 1e6, self.timed.now_us)

    def advance(self) -> float:
        """Simulate the firmware up to the clock's now (the host's calls do this by themselves)."""
        assert self.backend is not None
        with self.backend.lock:
            t = self.now_us()
            if self.plugged:
                self.timed.advance_to(t)
            return t

    def state(self) -> BoardState:
        """The firmware's registers as of now (see :meth:`Emulator.state`)."""
        self.advance()
        return self.timed.state()

    @property
    def busy(self) -> bool:
        """Bytes on their way to, or waiting in front of, a parser that will read them."""
        return self.plugged and not self.timed.run_until_idle(limit_us=0)

    def settle(self, timeout_s: float = 1.0) -> bool:
        """Let the clock run until every byte sent has been delivered and read by the parser (or the
        parser is locked or spinning on half a u16).  False if that took over ``timeout_s``."""
        assert self.backend is not None
        clock = self.backend.clock
        deadline = clock.now() + timeout_s
        while True:
            self.advance()
            if not self.busy:
                return True
            if clock.now() >= deadline:
                return False
            clock.sleep(_POLL_S)

    # --- host traffic ----------------------------------------------------------------------------------

    def host_write(self, packet: bytes) -> None:
        t = self.advance()
        self.bytes_accepted += len(packet)
        if self.running:
            self.timed.write(packet, at_us=t)

    def host_read(self, size: int) -> bytes:
        self.advance()
        return self.timed.read_tx(size)

    @property
    def running(self) -> bool:
        """Whether the application runs (not held in reset, not in the ROM download mode)."""
        return not (self.rts and not self.dtr) and not self.download_mode

    # --- bus events ------------------------------------------------------------------------------------

    def plug_in(self, backend: EmulatedUsbBackend, address: int) -> None:
        self.backend = backend
        self.plugged = True
        self.generation += 1
        self.address = address
        self.t0 = backend.clock.now()
        self.configuration = 1 if self._start_configured else 0
        self.kernel_bound = set(self._kernel_default)
        self.claims.clear()
        self.halted.clear()
        self.sticky_halts.clear()
        self.dtr = self.rts = False
        self.download_mode = False
        self.bytes_accepted = 0
        self.unplug_after_out = None
        if self.generation > 1:
            self.timed = self._new_timed()  # plugging in powers the board up

    def unplug_now(self) -> None:
        if self.plugged:
            self.advance()
        self.plugged = False
        self.claims.clear()

    def set_lines(self, dtr: bool, rts: bool) -> None:
        """The USB Serial/JTAG controller holds the chip in reset while RTS is asserted and DTR is not;
        DTR high at the moment the reset ends selects the ROM download mode (no application runs)."""
        self.advance()
        was_reset = self.rts and not self.dtr
        now_reset = rts and not dtr
        self.dtr, self.rts = dtr, rts
        if now_reset and not was_reset:
            # held in reset: nothing runs, nothing stimulates; bytes sent meanwhile are dropped
            self.timed.reset("USB Serial/JTAG reset held (RTS without DTR)")
            self.timed.read_tx()  # the chip's transmit buffer goes with it
        elif was_reset and not now_reset:
            self.resets += 1
            self.download_mode = dtr
            self.timed.reset("USB Serial/JTAG reset released")
            self.timed.read_tx()

    def run_firmware(self, timed: TimedModel, t0: float) -> None:
        """Put ``timed`` (a real-time board's model, whose device time 0 is ``t0`` on the bus clock)
        behind this device's endpoints: the board served by ``emulate --usb`` is then one model, seen
        by the USB endpoints and by the live view alike."""
        if timed.firmware is not self.firmware:
            raise ConfigurationError(
                f"firmware={timed.firmware.name!r}: this device runs {self.firmware.name!r}"
            )
        self.timed = timed
        self.t0 = t0

    def __repr__(self) -> str:
        state = f"bus {self.bus} address {self.address}" if self.plugged else "unplugged"
        return f"EmulatedUsbDevice({self.vid:04x}:{self.pid:04x}, {state})"


class _Handle:
    def __init__(self, device: EmulatedUsbDevice) -> None:
        self.device = device
        self.generation = device.generation
        self.open = True


# --- the backend ----------------------------------------------------------------------------------------


class EmulatedUsbBackend(EmulatedBoardBackend):
    """A pyusb backend whose bus holds emulated boards.  ``EmulatedUsbBackend()`` has one ESP32-S3.

    Pass it to ``usb.core.find(backend=...)`` or to
    :class:`tactdeform_hw.device.driver.usb_transport.UsbCdcPort`.
    """

    def __init__(
        self,
        devices: list[EmulatedUsbDevice] | None = None,
        *,
        clock: Clock | None = None,
        lock: threading.RLock | None = None,
    ) -> None:
        try:
            import usb.core
        except ImportError as exc:
            raise MissingDependencyError("pyusb", "usb", "the emulated USB device") from exc
        self._usb_error: type[Exception] = usb.core.USBError
        self._usb_timeout: type[Exception] = usb.core.USBTimeoutError
        self.clock: Clock = clock if clock is not None else RealClock()
        # a served board shares its real-time model's lock (see :mod:`.usb_server`)
        self.lock = lock if lock is not None else threading.RLock()
        self.devices: list[EmulatedUsbDevice] = []
        self._next_address = 1
        for d in devices if devices is not None else [EmulatedUsbDevice()]:
            self.plug(d)

    @property
    def usb_error(self) -> type[Exception]:
        """pyusb's ``USBError``: what every failed request on this bus raises."""
        return self._usb_error

    @property
    def usb_timeout(self) -> type[Exception]:
        """pyusb's ``USBTimeoutError``: a transfer that timed out."""
        return self._usb_timeout

    @property
    def device(self) -> EmulatedUsbDevice:
        """The first device (the usual single-board case)."""
        if not self.devices:
            raise ConfigurationError("the emulated bus has no device")
        return self.devices[0]

    # --- bus control (tests) -------------------------------------------------------------------------

    def plug(self, device: EmulatedUsbDevice) -> EmulatedUsbDevice:
        with self.lock:
            if device not in self.devices:
                self.devices.append(device)
            self._next_address += 1
            device.plug_in(self, self._next_address)
        return device

    def unplug(self, device: EmulatedUsbDevice | None = None) -> None:
        """Pull the cable: open handles fail with "no such device" from now on."""
        with self.lock:
            (device or self.device).unplug_now()

    def replug(self, device: EmulatedUsbDevice | None = None) -> EmulatedUsbDevice:
        """Plug a device back: a new address, a powered-up board, the kernel driver bound again."""
        with self.lock:
            d = device or self.device
            d.unplug_now()
            return self.plug(d)

    # --- errors (raised as pyusb raises libusb's: :class:`~.usb_client.EmulatedBoardBackend`) -----------

    def _live(self, handle: _Handle) -> EmulatedUsbDevice:
        d = handle.device
        if not handle.open:
            raise self._error("invalid")
        if not d.plugged or handle.generation != d.generation:
            raise self._error("no_device")
        return d

    def _interface(self, d: EmulatedUsbDevice, intf: int) -> InterfaceDescriptor:
        for i in d.interfaces:
            if i.bInterfaceNumber == intf:
                return i
        raise self._error("not_found")

    # --- IBackend: enumeration and descriptors ----------------------------------------------------------

    def enumerate_devices(self) -> list[EmulatedUsbDevice]:
        with self.lock:
            return [d for d in self.devices if d.plugged]

    def get_parent(self, dev: EmulatedUsbDevice) -> None:
        return None

    def get_device_descriptor(self, dev: EmulatedUsbDevice) -> DeviceDescriptor:
        return dev.descriptor()

    def get_configuration_descriptor(self, dev: EmulatedUsbDevice, config: int) -> ConfigurationDescriptor:
        if config != 0:
            raise IndexError(f"Invalid configuration index {config}")
        return dev.configuration_descriptor()

    def get_interface_descriptor(
        self, dev: EmulatedUsbDevice, intf: int, alt: int, config: int
    ) -> InterfaceDescriptor:
        cfg = self.get_configuration_descriptor(dev, config)
        numbers = sorted({i.bInterfaceNumber for i in cfg.interfaces})
        if not 0 <= intf < len(numbers):
            raise IndexError(f"Invalid interface index {intf}")
        alts = [i for i in cfg.interfaces if i.bInterfaceNumber == numbers[intf]]
        if not 0 <= alt < len(alts):
            raise IndexError(f"Invalid alternate setting index {alt}")
        return alts[alt]

    def get_endpoint_descriptor(
        self, dev: EmulatedUsbDevice, ep: int, intf: int, alt: int, config: int
    ) -> EndpointDescriptor:
        i = self.get_interface_descriptor(dev, intf, alt, config)
        if not 0 <= ep < len(i.endpoints):
            raise IndexError(f"Invalid endpoint index {ep}")
        return i.endpoints[ep]

    # --- IBackend: handles, configuration, interfaces ---------------------------------------------------

    def open_device(self, dev: EmulatedUsbDevice) -> _Handle:
        with self.lock:
            if not dev.plugged:
                raise self._error("no_device")
            if dev.access_denied:
                raise self._error("access")
            return _Handle(dev)

    def close_device(self, dev_handle: _Handle) -> None:
        with self.lock:
            d = dev_handle.device
            for n in [n for n, h in d.claims.items() if h is dev_handle]:
                del d.claims[n]
            dev_handle.open = False

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        with self.lock:
            d = self._live(dev_handle)
            if config_value not in (0, 1):
                raise self._error("invalid")
            if d.kernel_bound or any(h is not dev_handle for h in d.claims.values()):
                raise self._error("busy")
            d.configuration = config_value

    def get_configuration(self, dev_handle: _Handle) -> int:
        with self.lock:
            return self._live(dev_handle).configuration

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        with self.lock:
            d = self._live(dev_handle)
            self._interface(d, intf)
            if altsetting != 0:
                raise self._error("invalid")

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        with self.lock:
            d = self._live(dev_handle)
            self._interface(d, intf)
            if d.configuration == 0:
                raise self._error("not_found")
            holder = d.claims.get(intf)
            if intf in d.kernel_bound or (holder is not None and holder is not dev_handle):
                raise self._error("busy")
            d.claims[intf] = dev_handle

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        with self.lock:
            d = self._live(dev_handle)
            if d.claims.get(intf) is not dev_handle:
                raise self._error("not_found")
            del d.claims[intf]

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        with self.lock:
            d = self._with_kernel_drivers(dev_handle)
            self._interface(d, intf)
            return intf in d.kernel_bound

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        with self.lock:
            d = self._with_kernel_drivers(dev_handle)
            if intf not in d.kernel_bound:
                raise self._error("not_found")
            d.kernel_bound.discard(intf)

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        with self.lock:
            d = self._with_kernel_drivers(dev_handle)
            self._interface(d, intf)
            if intf in d.kernel_bound or intf in d.claims:
                raise self._error("busy")
            d.kernel_bound.add(intf)

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        with self.lock:
            d = self._live(dev_handle)
            if d.endpoint(ep) is None:
                raise self._error("not_found")
            if ep not in d.sticky_halts:
                d.halted.discard(ep)

    def reset_device(self, dev_handle: _Handle) -> None:
        """A USB port reset: the controller re-enumerates; the chip (and its firmware) keeps running."""
        with self.lock:
            d = self._live(dev_handle)
            d.halted = set(d.sticky_halts)
            d.claims.clear()

    # --- IBackend: transfers ----------------------------------------------------------------------------

    def _check_transfer(
        self, dev_handle: _Handle, ep: int, intf: int, *, direction_in: bool
    ) -> tuple[EmulatedUsbDevice, EndpointDescriptor]:
        d = self._live(dev_handle)
        desc = d.endpoint(ep)
        if desc is None or bool(ep & DIR_IN) != direction_in:
            raise self._error("not_found")
        if d.claims.get(intf) is not dev_handle:
            raise self._error("not_found")
        if ep in d.halted:
            raise self._error("pipe")
        return d, desc

    def bulk_write(self, dev_handle: _Handle, ep: int, intf: int, data: Any, timeout: int) -> int:
        payload = bytes(data)
        deadline = None if not timeout else self.clock.now() + timeout / 1000.0
        while True:
            with self.lock:
                d, desc = self._check_transfer(dev_handle, ep, intf, direction_in=False)
                if ep != self._cdc_endpoint(d, direction_in=False):
                    return len(payload)  # the JTAG interface: accepted and ignored
                if not d.nak_out:
                    size = desc.wMaxPacketSize
                    sent = 0
                    for i in range(0, len(payload), size):
                        pkt = payload[i : i + size]
                        if d.unplug_after_out is not None:
                            if len(pkt) > d.unplug_after_out:
                                d.unplug_now()
                                raise self._error("no_device")
                            d.unplug_after_out -= len(pkt)
                        d.host_write(pkt)
                        sent += len(pkt)
                    return sent
            # every packet is NAKed: the transfer waits (out its timeout) without sending a byte
            self._poll_until(deadline)

    def bulk_read(self, dev_handle: _Handle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        """Bytes that have crossed the link by now, up to the buffer's size; otherwise wait for them,
        polling the firmware's clock every quarter frame."""
        deadline = None if not timeout else self.clock.now() + timeout / 1000.0
        while True:
            with self.lock:
                d, _ = self._check_transfer(dev_handle, ep, intf, direction_in=True)
                if ep == self._cdc_endpoint(d, direction_in=True):
                    data = d.host_read(len(buff) * buff.itemsize)
                    if data:
                        buff[: len(data)] = type(buff)(buff.typecode, data)
                        return len(data)
                else:
                    d.advance()  # the JTAG interface never sends here
            self._poll_until(deadline)

    def intr_read(self, dev_handle: _Handle, ep: int, intf: int, buff: Any, timeout: int) -> int:
        """The CDC notification endpoint: the USB Serial/JTAG controller never sends serial-state
        notifications, so a read waits out its timeout."""
        with self.lock:
            self._check_transfer(dev_handle, ep, intf, direction_in=True)
        self.clock.sleep((timeout or 1) / 1000.0)
        raise self._error("timeout")

    def _poll_until(self, deadline: float | None) -> None:
        """One wait of a transfer that cannot complete yet: a poll interval on the firmware's clock, cut
        to the deadline, or the timeout error once the deadline has passed (``None``: no deadline)."""
        now = self.clock.now()
        if deadline is not None and now >= deadline:
            raise self._error("timeout")
        self.clock.sleep(_POLL_S if deadline is None else min(_POLL_S, deadline - now))

    def _with_kernel_drivers(self, dev_handle: _Handle) -> EmulatedUsbDevice:
        """The open device behind ``dev_handle``, for a kernel-driver call; on a device emulating a
        platform without kernel drivers, the ``NotImplementedError`` pyusb raises there."""
        d = self._live(dev_handle)
        if not d.kernel_driver_supported:
            raise NotImplementedError("Operation not supported or unimplemented on this platform")
        return d

    @staticmethod
    def _cdc_endpoint(d: EmulatedUsbDevice, direction_in: bool) -> int | None:
        for i in d.interfaces:
            if i.bInterfaceClass == CLASS_CDC_DATA:
                for e in i.endpoints:
                    if bool(e.bEndpointAddress & DIR_IN) == direction_in:
                        return e.bEndpointAddress
        return None

    def ctrl_transfer(
        self,
        dev_handle: _Handle,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        with self.lock:
            d = self._live(dev_handle)
            payload = bytes(data) if not bmRequestType & DIR_IN else b""
            d.control_log.append((bmRequestType, bRequest, wValue, wIndex, payload))
            if bmRequestType == 0x80 and bRequest == REQ_GET_DESCRIPTOR and wValue >> 8 == DESC_STRING:
                return self._string(d, wValue & 0xFF, data)
            comm = next(
                (i.bInterfaceNumber for i in d.interfaces if i.bInterfaceClass == CLASS_CDC_COMM), None
            )
            if bmRequestType in (0x21, 0xA1) and wIndex == comm:
                if bmRequestType == 0x21 and bRequest == CDC_SET_LINE_CODING and len(payload) == 7:
                    d.line_coding = payload
                    return 7
                if bmRequestType == 0xA1 and bRequest == CDC_GET_LINE_CODING:
                    n = min(len(data), 7)
                    data[:n] = type(data)(data.typecode, d.line_coding[:n])
                    return n
                if bmRequestType == 0x21 and bRequest == CDC_SET_CONTROL_LINE_STATE:
                    d.set_lines(bool(wValue & 1), bool(wValue & 2))
                    return 0
                if bmRequestType == 0x21 and bRequest == CDC_SEND_BREAK:
                    return 0
            raise self._error("pipe")  # a request the device does not support stalls endpoint 0

    def _string(self, d: EmulatedUsbDevice, index: int, buff: Any) -> int:
        if index == 0:
            raw = bytes([4, DESC_STRING]) + struct.pack("<H", LANGID_EN_US)
        else:
            text = d.strings.get(index)
            if not text:
                raise self._error("pipe")
            enc = text.encode("utf-16-le")
            raw = bytes([2 + len(enc), DESC_STRING]) + enc
        n = min(len(buff), len(raw))
        buff[:n] = type(buff)(buff.typecode, raw[:n])
        return n


# --- names ---------------------------------------------------------------------------------------------

EMULATOR_NAME = "usb-emulator"
_OPTIONS = ("board", "switching_boards", "serial", "kernel_driver", "firmware")


def backend_from_name(name: str) -> EmulatedUsbBackend:
    """``usb-emulator[?board=compact|large&switching_boards=N&serial=S&kernel_driver=0|1&firmware=v1.2|v2]``:
    a fresh emulated bus with one board (firmware v1.2 unless named).  Unknown options are refused."""
    base, _, query = name.partition("?")
    if base != EMULATOR_NAME:
        raise ConfigurationError(f"device={name!r}: expected {EMULATOR_NAME}[?options]")
    opts: dict[str, str] = {}
    for option, values in urlparse.parse_qs(query, keep_blank_values=True).items():
        if option not in _OPTIONS:
            raise ConfigurationError(
                f"device={name!r}: unknown option {option!r} (known: {', '.join(_OPTIONS)})"
            )
        opts[option] = values[-1]
    try:
        switching = int(opts.get("switching_boards", "1"))
    except ValueError as exc:
        raise ConfigurationError(f"device={name!r}: switching_boards must be an integer") from exc
    kernel = opts.get("kernel_driver", "1") not in ("0", "no", "false")
    device = EmulatedUsbDevice(
        opts.get("board", "compact"),
        switching,
        serial_number=opts.get("serial", "F4:12:FA:C0:FF:EE"),
        kernel_driver=kernel,
        firmware=opts.get("firmware", "v1.2"),
    )
    return EmulatedUsbBackend([device])


__all__ = [
    "Clock",
    "ConfigurationDescriptor",
    "DeviceDescriptor",
    "EMULATOR_NAME",
    "EmulatedUsbBackend",
    "EmulatedUsbDevice",
    "EndpointDescriptor",
    "InterfaceDescriptor",
    "RealClock",
    "VirtualClock",
    "backend_from_name",
    "esp32s3_interfaces",
]
