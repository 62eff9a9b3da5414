"""Which attached devices may be an eTactileKit controller, seen through pyserial and through pyusb.

The controller is an ESP32-S3 whose ``Serial`` is the chip's USB Serial/JTAG controller, so the same
board can show up twice: as a serial port (``/dev/ttyACM0``, ``COM3``) where the system's CDC-ACM driver
owns it, and as USB device 303a:1001 that pyusb can open directly.  Each candidate says which route it
is, the name to pass as ``--device``, and the evidence that it looks like the controller — nothing here
opens a port or sends a byte, because a board's identity cannot be asked over this protocol (there is
no version query) and an unknown device must not be sent commands.

pyusb and libusb are optional: without them the serial ports are still listed, with a note saying why
USB devices are not.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from tactdeform_hw.device.driver.usb_transport import CLASS_CDC_COMM, CLASS_CDC_DATA, NO_BACKEND_HELP
from tactdeform_hw.errors import MissingDependencyError, TransportError
from tactdeform_hw.protocol.constants import ESP32S3_USB_JTAG_PID, ESPRESSIF_VID

_CLASS_VENDOR = 0xFF
_JTAG_PRODUCT_HINT = "jtag/serial"


@dataclass(frozen=True)
class Candidate:
    """One attached device; ``device`` is what ``--device`` (and ``open_device``) takes."""

    transport: str  # "serial" (a port of the system's serial driver) or "usb" (pyusb, no serial driver)
    device: str
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    location: str | None = None
    reasons: tuple[str, ...] = ()
    likely: bool = False
    same_board_as: str | None = None
    notes: tuple[str, ...] = ()

    @property
    def ids(self) -> str:
        return (
            f"{self.vid:04x}:{self.pid:04x}" if self.vid is not None and self.pid is not None else "----:----"
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["vid"] = f"{self.vid:04x}" if self.vid is not None else None
        d["pid"] = f"{self.pid:04x}" if self.pid is not None else None
        d["reasons"] = list(self.reasons)
        d["notes"] = list(self.notes)
        return d


@dataclass
class Discovery:
    """Every candidate found, and why a route could not be searched (``usb_available`` False)."""

    candidates: list[Candidate] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    usb_available: bool = True

    @property
    def likely(self) -> list[Candidate]:
        return [c for c in self.candidates if c.likely]

    def to_dict(self) -> dict[str, Any]:
        return {
            "candidates": [c.to_dict() for c in self.candidates],
            "usb_available": self.usb_available,
            "notes": list(self.notes),
        }


def _id_reasons(vid: int | None, pid: int | None, product: str | None) -> list[str]:
    reasons = []
    if vid == ESPRESSIF_VID:
        reasons.append("Espressif vendor id 0x303A")
        if pid == ESP32S3_USB_JTAG_PID:
            reasons.append(
                "product id 0x1001: the ESP32-S3 USB Serial/JTAG controller (the XIAO ESP32S3's Serial)"
            )
    if product and _JTAG_PRODUCT_HINT in product.lower():
        reasons.append(f"product string {product!r}")
    return reasons


# --- pyserial ------------------------------------------------------------------------------------------


def serial_candidates(ports: Iterable[Any] | None = None, *, include_all: bool = True) -> list[Candidate]:
    """Serial ports from ``serial.tools.list_ports`` (or the given port records, e.g. a recorded
    snapshot), marking those with Espressif's vendor id as likely controllers."""
    if ports is None:
        from serial.tools import list_ports

        ports = list_ports.comports()
    out = []
    for info in ports:
        vid, pid = getattr(info, "vid", None), getattr(info, "pid", None)
        product = getattr(info, "product", None)
        reasons = _id_reasons(vid, pid, product)
        likely = vid == ESPRESSIF_VID
        if not include_all and not likely:
            continue
        out.append(
            Candidate(
                transport="serial",
                device=str(info.device),
                vid=vid,
                pid=pid,
                serial_number=getattr(info, "serial_number", None),
                manufacturer=getattr(info, "manufacturer", None),
                product=product or getattr(info, "description", None),
                location=getattr(info, "location", None),
                reasons=tuple(reasons),
                likely=likely,
            )
        )
    return out


# --- pyusb ---------------------------------------------------------------------------------------------


def usb_candidates(backend: Any = None, *, include_all: bool = False) -> list[Candidate]:
    """USB devices seen through pyusb that are Espressif's or carry a CDC-ACM function (all of them
    with ``include_all``).  Raises :class:`MissingDependencyError` without pyusb and
    :class:`TransportError` without a libusb backend."""
    from tactdeform_hw.device.driver.usb_transport import default_backend, import_usb

    core, util = import_usb()
    if backend is None:
        backend = default_backend()
        if backend is None:
            raise TransportError(NO_BACKEND_HELP)
    try:
        devices = list(core.find(find_all=True, backend=backend))
    except core.NoBackendError as exc:
        raise TransportError(NO_BACKEND_HELP) from exc
    except core.USBError as exc:
        raise TransportError(f"cannot list USB devices: {exc}") from exc
    out = []
    for dev in devices:
        cand = _usb_candidate(dev, core, util, include_all)
        if cand is not None:
            out.append(cand)
    return out


def _usb_candidate(dev: Any, core: Any, util: Any, include_all: bool) -> Candidate | None:
    vid, pid = int(dev.idVendor), int(dev.idProduct)
    classes: set[int] = set()
    try:
        for cfg in dev:
            for intf in cfg:
                classes.add(int(intf.bInterfaceClass))
    except (core.USBError, NotImplementedError):
        pass
    cdc = CLASS_CDC_COMM in classes and CLASS_CDC_DATA in classes
    if not include_all and vid != ESPRESSIF_VID and not cdc:
        return None
    notes: list[str] = []
    strings: dict[str, str | None] = {}
    for key, index in (
        ("serial", dev.iSerialNumber),
        ("manufacturer", dev.iManufacturer),
        ("product", dev.iProduct),
    ):
        try:
            strings[key] = util.get_string(dev, index) if index else None
        except (core.USBError, ValueError, NotImplementedError):
            strings[key] = None
            if "no permission" not in " ".join(notes):
                notes.append(
                    "string descriptors unreadable (no permission to open the device: on Linux add a udev "
                    'rule for ATTR{idVendor}=="303a" with GROUP="plugdev" — see '
                    "docs/firmware-guide-conformance.md)"
                )
    reasons = _id_reasons(vid, pid, strings["product"])
    if cdc:
        reasons.append(
            "CDC-ACM function (communication interface 0x02 + data interface 0x0A) for the serial link"
        )
    if _CLASS_VENDOR in classes and vid == ESPRESSIF_VID:
        reasons.append("vendor-specific JTAG interface beside it, as on the USB Serial/JTAG controller")
    likely = vid == ESPRESSIF_VID and cdc
    if vid == ESPRESSIF_VID and not cdc:
        notes.append("no CDC-ACM function: the board may be in a mode without the serial interface")
    name = f"usb:{vid:04x}:{pid:04x}" + (f":{strings['serial']}" if strings["serial"] else "")
    return Candidate(
        transport="usb",
        device=name,
        vid=vid,
        pid=pid,
        serial_number=strings["serial"],
        manufacturer=strings["manufacturer"],
        product=strings["product"],
        location=f"bus {dev.bus} address {dev.address}" if dev.bus is not None else None,
        reasons=tuple(reasons),
        likely=likely,
        notes=tuple(notes),
    )


# --- both ----------------------------------------------------------------------------------------------


def discover(
    *,
    usb: bool = True,
    usb_backend: Any = None,
    include_all: bool = False,
    serial_ports: Iterable[Any] | None = None,
) -> Discovery:
    """Serial ports and USB devices together.  A board seen both ways is linked (``same_board_as``) by
    vendor id, product id and serial number.  USB problems become notes, never exceptions."""
    result = Discovery(candidates=serial_candidates(serial_ports, include_all=True))
    if not include_all:
        # a serial port without any USB ids (a built-in UART, a pty) cannot be the controller
        result.candidates = [c for c in result.candidates if c.vid is not None]
    if not usb:
        result.usb_available = False
        result.notes.append("USB devices not searched (--no-usb)")
        return result
    try:
        found = usb_candidates(usb_backend, include_all=include_all)
    except MissingDependencyError as exc:
        result.usb_available = False
        result.notes.append(f"USB devices not searched: {exc}")
        return result
    except TransportError as exc:
        result.usb_available = False
        result.notes.append(f"USB devices not searched: {exc}")
        return result
    by_id: dict[tuple[int | None, int | None, str | None], str] = {
        (c.vid, c.pid, c.serial_number): c.device
        for c in result.candidates
        if c.vid is not None and c.serial_number
    }
    for c in found:
        twin = by_id.get((c.vid, c.pid, c.serial_number)) if c.serial_number else None
        if twin is not None:
            c = replace(c, same_board_as=twin)
        result.candidates.append(c)
    return result
