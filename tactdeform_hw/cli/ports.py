"""``tactdeform-hw ports``: serial ports and USB devices that may be an eTactileKit."""

from __future__ import annotations

import argparse
from typing import Any

from .common import print_json


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "ports",
        help="list serial ports and USB devices, marking the ones that look like an eTactileKit",
        description="List candidate boards seen two ways: serial ports (pyserial; the system's CDC-ACM "
        "driver owns the board, e.g. /dev/ttyACM0 or COM3) and USB devices (pyusb; opened directly, "
        "e.g. usb:303a:1001:SERIAL). The DEVICE column is what --device takes. A device with Espressif's "
        "vendor id 0x303A is marked as a likely controller (ESP32-S3 native USB), with the evidence. "
        "Nothing is opened and no byte is sent. Without pyusb or libusb the serial ports are still "
        "listed and a note says why USB devices are not.",
    )
    p.add_argument(
        "--json", action="store_true", help="print one JSON object: candidates, usb_available, notes"
    )
    p.add_argument("--no-usb", action="store_true", help="list serial ports only (skip pyusb)")
    p.add_argument(
        "--all",
        action="store_true",
        help="also list serial ports without USB ids and USB devices that are neither Espressif nor CDC-ACM",
    )
    p.add_argument(
        "--usb-emulator",
        action="store_true",
        help="search the emulated USB bus (one emulated board) instead of the system's: shows what a "
        "board looks like without hardware",
    )
    p.add_argument(
        "--wifi",
        metavar="HOST:PORT",
        nargs="?",
        const="255.255.255.255:8888",
        default=None,
        help="also ask Wi-Fi boards (firmware v2) by UDP discovery: ETK? to HOST:PORT (default the subnet "
        "broadcast on 8888; 127.0.0.1:PORT for an emulated kit); DEVICE is etactilekit://ID, or "
        "socket://IP:PORT when two kits share an id",
    )
    p.set_defaults(func=run)


def wifi_kits(target: str) -> list[dict[str, Any]]:
    """Kits that answer UDP discovery at ``target`` (HOST:PORT), with what ``--device`` takes for each."""
    return _wifi(target)[0]


def _wifi(target: str) -> tuple[list[dict[str, Any]], str]:
    """:func:`wifi_kits`, and where discovery asked and how long it listened (in words)."""
    from tactdeform_hw.device.driver.wifi_discovery import discover

    from ..errors import LimitError

    host, _, port = target.rpartition(":")
    try:
        addr = (host or "127.0.0.1", int(port))
    except ValueError as exc:
        raise LimitError("--wifi", target, "HOST:PORT") from exc
    kits = discover([addr])
    ids = [k.id for k in kits]
    rows = [
        {
            "device": k.url if ids.count(k.id) > 1 else f"etactilekit://{k.id}",
            "id": k.id,
            "name": k.name,
            "ip": k.ip,
            "port": k.port,
            "mode": k.mode,
            "fw": k.fw,
            "id_shared": ids.count(k.id) > 1,
        }
        for k in kits
    ]
    return rows, kits.asked()


def serial_candidates() -> list[dict[str, Any]]:
    """Serial ports as plain records (kept for callers of the earlier API)."""
    from tactdeform_hw.device.driver.discovery import serial_candidates as _serial

    return [c.to_dict() for c in _serial()]


def run(args: argparse.Namespace) -> int:
    from tactdeform_hw.device.driver.discovery import discover

    backend = None
    if args.usb_emulator:
        from tactdeform_hw.emulator.serving.usb_backend import EmulatedUsbBackend

        backend = EmulatedUsbBackend()
    result = discover(usb=not args.no_usb, usb_backend=backend, include_all=args.all)
    kits, asked = _wifi(args.wifi) if args.wifi else ([], "")
    if args.json:
        out = result.to_dict()
        if args.wifi:
            out["wifi"] = kits
        print_json(out)
        return 0
    if not result.candidates and not kits:
        print("no candidate boards found (the emulator is always available as --device emulator)")
    else:
        print(f"{'ROUTE':<7} {'DEVICE':<36} {'VID:PID':<9}  DESCRIPTION")
    for k in kits:
        shared = "  (id shared with another kit: use the socket:// address)" if k["id_shared"] else ""
        print(
            f"{'wifi':<7} {k['device']:<36} {'':<9}  {k['name']} {k['ip']}:{k['port']} {k['mode']} "
            f"fw={k['fw']}{shared}"
        )
    if kits and not result.candidates:
        print(f"{len(kits)} Wi-Fi kit(s) answered discovery; no serial port or USB device looks like a board")
    if args.wifi and not kits:
        print(f"note: no Wi-Fi kit answered discovery ({asked})")
    for c in result.candidates:
        desc = " ".join(
            x for x in (c.product, f"[{c.location}]" if c.location and c.transport == "usb" else None) if x
        )
        print(f"{c.transport:<7} {c.device:<36} {c.ids:<9}  {desc}")
        if c.likely:
            print(f"{'':<7} likely an eTactileKit controller: {'; '.join(c.reasons)}")
        elif c.reasons:
            print(f"{'':<7} {'; '.join(c.reasons)}")
        if c.same_board_as:
            print(
                f"{'':<7} the same board as {c.same_board_as} (opening it over USB detaches that serial port)"
            )
        for note in c.notes:
            print(f"{'':<7} note: {note}")
    for note in result.notes:
        print(f"note: {note}")
    return 0
