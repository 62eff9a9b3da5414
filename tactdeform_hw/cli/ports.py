"""``tactdeform-hw ports``: serial ports that may be an eTactileKit."""

from __future__ import annotations

import argparse
from typing import Any

from ..protocol.constants import ESPRESSIF_VID
from .common import print_json


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "ports",
        help="list serial ports, marking the ones that look like an eTactileKit (ESP32-S3, VID 0x303A)",
        description="List serial ports with VID:PID, serial number and product. A port with Espressif's "
        "vendor id 0x303A is marked as a likely eTactileKit controller (ESP32-S3 native USB).",
    )
    p.add_argument("--json", action="store_true", help="print JSON records")
    p.set_defaults(func=run)


def serial_candidates() -> list[dict[str, Any]]:
    from serial.tools import list_ports

    out = []
    for info in list_ports.comports():
        vid, pid = info.vid, info.pid
        hint = ""
        if vid == ESPRESSIF_VID:
            hint = "Espressif VID 0x303A: likely an ESP32-S3 eTactileKit controller"
        out.append(
            {
                "transport": "serial",
                "device": info.device,
                "vid": f"{vid:04x}" if vid is not None else None,
                "pid": f"{pid:04x}" if pid is not None else None,
                "serial_number": info.serial_number,
                "product": info.product,
                "description": info.description,
                "hint": hint,
            }
        )
    return out


def run(args: argparse.Namespace) -> int:
    rows = serial_candidates()
    if args.json:
        print_json(rows)
        return 0
    if not rows:
        print("no serial ports found (the emulator is always available as --device emulator)")
        return 0
    for r in rows:
        ids = f"{r['vid']}:{r['pid']}" if r["vid"] else "----:----"
        line = f"{r['device']:<20} {ids}  {r['description'] or ''}"
        if r["hint"]:
            line += f"   <- {r['hint']}"
        print(line)
    return 0
